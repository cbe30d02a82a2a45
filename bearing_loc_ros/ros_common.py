"""Small rclpy utilities shared by every node: main runner, typed parameters, diagnostics.

No numerics here (those live in ``bearing_loc_ros.core``).
"""

import sys

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.parameter import Parameter

OK = DiagnosticStatus.OK
WARN = DiagnosticStatus.WARN
ERROR = DiagnosticStatus.ERROR
STALE = DiagnosticStatus.STALE


class ParameterError(ValueError):
    """A parameter value is invalid; the node exits with code 1 and names the parameter."""

    def __init__(self, name, problem):
        super().__init__(f"parameter '{name}': {problem}")
        self.name = name


def run_node(node_factory, args=None):
    """Run a node the ros2/demos way; return the process exit code.

    ``node_factory()`` builds the node; a :class:`ParameterError` (or ValueError) raised while
    building it is printed as ``error: <message>`` on stderr and gives exit code 1 (bad
    configuration fails loudly and early, like joy_teleop). Ctrl-C and external shutdown end
    the spin cleanly with exit code 0.
    """
    try:
        rclpy.init(args=args)
    except Exception as exc:  # rcl rejects unparsable --ros-args with RCLError
        print(f'error: invalid command line: {str(exc).splitlines()[0]}', file=sys.stderr,
              flush=True)
        return 1
    node = None
    code = 0
    try:
        node = node_factory()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as exc:
        print(f'error: {exc}', file=sys.stderr, flush=True)
        code = 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


def main_for(node_cls):
    """Return a console-script ``main(args=None)`` that runs ``node_cls`` via run_node."""
    def main(args=None):
        sys.exit(run_node(node_cls, args))
    return main


def declare(node, name, default, description, *, read_only=False, min_value=None,
            max_value=None, additional_constraints=''):
    """Declare a typed parameter with a ParameterDescriptor and return its value.

    ``default`` fixes the type (a double default rejects an integer in YAML: write 3.0).
    ``min_value``/``max_value`` become a FloatingPointRange or IntegerRange (checked by rclpy
    on later sets; at start-up the value is also checked here and a ParameterError raised).
    """
    desc = ParameterDescriptor(description=description, read_only=read_only,
                               additional_constraints=additional_constraints)
    if min_value is not None or max_value is not None:
        lo = -sys.float_info.max if min_value is None else min_value
        hi = sys.float_info.max if max_value is None else max_value
        if isinstance(default, bool):
            pass
        elif isinstance(default, int):
            desc.integer_range = [IntegerRange(from_value=int(max(lo, -2 ** 63)),
                                               to_value=int(min(hi, 2 ** 63 - 1)), step=0)]
        elif isinstance(default, float):
            desc.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                            to_value=float(hi), step=0.0)]
    try:
        value = node.declare_parameter(name, default, desc).value
    except Exception as exc:  # rclpy raises several types for bad overrides
        raise ParameterError(name, str(exc).splitlines()[0] if str(exc) else repr(exc)) from None
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if min_value is not None and value < min_value:
            raise ParameterError(name, f'{value} is below the minimum {min_value}')
        if max_value is not None and value > max_value:
            raise ParameterError(name, f'{value} is above the maximum {max_value}')
    return value


def declare_array(node, name, default, description, kind=float, read_only=False):
    """Declare an array parameter (DOUBLE_ARRAY or STRING_ARRAY) and return it as a list.

    An empty default needs an explicit type, which rclpy cannot infer from ``[]``.
    """
    ptype = {float: Parameter.Type.DOUBLE_ARRAY, str: Parameter.Type.STRING_ARRAY,
             int: Parameter.Type.INTEGER_ARRAY}[kind]
    desc = ParameterDescriptor(description=description, read_only=read_only)
    try:
        if default:
            value = node.declare_parameter(name, list(default), desc).value
        else:
            value = node.declare_parameter(name, ptype, desc).value
    except Exception as exc:
        raise ParameterError(name, str(exc).splitlines()[0] if str(exc) else repr(exc)) from None
    return list(value) if value is not None else []


def diagnostic_status(name, level, message, values, hardware_id=''):
    """Build a DiagnosticStatus; ``values`` is a dict rendered as string KeyValue pairs."""
    return DiagnosticStatus(level=level, name=name, message=message, hardware_id=hardware_id,
                            values=[KeyValue(key=str(k), value=str(v))
                                    for k, v in values.items()])


def station_id_from_namespace(namespace):
    """Station id from a node namespace: '/station_1' -> 'station_1', '/a/b' -> 'a/b'."""
    return namespace.strip('/')
