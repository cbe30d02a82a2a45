"""``bearing_loc bag``: rosbag2 datasets without the ROS 2 CLI (docs/bags.md).

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
import time

from . import InputError
from ..bag_player import DEFAULT_WAIT_S
from .helptext import sub_command

NS_PER_S = 1_000_000_000


def add_arguments(parser):
    """Register the ``bag`` sub-commands."""
    sub = parser.add_subparsers(dest='bag_command', metavar='COMMAND')
    sub.required = True

    p = sub_command(sub, 'simulate', 'write a simulated rosbag2 bag from a scenario',
                    'bearing_loc bag simulate --scenario seed000 --duration 30 --out run1')
    p.add_argument('--scenario', required=True,
                   help='scenario YAML: a path, or the name of a shipped scenario (seed000)')
    p.add_argument('--duration', type=float, default=0.0,
                   help="simulated seconds (default 0: the scenario's duration)")
    p.add_argument('--seed', type=int, default=0, help='simulator seed (default 0)')
    p.add_argument('--out', required=True, help='bag directory to create (must not exist)')
    p.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap',
                   help='storage plugin (default mcap, the rosbag2 default)')
    p.add_argument('--clock-rate', type=float, default=100.0,
                   help='/clock messages per simulated second (default 100, as '
                        'simulator_node; 0: no /clock topic)')

    p = sub_command(sub, 'play', "publish a bag's messages with /clock (rclpy)",
                    'bearing_loc bag play run1 --rate 4')
    p.add_argument('bag', help='bag directory')
    p.add_argument('--rate', type=float, default=1.0, help='playback speed factor (default 1)')
    p.add_argument('--loop', action='store_true', help='play again from the start when done')
    p.add_argument('--clock-rate', type=float, default=0.0,
                   help='generate /clock at this many Hz of wall time from the playback time '
                        "(ignoring the bag's own /clock); default 0: replay the bag's /clock "
                        'topic, or generate at 100 Hz if it has none')
    p.add_argument('--delay', type=float, default=0.0,
                   help='wall seconds to wait before playing (default 0)')
    p.add_argument('--wait-for-subscribers', type=float, default=DEFAULT_WAIT_S,
                   metavar='SECONDS',
                   help='before playing, wait up to SECONDS until every topic that has a '
                        'subscriber is matched; topics nobody subscribes to are not waited '
                        f'for (default {DEFAULT_WAIT_S:g}; 0: do not wait)')
    p.add_argument('--topics', nargs='+', default=None, help='play only these topics')
    p.add_argument('--quiet', action='store_true', help='no progress output')

    p = sub_command(sub, 'process', 'offline fusion over a bag: error statistics, and with '
                    '--out a fixes bag and CSV',
                    'bearing_loc bag process run1 --estimator wmle --out run1_fixes')
    p.add_argument('bag', help='input bag directory')
    p.add_argument('--estimator', default=None,
                   help="estimator name (default: the fusion node's default)")
    p.add_argument('--params-file', default=None,
                   help="the fusion node's parameters YAML (as given to --ros-args "
                        '--params-file), so the offline run uses the same settings')
    p.add_argument('-p', '--param', action='append', default=[], metavar='NAME=VALUE',
                   help='one fusion node parameter (YAML value), e.g. -p trigger=timer; '
                        'overrides --params-file')
    p.add_argument('--namespace', default='',
                   help='target namespace of the bearing topics (<ns>/<station>/bearing, '
                        '<ns>/truth); default: the root namespace')
    p.add_argument('--out', default=None,
                   help='write the fixes as bag directory OUT/ (fix topic) and OUT.csv '
                        '(default: print the statistics only)')
    p.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap')
    p.add_argument('--fix-topic', default='fix',
                   help='topic of the fixes, relative to the namespace (default fix)')
    from .gisargs import add_gis_arguments
    add_gis_arguments(p)

    p = sub_command(sub, 'info', 'print a summary of a bag', 'bearing_loc bag info run1')
    p.add_argument('bag', help='bag directory')

    p = sub_command(sub, 'import', 'recorded KrakenSDR CSV logs -> a bag of bearings',
                    'bearing_loc bag import --station s1=s1.csv --station s2=s2.csv '
                    '--params stations.yaml --out run2')
    from ..bag_import import add_import_arguments
    add_import_arguments(p)


def run(args):
    """Dispatch to the sub-command."""
    if args.bag_command == 'import':
        from ..bag_import import run_import
        return run_import(args)
    return {'simulate': run_simulate, 'play': run_play, 'process': run_process,
            'info': run_info}[args.bag_command](args)


# --------------------------------------------------------------------------- shared functions

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

    ``duration`` (s; None or 0: the scenario's) has the bounds of a scenario's duration
    (``core.simulation.check_duration``), and the /clock messages are at most
    ``MAX_CLOCK_TICKS`` (1e7); beyond either it raises ValueError ``duration: ...``
    (``clock_rate: ...`` for the ticks when the scenario's own duration is used) before
    anything is written. Messages are built while writing (the three streams are merged in
    time order), so memory is that of the simulation alone.
    """
    import heapq
    from .. import bagio
    from ..core.scenario_loader import RATE_RANGE
    from ..core.simulation import (bearing_topic, check_duration, MAX_CLOCK_TICKS, simulate,
                                   truth_topic)
    if not (clock_rate == 0 or RATE_RANGE[0] <= clock_rate <= RATE_RANGE[1]):
        raise InputError(f'clock_rate: must be 0 or within [{RATE_RANGE[0]:g}, '
                         f'{RATE_RANGE[1]:g}] Hz (got {clock_rate:g})')
    period = int(round(NS_PER_S / clock_rate)) if clock_rate > 0 else 0

    def check_clock(span):           # span: ns of /clock from the epoch; returns the count
        n = span // period + 1 + (span % period != 0) if period else 0
        if n > MAX_CLOCK_TICKS:
            raise InputError(f'{"duration" if duration else "clock_rate"}: '
                             f'{span / NS_PER_S:g} s of /clock at {clock_rate:g} Hz is {n} '
                             f'messages, more than {MAX_CLOCK_TICKS:g} (lower --duration or '
                             f'--clock-rate)')
        return n

    check_clock(int(round(check_duration(scenario, duration or None) * NS_PER_S)))  # fast
    sim = simulate(scenario, duration=duration or None, seed=seed)
    n_clock = check_clock(sim.end_ns - scenario.epoch_ns)     # latency may lengthen the run
    custom = {'generator': 'bearing_loc bag simulate', 'scenario': scenario.source,
              'scenario_name': scenario.name, 'seed': str(seed),
              'duration': repr(sim.duration)}

    def ticks():
        k = -1
        for k, t in enumerate(range(scenario.epoch_ns, sim.end_ns + 1, period)):
            yield t, 2, k, bagio.CLOCK_TOPIC, None
        if (sim.end_ns - scenario.epoch_ns) % period:
            yield sim.end_ns, 2, k + 1, bagio.CLOCK_TOPIC, None

    # Each stream is sorted by (time, index): the merge is the order of sorting them all.
    streams = [((ev.publish_ns, 0, k, _abs(ev.topic), ev) for k, ev in enumerate(sim.truth)),
               ((ev.publish_ns, 1, k, _abs(ev.topic), ev) for k, ev in enumerate(sim.bearings))]
    if period:
        streams.append(ticks())
    with bagio.BagWriter(out, storage=storage, custom_data=custom) as bag:
        for tg in sim.targets:
            if scenario.truth_rate > 0:
                bag.add_topic(_abs(truth_topic(tg.namespace)), bagio.POSE_STAMPED,
                              bagio.SIM_TRUTH_QOS)
            for st in scenario.stations:
                bag.add_topic(_abs(bearing_topic(tg.namespace, st.id)),
                              bagio.POSE_COV_STAMPED, bagio.SIM_BEARING_QOS)
        if period:
            bag.add_topic(bagio.CLOCK_TOPIC, bagio.CLOCK, bagio.CLOCK_QOS)
        for t, kind, _, topic, ev in heapq.merge(*streams, key=lambda e: e[:3]):
            if kind == 0:
                msg = bagio.truth_message(ev.position, ev.stamp_ns, scenario.frame_id)
            elif kind == 1:
                msg = bagio.bearing_message(ev.bearing)
            else:
                msg = bagio.clock_message(t)
            bag.write(topic, t, msg)
    return {'bearings': len(sim.bearings), 'truth': len(sim.truth), 'clock': n_clock,
            'start_ns': scenario.epoch_ns, 'end_ns': sim.end_ns, 'duration': sim.duration,
            'unobserved': sim.unobserved_note()}


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
    from ..scenarios import resolve_scenario
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
    if s['unobserved']:
        print(f'note: {s["unobserved"]}')
    return 0


# -------------------------------------------------------------------------------------- info

def format_qos(q):
    """One offered QoS profile (metadata dict): reliability, durability, history and depth,
    then deadline, lifespan and liveliness when they are not the defaults."""
    text = (f'{q.get("reliability", "?")}, {q.get("durability", "?")}, '
            f'{q.get("history", "?")} {q.get("depth", "?")}')
    for key in ('deadline', 'lifespan', 'liveliness_lease_duration'):
        d = q.get(key) or {}
        if d.get('sec') or d.get('nsec'):
            text += f', {key} {d.get("sec", 0) + d.get("nsec", 0) / NS_PER_S:g} s'
    if q.get('liveliness', 'automatic') not in ('automatic', 'system_default'):
        text += f', liveliness {q["liveliness"]}'
    return text


def run_info(args):
    """``bag info``: files, duration, start, message count, topics with type/count/QoS, as
    metadata.yaml lists them (no message is read: ``bag process`` and ``bag play`` compare
    the counts with the messages they read)."""
    from .. import bagio
    _check_bag_dir(args.bag)
    with bagio.BagReader(args.bag) as r:
        meta, topics = r.metadata, r.topics
        print(f'Files:             {", ".join(meta.get("relative_file_paths", []))}')
        print(f'Storage id:        {meta.get("storage_identifier")}  '
              f'(metadata version {meta.get("version")})')
        print(f'Duration:          {_fmt_duration(meta["duration"]["nanoseconds"])}')
        print(f'Start:             {r.start_time_ns / NS_PER_S:.9f} s')
        print(f'Messages:          {r.message_count}')
        for name in sorted(topics):
            t = topics[name]
            print(f'  {name} | {t.msgtype} | {t.count} msgs | '
                  f'{"; ".join(map(format_qos, t.qos)) or "no QoS recorded"} | {t.type_hash}')
    return 0


def _check_bag_dir(path):
    """InputError unless ``path`` is a directory (a rosbag2 bag)."""
    if not os.path.isdir(path):
        why = 'is not a directory' if os.path.exists(path) else 'does not exist'
        raise InputError(f'bag: {path} {why}')


# -------------------------------------------------------------------------------------- play

def run_play(args):
    """``bag play``."""
    from ..bag_player import play_bag
    _check_bag_dir(args.bag)
    return play_bag(args.bag, args.rate, args.loop, args.clock_rate, args.delay,
                    args.wait_for_subscribers, args.topics, args.quiet)


# ----------------------------------------------------------------------------------- process

def run_process(args):
    """``bag process``: see bag_process.process_bag."""
    from ..bag_process import fusion_params, process_bag
    _check_bag_dir(args.bag)
    params = fusion_params(args.params_file, args.param, args.estimator, args.namespace)
    reserved = ()
    if args.out is not None:
        check_out_parent(args.out)
        out = args.out.rstrip('/')
        reserved = (('--out', out), ('--out', out + '.csv'))     # OUT/ and OUT.csv
    from . import gisargs
    gisargs.check(args, params, reserved)
    t0 = time.perf_counter()
    s = process_bag(args.bag, args.out, params, args.storage, args.namespace, args.fix_topic)
    dt = time.perf_counter() - t0
    no_fix = ', '.join(f'{k} {v}' for k, v in sorted(s['no_fix'].items())) or 'none'
    dropped = ', '.join(f'{k} {v}' for k, v in sorted(s['dropped'].items())) or 'none'
    bad = '; '.join(f'{where}: ' + ', '.join(f'{k} {v}' for k, v in sorted(reasons.items()))
                    for where, reasons in s['bad'].items())
    print(f'{args.bag}: stations {", ".join(s["stations"])}; estimator {s["estimator"]}; '
          f'{s["epochs"]} epochs, {s["fixes"]} fixes (no fix: {no_fix}); dropped bearings: '
          f'{dropped}; bad messages {s["bad_messages"]}{f" ({bad})" if bad else ""}; '
          f'outliers rejected {s["outliers"]}; {dt:.2f} s')
    if s['bag'] is not None:
        print(f'wrote {s["bag"]}/ ({s["fix_topic"]}) and {s["csv"]}')
    e = s['errors']
    if e is not None and e['n']:
        print(f'error against truth ({e["n"]} fixes): RMSE {e["rmse"]:.3f} m, mean '
              f'{e["mean_error"]:.3f} m, median {e["median_error"]:.3f} m, 95% '
              f'{e["p95_error"]:.3f} m, max {e["max_error"]:.3f} m, bias ('
              + ', '.join(f'{v:.3f}' for v in e['bias']) + f') m, mean NEES '
              f'{e["mean_nees"]:.2f} ({e.get("nees_dof", 3):g} = consistent)')
    elif e is not None:
        print('error against truth: no fix within the truth time span')
    gisargs.export_epochs(args, params, s['epoch_list'])
    return 0
