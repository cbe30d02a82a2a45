"""Offline fusion over a rosbag2 bag (``bearing_loc bag process``).

Runs the fusion node's alignment and estimation core (core.fusion) message by message over a
bag, with the fusion node's parameters, and writes the fixes as a bag and a CSV.
"""

import math
import os
import re
import sys

from .cli import InputError
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


#: The fusion node's name (fusion_node.FusionNode); its namespace is ``--namespace``.
FUSION_NODE_NAME = 'fusion'
#: The key of a node's parameters in a ROS 2 parameter file.
ROS_PARAMETERS = 'ros__parameters'
#: A token of a ROS name: the characters rcl accepts in a node name or namespace.
_TOKEN = re.compile(r'[A-Za-z0-9_]+')


def fusion_node_fqn(namespace=''):
    """Fully qualified name of the fusion node in ``namespace`` ('' or '/': the root):
    ``/fusion``, ``/tx1/fusion``."""
    ns = namespace.strip('/')
    return f'/{ns}/{FUSION_NODE_NAME}' if ns else f'/{FUSION_NODE_NAME}'


def _node_name_problem(name):
    """Why rcl's parameter file parser refuses the node name ``name`` (the keys before
    ``ros__parameters`` joined by '/'), or None. Each token is a ROS name token not starting
    with a digit, or a wildcard ``*`` (one token) or ``**`` (any number of tokens)."""
    full = name if name.startswith('/') else '/' + name
    if '//' in full:
        return 'contains repeated forward slash'
    *spaces, node = full[1:].split('/')
    if not node:
        return 'node name must not be empty'
    for token in spaces:
        if token not in ('*', '**'):
            if not _TOKEN.fullmatch(token):
                return "namespace must not contain characters other than alphanumerics, '_', " \
                       "or '/'"
            if token[0].isdigit():
                return 'namespace must not have a token that starts with a number'
    if node not in ('*', '**'):
        if not _TOKEN.fullmatch(node):
            return "node name must not contain characters other than alphanumerics or '_'"
        if node[0].isdigit():
            return 'node name must not start with a number'
    return None


def node_name_matches(name, fqn):
    """True when the node name ``name`` of a parameter file entry applies to the node whose
    fully qualified name is ``fqn``, as rclpy matches them: a leading '/' is implied, ``*``
    stands for one token and ``**`` for any number of tokens (``/**`` every node,
    ``/**/fusion`` every node named fusion, ``/*/fusion`` one named fusion one namespace
    down)."""
    full = name if name.startswith('/') else '/' + name
    pattern = ''.join('(?:/[A-Za-z0-9_]+)*' if t == '**' else '/[A-Za-z0-9_]+' if t == '*'
                      else '/' + re.escape(t) for t in full[1:].split('/'))
    return re.fullmatch(pattern, fqn) is not None


class _Refused:
    """A parameter value that rcl reads but that is refused here (an empty list, a list of
    lists or mappings, an explicit YAML tag, an integer of thousands of digits): its
    InputError is raised only when the value is the fusion node's, for rcl refuses the
    file for no node then."""

    def __init__(self, error):
        self.error = error


def params_file_entries(path):
    """The node entries of ROS 2 parameter file ``path`` as rcl's parser makes them: a list
    of (node name as written, {dotted parameter name: value}).

    Checked against rclpy (``--ros-args --params-file``), ROS 2 Jazzy: the keys above
    ``ros__parameters`` are joined by '/' into the node name (``ns: {fusion:
    {ros__parameters: ...}}`` is ``ns/fusion``); entries with the same name, also in later
    documents of the file, are one entry at the place of the first; within an entry a
    parameter given again (directly, or as ``a.b`` and ``a: {b: ...}``) takes the later
    value. Values are typed as rcl types them (core.yaml_file.params_loader); one that rcl
    reads but that is refused here (``[]``) is a ``_Refused`` holding its error. Raises
    InputError naming the file and line for what rcl refuses: invalid YAML, an empty value
    or a list mixing types, an alias (``*name``), a node name rcl refuses, a value where a
    node name or ``ros__parameters`` is expected, keys after ``ros__parameters``.
    """
    import yaml
    from .core.yaml_file import params_loader
    label = f'params_file: {path}'
    try:
        with open(path, encoding='utf-8') as f:
            text = f.read()
    except OSError as exc:
        raise InputError(f'{label}: cannot read file ({exc.strerror or exc})') from None
    except UnicodeDecodeError:
        raise InputError(f'{label}: not a UTF-8 text file') from None
    loader_class = params_loader()
    try:
        documents = list(yaml.compose_all(text, Loader=loader_class))
    except yaml.YAMLError as exc:
        raise InputError(f'{label}: invalid YAML ({" ".join(str(exc).split())})') from None
    except RecursionError:
        raise InputError(f'{label}: invalid YAML (nested too deeply)') from None
    constructor = loader_class('')
    entries = {}
    seen = set()

    def fail(node, problem):
        raise InputError(f'{label}: line {node.start_mark.line + 1}: {problem}')

    def visit(node):            # each YAML node once: rcl refuses aliases
        if id(node) in seen:
            fail(node, 'an alias (*name): ROS 2 parameter files cannot use them')
        seen.add(id(node))

    def key_text(key):
        visit(key)
        if not isinstance(key, yaml.ScalarNode):
            fail(key, 'a key must be a name, not a list or a mapping')
        return key.value

    def value(node, name):
        visit(node)
        items = node.value if isinstance(node, yaml.SequenceNode) else ()
        for child in items:
            visit(child)
        try:
            return constructor.construct_document(node)
        except (yaml.YAMLError, ValueError) as exc:
            problem = getattr(exc, 'problem', None) or ''
            error = InputError(f'{label}: invalid YAML ({name}: '
                               f'{" ".join(str(exc).split())})')
        if problem == 'no value' or (problem.startswith('a list must hold') and all(
                isinstance(c, yaml.ScalarNode) for c in items)):
            raise error                 # rcl refuses the file: no node starts
        return _Refused(error)          # rcl reads it: an error only for the node it is for

    def parameters(node, prefix, out):
        for key, child in node.value:
            name = prefix + key_text(key)
            if isinstance(child, yaml.MappingNode):
                visit(child)
                parameters(child, name + '.', out)
            else:
                out[name] = value(child, name)

    def nodes(node, names):
        visit(node)
        if not isinstance(node, yaml.MappingNode):
            fail(node, f'expected "<node>: {ROS_PARAMETERS}:" mappings'
                 + (f' under {"/".join(names)}' if names else ''))
        after = None
        for key, child in node.value:
            text = key_text(key)
            if after is not None:
                fail(key, f'{text!r} after the {ROS_PARAMETERS} of {after} (ROS 2 refuses '
                     'keys that follow a ros__parameters mapping)')
            if text != ROS_PARAMETERS:
                nodes(child, names + [text])
                continue
            if not names:
                fail(key, f'{ROS_PARAMETERS} without a node name above it')
            name = '/'.join(names)
            problem = _node_name_problem(name)
            if problem:
                fail(key, f'node name {name!r}: {problem}')
            visit(child)
            if isinstance(child, yaml.SequenceNode) and not child.value:
                child = yaml.MappingNode('tag:yaml.org,2002:map', [])   # rcl: no parameter
            if not isinstance(child, yaml.MappingNode):
                fail(child, f'the {ROS_PARAMETERS} of {name}: expected a mapping of '
                     'parameter names to values')
            parameters(child, '', entries.setdefault(name, {}))
            after = name

    for doc in documents:
        if not isinstance(doc, (type(None), yaml.ScalarNode)):   # rcl skips a bare scalar
            nodes(doc, [])
    return list(entries.items())


def fusion_file_parameters(path, namespace=''):
    """{dotted name: value} the fusion node in ``namespace`` gets from parameter file
    ``path``, as rclpy gives them: every entry whose node name matches the node
    (:func:`node_name_matches`: ``/**``, ``fusion``, ``/fusion``, ``/<ns>/fusion``,
    ``/**/fusion``, ``/*/fusion`` ...) in the order of :func:`params_file_entries`, a later
    entry overriding an earlier one; entries of other nodes (``station_1:``) are ignored.
    The second value is the list of the file's node names, None when some matched."""
    fqn = fusion_node_fqn(namespace)
    entries = params_file_entries(path)
    out, matched = {}, False
    for name, params in entries:
        if node_name_matches(name, fqn):
            out.update(params)
            matched = True
    for v in out.values():
        if isinstance(v, _Refused):
            raise v.error
    return out, (None if matched else [name for name, _ in entries])


def read_params_file(path, namespace=''):
    """The fusion node's parameters from ROS 2 parameter file ``path`` as nested mappings
    (dotted names nested: ``accuracy_map: {enabled: ...}``), picked and merged as
    :func:`fusion_file_parameters` says. Raises InputError naming the file."""
    flat, _ = fusion_file_parameters(path, namespace)
    out = {}
    for name, v in flat.items():
        *parents, leaf = name.split('.')
        node = out
        for p in parents:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):       # 'a' and 'a.b' both given: keep it flat
                node = None
                break
        if node is None:
            out[name] = v
        else:
            node[leaf] = v
    return out


def fusion_params(params_file=None, overrides=(), estimator=None, namespace=''):
    """Fusion node parameters: schema defaults < params file < NAME=VALUE overrides <
    estimator; each checked against the schema (type, range, allowed values), and the
    ``stations`` as the node checks them (``check_station_ids``: valid ids, each once).
    The params file gives what the fusion node in ``namespace`` gets from it
    (:func:`fusion_file_parameters`; a warning on stderr when no entry of the file is the
    node's). Deprecated names are mapped to the current ones with a warning on stderr."""
    import yaml
    from .core.fusion.config import check_station_ids
    from .core.yaml_file import load_param_text
    given = {}
    if params_file:
        given, others = fusion_file_parameters(params_file, namespace)
        if others is not None:
            print(f'warning: params_file: {params_file}: no entry applies to the fusion node '
                  f'{fusion_node_fqn(namespace)} (entries: {", ".join(others) or "none"}); '
                  'its defaults are used', file=sys.stderr)
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
        params = parameters.resolve('fusion_node', given,
                                    warn=lambda text: print(f'warning: {text}',
                                                            file=sys.stderr))
    except ValueError as exc:
        name, _, problem = str(exc).partition(': ')
        if problem.startswith('not a parameter'):
            raise InputError(f'{name}: not a fusion node parameter'
                             f'{parameters.did_you_mean("fusion_node", name)}') from None
        raise InputError(str(exc)) from None
    try:
        check_station_ids(params.get('stations') or [])
    except ValueError as exc:
        raise InputError(str(exc)) from None
    return params


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
    has it), and ``count_mismatches`` ([(topic, read, listed)]: the topics of which another
    number of messages was read than metadata.yaml lists, also named in a warning through
    ``log``; a damaged storage file that cannot be read on is a ValueError, see
    bagio.BagReader.messages).
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
        mismatches = reader.count_mismatches()
    text = bagio.count_warning(mismatches)
    if text:
        log(f'bag process: warning: {text}')
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
               'csv': csv_path, 'errors': None, 'epoch_list': epochs,
               'count_mismatches': mismatches}
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
