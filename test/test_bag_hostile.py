"""bag process / play / info given hostile input: each bad message is counted, each unusable
topic or option named in one line, never a traceback.

Every bag here is the 2 s static3 bag (seed 7) rewritten: one message cut short, /clock or
truth of another type, a station topic of another type, missing or not installed, bearing
topics in two nested namespaces, an MCAP file cut short; plus `bag play` options out of
range and the clock of a looping `bag play`.
"""
import os
import shutil

import pytest

from bearing_loc_ros import bagio
from bearing_loc_ros.bag_process import fusion_params, process_bag
from bearing_loc_ros.cli import main as cli_main

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
STATIC3 = os.path.join(REPO, 'config', 'scenarios', 'static3.yaml')
SEED = 7
STRING = 'std_msgs/msg/String'
NOT_INSTALLED = 'df_msgs/msg/Doa'


@pytest.fixture(scope='module')
def src(tmp_path_factory):
    """The static3 bag (mcap), 2 s: /station_1..3/bearing, /truth, /clock."""
    from bearing_loc_ros.cli.bag import simulate_bag
    from bearing_loc_ros.core.simulation import load_scenario
    path = tmp_path_factory.mktemp('hostile') / 'static3'
    simulate_bag(load_scenario(STATIC3), path, seed=SEED)
    return path


def rewrite(src, dst, transform=None, types=None):
    """Copy bag ``src`` to ``dst``: ``transform(m)`` -> [(topic, bag time, raw or message)]
    (default: the message as it is); ``types``: {topic: message type} of the copy's topics
    (default: the source's, for the topics the transform writes)."""
    with bagio.BagReader(src) as reader:
        msgs = list(reader.messages())
        types = dict({n: t.msgtype for n, t in reader.topics.items()}, **(types or {}))
    out = [o for m in msgs for o in (transform(m) if transform else
                                     [(m.topic, m.log_time_ns, m.raw)])]
    with bagio.BagWriter(dst) as bag:
        for topic in dict.fromkeys(o[0] for o in out):
            bag.add_topic(topic, types[topic])
        for o in out:
            bag.write(*o)
    return dst


def cut_nth(topic, n, keep):
    """Transform: the ``n``-th message on ``topic`` cut to its first ``keep`` bytes."""
    seen = [0]

    def transform(m):
        if m.topic == topic:
            seen[0] += 1
            if seen[0] == n:
                return [(m.topic, m.log_time_ns, m.raw[:keep])]
        return [(m.topic, m.log_time_ns, m.raw)]
    return transform


def string_on(topic):
    """Transform: every message on ``topic`` replaced by a std_msgs/String."""
    text = bagio.typestore().types[STRING](data='x')

    def transform(m):
        return [(m.topic, m.log_time_ns, text if m.topic == topic else m.raw)]
    return transform


def run(capsys, *args):
    """``bearing_loc <args>`` in-process: (exit code, stdout, stderr)."""
    capsys.readouterr()
    code = cli_main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize('topic,keep,where', [
    ('/station_1/bearing', 20, 'station_1'), ('/clock', 6, '/clock'), ('/truth', 10, '/truth')])
def test_an_unreadable_message_is_counted_not_raised(src, tmp_path, capsys, topic, keep,
                                                     where):
    bag = rewrite(src, tmp_path / 'cut', cut_nth(topic, 3, keep))
    ref = process_bag(src, None, fusion_params(), log=lambda s: None)
    got = process_bag(bag, None, fusion_params(), log=lambda s: None)
    assert got['bad'] == {where: {'malformed_cdr': 1}}
    assert got['bad_messages'] == 1 and got['fixes'] > 0 and got['errors']['n'] > 0
    if where != 'station_1':          # a lost /clock tick or truth sample changes no fix
        assert [e.position.tolist() for e in got['epoch_list'] if e.ok] == \
            [e.position.tolist() for e in ref['epoch_list'] if e.ok]
    code, out, err = run(capsys, 'bag', 'process', str(bag))
    assert code == 0 and 'Traceback' not in err
    assert f'bad messages 1 ({where}: malformed_cdr 1)' in out


def test_clock_or_truth_of_another_type_is_ignored_with_a_warning(src, tmp_path, capsys):
    no_clock = rewrite(src, tmp_path / 'no_clock',
                       lambda m: [] if m.topic == '/clock' else [(m.topic, m.log_time_ns, m.raw)])
    bag = rewrite(src, tmp_path / 'clock_str', string_on('/clock'), {'/clock': STRING})
    warnings = []
    got = process_bag(bag, None, fusion_params(), log=warnings.append)
    assert warnings == ['bag process: warning: /clock has type std_msgs/msg/String, not '
                        'rosgraph_msgs/msg/Clock: ignored (the bag time is taken as the node '
                        'clock)']
    ref = process_bag(no_clock, None, fusion_params(), log=lambda s: None)
    assert [e.position.tolist() for e in got['epoch_list'] if e.ok] == \
        [e.position.tolist() for e in ref['epoch_list'] if e.ok]
    bag = rewrite(src, tmp_path / 'truth_str', string_on('/truth'), {'/truth': STRING})
    code, out, err = run(capsys, 'bag', 'process', str(bag))
    assert code == 0 and 'Traceback' not in err
    assert '/truth has type std_msgs/msg/String' in err and 'no error statistics' in err
    assert 'fixes' in out and 'error against truth' not in out


def _with_topic_not_installed(src, dst, topic):
    """Copy of ``src`` plus ``topic`` of a message type that no installed package has."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import get_types_from_msg, get_typestore, Stores
    ts = get_typestore(Stores.ROS2_JAZZY)
    ts.register(get_types_from_msg('float64 azimuth', NOT_INSTALLED))
    doa = bytes(ts.serialize_cdr(ts.types[NOT_INSTALLED](azimuth=1.0), NOT_INSTALLED))
    writer = Writer(dst, version=9)
    writer.open()
    with bagio.BagReader(src) as reader:
        conns = {n: writer.add_connection(n, t.msgtype, typestore=ts)
                 for n, t in reader.topics.items()}
        extra = writer.add_connection(topic, NOT_INSTALLED, typestore=ts)
        for m in reader.messages():
            writer.write(conns[m.topic], m.log_time_ns, m.raw)
            if m.topic == '/station_1/bearing':
                writer.write(extra, m.log_time_ns, doa)
    writer.close()
    return dst


def test_stations_without_a_usable_topic_are_named(src, tmp_path, capsys):
    """-p stations=[...]: a station whose topic is missing, of another type or of a type not
    installed is named in a warning; with no usable one left, a one-line error."""
    def pose_on_station_4(m):
        out = [(m.topic, m.log_time_ns, m.raw)]
        if m.topic == '/station_1/bearing':
            msg = bagio.deserialize(m.raw, m.msgtype)
            out.append(('/station_4/bearing', m.log_time_ns, bagio.truth_message(
                bagio.position_of(msg), bagio.stamp_ns(msg))))
        return out
    bag = rewrite(src, tmp_path / 'pose', pose_on_station_4,
                  {'/station_4/bearing': bagio.POSE_STAMPED})
    stations = '-p', 'stations=["station_1", "station_2", "station_4", "nope"]'
    code, out, err = run(capsys, 'bag', 'process', str(bag), *stations)
    assert code == 0 and 'Traceback' not in err
    assert ('/station_4/bearing has type geometry_msgs/msg/PoseStamped, not '
            'geometry_msgs/msg/PoseWithCovarianceStamped: ignored') in err
    assert 'no topic in the bag for these stations of the stations parameter: /nope/bearing' \
        in err
    assert 'stations station_1, station_2, station_4, nope;' in out
    code, out, err = run(capsys, 'bag', 'process', str(bag), '-p', 'stations=["station_4"]')
    assert code == 2 and 'Traceback' not in err and out == ''
    assert err.splitlines()[-1] == (
        f'bearing_loc bag: error: bag: no bearing topic of the stations station_4 '
        f'(/<station>/bearing, geometry_msgs/msg/PoseWithCovarianceStamped) in {bag}')
    bag = _with_topic_not_installed(src, tmp_path / 'doa', '/station_5/bearing')
    code, out, err = run(capsys, 'bag', 'process', str(bag), '-p', 'stations=["station_5"]')
    assert code == 2 and 'Traceback' not in err
    assert f'/station_5/bearing ({NOT_INSTALLED})' in err
    assert 'no bearing topic of the stations station_5' in err


class GraphOf:
    """The ROS graph the fusion node's discovery sees while bag ``topics`` play, for a node
    in ``namespace`` (what ros_common.topics_under_namespace asks)."""

    def __init__(self, topics, namespace):
        self.topics, self.namespace = topics, namespace

    def get_namespace(self):
        return self.namespace

    def get_topic_names_and_types(self):
        return [(n, [t.msgtype]) for n, t in self.topics.items()]


def test_nested_namespaces_choose_the_live_nodes_topics_and_warn(src, tmp_path):
    """Two emitters' networks in /tx1 and /tx2: bag process takes the topics fusion_node
    with discover:=true takes in the same namespace, and says when some are nested."""
    from bearing_loc_ros.core.fusion.config import STATION_ID_RE
    from bearing_loc_ros.fusion_wiring import BEARING_TYPE
    from bearing_loc_ros.ros_common import topics_under_namespace

    def two_networks(m):
        if m.topic == '/clock':
            return [(m.topic, m.log_time_ns, m.raw)]
        out = [(f'/tx1{m.topic}', m.log_time_ns, m.raw), (f'/tx2{m.topic}', m.log_time_ns, m.raw)]
        if m.topic == '/station_1/bearing':       # not a ROS name: no station of the node's
            out.append(('/tx1/1st/bearing', m.log_time_ns, m.raw))
        return out
    names = [('/truth', bagio.POSE_STAMPED)] + [
        (f'/station_{k}/bearing', bagio.POSE_COV_STAMPED) for k in (1, 2, 3)]
    types = {f'/{ns}{n}': t for ns in ('tx1', 'tx2') for n, t in names}
    bag = rewrite(src, tmp_path / 'two', two_networks,
                  dict(types, **{'/tx1/1st/bearing': bagio.POSE_COV_STAMPED}))
    with bagio.BagReader(bag) as reader:
        topics = reader.topics
    for ns in ('/', '/tx1'):
        live = topics_under_namespace(GraphOf(topics, ns), '/bearing', BEARING_TYPE,
                                      STATION_ID_RE)
        warnings = []
        s = process_bag(bag, None, fusion_params(), namespace=ns, log=warnings.append)
        assert s['stations'] == sorted(live), ns
        if ns == '/':
            assert s['stations'] == [f'tx{k}/station_{j}' for k in (1, 2) for j in (1, 2, 3)]
            assert len(warnings) == 1 and '(/tx1, /tx2)' in warnings[0]
            assert '--namespace' in warnings[0]
        else:
            assert s['stations'] == ['station_1', 'station_2', 'station_3'] and not warnings
            assert s['errors']['n'] > 0
    # stations given: no guess, no warning
    warnings = []
    s = process_bag(bag, None, fusion_params(None, ['stations=["tx1/station_1", '
                                                    '"tx1/station_2", "tx1/station_3"]']),
                    log=warnings.append)
    assert not warnings and s['fixes'] > 0


def test_out_in_missing_directories_is_created_before_writing(src, tmp_path, monkeypatch,
                                                              capsys):
    monkeypatch.chdir(tmp_path)
    code, out, err = run(capsys, 'bag', 'process', str(src), '--out', 'nodir/sub/fx')
    assert code == 0 and 'Traceback' not in err, err
    assert (tmp_path / 'nodir/sub/fx/metadata.yaml').is_file()
    assert (tmp_path / 'nodir/sub/fx.csv').is_file()
    (tmp_path / 'file').write_text('')
    code, out, err = run(capsys, 'bag', 'process', str(src), '--out', 'file/sub/fx')
    assert code == 2 and "file' is not a directory" in err and err.count('\n') == 1


@pytest.mark.parametrize('size,problem', [(0.5, 'looks truncated'), (0, 'is empty')])
@pytest.mark.parametrize('verb', ['info', 'process', 'play'])
def test_truncated_mcap_is_named_with_what_to_do(src, tmp_path, capsys, size, problem, verb):
    bag = tmp_path / 'cut'
    shutil.copytree(src, bag)
    mcap = bag / 'static3.mcap'
    os.truncate(mcap, int(mcap.stat().st_size * size))
    code, out, err = run(capsys, 'bag', verb, str(bag))
    assert code == 2 and 'Traceback' not in err
    assert err.startswith(f'bearing_loc bag: error: bag: cannot open {bag}: static3.mcap '
                          f'{problem}') and err.count('\n') == 1
    if size:
        assert 'mcap recover static3.mcap -o recovered.mcap' in err


@pytest.mark.parametrize('option', ['--delay', '--wait-for-subscribers'])
@pytest.mark.parametrize('value', ['inf', 'nan', '-1', '1e300'])
def test_play_refuses_waits_out_of_range(src, capsys, option, value):
    code, out, err = run(capsys, 'bag', 'play', str(src), option, value, '--quiet')
    name = option[2:].replace('-', '_')
    assert code == 2 and 'Traceback' not in err
    assert err == f'bearing_loc bag: error: {name}: must be within [0, 86400] s (got ' \
                  f'{float(value)})\n'


class Recorder:
    """A publisher that appends (topic, message) to a shared list."""

    def __init__(self, topic, sent):
        self.topic, self.sent = topic, sent

    def publish(self, msg):
        self.sent.append((self.topic, msg))


def test_loop_pass_jumps_the_clock_back_before_its_first_data(src):
    """A pass of `bag play --loop` after the first sends the bag's first /clock before the
    first instant's data (the node would take them for data of the bag's end and drop
    them as out of order); the first pass sends data before the clock of their instant."""
    from bearing_loc_ros.bag_player import _play_once
    with bagio.BagReader(src) as reader:
        topics = set(reader.topics)
        first_clock = next(m.raw for m in reader.messages(topics={'/clock'}))
    for again in (False, True):
        sent = []
        pubs = {t: Recorder(t, sent) for t in topics}
        n = _play_once(src, pubs, None, 1e9, 10_000_000, topics, True, print, again)
        data = [k for k, (t, _) in enumerate(sent) if t != '/clock']
        if again:
            assert sent[0] == ('/clock', first_clock) and data[0] > 0
            assert len(sent) == n + 1
        else:
            assert data[0] == 0 and len(sent) == n


@pytest.mark.ros
def test_loop_passes_after_the_first_jump_the_clock_first(src, monkeypatch):
    from bearing_loc_ros import bag_player
    calls = []

    def one_pass(*args):
        calls.append(args[-1])
        if len(calls) == 3:
            raise KeyboardInterrupt
        return 0
    monkeypatch.setattr(bag_player, '_play_once', one_pass)
    assert bag_player.play_bag(src, loop=True, wait_for_subscribers=0, quiet=True) == 0
    assert calls == [False, True, True]


@pytest.mark.parametrize('option, value, message', [
    ('--rate', '1e-300', 'rate: must be in [1e-06, 1e+06] (got 1e-300)'),
    ('--rate', 'inf', 'rate: must be in [1e-06, 1e+06] (got inf)'),
    ('--clock-rate', '1e9', 'clock_rate: must be in [0, 1e4] Hz (got 1000000000.0)')])
def test_play_refuses_rates_out_of_range(src, capsys, option, value, message):
    # --rate 1e-300 overflowed in the wait (bag time / rate)
    code, out, err = run(capsys, 'bag', 'play', str(src), option, value, '--quiet')
    assert code == 2 and err == f'bearing_loc bag: error: {message}\n'


def test_csv_counts_distinct_stations_and_the_bearings(tmp_path):
    # A window-mode fix holds a window of one station's bearings: n_stations was the bearing
    # count and stations repeated "car" once per bearing.
    import csv
    from types import SimpleNamespace

    import numpy as np

    from bearing_loc_ros.bag_process import _write_fix_csv
    fix = SimpleNamespace(stamp_ns=10 ** 9, position=np.zeros(3), covariance=np.eye(3),
                          bearings=[object()] * 5, stations=['car', 'car', 'van', 'car', 'van'],
                          rejected=[], estimator='mle', status='ok', iterations=3, chi2=1.0,
                          dof=3, produced_ns=10 ** 9)
    _write_fix_csv(tmp_path / 'f.csv', [fix], None)
    with open(tmp_path / 'f.csv', encoding='utf-8') as f:
        (row,) = csv.DictReader(f)
    assert (row['n_stations'], row['stations'], row['n_bearings']) == ('2', 'car van', '5')
    from bearing_loc_ros.core.gis import GeoFix      # the GeoJSON, KML and geo CSV record
    assert GeoFix.from_epoch(SimpleNamespace(**vars(fix), reason='')).stations == ['car', 'van']
