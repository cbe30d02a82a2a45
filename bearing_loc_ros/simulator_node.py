"""simulator_node: publishes the bearings a station network would produce, from a scenario.

All bearings and truth samples are generated up front by the core
(:func:`bearing_loc_ros.core.simulation.simulate`, deterministic in ``seed``); this node only
releases them when the simulated time reaches their publication time. Simulated time runs at
``time_scale`` × wall time (steady clock) from ``epoch`` and is published on ``/clock``, so
nodes started with ``use_sim_time:=true`` follow it. Topics (relative, so a namespaced
simulator publishes under its namespace):

* ``<target ns>/<station>/bearing`` geometry_msgs/PoseWithCovarianceStamped (DESIGN.md
  bearing message, via ros_conversions.bearing_to_msg), reliable, keep-last 100;
* ``<target ns>/truth`` geometry_msgs/PoseStamped, stamped with the true time;
* ``/clock`` rosgraph_msgs/Clock when ``publish_clock`` is true.

Parameters: ``python -m bearing_loc_ros.core.parameters --markdown simulator_node``; the
truth message is built by ``ros_conversions.truth_to_msg``.
"""

import time

from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock as ClockMsg

from .core.simulation import bearing_topic, load_scenario, NS_PER_S, simulate, truth_topic
from .discovery_probe import NODE_NAME_PREFIX as PROBE_PREFIX
from .ros_common import declare_schema, Finished, main_for, ParameterError
from .ros_conversions import bearing_to_msg, ns_to_time, truth_to_msg
from .scenarios import resolve_scenario, ScenarioNotFoundError

PACKAGE = 'bearing_loc_ros'
BEARING_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                         reliability=ReliabilityPolicy.RELIABLE)
TRUTH_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                       reliability=ReliabilityPolicy.RELIABLE)
CLOCK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                       reliability=ReliabilityPolicy.RELIABLE)
#: Wall period of the publication tick: 10 ms of simulated time (>= 100 Hz simulated /clock)
#: but never shorter than MIN_TICK (then /clock is published on every tick).
SIM_TICK = 0.01
MIN_TICK = 0.004
#: Wall seconds to wait for subscribers to acknowledge the last reliable messages on exit
#: (Fast DDS's reliable writers send heartbeats every 3 s by default).
ACK_TIMEOUT = 4.0


def resolve_scenario_path(path, cwd=None):
    """Scenario file of the ``scenario`` parameter (scenarios.resolve_scenario).

    Raises ParameterError('scenario', ...) if not found.
    """
    try:
        return resolve_scenario(path, cwd)
    except ScenarioNotFoundError as exc:
        raise ParameterError('scenario', exc.problem) from None


#: Wall time the bearing topics' subscriber counts must hold before an early start, ns (as
#: ``bag play`` waits for discovery to settle).
SETTLE_NS = NS_PER_S
#: What the subscribers of the bearing topics allow (:meth:`SimulatorNode._subscriber_state`):
#: keep waiting; release the messages due at the epoch (every topic has a subscriber, some
#: only a fusion node's discovery probe); start.
WAIT, PROBED, READY = 'wait', 'probed', 'ready'
#: Wall seconds the wait may last beyond ``start_delay`` while only probes subscribe to some
#: topic (:data:`PROBED`): the fusion node subscribes a second or two after its probe saw the
#: epoch's bearings (a discovery scan, then SETTLE_NS), and the probe itself takes seconds
#: to start, so the default 5 s often ran out in the middle of that hand-over.
PROBE_GRACE = 10.0


class SimulatorNode(Node):
    """Replays a core Simulation in (scaled) real time over DDS."""

    def __init__(self, **kwargs):
        super().__init__('simulator', **kwargs)
        p = declare_schema(self, 'simulator_node')
        scenario, seed, duration = p['scenario'], p['seed'], p['duration']
        self._time_scale = p['time_scale']
        self._publish_clock = p['publish_clock']
        self._start_delay = p['start_delay']
        self._wait_for_subs = p['wait_for_subscribers']
        self._matched = None             # (subscriber counts, since when) while they hold
        self._exit_when_done = p['exit_when_done']
        path = resolve_scenario_path(scenario)
        self.scenario = load_scenario(path)   # ValueError names the file and key -> exit 1
        self.sim = simulate(self.scenario, duration=duration or None, seed=seed)
        sc = self.scenario

        self._bearing_pubs = {}          # every station/target topic, even if all dropped
        for st in sc.stations:
            for tg in self.sim.targets:
                topic = bearing_topic(tg.namespace, st.id)
                self._bearing_pubs[topic] = self.create_publisher(
                    PoseWithCovarianceStamped, topic, BEARING_QOS)
        self._truth_pubs = {}
        if sc.truth_rate > 0:
            for tg in self.sim.targets:
                topic = truth_topic(tg.namespace)
                self._truth_pubs[topic] = self.create_publisher(PoseStamped, topic, TRUTH_QOS)
        self._clock_pub = (self.create_publisher(ClockMsg, '/clock', CLOCK_QOS)
                           if self._publish_clock else None)

        # one merged queue ordered by publication time (truth first on ties: it is due at the
        # true time, which precedes or equals any bearing's publication)
        self._queue = sorted(
            [(e.publish_ns, 0, k, e) for k, e in enumerate(self.sim.truth)]
            + [(e.publish_ns, 1, k, e) for k, e in enumerate(self.sim.bearings)],
            key=lambda q: q[:3])
        self._next = 0
        self._sent_bearings = 0
        self._sent_truth = 0
        self._created = time.monotonic_ns()
        self._wall0 = None
        self._done = False
        tick = max(MIN_TICK, SIM_TICK / self._time_scale)
        self._timer = self.create_timer(tick, self._tick,
                                        clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(
            f'scenario {path} ({sc.name or "unnamed"}): {len(sc.stations)} stations, '
            f'{len(self.sim.targets)} targets, {self.sim.duration:g} s, seed {seed}, '
            f'{len(self.sim.bearings)} bearings, time_scale {self._time_scale:g}, '
            f'start within {self._start_delay:g} s')
        if self.sim.unobserved():
            self.get_logger().warning(self.sim.unobserved_note())

    # ----------------------------------------------------------------------------------------
    def sim_time_ns(self, wall_ns=None):
        """Simulated time (ns) at steady wall time ``wall_ns``: epoch + (wall − start)·scale."""
        if self._wall0 is None:
            return self.scenario.epoch_ns
        wall_ns = time.monotonic_ns() if wall_ns is None else wall_ns
        return self.scenario.epoch_ns + int((wall_ns - self._wall0) * self._time_scale)

    def _publish_clock_at(self, ns):
        if self._clock_pub is not None:
            self._clock_pub.publish(ClockMsg(clock=ns_to_time(ns)))

    def _tick(self):
        if self._done:
            return
        now = time.monotonic_ns()
        if self._wall0 is None:
            waited = now - self._created
            delay = int(self._start_delay * NS_PER_S)
            state = (self._subscriber_state(now)
                     if waited < delay + int(PROBE_GRACE * NS_PER_S) else READY)
            if waited >= delay and state == WAIT:
                state = READY               # start_delay is over; no hand-over in progress
            if state != READY:
                if state == PROBED:     # clock held at the epoch: what is due there
                    self._release(self.scenario.epoch_ns)
                self._publish_clock_at(self.scenario.epoch_ns)
                return
            self._wall0 = now
            self.get_logger().info(f'simulation started after {waited / NS_PER_S:.2f} s')
        sim_ns = min(self.sim_time_ns(now), self.sim.end_ns)
        self._publish_clock_at(sim_ns)
        self._release(sim_ns)
        if sim_ns >= self.sim.end_ns and self._next >= len(self._queue):
            self._finish()

    def _release(self, sim_ns):
        """Publish every queued message due at or before ``sim_ns`` (ns), in order."""
        frame = self.scenario.frame_id
        q = self._queue
        while self._next < len(q) and q[self._next][0] <= sim_ns:
            _, kind, _, ev = q[self._next]
            self._next += 1
            if kind == 0:
                self._truth_pubs[ev.topic].publish(
                    truth_to_msg(ev.position, ev.stamp_ns, frame))
                self._sent_truth += 1
            else:
                self._bearing_pubs[ev.topic].publish(bearing_to_msg(ev.bearing))
                self._sent_bearings += 1

    def _subscriber_state(self, now):
        """:data:`READY` when waiting may end early: every bearing topic has a matched
        subscriber that is not a fusion node's discovery probe and the counts have not
        changed for SETTLE_NS (``now``, monotonic ns). Several nodes subscribe (a fusion
        node, a view): the first match must not start the run while the others are still
        being discovered, or they lose its first seconds. A probe (node
        ``discovery_probe_<pid>``) is a short-lived child that subscribes only until it has
        seen a valid bearing, and its fusion node subscribes only then: when every topic has
        a subscriber but some only probes (:data:`PROBED`) the messages due at the epoch are
        released with the clock held there, so the fusion node can join before the clock
        runs. :data:`WAIT` otherwise (and always without ``wait_for_subscribers``)."""
        if not self._wait_for_subs:
            return WAIT
        pubs = list(self._bearing_pubs.values())
        counts = tuple(p.get_subscription_count() for p in pubs)
        if not all(counts):
            self._matched = None
            return WAIT
        real = tuple(sum(not e.node_name.startswith(PROBE_PREFIX)
                         for e in self.get_subscriptions_info_by_topic(p.topic_name))
                     for p in pubs)
        if self._matched is None or self._matched[0] != (counts, real):
            self._matched = ((counts, real), now)
        if now - self._matched[1] < SETTLE_NS:
            return WAIT
        return READY if all(real) else PROBED

    def _finish(self):
        self._done = True
        self._timer.cancel()
        n_sched = sum(len(s.t) for s in self.sim.streams)
        self.get_logger().info(
            f'simulation done: {self._sent_bearings} bearings ({n_sched - self._sent_bearings}'
            f' dropped), {self._sent_truth} truth samples, sim time '
            f'{(self.sim.end_ns - self.scenario.epoch_ns) / NS_PER_S:g} s')
        if not self._exit_when_done:
            return
        pubs = list(self._bearing_pubs.values()) + list(self._truth_pubs.values())
        deadline = time.monotonic() + ACK_TIMEOUT
        for p in pubs:
            left = deadline - time.monotonic()
            if left <= 0 or not p.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
                self.get_logger().warning('not every subscriber acknowledged the last messages '
                                          f'within {ACK_TIMEOUT:g} s')
                break
        raise Finished('simulation done')


main = main_for(SimulatorNode)


if __name__ == '__main__':
    main()
