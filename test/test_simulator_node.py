"""simulator_node over DDS: bearings honour the message contract and equal the core's, truth and
/clock arrive, same seed gives the same bearings, bad parameters / scenarios exit 1."""
import contextlib
import os

from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
import yaml

from bearing_loc_ros.core.simulation import load_scenario, simulate
from bearing_loc_ros.ros_common import ParameterError
from bearing_loc_ros.ros_conversions import bearing_from_msg, time_to_ns
from bearing_loc_ros.simulator_node import resolve_scenario_path
from ros_helpers import REPO, spin_until, start_node

MODULE = 'bearing_loc_ros.simulator_node'
SCENARIO = 'config/scenarios/static3.yaml'
STATIONS = ('station_1', 'station_2', 'station_3')
SEED = 3
QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)


@contextlib.contextmanager
def _listening_node(name):
    """(node, executor) of a node in a context of its own, shut down on exit."""
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node(name, context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    try:
        yield node, ex
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


@pytest.fixture(scope='module')
def listener():
    with _listening_node('simulator_test_listener') as pair:
        yield pair


def _subscribe(node, msg_type, topic, box):
    box[topic] = []
    node.create_subscription(msg_type, topic, box[topic].append, QOS)


def test_node_publishes_core_bearings_truth_and_clock(listener):
    node, ex = listener
    got = {}
    for ns in ('', '/run_b'):
        for st in STATIONS:
            _subscribe(node, PoseWithCovarianceStamped, f'{ns}/{st}/bearing', got)
    _subscribe(node, PoseStamped, '/truth', got)
    _subscribe(node, Clock, '/clock', got)
    common = ['-p', f'scenario:={SCENARIO}', '-p', f'seed:={SEED}', '-p', 'time_scale:=10.0',
              '-p', 'start_delay:=15.0']   # starts once this listener is matched
    # two runs with the same seed at once: one in the root namespace (with /clock), one in
    # /run_b without /clock; both must publish exactly the core's bearings
    with start_node(MODULE, common) as a, \
            start_node(MODULE, common + ['-p', 'publish_clock:=false', '-r',
                                         '__ns:=/run_b']) as b:
        spin_until(ex, lambda: a.proc.poll() is not None and b.proc.poll() is not None, 30.0)
        spin_until(ex, lambda: False, 0.3)                     # drain the last messages
        assert a.proc.poll() == 0, a.output()                  # exit_when_done, exit code 0
        assert b.proc.poll() == 0, b.output()

    sim = simulate(load_scenario(os.path.join(REPO, SCENARIO)), seed=SEED)
    assert sum(len(got[f'/{st}/bearing']) for st in STATIONS) == len(sim.bearings) > 20
    for st in STATIONS:
        expected = [e.bearing for e in sim.bearings if e.bearing.station == st]
        for ns in ('', '/run_b'):
            received = [bearing_from_msg(m, st, expected_frame='map')
                        for m in got[f'{ns}/{st}/bearing']]     # the contract check
            assert len(received) == len(expected), (ns, st)
            for r, e in zip(received, expected):
                assert r.stamp_ns == e.stamp_ns
                assert np.allclose(r.position, e.position)
                assert r.azimuth == pytest.approx(e.azimuth, abs=1e-9)
                assert r.sigma_azimuth == pytest.approx(e.sigma_azimuth, rel=1e-12)
                if st == 'station_3':                           # 1D station
                    assert np.isnan(r.elevation) and np.isnan(r.sigma_elevation)
                else:
                    assert r.elevation == pytest.approx(e.elevation, abs=1e-9)

    truth = got['/truth']
    assert [time_to_ns(m.header.stamp) for m in truth] == [e.stamp_ns for e in sim.truth]
    assert all(m.header.frame_id == 'map' for m in truth)
    assert np.allclose([[m.pose.position.x, m.pose.position.y, m.pose.position.z]
                        for m in truth], [1000.0, 1500.0, 300.0])

    clock = [time_to_ns(m.clock) for m in got['/clock']]
    assert len(clock) > 10
    assert clock == sorted(clock)
    assert clock[0] >= sim.scenario.epoch_ns and clock[-1] == sim.end_ns


def test_bad_parameters_and_scenarios_exit_1(tmp_path):
    with open(os.path.join(REPO, SCENARIO), encoding='utf-8') as f:
        bad = yaml.safe_load(f)
    bad['stations'][0]['rate'] = -5.0
    bad_path = tmp_path / 'bad.yaml'
    bad_path.write_text(yaml.safe_dump(bad))
    ok = ['-p', f'scenario:={SCENARIO}']
    cases = [
        ([], "parameter 'scenario': required"),
        (['-p', 'scenario:=config/scenarios/nope.yaml'], "parameter 'scenario': file not found"),
        (['-p', f'scenario:={bad_path}'], f'{bad_path}: stations[0].rate: must be > 0'),
        (ok + ['-p', 'time_scale:=-1.0'], "parameter 'time_scale'"),
        (ok + ['-p', 'seed:=-2'], "parameter 'seed'"),
        (ok + ['-p', 'duration:=1e8'], "parameter 'duration'"),   # beyond MAX_TIME
    ]
    procs = [(start_node(MODULE, args), expect) for args, expect in cases]
    for p, expect in procs:
        with p:
            code = p.wait(30.0)
            out = p.output()
            assert code == 1, out
            assert f'error: {expect}' in out, out


def test_duration_parameter_has_the_scenario_bound():
    from bearing_loc_ros.core.parameters import param
    from bearing_loc_ros.core.scenario_loader import MAX_TIME
    assert param('simulator_node', 'duration').max == MAX_TIME


def test_resolve_scenario_path_cwd_then_share(tmp_path, monkeypatch):
    assert resolve_scenario_path(SCENARIO, cwd=REPO) == os.path.join(REPO, SCENARIO)
    prefix = tmp_path / 'prefix'
    (prefix / 'share/ament_index/resource_index/packages').mkdir(parents=True)
    (prefix / 'share/ament_index/resource_index/packages/bearing_loc_ros').write_text('')
    (prefix / 'share/bearing_loc_ros/config/scenarios').mkdir(parents=True)
    target = prefix / 'share/bearing_loc_ros/config/scenarios/x.yaml'
    target.write_text('duration: 1.0\n')
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(prefix))
    elsewhere = str(tmp_path / 'cwd')
    assert resolve_scenario_path('config/scenarios/x.yaml', cwd=elsewhere) == str(target)
    assert resolve_scenario_path('x.yaml', cwd=elsewhere) == str(target)
    with pytest.raises(ParameterError, match="parameter 'scenario': file not found"):
        resolve_scenario_path('y.yaml', cwd=elsewhere)


def test_an_early_start_waits_for_the_subscriber_counts_to_settle():
    # The run starts before start_delay only once every bearing topic has a subscriber and
    # the counts held for 1 s: with a fusion node and a view both subscribing, the first
    # match used to start a 10x run while the other was still being discovered (it then
    # missed the first seconds: 30 of 60 epochs).
    from types import SimpleNamespace
    from bearing_loc_ros.simulator_node import READY, SETTLE_NS, SimulatorNode, WAIT
    counts = {'a': 0, 'b': 0}
    pubs = {t: SimpleNamespace(get_subscription_count=lambda t=t: counts[t], topic_name=t)
            for t in counts}
    info = {'a': [], 'b': []}
    node = SimpleNamespace(_wait_for_subs=True, _matched=None, _bearing_pubs=pubs,
                           get_subscriptions_info_by_topic=lambda t: info[t])
    state = SimulatorNode._subscriber_state
    assert state(node, 0) == WAIT

    def subscribe(topic, name):
        counts[topic] += 1
        info[topic].append(SimpleNamespace(node_name=name))

    subscribe('a', 'fusion')
    subscribe('b', 'fusion')                             # the first subscriber matched
    assert state(node, 10) == WAIT and state(node, 10 + SETTLE_NS - 1) == WAIT
    subscribe('a', 'view')                               # another node matches: wait again
    assert state(node, 10 + SETTLE_NS) == WAIT
    assert state(node, 10 + 2 * SETTLE_NS) == READY
    node._wait_for_subs = False
    assert state(node, 10 + 3 * SETTLE_NS) == WAIT


def test_a_discovery_probe_is_not_the_subscriber_waited_for():
    # fusion_node discover:=true first watches a new topic in a short-lived child process
    # (node discovery_probe_<pid>) and subscribes itself only once that child has seen a
    # valid bearing. The simulator took the probe for the subscriber and started: the
    # fusion node joined ~1 s of wall time later and lost the first 8-10 s of a 10x run
    # (45 of 50 fixes). Now only probes on a topic release what is due at the epoch, with
    # the clock held, and the run starts once the fusion node itself has subscribed.
    from types import SimpleNamespace
    from bearing_loc_ros.discovery_probe import NODE_NAME_PREFIX
    from bearing_loc_ros.simulator_node import PROBED, READY, SETTLE_NS, SimulatorNode, WAIT
    counts = {'a': 0, 'b': 0}
    info = {'a': [], 'b': []}
    pubs = {t: SimpleNamespace(get_subscription_count=lambda t=t: counts[t], topic_name=t)
            for t in counts}
    node = SimpleNamespace(_wait_for_subs=True, _matched=None, _bearing_pubs=pubs,
                           get_subscriptions_info_by_topic=lambda t: info[t])
    state = SimulatorNode._subscriber_state
    probe = f'{NODE_NAME_PREFIX}4242'
    for t in counts:
        counts[t] += 1
        info[t].append(SimpleNamespace(node_name=probe))
    assert state(node, 0) == WAIT
    assert state(node, SETTLE_NS) == PROBED               # not READY: release the epoch only
    counts['a'] += 1
    info['a'].append(SimpleNamespace(node_name='fusion'))   # the fusion node on one topic
    assert state(node, 2 * SETTLE_NS) == WAIT
    assert state(node, 3 * SETTLE_NS) == PROBED
    counts['b'] += 1
    info['b'].append(SimpleNamespace(node_name='fusion'))
    assert state(node, 3 * SETTLE_NS + 1) == WAIT
    assert state(node, 4 * SETTLE_NS + 1) == READY


def _log_time(output, text):
    """Wall time (s) of the first log line of ``output`` containing ``text``, or None."""
    for line in output.splitlines():
        if text in line:
            return float(line.split('[')[2].split(']')[0])
    return None


def test_the_readme_pair_starts_once_the_fusion_node_itself_subscribed():
    # README: simulator_node + fusion_node discover:=true. The fusion node's discovery probe
    # subscribed first, the simulator started, and the fusion node, which subscribes only
    # after its probe saw a valid bearing, lost the first 8-10 s of the 10x run. Causal
    # check (no timing): the run starts after the fusion node has subscribed to every
    # station (before, it could not: the node subscribes after a bearing), and its first
    # fix is at most one epoch after the epoch (t = 0 s) the probe consumed.
    from geometry_msgs.msg import PoseWithCovarianceStamped as Fix
    fixes = []
    # in a namespace of its own: the module's listener subscribes to /station_<k>/bearing
    ns = ['-r', '__ns:=/readme_pair']
    with _listening_node('readme_pair_listener') as (node, ex):
        sub = node.create_subscription(Fix, '/readme_pair/fix',
                                       lambda m: fixes.append(time_to_ns(m.header.stamp)), QOS)
        with start_node('bearing_loc_ros.fusion_node', ['-p', 'use_sim_time:=true', '-p',
                                                        'discover:=true', *ns]) as fusion:
            assert spin_until(ex, lambda: sub.get_publisher_count() > 0, 60.0)
            with start_node(MODULE, ['-p', 'scenario:=config/scenarios/seed000.yaml', '-p',
                                     'time_scale:=10.0', '-p', 'start_delay:=60.0',
                                     *ns]) as sim:
                spin_until(ex, lambda: sim.proc.poll() is not None, 120.0)
                spin_until(ex, lambda: False, 1.0)
                assert sim.proc.poll() == 0, sim.output()
            started = _log_time(sim.output(), 'simulation started')
            # the fusion node logs 'discovered station' when it subscribes itself
            subscribed = [_log_time(fusion.output(), f'discovered station station_{k} ')
                          for k in (1, 2, 3)]
    assert None not in subscribed and started is not None, (sim.output(), fusion.output())
    assert started > max(subscribed)
    epoch = load_scenario(os.path.join(REPO, 'config/scenarios/seed000.yaml')).epoch_ns
    assert fixes and min(fixes) <= epoch + 4 * 10 ** 9, fixes[:3]
