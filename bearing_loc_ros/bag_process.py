"""Offline fusion over a rosbag2 bag (``bearing_loc bag process``).

Runs the fusion node's alignment and estimation core (core.fusion) message by message over a
bag, with the fusion node's parameters, and writes the fixes as a bag and a CSV.
"""

import math
import os
import sys

from .cli import InputError, load_yaml
from .core import parameters
from .core.receiver_params import flatten

NS_PER_S = 1_000_000_000
UPPER_TRIANGLE = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


#: The fusion node's parameters (core.parameters is their one definition): those that shape
#: the fusion, their defaults, and those with no effect on the fixes (accepted in a params
#: file, ignored here). A bag processed offline with the node's --params-file gives the
#: node's fixes.
FUSION_ESTIMATOR_OPTIONS = parameters.ESTIMATOR_OPTIONS
FUSION_NODE_DEFAULTS = {k: v for k, v in parameters.defaults('fusion_node').items()
                        if k in parameters.FUSION_CONFIG_FIELDS + FUSION_ESTIMATOR_OPTIONS
                        + ('stations',)}
FUSION_DISPLAY_PARAMS = tuple(k for k in parameters.defaults('fusion_node')
                              if k not in FUSION_NODE_DEFAULTS) + (
    'use_sim_time', 'start_type_description_service', 'accuracy_map')


def read_params_file(path):
    """ros__parameters of the first node entry of a ROS 2 parameters YAML file (a dict).

    Accepts ``fusion:``, ``/fusion:``, ``/**:`` or ``/ns/fusion:`` keys (the forms
    ``--ros-args --params-file`` accepts). Raises InputError naming the file.
    """
    data = load_yaml(path, 'params_file', params=True)
    if isinstance(data, dict):
        for node, body in data.items():
            if isinstance(body, dict) and isinstance(body.get('ros__parameters'), dict):
                return dict(body['ros__parameters'])
    raise InputError(f'params_file: {path}: no "<node>: ros__parameters:" mapping')


def fusion_params(params_file=None, overrides=(), estimator=None):
    """Fusion node parameters: schema defaults < params file < NAME=VALUE overrides <
    estimator; each checked against the schema (type, range, allowed values). Deprecated
    names are mapped to the current ones with a warning on stderr."""
    import yaml
    from .core.yaml_file import load_param_text
    given = dict(read_params_file(params_file)) if params_file else {}
    for item in overrides:
        name, sep, value = item.partition('=')
        if not sep or not name:
            raise InputError(f'param: expected NAME=VALUE, got {item!r}')
        try:
            given[name.strip()] = load_param_text(value)
        except yaml.constructor.ConstructorError as exc:     # a value rcl refuses
            raise InputError(f'param: {name.strip()}: {exc.problem} ({value!r})') from None
        except (yaml.YAMLError, ValueError):
            raise InputError(f'param: {name.strip()}: invalid YAML value {value!r}') from None
    if estimator is not None:
        given['estimator'] = estimator
    given = {k: v for k, v in flatten(given).items() if not parameters.ros_builtin(k)}
    try:
        return parameters.resolve('fusion_node', given,
                                  warn=lambda text: print(f'warning: {text}', file=sys.stderr))
    except ValueError as exc:
        name, _, problem = str(exc).partition(': ')
        if problem.startswith('not a parameter'):
            raise InputError(f'{name}: not a fusion node parameter'
                             f'{parameters.did_you_mean("fusion_node", name)}') from None
        raise InputError(str(exc)) from None


def fusion_config(p):
    """FusionConfig from fusion node parameters (FusionConfig.from_parameters, as the node)."""
    from .core.fusion import FusionConfig
    try:
        return FusionConfig.from_parameters(p)
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


def _typed_topic(topics, name, types, consequence, log):
    """True when the bag has topic ``name`` of one of the message ``types``. A topic of
    another installed type is ignored with a warning naming the ``consequence`` (one of a
    type that is not installed was warned about with the others)."""
    from . import bagio
    t = topics.get(name)
    if t is None:
        return False
    if t.msgtype in types:
        return True
    if t.msgtype in bagio.typestore().types:
        log(f'bag process: warning: {name} has type {t.msgtype}, not {" or ".join(types)}: '
            f'ignored ({consequence})')
    return False


def _station_topics(topics, prefix, configured, log):
    """The stations and their bearing topics ({topic: station}) in namespace ``prefix``.

    ``configured`` (the ``stations`` parameter): those stations, in that order; their topics
    missing from the bag, or of another message type, are named in a warning. Else, as
    fusion_node with ``discover`` in that namespace: every PoseWithCovarianceStamped topic
    ``<prefix><station>/bearing`` whose station id is valid (STATION_ID_RE), nested
    namespaces included, in sorted order, with a warning when some are nested.
    """
    from . import bagio
    from .core.fusion.config import STATION_ID_RE
    if configured:
        wanted, missing = {}, []
        for s in configured:
            name = prefix + s + '/bearing'
            if _typed_topic(topics, name, (bagio.POSE_COV_STAMPED,), 'fusion_node receives '
                            'nothing from a publisher of another type', log):
                wanted[name] = s
            elif name not in topics:
                missing.append(name)
        if missing:
            log('bag process: warning: no topic in the bag for these stations of the stations '
                'parameter: ' + ', '.join(missing))
        return list(configured), wanted
    wanted = {}
    for name, t in topics.items():
        if t.msgtype == bagio.POSE_COV_STAMPED and name.startswith(prefix):
            station = bagio.station_from_topic(name[len(prefix) - 1:])
            if station is not None and STATION_ID_RE.match(station):
                wanted[name] = station
    stations = sorted(wanted.values())
    nested = [s for s in stations if '/' in s]
    if nested:
        spaces = sorted({prefix + s.rpartition('/')[0] for s in nested})
        log(f'bag process: warning: stations {", ".join(nested)} are bearing topics of nested '
            f'namespaces ({", ".join(spaces)}), all fused as one network (as '
            'fusion_node does with discover:=true); if a namespace holds the bearings of '
            'another emitter, process it alone with --namespace, or list the stations with '
            '-p stations=[...]')
    return stations, wanted


def process_bag(path, out, params, storage='mcap', namespace='', fix_topic='fix', log=None):
    """Run the fusion node's pipeline (core.fusion.FusionCore + replay) offline over a bag.

    Exactly what fusion_node does, message by message in bag order: a ``/clock`` message
    sets the node clock (and runs the node's timer ticks, via core.fusion.replay); a
    bearing on ``<ns>/<station>/bearing`` is converted from its CDR bytes by
    ``ros_conversions.bearing_from_cdr`` (as the node's raw subscriptions; a ConversionError,
    unreadable bytes included, is counted as a bad message of the station) and given to the
    core at the current node-clock time (the bearing's stamp before the first /clock; the
    bag time when the bag has no /clock). Stations: the ``stations`` parameter, else every
    bearing topic of the namespace in sorted order (:func:`_station_topics`). A ``/clock``
    or ``<ns>/truth`` message that cannot be read is counted as a bad message of its topic
    (reason ``malformed_cdr``) and skipped; such a topic of another message type is ignored
    with a warning. With ``out``, writes ``<out>/`` (a bag with the fixes on
    ``<ns>/fix``, bag time = node-clock time the fix was computed) and ``<out>.csv``,
    creating missing parent directories; with ``out`` None, nothing is written. With
    parameter ``publish_low_confidence`` the CSV also has the epochs whose fix failed its
    consistency checks (column status ``low_confidence``; core.robust). Topics of message
    types that are not installed are ignored with a warning through ``log``. Returns a
    summary dict (epochs, fixes, no_fix reasons, dropped, bad_messages (total) and ``bad``
    ({station or topic: {reason: n}}), and ``errors`` against ``<ns>/truth`` when the bag
    has it).
    """
    from collections import Counter

    import numpy as np
    from rosbags.serde import SerdeError

    from . import bagio
    from .core.evaluation import track_errors
    from .core.fusion import make_core, replay
    from .ros_conversions import bearing_from_cdr, ConversionError
    log = log or (lambda text: print(text, file=sys.stderr, flush=True))
    out = None if out is None else str(out).rstrip('/')
    csv_path = None if out is None else out + '.csv'
    if out is not None and (os.path.exists(out) or os.path.exists(csv_path)):
        raise InputError(f'out: {out} or {csv_path} exists already (never overwritten)')
    ns = namespace.strip('/')
    prefix = '/' + ns + '/' if ns else '/'
    config = fusion_config(params)
    with bagio.BagReader(path) as reader:
        topics = reader.topics
        unknown = [f'{n} ({t.msgtype})' for n, t in sorted(topics.items())
                   if t.msgtype not in bagio.typestore().types]
        if unknown:
            log('bag process: warning: message type not installed, topic ignored: '
                + ', '.join(unknown))
        stations, wanted = _station_topics(topics, prefix, params.get('stations'), log)
        if not wanted:
            which = (f'of the stations {", ".join(stations)} ' if params.get('stations')
                     else '')
            raise InputError(f'bag: no bearing topic {which}({prefix}<station>/bearing, '
                             f'{bagio.POSE_COV_STAMPED}) in {path}')
        truth_topic = prefix + 'truth'
        truth_types = (bagio.POSE_STAMPED, bagio.POSE_COV_STAMPED)
        has_truth = _typed_topic(topics, truth_topic, truth_types,
                                 'no error statistics', log)
        has_clock = _typed_topic(topics, bagio.CLOCK_TOPIC, (bagio.CLOCK,),
                                 'the bag time is taken as the node clock', log)
        core = make_core(config, stations=stations, mode=params.get('mode') or 'auto')
        truth_t, truth_p = [], []
        clock = [None]
        unreadable = Counter()      # (topic, reason) of the /clock and truth messages skipped

        def read(m, types):
            """Message ``m`` deserialized, or None (another type, or unreadable: counted)."""
            if m.msgtype not in types:
                return None
            try:
                return bagio.deserialize(m.raw, m.msgtype)
            except SerdeError:
                unreadable[m.topic, 'malformed_cdr'] += 1
                return None

        def items():
            for m in reader.messages():
                if m.topic == bagio.CLOCK_TOPIC:
                    msg = read(m, (bagio.CLOCK,)) if has_clock else None
                    if msg is not None:
                        clock[0] = bagio.stamp_ns(msg)
                        yield clock[0], None
                elif m.topic in wanted:
                    if m.msgtype != bagio.POSE_COV_STAMPED:
                        continue
                    now = clock[0] if has_clock else m.log_time_ns
                    station = wanted[m.topic]
                    try:
                        b = bearing_from_cdr(m.raw, station, expected_frame=config.frame_id)
                    except ConversionError as exc:
                        core.count_bad_message(station, exc.reason, now)
                        continue
                    yield (now if now is not None else b.stamp_ns), b
                elif m.topic == truth_topic and has_truth:
                    msg = read(m, truth_types)
                    if msg is not None:
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
    fix_name = prefix + fix_topic.strip('/')
    if out is not None:
        rows, row_truth = fixes, truth
        if params.get('publish_low_confidence'):
            # as the node's fix/low_confidence: the CSV also lists the fixes that failed
            # their consistency checks, status low_confidence (never in the bag's fix topic)
            rows = sorted(fixes + [e for e in epochs if e.reason == 'low_confidence'
                                   and e.position is not None], key=lambda e: e.stamp_ns)
            if has_truth and rows:
                gap = int(np.median(np.diff(np.unique(truth_t)))) if len(set(truth_t)) > 1 \
                    else 0
                row_truth = _interp_truth(truth_t, truth_p,
                                          np.array([e.stamp_ns for e in rows], np.int64),
                                          max(gap, NS_PER_S))
        os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
        _write_fix_csv(csv_path, rows, row_truth)
        with bagio.BagWriter(out, storage=storage, custom_data={
                'generator': 'bearing_loc bag process', 'source': str(path),
                'estimator': config.estimator, 'trigger': config.trigger}) as bag:
            bag.add_topic(fix_name, bagio.POSE_COV_STAMPED, bagio.qos_profile(10))
            for e in fixes:
                bag.write(fix_name, e.produced_ns, bagio.fix_message(
                    e.position, e.covariance, e.stamp_ns, config.frame_id))
    bad = {station: dict(st.bad) for station, st in core.registry.all_stats() if st.bad}
    for (topic, reason), n in sorted(unreadable.items()):
        bad.setdefault(topic, {})[reason] = n
    summary = {'stations': stations, 'epochs': len(epochs), 'fixes': len(fixes),
               'no_fix': dict(Counter(e.reason for e in epochs if not e.ok)),
               'dropped': dict(core.dropped),
               'bad_messages': core.bad_messages + sum(unreadable.values()), 'bad': bad,
               'outliers': core.outliers, 'time_jumps': core.time_jumps,
               'estimator': config.estimator, 'fix_topic': fix_name, 'bag': out,
               'csv': csv_path, 'errors': None, 'epoch_list': epochs}
    if truth is not None:
        summary['errors'] = track_errors(truth, pos, cov)
    return summary


def _write_fix_csv(path, fixes, truth):
    """One CSV row per fix: the fix time ``stamp_ns`` first, ``produced_ns`` (node-clock time
    the fix was computed) after the solver figures; ``n_stations``/``stations`` the distinct
    stations, ``n_bearings`` the bearings (more than the stations in window mode)."""
    import csv
    cols = ['stamp_ns', 'stamp_s', 'x', 'y', 'z', 'cov_xx', 'cov_xy', 'cov_xz', 'cov_yy',
            'cov_yz', 'cov_zz', 'n_stations', 'stations', 'rejected', 'estimator', 'status',
            'iterations', 'chi2', 'dof', 'produced_ns', 'n_bearings']
    if truth is not None:
        cols += ['truth_x', 'truth_y', 'truth_z', 'error_m']
    with open(path, 'w', newline='', encoding='utf-8') as f:
        w = csv.writer(f)
        w.writerow(cols)
        for k, e in enumerate(fixes):
            c = e.covariance
            # distinct, in order (a window-mode fix holds many bearings of one station)
            stations = list(dict.fromkeys(e.stations))
            row = [e.stamp_ns, f'{e.stamp_ns / NS_PER_S:.9f}', *map(repr, map(float, e.position)),
                   *(repr(float(c[i, j])) for i, j in UPPER_TRIANGLE),
                   len(stations), ' '.join(stations),
                   ' '.join(b.station for b in e.rejected), e.estimator, e.status,
                   e.iterations, repr(float(e.chi2)), e.dof, e.produced_ns, len(e.bearings)]
            if truth is not None:
                t = truth[k]
                err = math.dist(t, e.position) if all(map(math.isfinite, t)) else float('nan')
                row += [*map(repr, map(float, t)), repr(err)]
            w.writerow(row)
