"""``bearing_loc bag``: rosbag2 datasets without the ROS 2 CLI (docs/readme/bags.md).

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
import sys
import time

from . import InputError

NS_PER_S = 1_000_000_000


def add_arguments(parser):
    """Register the ``bag`` sub-commands."""
    sub = parser.add_subparsers(dest='bag_command', metavar='COMMAND')
    sub.required = True

    p = sub.add_parser('simulate', help='write a simulated rosbag2 bag from a scenario')
    p.add_argument('--scenario', required=True, help='scenario YAML (docs/readme/simulator.md)')
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
                   help='estimator name (default: the fusion default, '
                        'core.estimators.DEFAULT_ESTIMATOR)')
    p.add_argument('--params', default=None,
                   help="fusion node parameters YAML (the node's --params-file) to use "
                        'the same settings offline')
    p.add_argument('--out', required=True, help='output prefix: <out>/ bag and <out>.csv')
    p.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap')
    p.add_argument('--fix-topic', default='/fix', help='topic of the fixes (default /fix)')

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
    rclpy.init(args=['--ros-args'])
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

def run_process(args):
    """``bag process``: see :func:`process_bag`."""
    raise InputError('bag process: the fusion core is not available in this build')
