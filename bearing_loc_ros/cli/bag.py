"""``bearing_loc bag``: rosbag2 datasets without the ROS 2 CLI (README "Recorded data").

Sub-commands:

* ``simulate``: run the simulator core on a scenario and write a rosbag2 bag (MCAP or
  sqlite3) with every station's ``bearing``, the targets' ``truth`` and ``/clock``, exactly
  the topics, types, QoS and timing simulator_node publishes, much faster than real time.
* ``play``: publish a bag's messages on their topics, paced by bag time (``--rate``,
  ``--loop``), with ``/clock`` (like ``ros2 bag play --clock``), for machines without rosbag2.
* ``process``: run the fusion node's alignment + estimation core offline over a bag and write
  the fixes as a bag (``fix`` topic) and CSV; prints error statistics when truth is present.
* ``info``: summary of a bag (like ``ros2 bag info``).
"""

import math
import os
import signal
import sys
import threading
import time

from . import InputError

NS_PER_S = 1_000_000_000
UPPER_TRIANGLE = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def add_arguments(parser):
    """Register the ``bag`` sub-commands."""
    sub = parser.add_subparsers(dest='bag_command', metavar='COMMAND')
    sub.required = True

    p = sub.add_parser('simulate', help='write a simulated rosbag2 bag from a scenario')
    p.add_argument('--scenario', required=True, help='scenario YAML (README "Simulator")')
    p.add_argument('--duration', type=float, default=0.0,
                   help="simulated seconds (default 0: the scenario's duration)")
    p.add_argument('--seed', type=int, default=0, help='simulator seed (default 0)')
    p.add_argument('--out', required=True, help='bag directory to create (must not exist)')
    p.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap',
                   help='storage plugin (default mcap, the rosbag2 default)')
    p.add_argument('--clock-rate', type=float, default=100.0,
                   help='/clock messages per simulated second (default 100, as '
                        'simulator_node; 0: no /clock topic)')

    p = sub.add_parser('play', help="publish a bag's messages with /clock (rclpy)")
    p.add_argument('bag', help='bag directory')
    p.add_argument('--rate', type=float, default=1.0, help='playback speed factor (default 1)')
    p.add_argument('--loop', action='store_true', help='play again from the start when done')
    p.add_argument('--clock-rate', type=float, default=0.0,
                   help='generate /clock at this many Hz of wall time from the playback time '
                        "(ignoring the bag's own /clock); default 0: replay the bag's /clock "
                        'topic, or generate at 100 Hz if it has none')
    p.add_argument('--delay', type=float, default=0.0,
                   help='wall seconds to wait before playing (default 0)')
    p.add_argument('--wait-for-subscribers', type=float, default=0.0, metavar='SECONDS',
                   help='wait up to SECONDS until every topic has a matched subscriber')
    p.add_argument('--topics', nargs='+', default=None, help='play only these topics')
    p.add_argument('--quiet', action='store_true', help='no progress output')

    p = sub.add_parser('process', help='offline fusion over a bag -> fixes bag + CSV')
    p.add_argument('bag', help='input bag directory')
    p.add_argument('--estimator', default=None,
                   help="estimator name (default: the fusion node's, "
                        'core.estimators.DEFAULT_ESTIMATOR)')
    p.add_argument('--params-file', default=None,
                   help="the fusion node's parameters YAML (as given to --ros-args "
                        '--params-file), so the offline run uses the same settings')
    p.add_argument('-p', '--param', action='append', default=[], metavar='NAME=VALUE',
                   help='one fusion node parameter (YAML value), e.g. -p trigger=timer; '
                        'overrides --params-file')
    p.add_argument('--namespace', default='',
                   help='target namespace of the bearing topics (<ns>/<station>/bearing, '
                        '<ns>/truth); default: the root namespace')
    p.add_argument('--out', required=True,
                   help='output name: bag directory OUT/ (fix topic) and OUT.csv')
    p.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap')
    p.add_argument('--fix-topic', default='fix',
                   help='topic of the fixes, relative to the namespace (default fix)')

    p = sub.add_parser('info', help='print a summary of a bag')
    p.add_argument('bag', help='bag directory')


def run(args):
    """Dispatch to the sub-command."""
    return {'simulate': run_simulate, 'play': run_play, 'process': run_process,
            'info': run_info}[args.bag_command](args)


# ----------------------------------------------------------------------------------- helpers

def resolve_scenario(path):
    """Scenario file: as given (absolute or cwd-relative), else in config/scenarios/.

    Looks in the source tree's config/scenarios and, when installed, the package share
    directory (``<share>/config/scenarios``). Raises InputError naming the file.
    """
    if os.path.isfile(path):
        return path
    here = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    cands = [os.path.join(here, path), os.path.join(here, 'config', 'scenarios', path)]
    try:
        from ament_index_python.packages import get_package_share_directory
        share = get_package_share_directory('bearing_loc_ros')
        cands += [os.path.join(share, path), os.path.join(share, 'config', 'scenarios', path)]
    except Exception:
        pass
    for c in cands:
        if os.path.isfile(c):
            return c
    raise InputError(f'scenario: file not found: {path!r}')


def _abs(topic):
    return topic if topic.startswith('/') else '/' + topic


def _fmt_duration(ns):
    return f'{ns / NS_PER_S:.3f} s'


# ---------------------------------------------------------------------------------- simulate

def simulate_bag(scenario, out, duration=None, seed=0, storage='mcap', clock_rate=100.0):
    """Write the bag of ``simulate(scenario, duration, seed)``; return a summary dict.

    Topics, types and offered QoS are those of simulator_node (root namespace):
    ``/<target ns>/<station>/bearing`` PoseWithCovarianceStamped (reliable, keep-last 100;
    one topic per station and target, even if every bearing was dropped),
    ``/<target ns>/truth`` PoseStamped (when the scenario's truth_rate > 0) and ``/clock``
    (every 1/clock_rate simulated seconds from the epoch up to the end of the run, and at
    the end). Bag (log) time of a message = its simulated publication time (bearings:
    observation + latency; truth: the true time), so the bag is what ``ros2 bag record``
    would have captured from simulator_node with no transport delay. Ties are written
    truth, bearings, then /clock, so a clock tick never precedes data of the same instant.
    """
    from .. import bagio
    from ..core.simulation import bearing_topic, simulate, truth_topic
    if not (clock_rate >= 0 and math.isfinite(clock_rate)):
        raise InputError(f'clock_rate: must be >= 0 (got {clock_rate})')
    sim = simulate(scenario, duration=duration or None, seed=seed)
    custom = {'generator': 'bearing_loc bag simulate', 'scenario': scenario.source,
              'scenario_name': scenario.name, 'seed': str(seed),
              'duration': repr(sim.duration)}
    events = []
    for k, ev in enumerate(sim.truth):
        events.append((ev.publish_ns, 0, k, _abs(ev.topic),
                       bagio.truth_message(ev.position, ev.stamp_ns, scenario.frame_id)))
    for k, ev in enumerate(sim.bearings):
        events.append((ev.publish_ns, 1, k, _abs(ev.topic), bagio.bearing_message(ev.bearing)))
    if clock_rate > 0:
        period = int(round(NS_PER_S / clock_rate))
        if period <= 0:
            raise InputError(f'clock_rate: too high ({clock_rate} Hz)')
        ticks = list(range(scenario.epoch_ns, sim.end_ns + 1, period))
        if ticks[-1] != sim.end_ns:
            ticks.append(sim.end_ns)
        events.extend((t, 2, k, bagio.CLOCK_TOPIC, None) for k, t in enumerate(ticks))
    events.sort(key=lambda e: e[:3])
    with bagio.BagWriter(out, storage=storage, custom_data=custom) as bag:
        for tg in sim.targets:
            if scenario.truth_rate > 0:
                bag.add_topic(_abs(truth_topic(tg.namespace)), bagio.POSE_STAMPED,
                              bagio.SIM_TRUTH_QOS)
            for st in scenario.stations:
                bag.add_topic(_abs(bearing_topic(tg.namespace, st.id)),
                              bagio.POSE_COV_STAMPED, bagio.SIM_BEARING_QOS)
        if clock_rate > 0:
            bag.add_topic(bagio.CLOCK_TOPIC, bagio.CLOCK, bagio.CLOCK_QOS)
        for t, kind, _, topic, msg in events:
            bag.write(topic, t, bagio.clock_message(t) if kind == 2 else msg)
    return {'bearings': len(sim.bearings), 'truth': len(sim.truth),
            'clock': sum(1 for e in events if e[1] == 2), 'start_ns': scenario.epoch_ns,
            'end_ns': sim.end_ns, 'duration': sim.duration}


def check_out_parent(out):
    """InputError naming --out unless the nearest existing ancestor of ``out`` is a writable
    directory (the bag writer creates the missing ones)."""
    parent = os.path.dirname(os.path.abspath(out))
    while not os.path.exists(parent):
        parent = os.path.dirname(parent)
    if not os.path.isdir(parent):
        raise InputError(f'out: cannot create {out!r}: {parent!r} is not a directory')
    if not os.access(parent, os.W_OK):
        raise InputError(f'out: cannot create {out!r}: {parent!r} is not writable')


def run_simulate(args):
    """``bag simulate``."""
    from ..core.simulation import load_scenario
    scenario = load_scenario(resolve_scenario(args.scenario))
    if args.duration < 0 or not math.isfinite(args.duration):
        raise InputError(f'duration: must be >= 0 s (got {args.duration})')
    if args.seed < 0:
        raise InputError(f'seed: must be >= 0 (got {args.seed})')
    if os.path.exists(args.out):
        raise InputError(f'out: {args.out} exists already (a bag is never overwritten)')
    check_out_parent(args.out)
    t0 = time.perf_counter()
    s = simulate_bag(scenario, args.out, args.duration, args.seed, args.storage,
                     args.clock_rate)
    dt = time.perf_counter() - t0
    print(f'wrote {args.out} ({args.storage}): {s["bearings"]} bearings, {s["truth"]} truth, '
          f'{s["clock"]} clock messages, {s["duration"]:g} s simulated in {dt:.2f} s wall')
    return 0


# -------------------------------------------------------------------------------------- info

def run_info(args):
    """``bag info``: files, duration, start, message count, topics with type/count/QoS."""
    from .. import bagio
    meta = bagio.read_metadata(args.bag)
    with bagio.BagReader(args.bag) as r:
        topics = r.topics
        print(f'Files:             {", ".join(meta.get("relative_file_paths", []))}')
        print(f'Storage id:        {meta.get("storage_identifier")}  '
              f'(metadata version {meta.get("version")})')
        print(f'Duration:          {_fmt_duration(meta["duration"]["nanoseconds"])}')
        print(f'Start:             {r.start_time_ns / NS_PER_S:.9f} s')
        print(f'Messages:          {r.message_count}')
        for name in sorted(topics):
            t = topics[name]
            q = t.qos[0] if t.qos else {}
            print(f'  {name} | {t.msgtype} | {t.count} msgs | '
                  f'{q.get("reliability", "?")}, {q.get("history", "?")} '
                  f'{q.get("depth", "?")} | {t.type_hash}')
    return 0


# -------------------------------------------------------------------------------------- play

def _import_msg_class(msgtype):
    import importlib
    pkg, kind, name = msgtype.split('/')
    try:
        return getattr(importlib.import_module(f'{pkg}.{kind}'), name)
    except (ImportError, AttributeError):
        raise InputError(f'bag: message type {msgtype!r} is not installed') from None


def _qos_from_dict(q):
    """rclpy QoSProfile of a recorded offered profile (metadata v9 dict)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    depth = max(int(q.get('depth', 10) or 10), 1)
    rel = (ReliabilityPolicy.BEST_EFFORT if q.get('reliability') == 'best_effort'
           else ReliabilityPolicy.RELIABLE)
    dur = (DurabilityPolicy.TRANSIENT_LOCAL if q.get('durability') == 'transient_local'
           else DurabilityPolicy.VOLATILE)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=rel,
                      durability=dur)


def play_bag(path, rate=1.0, loop=False, clock_rate=0.0, delay=0.0, wait_for_subscribers=0.0,
             topics=None, quiet=False, log=None):
    """Publish the messages of bag ``path`` paced by bag time / ``rate`` (rclpy node).

    Raw CDR bytes are published as they are (``Publisher.publish(bytes)``), on publishers with
    each topic's recorded reliability/durability/depth (rosbag2 player's QoS adaptation).
    ``/clock``: with ``clock_rate`` > 0, a rosgraph_msgs/Clock with the playback time
    t0 + (wall − wall0) · rate is published at ``clock_rate`` Hz wall and the bag's own
    /clock is skipped; otherwise the bag's /clock messages are replayed, or, if it has none,
    a clock is generated at 100 Hz. Messages of one bag instant go out before its clock tick.
    Returns 0; Ctrl-C stops cleanly.
    """
    import rclpy
    from rclpy.duration import Duration
    from rclpy.executors import ExternalShutdownException
    from rosgraph_msgs.msg import Clock
    from .. import bagio
    if not (rate > 0 and math.isfinite(rate)):
        raise InputError(f'rate: must be > 0 (got {rate})')
    if clock_rate < 0 or not math.isfinite(clock_rate):
        raise InputError(f'clock_rate: must be >= 0 (got {clock_rate})')
    log = log or (lambda s: print(s, file=sys.stderr, flush=True))
    with bagio.BagReader(path) as reader:
        info = reader.topics
    if topics:
        missing = [t for t in topics if t not in info]
        if missing:
            raise InputError(f'topics: not in the bag: {", ".join(missing)}')
        info = {k: v for k, v in info.items() if k in topics}
    has_clock = bagio.CLOCK_TOPIC in info
    generate = clock_rate > 0 or not has_clock
    gen_hz = clock_rate if clock_rate > 0 else 100.0
    from rclpy.signals import SignalHandlerOptions
    # No rclpy signal handler: with it, Ctrl-C shuts the context down and the next
    # publish raises RCLError (a traceback, exit 1). Python's own handler raises
    # KeyboardInterrupt, caught below; installed explicitly because a shell starts
    # background jobs with SIGINT ignored.
    old_sigint = None
    if threading.current_thread() is threading.main_thread():
        old_sigint = signal.signal(signal.SIGINT, signal.default_int_handler)
    rclpy.init(args=['--ros-args'], signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('bag_player')
    try:
        pubs = {}
        for name, t in info.items():
            if name == bagio.CLOCK_TOPIC and generate:
                continue
            pubs[name] = node.create_publisher(_import_msg_class(t.msgtype), name,
                                               _qos_from_dict(t.qos[0] if t.qos else {}))
        clock_pub = node.create_publisher(Clock, bagio.CLOCK_TOPIC,
                                          _qos_from_dict(bagio.CLOCK_QOS)) if generate else None
        if wait_for_subscribers > 0:
            deadline = time.monotonic() + wait_for_subscribers
            while time.monotonic() < deadline:
                if all(p.get_subscription_count() > 0 for p in pubs.values()):
                    break
                time.sleep(0.02)
            lonely = [n for n, p in pubs.items() if p.get_subscription_count() == 0]
            if lonely and not quiet:
                log(f'bag play: no subscriber yet on {", ".join(sorted(lonely))}')
        if delay > 0:
            time.sleep(delay)
        period_ns = int(NS_PER_S / gen_hz)
        while True:
            n = _play_once(path, pubs, clock_pub, rate, period_ns, set(info), quiet, log)
            if not loop or not rclpy.ok():
                break
        for p in pubs.values():
            p.wait_for_all_acked(Duration(seconds=2.0))
        if not quiet:
            log(f'bag play: done ({n} messages per pass)')
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        if old_sigint is not None:
            signal.signal(signal.SIGINT, old_sigint)
    return 0


def _play_once(path, pubs, clock_pub, rate, period_ns, topics, quiet, log):
    """One pass over the bag; returns the number of messages published."""
    from rosgraph_msgs.msg import Clock
    from .. import bagio
    from ..ros_conversions import ns_to_time

    def clock_at(t_ns):
        if clock_pub is not None:
            clock_pub.publish(Clock(clock=ns_to_time(max(0, t_ns))))

    count = 0
    with bagio.BagReader(path) as reader:
        t0 = reader.start_time_ns
        wall0 = time.monotonic_ns()
        next_tick = wall0
        clock_at(t0)
        held_clock = []   # bag /clock messages of the current instant: sent after its data
        current = None
        for m in reader.messages(topics=topics):
            if m.log_time_ns != current:
                for raw in held_clock:
                    pubs[bagio.CLOCK_TOPIC].publish(raw)
                held_clock = []
                current = m.log_time_ns
            due = wall0 + int((m.log_time_ns - t0) / rate)
            while True:
                now = time.monotonic_ns()
                if clock_pub is not None and next_tick <= min(now, due):
                    clock_at(min(t0 + int((next_tick - wall0) * rate), m.log_time_ns))
                    next_tick += period_ns
                    continue
                if now >= due:
                    break
                wake = due if clock_pub is None else min(due, next_tick)
                time.sleep(max(0.0, (wake - now) / NS_PER_S))
            pub = pubs.get(m.topic)
            if pub is None:
                continue
            if m.topic == bagio.CLOCK_TOPIC:
                held_clock.append(m.raw)
            else:
                pub.publish(m.raw)
            count += 1
        for raw in held_clock:
            pubs[bagio.CLOCK_TOPIC].publish(raw)
        if current is not None:
            clock_at(current)
    return count


def run_play(args):
    """``bag play``."""
    if not os.path.isdir(args.bag):
        raise InputError(f'bag: {args.bag} is not a directory')
    return play_bag(args.bag, args.rate, args.loop, args.clock_rate, args.delay,
                    args.wait_for_subscribers, args.topics, args.quiet)


# ----------------------------------------------------------------------------------- process

#: Defaults of the fusion node's parameters that shape the fusion (fusion_node.py
#: _declare_parameters; test_bag.py checks them against a live FusionNode). bag process
#: starts from these, so a bag processed offline with the node's --params-file gives the
#: node's fixes.
FUSION_NODE_DEFAULTS = {
    'frame_id': 'map', 'stations': [], 'trigger': 'event', 'rate': 10.0, 'max_latency': 0.2,
    'sync_tolerance': 0.05, 'interpolation': False, 'max_interpolation_gap': 1.0,
    'station_timeout': 5.0, 'buffer_size': 50, 'buffer_age': 10.0,
    'time_jump_tolerance': 0.1, 'estimator': None, 'min_stations': 2, 'outlier_gate': 0.999,
    'max_iterations': 50, 'tolerance': 1e-9, 'reference_range': None, 'step_decay': 1.0,
    'target_speed': 0.0, 'window': 120.0, 'speed_reference': 'relative',
}
#: Node parameters that go into FusionConfig.estimator_options (fusion_node.ESTIMATOR_OPTIONS).
FUSION_ESTIMATOR_OPTIONS = ('max_iterations', 'tolerance', 'reference_range', 'step_decay')
#: Node parameters with no effect on the fixes (accepted in a params file, ignored here).
FUSION_DISPLAY_PARAMS = ('mode', 'discover', 'discovery_period', 'qos_depth', 'qos_reliability',
                         'geodetic_origin', 'publish_markers', 'marker_ray_length',
                         'ellipsoid_sigma', 'diagnostics_period', 'use_sim_time',
                         'start_type_description_service', 'accuracy_map.enabled',
                         'accuracy_map.size', 'accuracy_map.resolution',
                         'accuracy_map.altitude', 'accuracy_map.center', 'accuracy_map.model',
                         'accuracy_map.scale', 'accuracy_map.min_error',
                         'accuracy_map.max_error', 'accuracy_map.move_threshold',
                         'accuracy_map')


def read_params_file(path):
    """ros__parameters of the first node entry of a ROS 2 parameters YAML file (a dict).

    Accepts ``fusion:``, ``/fusion:``, ``/**:`` or ``/ns/fusion:`` keys (the forms
    ``--ros-args --params-file`` accepts). Raises InputError naming the file.
    """
    import yaml
    try:
        with open(path, encoding='utf-8') as f:
            data = yaml.safe_load(f)
    except OSError as exc:
        raise InputError(f'params_file: cannot read {path} ({exc.strerror})') from None
    except yaml.YAMLError as exc:
        raise InputError(f'params_file: {path}: invalid YAML ({" ".join(str(exc).split())})') \
            from None
    if isinstance(data, dict):
        for node, body in data.items():
            if isinstance(body, dict) and isinstance(body.get('ros__parameters'), dict):
                return dict(body['ros__parameters'])
    raise InputError(f'params_file: {path}: no "<node>: ros__parameters:" mapping')


def fusion_params(params_file=None, overrides=(), estimator=None):
    """Fusion node parameters: node defaults < params file < NAME=VALUE overrides < estimator."""
    import yaml
    from ..core import estimators
    p = dict(FUSION_NODE_DEFAULTS)
    p['estimator'] = estimators.DEFAULT_ESTIMATOR
    p['reference_range'] = float(estimators.DEFAULT_REFERENCE_RANGE)
    given = dict(read_params_file(params_file)) if params_file else {}
    for item in overrides:
        name, sep, value = item.partition('=')
        if not sep or not name:
            raise InputError(f'param: expected NAME=VALUE, got {item!r}')
        given[name.strip()] = yaml.safe_load(value)
    if estimator is not None:
        given['estimator'] = estimator
    for name, value in given.items():
        if name not in p and name not in FUSION_DISPLAY_PARAMS:
            raise InputError(f'{name}: not a fusion node parameter')
        p[name] = value
    return p


def fusion_config(p):
    """FusionConfig from fusion node parameters (the mapping fusion_node uses)."""
    from ..core.fusion import FusionConfig
    try:
        return FusionConfig(
            frame_id=p['frame_id'], trigger=p['trigger'], rate=float(p['rate']),
            max_latency=float(p['max_latency']), sync_tolerance=float(p['sync_tolerance']),
            interpolation=bool(p['interpolation']),
            max_interpolation_gap=float(p['max_interpolation_gap']),
            station_timeout=float(p['station_timeout']), buffer_size=int(p['buffer_size']),
            buffer_age=float(p['buffer_age']), min_stations=int(p['min_stations']),
            estimator=p['estimator'],
            estimator_options={k: p[k] for k in FUSION_ESTIMATOR_OPTIONS},
            outlier_gate=float(p['outlier_gate']),
            time_jump_tolerance=float(p['time_jump_tolerance']),
            target_speed=float(p['target_speed']), window=float(p['window']),
            speed_reference=p['speed_reference']).validate()
    except (TypeError, ValueError) as exc:
        raise InputError(str(exc)) from None


def _interp_truth(stamps, positions, t, max_gap_ns):
    """Truth at fix times t: linear between samples, nearest within max_gap outside, else NaN."""
    import numpy as np
    out = np.full((len(t), 3), np.nan)
    if not len(stamps):
        return out
    order = np.argsort(stamps, kind='stable')
    s = np.asarray(stamps, dtype=np.int64)[order]
    p = np.asarray(positions, dtype=float)[order]
    t = np.asarray(t, dtype=np.int64)
    inside = (t >= s[0] - max_gap_ns) & (t <= s[-1] + max_gap_ns)
    for a in range(3):
        out[:, a] = np.interp(t.astype(float), s.astype(float), p[:, a])
    out[~inside] = np.nan
    return out


def process_bag(path, out, params, storage='mcap', namespace='', fix_topic='fix'):
    """Run the fusion node's pipeline (core.fusion.FusionCore + replay) offline over a bag.

    Exactly what fusion_node does, message by message in bag order: a ``/clock`` message
    sets the node clock (and runs the node's timer ticks, via core.fusion.replay); a
    bearing on ``<ns>/<station>/bearing`` is converted by ``ros_conversions.bearing_from_msg``
    (a ConversionError is counted as a bad message) and given to the core at the current
    node-clock time (the bearing's stamp before the first /clock; the bag time when the bag
    has no /clock). Stations: the ``stations`` parameter, else every bearing topic of the
    namespace in sorted order. Writes ``<out>/`` (a bag with the fixes on ``<ns>/fix``, bag
    time = node-clock time the fix was computed) and ``<out>.csv``; returns a summary dict
    (epochs, fixes, no_fix reasons, dropped, bad, and ``errors`` against ``<ns>/truth`` when
    the bag has it).
    """
    import numpy as np
    from .. import bagio
    from ..core.evaluation import track_errors
    from ..core.fusion import make_core, replay
    from ..ros_conversions import bearing_from_msg, ConversionError
    out = str(out).rstrip('/')
    csv_path = out + '.csv'
    if os.path.exists(out) or os.path.exists(csv_path):
        raise InputError(f'out: {out} or {csv_path} exists already (never overwritten)')
    ns = namespace.strip('/')
    prefix = '/' + ns + '/' if ns else '/'
    config = fusion_config(params)
    with bagio.BagReader(path) as reader:
        topics = reader.topics
        station_topics = {}
        for name, t in topics.items():
            if t.msgtype != bagio.POSE_COV_STAMPED or not name.startswith(prefix):
                continue
            station = bagio.station_from_topic(name[len(prefix) - 1:])
            if station is not None:
                station_topics[name] = station
        stations = list(params.get('stations') or sorted(set(station_topics.values())))
        wanted = {prefix + s + '/bearing': s for s in stations}
        if not any(t in topics for t in wanted):
            raise InputError(f'bag: no bearing topics {prefix}<station>/bearing in {path}')
        truth_topic = prefix + 'truth'
        has_truth = truth_topic in topics
        has_clock = bagio.CLOCK_TOPIC in topics
        core = make_core(config, stations=stations)
        truth_t, truth_p = [], []
        clock = [None]

        def items():
            for m in reader.messages():
                if m.topic == bagio.CLOCK_TOPIC:
                    clock[0] = bagio.stamp_ns(bagio.deserialize(m.raw, m.msgtype))
                    yield clock[0], None
                elif m.topic in wanted:
                    now = clock[0] if has_clock else m.log_time_ns
                    station = wanted[m.topic]
                    try:
                        b = bearing_from_msg(bagio.deserialize(m.raw, m.msgtype), station,
                                             expected_frame=config.frame_id)
                    except ConversionError as exc:
                        core.count_bad_message(station, exc.reason, now)
                        continue
                    yield (now if now is not None else b.stamp_ns), b
                elif m.topic == truth_topic and has_truth:
                    msg = bagio.deserialize(m.raw, m.msgtype)
                    truth_t.append(bagio.stamp_ns(msg))
                    truth_p.append(bagio.position_of(msg))

        epochs = list(replay(core, items()))
    fixes = [e for e in epochs if e.ok]
    stamps = np.array([e.stamp_ns for e in fixes], dtype=np.int64)
    pos = np.array([e.position for e in fixes]).reshape(-1, 3)
    cov = np.array([e.covariance for e in fixes]).reshape(-1, 3, 3)
    truth = None
    if has_truth and fixes:
        period = int(np.median(np.diff(np.unique(truth_t)))) if len(set(truth_t)) > 1 else 0
        truth = _interp_truth(truth_t, truth_p, stamps, max(period, NS_PER_S))
    _write_fix_csv(csv_path, fixes, truth)
    fix_name = prefix + fix_topic.strip('/')
    with bagio.BagWriter(out, storage=storage, custom_data={
            'generator': 'bearing_loc bag process', 'source': str(path),
            'estimator': config.estimator, 'trigger': config.trigger}) as bag:
        bag.add_topic(fix_name, bagio.POSE_COV_STAMPED, bagio.qos_profile(10))
        for e in fixes:
            bag.write(fix_name, e.produced_ns,
                      bagio.fix_message(e.position, e.covariance, e.stamp_ns, config.frame_id))
    from collections import Counter
    summary = {'stations': stations, 'epochs': len(epochs), 'fixes': len(fixes),
               'no_fix': dict(Counter(e.reason for e in epochs if not e.ok)),
               'dropped': dict(core.dropped), 'bad_messages': core.bad_messages,
               'outliers': core.outliers, 'time_jumps': core.time_jumps,
               'estimator': config.estimator, 'fix_topic': fix_name, 'bag': out,
               'csv': csv_path, 'errors': None, 'epoch_list': epochs}
    if truth is not None:
        summary['errors'] = track_errors(truth, pos, cov)
    return summary


def _write_fix_csv(path, fixes, truth):
    import csv
    cols = ['stamp_ns', 'stamp_s', 'x', 'y', 'z', 'cov_xx', 'cov_xy', 'cov_xz', 'cov_yy',
            'cov_yz', 'cov_zz', 'n_stations', 'stations', 'rejected', 'estimator', 'status',
            'iterations', 'chi2', 'dof', 'produced_ns']
    if truth is not None:
        cols += ['truth_x', 'truth_y', 'truth_z', 'error_m']
    with open(path, 'w', newline='', encoding='utf-8') as f:
        w = csv.writer(f)
        w.writerow(cols)
        for k, e in enumerate(fixes):
            c = e.covariance
            row = [e.stamp_ns, f'{e.stamp_ns / NS_PER_S:.9f}', *map(repr, map(float, e.position)),
                   *(repr(float(c[i, j])) for i, j in UPPER_TRIANGLE),
                   len(e.bearings), ' '.join(e.stations),
                   ' '.join(b.station for b in e.rejected), e.estimator, e.status,
                   e.iterations, repr(float(e.chi2)), e.dof, e.produced_ns]
            if truth is not None:
                t = truth[k]
                err = math.dist(t, e.position) if all(map(math.isfinite, t)) else float('nan')
                row += [*map(repr, map(float, t)), repr(err)]
            w.writerow(row)


def run_process(args):
    """``bag process``: see :func:`process_bag`."""
    if not os.path.isdir(args.bag):
        raise InputError(f'bag: {args.bag} is not a directory')
    params = fusion_params(args.params_file, args.param, args.estimator)
    check_out_parent(args.out)
    t0 = time.perf_counter()
    s = process_bag(args.bag, args.out, params, args.storage, args.namespace, args.fix_topic)
    dt = time.perf_counter() - t0
    no_fix = ', '.join(f'{k} {v}' for k, v in sorted(s['no_fix'].items())) or 'none'
    dropped = ', '.join(f'{k} {v}' for k, v in sorted(s['dropped'].items())) or 'none'
    print(f'{args.bag}: stations {", ".join(s["stations"])}; estimator {s["estimator"]}; '
          f'{s["epochs"]} epochs, {s["fixes"]} fixes (no fix: {no_fix}); dropped bearings: '
          f'{dropped}; bad messages {s["bad_messages"]}; outliers rejected {s["outliers"]}; '
          f'{dt:.2f} s')
    print(f'wrote {s["bag"]}/ ({s["fix_topic"]}) and {s["csv"]}')
    e = s['errors']
    if e is not None and e['n']:
        print(f'error against truth ({e["n"]} fixes): RMSE {e["rmse"]:.3f} m, mean '
              f'{e["mean_error"]:.3f} m, median {e["median_error"]:.3f} m, 95% '
              f'{e["p95_error"]:.3f} m, max {e["max_error"]:.3f} m, bias ('
              + ', '.join(f'{v:.3f}' for v in e['bias']) + f') m, mean NEES '
              f'{e["mean_nees"]:.2f} (3 = consistent)')
    elif e is not None:
        print('error against truth: no fix within the truth time span')
    return 0
