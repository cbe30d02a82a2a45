"""Several channels in one fusion process: one complete fusion node per channel (emitter).

A receiver tuned to several frequencies reports several emitters; its station node
publishes each channel's bearings on ``/<channel>/<station>/bearing`` (``kraken.channels``,
the simulator's target namespace scheme). With the fusion node parameter
``channels: [a, b]`` the node started (``/<ns>/fusion``) only hosts, in the same process
and executor, one fusion node per channel, ``/<ns>/<channel>/fusion``, with the host's
parameter values (``channels`` emptied). Each is the ordinary fusion node in the channel's
namespace, so channel ``c``:

* subscribes to ``<ns>/c/<station>/bearing`` for each station of ``stations`` (and, with
  ``discover``, to the bearing topics found under ``<ns>/c``);
* publishes ``<ns>/c/fix``, ``<ns>/c/fix/navsat`` (with a ``geodetic_origin``),
  ``<ns>/c/markers``, ``<ns>/c/accuracy_map`` (and ``<ns>/c/track`` in TMA mode);
* reports on ``/diagnostics`` as ``<ns>/c/fusion: fusion`` (overall) and
  ``<ns>/c/fusion: station <id>``;
* takes run-time parameter changes on ``<ns>/c/fusion``.

The channel nodes are made without the process's global ROS arguments (their namespace,
parameters and ``use_sim_time`` come from the host), so a ``/**`` parameter file or a
``__ns`` remap given to the host cannot re-enter them. Empty ``channels`` keeps the single
pipeline. ``bearing_loc bag process --namespace <channel>`` runs the same pipeline offline
on one channel of a bag.
"""

import re

from rclpy.clock import Clock, ClockType
from rclpy.parameter import Parameter

#: A channel name: ROS name tokens separated by '/' (a topic namespace).
CHANNEL_RE = re.compile(r'^[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$')


def check_channels(names):
    """The channel names as a list; ValueError('channels: ...') for an invalid or repeated
    name."""
    names = list(names)
    for name in names:
        if not CHANNEL_RE.match(name):
            raise ValueError(f'channels: {name!r} is not a valid channel name (ROS name '
                             'tokens separated by /)')
    if len(set(names)) != len(names):
        raise ValueError(f'channels: repeated name in {names}')
    return names


class ChannelHost:
    """The channel fusion nodes of a host node (module docstring).

    ``make_node(namespace, overrides)`` builds one fusion node; the nodes join the host's
    executor on the host's first timer callback (the executor is known only then).
    """

    def __init__(self, host, channels, values, make_node):
        names = check_channels(channels)
        base = host.get_namespace().rstrip('/')
        # every value but the empty arrays (their default; rclpy cannot type an empty list)
        overrides = [Parameter(k, value=v) for k, v in values.items()
                     if k != 'channels' and not (isinstance(v, list) and not v)]
        overrides.append(Parameter('use_sim_time',
                                   value=host.get_parameter('use_sim_time').value))
        self.host = host
        self.nodes = {}
        for name in names:
            self.nodes[name] = make_node(f'{base}/{name}', overrides)
        # A steady-clock timer: on the host's ROS clock it would not fire under use_sim_time
        # until /clock runs, and the channel nodes would neither fuse nor answer until then.
        self._timer = host.create_timer(0.01, self._join,
                                        clock=Clock(clock_type=ClockType.STEADY_TIME))
        host.get_logger().info('channels: ' + ', '.join(
            n.get_fully_qualified_name() for n in self.nodes.values()))

    def _join(self):
        self._timer.cancel()
        for node in self.nodes.values():
            self.host.executor.add_node(node)

    def destroy(self):
        """Remove the channel nodes from the executor and destroy them."""
        executor = self.host.executor
        for node in self.nodes.values():
            if executor is not None:
                executor.remove_node(node)
            node.destroy_node()
        self.nodes = {}
