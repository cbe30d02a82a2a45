"""Small rclpy utilities shared by every node: main runner, typed parameters, diagnostics.

No numerics here (those live in ``bearing_loc_ros.core``).
"""

import gc
import sys
import traceback

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

OK = DiagnosticStatus.OK
WARN = DiagnosticStatus.WARN
ERROR = DiagnosticStatus.ERROR
STALE = DiagnosticStatus.STALE


class ParameterError(ValueError):
    """A parameter value is invalid; the node exits with code 1 and names the parameter."""

    def __init__(self, name, problem):
        super().__init__(f"parameter '{name}': {problem}")
        self.name = name


def core_parameter_error(exc, default_name):
    """A core ValueError ``'<field>: <problem>'`` (or ``'options.<field>: ...'``, an
    estimator option) as a ParameterError naming ``<field>``; a message without a field
    names ``default_name``."""
    text = str(exc)
    head, _, rest = text.partition(':')
    name = head.replace('options.', '') if rest and ' ' not in head else default_name
    return ParameterError(name, rest.strip() if rest else text)


#: Exit code of a node stopped by an unexpected exception raised while it was running.
INTERNAL_ERROR = 70


class Finished(Exception):
    """Raised by a callback to end its node normally: :func:`run_node` returns exit code 0.

    A node that is done (the simulator with ``exit_when_done``) ends the spin this way
    instead of shutting its context down from inside the callback, which can leave rclpy's
    executor waiting for ever (ros2/rclpy issues 944 and 1646).
    """


def run_node(node_factory, args=None, executor=None):
    """Run a node the ros2/demos way; return the process exit code.

    ``executor``: the executor class to spin with (built after ``rclpy.init``, shut down
    after the node is destroyed), or None for rclpy's global executor.

    Start-up: ``node_factory()`` builds the node (parameters, configuration); a
    :class:`ParameterError` (or ValueError) raised there is a configuration error, printed
    as one line ``error: <message>`` on stderr, exit code 1 (bad configuration fails loudly
    and early, like joy_teleop). Running: an exception escaping a callback during the spin
    is not a configuration error: it is printed with its traceback as ``internal error``,
    and the node exits with :data:`INTERNAL_ERROR` (70, EX_SOFTWARE). Ctrl-C, external
    shutdown and :class:`Finished` end the spin cleanly with exit code 0.
    """
    try:
        rclpy.init(args=args)
    except Exception as exc:  # rcl rejects unparsable --ros-args with RCLError
        print(f'error: invalid command line: {str(exc).splitlines()[0]}', file=sys.stderr,
              flush=True)
        return 1
    node = None
    spinner = None
    code = 0
    try:
        try:
            node = node_factory()
        except ValueError as exc:
            print(f'error: {exc}', file=sys.stderr, flush=True)
            code = 1
        if node is not None:
            spinner = executor() if executor is not None else None
            rclpy.spin(node, spinner)
    except (KeyboardInterrupt, ExternalShutdownException, Finished):
        pass
    except Exception:  # noqa: B902 - a bug in a callback: report it as one, not as config
        print('internal error: unexpected exception in a running node (not a configuration '
              'problem):\n' + traceback.format_exc(), file=sys.stderr, flush=True)
        code = INTERNAL_ERROR
    finally:
        if node is not None:
            node.destroy_node()
        if spinner is not None:
            spinner.shutdown()
        if code == 1:
            # The factory failed inside the node's constructor: that half-built node (held
            # in reference cycles) is collected now, while the context is alive, rather than
            # during interpreter exit after rclpy's shutdown (one start-up error run in CI
            # printed its error and then did not exit within 30 s).
            gc.collect()
        rclpy.try_shutdown()
    return code


def main_for(node_cls, executor=None):
    """Return a console-script ``main(args=None)`` that runs ``node_cls`` via run_node
    (spun by an ``executor`` class, default rclpy's global executor)."""
    def main(args=None):
        sys.exit(run_node(node_cls, args, executor))
    return main


def _descriptor(p, description=None):
    """ParameterDescriptor of schema Param ``p`` (description with unit, range, read_only,
    allowed strings as additional_constraints)."""
    desc = ParameterDescriptor(
        description=description or (p.description + (f' [{p.unit}]' if p.unit else '')),
        read_only=p.read_only,
        additional_constraints=('one of: ' + ', '.join(p.choices)) if p.choices else '')
    if p.min is not None or p.max is not None:
        if p.type == 'integer':
            desc.integer_range = [IntegerRange(
                from_value=int(-2 ** 63 if p.min is None else p.min),
                to_value=int(2 ** 63 - 1 if p.max is None else p.max), step=0)]
        elif p.type == 'double':
            desc.floating_point_range = [FloatingPointRange(
                from_value=float(-sys.float_info.max if p.min is None else p.min),
                to_value=float(sys.float_info.max if p.max is None else p.max), step=0.0)]
    return desc


_PTYPE = {'bool': Parameter.Type.BOOL, 'integer': Parameter.Type.INTEGER,
          'double': Parameter.Type.DOUBLE, 'string': Parameter.Type.STRING,
          'double_array': Parameter.Type.DOUBLE_ARRAY,
          'string_array': Parameter.Type.STRING_ARRAY}


def _as_double(param):
    """An INTEGER (array) override of a double (array) parameter as DOUBLE (array), so
    ``position:=[1,2,3]`` or ``rate:=10`` is accepted; any other Parameter unchanged."""
    if param.type_ == Parameter.Type.INTEGER:
        return Parameter(param.name, Parameter.Type.DOUBLE, float(param.value))
    if param.type_ == Parameter.Type.INTEGER_ARRAY:
        return Parameter(param.name, Parameter.Type.DOUBLE_ARRAY,
                         [float(v) for v in param.value])
    return param


def _declare_one(node, p, name=None, description=None):
    """Declare schema Param ``p`` (under ``name``, default p.name) and return its value
    (None for an unset parameter declared without a default)."""
    name = name or p.name
    ptype = _PTYPE[p.type]
    overrides = getattr(node, '_parameter_overrides', {})
    if ptype in (Parameter.Type.DOUBLE, Parameter.Type.DOUBLE_ARRAY) and name in overrides:
        overrides[name] = _as_double(overrides[name])
    desc = _descriptor(p, description)
    try:
        if name != p.name or (isinstance(p.default, list) and not p.default):
            value = node.declare_parameter(name, ptype, desc).value
        else:
            value = node.declare_parameter(name, p.default, desc).value
    except Exception as exc:  # rclpy raises several types for bad overrides
        raise ParameterError(name, str(exc).splitlines()[0] if str(exc) else repr(exc)) from None
    return value


def declare_schema(node, node_name):
    """Declare every parameter of ``node_name``'s schema (core.parameters) on ``node``.

    Returns {name: value}, each value checked against the schema (type, range, allowed
    strings; ParameterError naming the parameter). Integers given for double parameters
    (``rate:=10``, ``position:=[1,2,3]``) are accepted as doubles. A deprecated name
    (Param.deprecated) is declared too; when set, its value is used for the current name
    and a deprecation warning is logged once (ParameterError when both names are set).
    Run-time sets of double parameters convert integers the same way. Names given for the
    node (command line, parameter file) that it does not have are logged in one warning,
    with the closest parameter name (ROS 2 itself ignores them without a word).
    """
    from .core import parameters as schema
    params = schema.schema(node_name)
    overrides = getattr(node, '_parameter_overrides', {})
    # Before the checks, so that a misspelt name is named also when another value stops
    # the node.
    known = {p.name for p in params} | set(schema.renamed(node_name))
    text = schema.unknown_message(node_name, [
        n for n in overrides if n not in known and not schema.ros_builtin(n)])
    if text is not None:
        node.get_logger().warning(text)
    values = {}
    for p in params:
        value = _declare_one(node, p)
        for old in p.deprecated:
            old_value = _declare_one(node, p, old, f'deprecated: use {p.name}')
            if old_value is None:
                continue
            if p.name in overrides:
                raise ParameterError(old, f'deprecated name of {p.name}, and both are set')
            node.get_logger().warning(
                f"parameter '{old}' is deprecated: use '{p.name}' (the old name will be "
                'removed in the next release)')
            value = old_value
        if value is None:
            value = [] if isinstance(p.default, list) else p.default
        try:
            values[p.name] = p.check(list(value) if p.type.endswith('_array') else value)
        except ValueError as exc:
            raise ParameterError(p.name, str(exc).partition(': ')[2]) from None
    doubles = {p.name for p in params if p.type in ('double', 'double_array')}
    doubles |= {old for p in params if p.type in ('double', 'double_array')
                for old in p.deprecated}
    node.add_pre_set_parameters_callback(
        lambda ps: [_as_double(x) if x.name in doubles else x for x in ps])
    return values


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


def keep_last_qos(depth, reliability='reliable', latched=False):
    """Keep-last QoS of ``depth``: ``reliability`` 'reliable' or 'best_effort'; ``latched``
    = transient local (late subscribers get the last message), else volatile."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=int(depth),
        reliability=(ReliabilityPolicy.BEST_EFFORT if reliability == 'best_effort'
                     else ReliabilityPolicy.RELIABLE),
        durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                    else DurabilityPolicy.VOLATILE))


def topics_under_namespace(node, suffix, msg_type, name_re):
    """{relative name: topic} of the topics ``<node namespace>/<relative name><suffix>`` of
    type ``msg_type`` (e.g. 'geometry_msgs/msg/PoseWithCovarianceStamped') whose relative
    name matches the regular expression ``name_re`` (graph query, no subscription)."""
    ns = node.get_namespace()
    prefix = ns if ns.endswith('/') else ns + '/'
    out = {}
    for name, types in node.get_topic_names_and_types():
        if name.startswith(prefix) and name.endswith(suffix) and msg_type in types:
            rel = name[len(prefix):len(name) - len(suffix)]
            if name_re.match(rel):
                out[rel] = name
    return out


def log_events(logger, events):
    """Log core events, (level, text) pairs: 'warn' as a warning, any other as info."""
    for level, text in events:
        # rclpy binds a severity to each call site: one call per severity.
        if level == 'warn':
            logger.warning(text)
        else:
            logger.info(text)
