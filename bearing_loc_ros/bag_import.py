"""``bearing_loc bag import``: recorded KrakenSDR CSV logs -> a rosbag2 bag of bearings.

Each station's log (one "Kraken App" CSV file per station) goes through exactly the path of
the station node's file input (``input: kraken_csv_file``): the same reader
(:class:`~bearing_loc_ros.receiver_inputs.CsvFileTail`), the same
:class:`~bearing_loc_ros.receiver_inputs.KrakenInput` (parsing, channel bands, time checks,
receiver geometry, confidence -> σ) configured from the same station parameter file. The
bag holds what the station nodes would have published:

* ``/<station>/bearing`` (one channel) or ``/<channel>/<station>/bearing`` (several
  channels, the simulator's target namespace scheme), geometry_msgs/PoseWithCovarianceStamped
  built by :func:`bearing_loc_ros.bagio.bearing_message`, bag time = header stamp = the
  receiver's ``TIME``;
* ``/clock`` from the first to the last bearing at ``clock_rate`` Hz (and at the last
  bearing), written after the bearings of the same instant, as ``bag simulate`` does.

``bag process`` over the result runs the fusion node's pipeline on those bearings, and ``bag
play`` replays them to live nodes with ``use_sim_time``.
"""

from collections import Counter

from .cli import InputError

NS_PER_S = 1_000_000_000


def station_bearings(station, path, params):
    """(list of (channel, Bearing), rejections Counter, channel names) of one station's log.

    ``params``: the station's node parameters (flat or nested), as
    :func:`bearing_loc_ros.core.receiver_params.receiver_from_params` takes them. Readings
    are stamped with the receiver's TIME (``kraken.stamp`` must be ``receiver``).
    """
    import os
    from .core.receiver_params import receiver_from_params, with_defaults
    from .core.station import ConfigError
    from .receiver_inputs import CsvFileTail, KrakenInput
    try:
        cfg, channels = receiver_from_params(station, params)
        p = with_defaults(params)
    except (ConfigError, ValueError) as exc:
        raise InputError(f'params: station {station}: {exc}') from None
    if p['kraken.stamp'] != 'receiver':
        raise InputError(f'params: station {station}: kraken.stamp must be "receiver" to '
                         'import a log (the bag keeps the recorded times)')
    if cfg.needs_odometry:
        raise InputError(f'params: station {station}: a log carries no odometry; use a '
                         'fixed or GPS heading and position')
    if not os.path.isfile(path):
        raise InputError(f'station: {path} is not a file')
    source = CsvFileTail(path, from_start=True, queue_size=10 ** 9)
    # A log keeps the times it was recorded with, even from a receiver whose clock was not
    # set (bag play replays them as /clock): no unset_clock check here.
    ki = KrakenInput(source, cfg, channels, stamp='receiver', receiver_id=p['kraken.receiver_id'],
                     min_time_ns=0)
    out, rejected = [], Counter()
    while True:
        n_before = ki.counts['readings']
        bearings, rej = ki.poll(None, max_items=10 ** 9)
        out += bearings
        rejected.update(r for r, _ in rej)
        if ki.counts['readings'] == n_before and source.poll() == 0:
            break
    source.close()
    return out, rejected, channels.names


def bearing_topic_of(channel, station):
    """Absolute topic of a station's bearings on ``channel`` ('' = the only channel)."""
    from .core.simulation import bearing_topic
    return '/' + bearing_topic(channel, station)


def import_logs(logs, out, params_data=None, storage='mcap', clock_rate=10.0):
    """Write the bag (module docstring) from ``logs`` {station: csv path}; return a summary.

    ``params_data``: a parsed station parameter YAML (``/NAME/station_node:``, ``/NAME/**:``
    or ``/**:`` entries, as ``bearing_loc calibrate`` reads and writes).
    """
    import math
    from . import bagio
    from .cli.calibrate import station_params
    if not (math.isfinite(clock_rate) and clock_rate >= 0.0):
        raise InputError(f'clock_rate: must be >= 0 (got {clock_rate})')
    events, topics, rejected, per_topic = [], [], {}, Counter()
    for k, (station, path) in enumerate(sorted(logs.items())):
        bearings, rej, names = station_bearings(station, path,
                                                station_params(params_data or {}, station))
        rejected[station] = dict(rej)
        for ch in names:
            topics.append(bearing_topic_of(ch, station))
        for j, (ch, b) in enumerate(bearings):
            topic = bearing_topic_of(ch, station)
            per_topic[topic] += 1
            events.append((b.stamp_ns, 0, k, j, topic, b))
    if not events:
        why = '; '.join(f'{station}: ' + ', '.join(f'{n} {r}' for r, n in sorted(rej.items()))
                        for station, rej in sorted(rejected.items()) if rej)
        raise InputError('station: no valid reading in any log'
                         + (f' (rejected: {why})' if why else ''))
    start, end = min(e[0] for e in events), max(e[0] for e in events)
    if clock_rate > 0:
        period = max(1, int(round(NS_PER_S / clock_rate)))
        ticks = list(range(start, end + 1, period))
        if ticks[-1] != end:
            ticks.append(end)
        events += [(t, 1, 0, j, bagio.CLOCK_TOPIC, None) for j, t in enumerate(ticks)]
    events.sort(key=lambda e: e[:4])
    custom = {'generator': 'bearing_loc bag import',
              'logs': ' '.join(f'{s}={p}' for s, p in sorted(logs.items()))}
    with bagio.BagWriter(out, storage=storage, custom_data=custom) as bag:
        for topic in topics:
            bag.add_topic(topic, bagio.POSE_COV_STAMPED, bagio.SIM_BEARING_QOS)
        if clock_rate > 0:
            bag.add_topic(bagio.CLOCK_TOPIC, bagio.CLOCK, bagio.CLOCK_QOS)
        for t, kind, _, _, topic, b in events:
            bag.write(topic, t, bagio.clock_message(t) if kind else bagio.bearing_message(b))
    return {'bearings': sum(per_topic.values()), 'per_topic': dict(per_topic),
            'topics': topics, 'rejected': rejected, 'start_ns': start, 'end_ns': end,
            'clock': sum(1 for e in events if e[1] == 1), 'bag': str(out)}


def add_import_arguments(p):
    """Options of ``bag import``."""
    p.add_argument('--station', action='append', required=True, metavar='NAME=CSV',
                   help='a station and its recorded Kraken CSV log (repeat per station)')
    p.add_argument('--params', metavar='YAML', help='station parameter file (the one the '
                   'station nodes use: position, kraken.*)')
    p.add_argument('--out', required=True, help='bag directory to create (must not exist)')
    p.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap',
                   help='storage plugin (default mcap)')
    p.add_argument('--clock-rate', type=float, default=10.0,
                   help='/clock messages per second of recorded time (default 10; 0: none)')


def run_import(args):
    """``bag import``: see :func:`import_logs`."""
    from .cli.calibrate import load_station_params, parse_station_args
    logs = parse_station_args(args.station)
    data = load_station_params(args.params) if args.params else {}
    s = import_logs(logs, args.out, data, args.storage, args.clock_rate)
    for station, rej in sorted(s['rejected'].items()):
        text = ', '.join(f'{r} {n}' for r, n in sorted(rej.items())) or 'none'
        print(f'{station}: rejected readings: {text}')
    for topic in s['topics']:
        print(f'{topic}: {s["per_topic"].get(topic, 0)} bearings')
    print(f'wrote {s["bag"]}/ ({s["bearings"]} bearings, {s["clock"]} /clock, '
          f'{(s["end_ns"] - s["start_ns"]) / NS_PER_S:.3f} s)')
    return 0
