"""Damaged or edited bags, and the fusion node's parameters as `bag process` reads them.

The bags are the 2 s static3 scenario (seed 7) written by `bag simulate`'s code, then
damaged: bytes of the .mcap file overwritten, a record hidden, metadata.yaml fields of the
wrong type, sqlite3 rows changed. Each must give one line on stderr with exit code 2 naming
the bag, the file and what is wrong, or a counted loss named in a warning; never a
traceback or silently fewer messages. The parameter-file tests compare what `bag process`
takes from a file with what rclpy gives a node named fusion from the same file.
"""
import os
import shutil
import sqlite3

import pytest
import yaml

from bearing_loc_ros import bagio
from bearing_loc_ros.bag_process import fusion_file_parameters, fusion_params, process_bag
from bearing_loc_ros.cli import InputError, main as cli_main

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
STATIC3 = os.path.join(REPO, 'config', 'scenarios', 'static3.yaml')
SEED = 7
PLAY = ('--rate', '1e6', '--wait-for-subscribers', '0', '--quiet')


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    """The static3 bag (2 s) in both storages: /station_1..3/bearing, /truth, /clock."""
    from bearing_loc_ros.cli.bag import simulate_bag
    from bearing_loc_ros.core.simulation import load_scenario
    root = tmp_path_factory.mktemp('damaged')
    out = {}
    for storage in bagio.STORAGES:
        out[storage] = root / f'static3_{storage}'
        simulate_bag(load_scenario(STATIC3), out[storage], seed=SEED, storage=storage)
    return out


def copy(src, dst):
    """A copy of bag directory ``src`` at ``dst``."""
    shutil.copytree(src, dst)
    return dst


def storage_file(bag):
    """The one storage file (.mcap or .db3) of ``bag``."""
    return next(p for p in bag.iterdir() if p.suffix in ('.mcap', '.db3'))


def xor_bytes(path, start, length):
    """Flip the bits of bytes ``start`` .. ``start + length`` of file ``path``."""
    data = bytearray(path.read_bytes())
    for i in range(start, min(len(data), start + length)):
        data[i] ^= 0xA5
    path.write_bytes(bytes(data))


def edit_metadata(bag, keys, value):
    """Set rosbag2_bagfile_information[keys[0]][keys[1]]... of ``bag`` to ``value``."""
    meta = bag / 'metadata.yaml'
    doc = yaml.safe_load(meta.read_text(encoding='utf-8'))
    node = doc[bagio.METADATA_KEY]
    for k in keys[:-1]:
        node = node[k]
    node[keys[-1]] = value
    meta.write_text(yaml.safe_dump(doc), encoding='utf-8')


def run(capsys, *args):
    """``bearing_loc <args>`` in-process: (exit code, stdout, stderr)."""
    capsys.readouterr()
    code = cli_main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(code, err):
    """True when the command failed as the tool's contract says: exit 2, one line."""
    return code == 2 and err.count('\n') == 1 and 'Traceback' not in err


# ------------------------------------------------------------ a storage file damaged inside

@pytest.mark.parametrize('verb', ['process', pytest.param('play', marks=pytest.mark.ros)])
def test_a_damaged_mcap_file_is_one_line_naming_the_bag(bags, tmp_path, capsys, verb):
    # rosbags raised OverflowError (or struct.error, ReaderError) while the messages were
    # read, and nothing caught it
    bag = copy(bags['mcap'], tmp_path / 'damaged')
    mcap = storage_file(bag)
    xor_bytes(mcap, mcap.stat().st_size // 3, 2000)
    code, out, err = run(capsys, 'bag', verb, str(bag), *(PLAY if verb == 'play' else ()))
    assert one_error_line(code, err), err
    assert err.startswith(f'bearing_loc bag: error: bag: cannot read {bag}: {mcap.name} is '
                          'damaged: reading stopped after '), err
    assert f'mcap recover {mcap.name} -o recovered.mcap' in err


def test_no_damage_of_an_mcap_file_escapes_as_another_error(bags, tmp_path):
    """Eight bytes flipped anywhere in the file: the messages are read, or a one-line
    ValueError naming the bag says why not; no other exception."""
    size = storage_file(bags['mcap']).stat().st_size
    failures = 0
    for k, start in enumerate(range(0, size, size // 60)):
        bag = copy(bags['mcap'], tmp_path / f'd{k}')
        xor_bytes(storage_file(bag), start, 8)
        try:
            with bagio.BagReader(bag) as reader:
                for _ in reader.messages():
                    pass
        except ValueError as exc:
            assert str(exc).startswith('bag: ') and '\n' not in str(exc)
            failures += 1
        shutil.rmtree(bag)
    assert failures > 0


# ----------------------------------------------------------------- metadata.yaml fields

@pytest.mark.parametrize('keys, value, shown', [
    (('topics_with_message_count', 0, 'message_count'), 'abc',
     'topics_with_message_count[0].message_count: expected a message count, got \'abc\''),
    (('starting_time', 'nanoseconds_since_epoch'), 'abc',
     'starting_time.nanoseconds_since_epoch: expected an integer (ns), got \'abc\''),
    (('message_count',), -5, 'message_count: expected a message count >= 0, got -5'),
    (('version',), 'nine', 'version: expected an integer, got \'nine\''),
    (('storage_identifier',), ['mcap'], 'storage_identifier: expected a string, got [\'mcap\']'),
    (('topics_with_message_count', 1, 'topic_metadata', 'offered_qos_profiles'), 'garbage',
     'topics_with_message_count[1].topic_metadata.offered_qos_profiles: expected a list of '
     'QoS profiles'),
    (('relative_file_paths',), [], 'relative_file_paths: the list is empty'),
])
@pytest.mark.parametrize('verb', ['info', 'process', 'play'])
def test_a_metadata_field_of_the_wrong_kind_is_named(bags, tmp_path, capsys, keys, value,
                                                     shown, verb):
    # a text message_count was a TypeError traceback; an empty file list gave "0 epochs"
    bag = copy(bags['mcap'], tmp_path / 'edited')
    edit_metadata(bag, keys, value)
    code, out, err = run(capsys, 'bag', verb, str(bag), *(PLAY if verb == 'play' else ()))
    assert one_error_line(code, err), err
    assert err.startswith(f'bearing_loc bag: error: bag: {bag / "metadata.yaml"}: '
                          f'rosbag2_bagfile_information.{shown}'), err


def test_a_text_time_in_an_sqlite3_bag_names_bag_file_and_column(bags, tmp_path, capsys):
    # was "error: invalid literal for int() with base 10: 'abc'", naming neither
    bag = copy(bags['sqlite3'], tmp_path / 'text_time')
    db = storage_file(bag)
    with sqlite3.connect(db) as con:
        con.execute("UPDATE messages SET timestamp = 'abc' WHERE id = 7")
    code, out, err = run(capsys, 'bag', 'process', str(bag))
    assert one_error_line(code, err), err
    assert err.startswith(f'bearing_loc bag: error: bag: cannot read {bag}: {db.name} is '
                          'damaged: '), err
    assert "(sqlite3 column messages.timestamp) is 'abc', not an integer (ns)" in err


# ------------------------------------------------------------------------ bag play /clock

def _clock_of_zeros(bags, dst):
    """The sqlite3 bag with its 10th /clock message's data replaced by 32 zero bytes."""
    bag = copy(bags['sqlite3'], dst)
    with sqlite3.connect(storage_file(bag)) as con:
        con.execute("UPDATE messages SET data = zeroblob(32) WHERE id = (SELECT m.id FROM "
                    "messages m JOIN topics t ON m.topic_id = t.id WHERE t.name = '/clock' "
                    "ORDER BY m.timestamp LIMIT 1 OFFSET 9)")
    return bag


@pytest.mark.ros
def test_play_skips_and_counts_an_unreadable_clock_message(bags, tmp_path, capsys):
    # was RCLError "Failed to publish: cannot publish data" with a traceback, exit 1
    bag = _clock_of_zeros(bags, tmp_path / 'clock')
    code, out, err = run(capsys, 'bag', 'play', str(bag), *PLAY)
    assert code == 0 and 'Traceback' not in err, err
    assert err == ('bag play: warning: skipped 1 message(s) that cannot be published: '
                   '/clock: malformed_cdr 1\n')
    code, out, err = run(capsys, 'bag', 'process', str(bag))
    assert code == 0 and 'bad messages 1 (/clock: malformed_cdr 1)' in out


class Recorder:
    """A publisher that appends (topic, raw) to a shared list; ``refuse``: the indexes of
    its messages it refuses as rclpy does (RCLError)."""

    def __init__(self, topic, sent, refuse=()):
        self.topic, self.sent, self.refuse, self.n = topic, sent, set(refuse), 0

    def publish(self, raw):
        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
        self.n += 1
        if self.n in self.refuse:
            raise _rclpy.RCLError('Failed to publish: cannot publish data')
        self.sent.append((self.topic, raw))


def test_play_counts_a_message_the_middleware_refuses(bags, monkeypatch):
    import rclpy
    from bearing_loc_ros.bag_player import _play_once
    monkeypatch.setattr(rclpy, 'ok', lambda *args, **kw: True)   # as in a running player
    with bagio.BagReader(bags['mcap']) as reader:
        topics = set(reader.topics)
        total = reader.message_count
    sent, logs = [], []
    pubs = {t: Recorder(t, sent, [3] if t == '/station_2/bearing' else []) for t in topics}
    n = _play_once(bags['mcap'], pubs, None, 1e9, 10_000_000, topics, True, logs.append)
    assert n == len(sent) == total - 1
    assert logs == ['bag play: warning: skipped 1 message(s) that cannot be published: '
                    '/station_2/bearing: publish_failed 1']


# ------------------------------------------------------------- messages silently lost

def _record_hidden(bags, dst, topic, n):
    """The mcap bag with the record of the ``n``-th message of ``topic`` given an opcode
    no reader knows: readers skip it as an unknown record, as they skip the records of a
    chunk whose bytes were zeroed."""
    bag = copy(bags['mcap'], dst)
    with bagio.BagReader(bag) as reader:
        raw = [m.raw for m in reader.messages(topics={topic})][n - 1]
    mcap = storage_file(bag)
    data = bytearray(mcap.read_bytes())
    at = data.index(raw) - 31      # opcode, length (8), channel (2), sequence (4), 2 times
    assert data[at] == 0x05        # a message record
    data[at] = 0x7F
    mcap.write_bytes(bytes(data))
    return bag


def test_messages_lost_from_the_storage_file_are_named_with_both_counts(
        bags, tmp_path, capsys):
    # process read fewer messages, exit 0, no word; info still listed them all
    bag = _record_hidden(bags, tmp_path / 'hidden', '/station_1/bearing', 5)
    warning = ('warning: messages read differ from the counts metadata.yaml lists (a '
               'damaged storage file, or a metadata.yaml that does not describe it): '
               '/station_1/bearing 19 read of 20 listed')
    logs = []
    s = process_bag(bag, None, fusion_params(), log=logs.append)
    assert s['count_mismatches'] == [('/station_1/bearing', 19, 20)]
    assert logs == ['bag process: ' + warning]
    code, out, err = run(capsys, 'bag', 'process', str(bag))
    assert code == 0 and err == f'bag process: {warning}\n'
    code, out, err = run(capsys, 'bag', 'process', str(bags['mcap']))
    assert code == 0 and err == ''
    from bearing_loc_ros.bag_player import _play_once
    with bagio.BagReader(bag) as reader:
        topics = set(reader.topics)
    logs = []
    _play_once(bag, {t: Recorder(t, []) for t in topics}, None, 1e9, 10_000_000, topics,
               True, logs.append)
    assert logs == ['bag play: ' + warning]


@pytest.mark.parametrize('storage, where', [('mcap', 'metadata'), ('sqlite3', 'metadata'),
                                            ('sqlite3', 'storage')])
def test_a_topic_described_otherwise_than_in_the_storage_file_is_an_error(
        bags, tmp_path, capsys, storage, where):
    # a bearing topic whose type differs between metadata.yaml and the storage file was
    # listed as a station that contributed nothing (or silently dropped from the stations)
    bag = copy(bags[storage], tmp_path / 'retyped')
    meta_type, stored_type = bagio.POSE_COV_STAMPED, bagio.POSE_COV_STAMPED
    if where == 'metadata':
        doc = yaml.safe_load((bag / 'metadata.yaml').read_text(encoding='utf-8'))
        k = next(k for k, t in enumerate(doc[bagio.METADATA_KEY]['topics_with_message_count'])
                 if t['topic_metadata']['name'] == '/station_1/bearing')
        edit_metadata(bag, ('topics_with_message_count', k, 'topic_metadata', 'type'),
                      bagio.POSE_STAMPED)
        meta_type = bagio.POSE_STAMPED
    else:           # the sqlite3 topics table (an MCAP channel's type is a shared schema)
        with sqlite3.connect(storage_file(bag)) as con:
            con.execute("UPDATE topics SET type = 'std_msgs/msg/String' "
                        "WHERE name = '/station_1/bearing'")
        stored_type = 'std_msgs/msg/String'
    for verb in ('process', 'play'):
        code, out, err = run(capsys, 'bag', verb, str(bag), *(PLAY if verb == 'play' else ()))
        assert one_error_line(code, err), err
        assert err.startswith(f'bearing_loc bag: error: bag: cannot read {bag}: metadata.yaml '
                              'does not describe its storage file: topic /station_1/bearing '
                              f'has type {meta_type} in metadata.yaml but {stored_type} in '
                              f'{storage_file(bag).name}, so its 20 messages cannot be read'), err
    code, out, err = run(capsys, 'bag', 'info', str(bag))
    assert code == 0 and '/station_1/bearing' in out


# --------------------------------------------------------- a directory without metadata

@pytest.mark.parametrize('verb', ['info', 'process', 'play'])
def test_a_directory_without_metadata_is_named_alike_by_every_verb(bags, tmp_path, capsys,
                                                                   verb):
    # process said "Expected metadata file 'notbag' does not exist."
    empty = tmp_path / 'notbag'
    empty.mkdir()
    extra = PLAY if verb == 'play' else ()
    code, out, err = run(capsys, 'bag', verb, str(empty), *extra)
    assert one_error_line(code, err)
    assert err == f'bearing_loc bag: error: bag: {empty} has no metadata.yaml (not a rosbag2 ' \
                  'directory?)\n'
    shutil.copy(storage_file(bags['sqlite3']), empty / 'run.db3')
    code, out, err = run(capsys, 'bag', verb, str(empty), *extra)
    assert one_error_line(code, err)
    assert err.startswith(f'bearing_loc bag: error: bag: {empty} has no metadata.yaml (it '
                          f'holds run.db3: in a ROS 2 install, ros2 bag reindex {empty} '
                          'writes')


# ------------------------------------------------------------ --params-file as rclpy reads it

PARAMS_FILES = {
    # files that a live node reads otherwise than the first-entry rule did
    'wildcard_then_node': '/**:\n  ros__parameters:\n    use_sim_time: true\n'
                          'fusion:\n  ros__parameters:\n    estimator: wmle\n'
                          '    trigger: timer\n',
    'node_twice': 'fusion:\n  ros__parameters:\n    estimator: wmle\n'
                  'fusion:\n  ros__parameters:\n    trigger: timer\n',
    'other_node_only': 'station_1:\n  ros__parameters:\n    estimator: wmle\n',
    'station_first': 'station_1:\n  ros__parameters:\n    position: [1.0, 2.0, 3.0]\n'
                     'fusion:\n  ros__parameters:\n    estimator: wmle\n',
    # a name written again joins its first entry, at that place; /fusion and fusion differ
    'merged_at_first_place': '/fusion:\n  ros__parameters: {estimator: lls, rate: 1.0}\n'
                             '/**:\n  ros__parameters: {estimator: mle, trigger: timer}\n'
                             'fusion:\n  ros__parameters: {estimator: wmle, rate: 3.0}\n'
                             '/fusion:\n  ros__parameters: {trigger: event}\n',
    'keys_twice_in_one_entry': 'fusion:\n  ros__parameters:\n    estimator: mle\n'
                               '    estimator: wmle\n    accuracy_map.enabled: true\n'
                               '    accuracy_map:\n      enabled: false\n      size: 10.0\n'
                               '    accuracy_map:\n      model: crlb\n',
    'wildcards': '/**/fusion:\n  ros__parameters: {rate: 1.0, window: 10.0}\n'
                 '/*/fusion:\n  ros__parameters: {rate: 2.0}\n'
                 '/tx1/*:\n  ros__parameters: {window: 20.0}\n'
                 '/tx1/**:\n  ros__parameters: {estimator: wmle}\n'
                 '/*:\n  ros__parameters: {trigger: timer}\n'
                 '/**/*:\n  ros__parameters: {min_stations: 3}\n',
    'nested_namespace_keys': 'tx1:\n  fusion:\n    ros__parameters: {estimator: wmle}\n'
                             '/**:\n  ros__parameters: {estimator: mle}\n'
                             'tx1/fusion:\n  ros__parameters: {rate: 4.0}\n'
                             '/tx1:\n  a:\n    fusion:\n      ros__parameters: {rate: 5.0}\n',
    'two_documents': 'fusion:\n  ros__parameters: {estimator: wmle}\n---\n'
                     '/**:\n  ros__parameters: {trigger: timer}\n---\n'
                     'fusion:\n  ros__parameters: {rate: 2.0}\n',
}
#: Files rcl refuses (no node starts): bag process refuses them too.
REFUSED_FILES = {
    'alias': 'fusion:\n  ros__parameters:\n    rate: &r 1.0\n    max_latency: *r\n',
    'node_name': 'station-1:\n  ros__parameters: {rate: 1.0}\n',
    'after_ros_parameters': 'fusion:\n  ros__parameters: {rate: 1.0}\n  sub:\n'
                            '    ros__parameters: {rate: 2.0}\n',
    'empty_value': 'station_1:\n  ros__parameters:\n    position:\n',
    'mixed_list': 'station_1:\n  ros__parameters:\n    position: [1, 2.5]\n',
}
NAMESPACES = ['', 'tx1', 'tx1/a']
#: Parameters every rclpy node declares (with their defaults when a file does not set them).
ROS_BUILTINS = ('use_sim_time', 'start_type_description_service')


def rclpy_parameters(path, namespace):
    """{name: value} rclpy gives a node named fusion in ``namespace`` from ``path`` (None
    when rcl refuses the file)."""
    pytest.importorskip('rclpy')
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    ctx = Context()
    try:
        rclpy.init(context=ctx, args=['--ros-args', '--params-file', str(path)])
    except Exception:   # rcl's parse error (RCLError)
        return None
    try:
        node = Node('fusion', namespace='/' + namespace, context=ctx,
                    automatically_declare_parameters_from_overrides=True,
                    start_parameter_services=False)
        try:
            return {k: p.value for k, p in node.get_parameters_by_prefix('').items()}
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


@pytest.mark.ros
@pytest.mark.parametrize('name', sorted(PARAMS_FILES))
def test_params_file_gives_what_rclpy_gives_the_fusion_node(tmp_path, name):
    path = tmp_path / f'{name}.yaml'
    path.write_text(PARAMS_FILES[name], encoding='utf-8')
    for ns in NAMESPACES:
        live = rclpy_parameters(path, ns)
        offline, _ = fusion_file_parameters(path, ns)
        for k in ROS_BUILTINS:
            if k not in offline:
                live.pop(k, None)
        assert offline == live, (name, ns)


@pytest.mark.ros
@pytest.mark.parametrize('name', sorted(REFUSED_FILES))
def test_params_file_rcl_refuses_is_refused(tmp_path, name):
    path = tmp_path / f'{name}.yaml'
    path.write_text(REFUSED_FILES[name], encoding='utf-8')
    assert rclpy_parameters(path, '') is None
    with pytest.raises(InputError, match=f'^params_file: {path}: '):
        fusion_file_parameters(path, '')


def test_bag_process_runs_what_the_node_takes_from_a_params_file(bags, tmp_path, capsys):
    """The settings `bag process --params-file` runs with: what a live node ran."""
    expect = {'wildcard_then_node': ('wmle', 'timer'), 'node_twice': ('wmle', 'timer'),
              'other_node_only': ('mle', 'event'), 'station_first': ('wmle', 'event')}
    for name, (estimator, trigger) in expect.items():
        path = tmp_path / f'{name}.yaml'
        path.write_text(PARAMS_FILES[name], encoding='utf-8')
        capsys.readouterr()
        p = fusion_params(str(path))
        err = capsys.readouterr().err
        assert (p['estimator'], p['trigger']) == (estimator, trigger), name
        assert ('no entry applies to the fusion node /fusion (entries: station_1)' in err) == \
            (name == 'other_node_only'), err
    path = tmp_path / 'nested_namespace_keys.yaml'
    path.write_text(PARAMS_FILES['nested_namespace_keys'], encoding='utf-8')
    assert fusion_params(str(path), namespace='/tx1')['estimator'] == 'mle'
    assert fusion_params(str(path), namespace='/tx1')['rate'] == 4.0
    assert fusion_params(str(path), namespace='tx1/a')['rate'] == 5.0


# ------------------------------------------------------------------------------ stations

@pytest.mark.parametrize('stations', ['[station_1, station_1, station_2]', '["../x"]'])
def test_a_station_list_the_node_refuses_is_refused(bags, tmp_path, capsys, stations):
    # gave fixes (duplicates) or only a warning ("../x"), where the node refuses to start
    from bearing_loc_ros.core.fusion.config import check_station_ids
    with pytest.raises(ValueError) as node:
        check_station_ids(yaml.safe_load(stations))
    code, out, err = run(capsys, 'bag', 'process', str(bags['mcap']), '-p',
                         f'stations={stations}')
    assert one_error_line(code, err) and out == ''
    assert err == f'bearing_loc bag: error: {node.value}\n'
    assert str(node.value).startswith('stations: ')
    path = tmp_path / 'stations.yaml'
    path.write_text(f'fusion:\n  ros__parameters:\n    stations: {stations}\n',
                    encoding='utf-8')
    code, out, err = run(capsys, 'bag', 'process', str(bags['mcap']), '--params-file',
                         str(path))
    assert one_error_line(code, err) and err == f'bearing_loc bag: error: {node.value}\n'
