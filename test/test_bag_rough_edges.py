"""bag play / process / info / simulate as a new user meets them, and plan's negative lists.

Each test is one rough edge: playing before subscribers match, a topic of a type that is not
installed, QoS shown in part, the recorded ROS distribution, statistics without --out, the
CSV column order and a negative --area-km.
"""
import csv
import json
import os
import sqlite3
import sys

import numpy as np
import pytest
import yaml

from bearing_loc_ros import bagio
from bearing_loc_ros.bag_process import fusion_params, process_bag
from bearing_loc_ros.cli import main as cli_main

UNKNOWN_TYPE = 'krakensdr_msgs/msg/Doa'
UNKNOWN_TOPIC = '/station_1/doa'


def bearing_loc(*args):
    """Run ``bearing_loc <args>`` as a separate process (test/ros_helpers.NodeProcess)."""
    from ros_helpers import node_env, NodeProcess
    code = 'import sys; from bearing_loc_ros.cli import main; sys.exit(main(sys.argv[1:]))'
    return NodeProcess([sys.executable, '-c', code, *args], env=node_env())


def _with_unknown_topic(src, dst):
    """Copy bag ``src`` to ``dst`` (mcap) adding a topic of a type no package installs."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import get_types_from_msg, get_typestore, Stores
    ts = get_typestore(Stores.ROS2_JAZZY)
    ts.register(get_types_from_msg('float64 doa\nfloat64 confidence', UNKNOWN_TYPE))
    writer = Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    with bagio.BagReader(src) as reader:
        conns = {}
        for name, t in reader.topics.items():
            conns[name] = writer.add_connection(
                name, t.msgtype, typestore=ts,
                offered_qos_profiles=[bagio._qos_to_rosbags(q) for q in t.qos])
        conns[UNKNOWN_TOPIC] = writer.add_connection(
            UNKNOWN_TOPIC, UNKNOWN_TYPE, typestore=ts,
            offered_qos_profiles=[bagio._qos_to_rosbags(bagio.qos_profile(10))])
        doa = ts.types[UNKNOWN_TYPE]
        for m in reader.messages():
            writer.write(conns[m.topic], m.log_time_ns, m.raw)
            if m.topic == '/station_1/bearing':
                writer.write(conns[UNKNOWN_TOPIC], m.log_time_ns,
                             bytes(ts.serialize_cdr(doa(doa=1.0, confidence=0.5),
                                                    UNKNOWN_TYPE)))
    writer.close()
    return dst


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    """static3 (2 s) in mcap and sqlite3, and the mcap one with a topic of an unknown type."""
    from ros_helpers import static3_bags
    root = tmp_path_factory.mktemp('rough')
    _, out = static3_bags(root, 3)
    out['unknown'] = _with_unknown_topic(out['mcap'], root / 'with_unknown')
    return out


def test_written_bags_record_jazzy(bags):
    for storage in bagio.STORAGES:
        assert bagio.read_metadata(bags[storage])['ros_distro'] == 'jazzy'
    db = next(p for p in os.listdir(bags['sqlite3']) if p.endswith('.db3'))
    with sqlite3.connect(bags['sqlite3'] / db) as con:
        assert con.execute('SELECT ros_distro FROM schema').fetchall() == [('jazzy',)]
        stored = con.execute('SELECT metadata FROM metadata').fetchone()[0]
    assert yaml.safe_load(stored)['ros_distro'] == 'jazzy'
    with open(next(bags['mcap'].glob('*.mcap')), 'rb') as f:
        data = f.read()
    assert b'ros_distro: jazzy' in data and b'ros_distro: rosbags' not in data


def test_info_shows_every_qos_profile_with_durability(bags, tmp_path, capsys):
    path = tmp_path / 'two_profiles'
    two = [bagio.qos_profile(100), bagio.qos_profile(1, reliable=False, transient_local=True)]
    with bagio.BagWriter(path) as bag:
        bag.add_topic('/a', bagio.POSE_STAMPED, two[0])
        bag.write('/a', 5, bagio.truth_message([1.0, 2.0, 3.0], 5))
    meta = path / 'metadata.yaml'
    doc = yaml.safe_load(meta.read_text())
    doc['rosbag2_bagfile_information']['topics_with_message_count'][0]['topic_metadata'][
        'offered_qos_profiles'] = two
    meta.write_text(yaml.safe_dump(doc))
    assert cli_main(['bag', 'info', str(path)]) == 0
    line = [x for x in capsys.readouterr().out.splitlines() if x.startswith('  /a ')][0]
    assert ('reliable, volatile, keep_last 100; best_effort, transient_local, keep_last 1'
            in line), line


def test_process_without_out_prints_statistics_only(bags, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert cli_main(['bag', 'process', str(bags['mcap'])]) == 0
    out, err = capsys.readouterr()
    assert 'fixes' in out and 'error against truth' in out and 'wrote' not in out
    assert os.listdir(tmp_path) == []


def test_csv_stamp_before_produced(bags, tmp_path):
    out = tmp_path / 'fixes'
    s = process_bag(bags['mcap'], out, fusion_params())
    with open(f'{out}.csv', encoding='utf-8') as f:
        rows = list(csv.reader(f))
    head = rows[0]
    assert head[0] == 'stamp_ns' and head.index('stamp_ns') < head.index('produced_ns')
    assert len(rows) - 1 == s['fixes'] > 0
    fixes = [e for e in s['epoch_list'] if e.ok]
    assert [int(r[0]) for r in rows[1:]] == [e.stamp_ns for e in fixes]
    assert [int(r[head.index('produced_ns')]) for r in rows[1:]] == \
        [e.produced_ns for e in fixes]


def test_process_skips_a_topic_of_an_unknown_type(bags, capsys):
    ref = process_bag(bags['mcap'], None, fusion_params(), log=lambda s: None)
    warnings = []
    got = process_bag(bags['unknown'], None, fusion_params(), log=warnings.append)
    assert len(warnings) == 1 and UNKNOWN_TOPIC in warnings[0] and UNKNOWN_TYPE in warnings[0]
    assert got['fixes'] == ref['fixes'] > 0
    a = [e.position for e in got['epoch_list'] if e.ok]
    b = [e.position for e in ref['epoch_list'] if e.ok]
    np.testing.assert_array_equal(a, b)
    assert cli_main(['bag', 'process', str(bags['unknown'])]) == 0
    assert UNKNOWN_TOPIC in capsys.readouterr().err


def test_play_waits_for_subscribers_skips_unknown_types_and_unheard_topics(bags):
    """Default `bag play`: the subscribed topic gets every message, /truth (no subscriber)
    does not hold playback, the unknown type is skipped with a warning."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from ros_helpers import Probe, spin_until
    topic = '/station_2/bearing'
    with bagio.BagReader(bags['unknown']) as r:
        want = [m.raw for m in r.messages(topics={topic})]
    probe = Probe('rough_edges_listener')
    node, ex = probe.node, probe.executor
    got = []
    node.create_subscription(PoseWithCovarianceStamped, topic, got.append,
                             QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE),
                             raw=True)
    try:
        with bearing_loc('bag', 'play', str(bags['unknown']), '--rate', '4') as proc:
            spin_until(ex, lambda: proc.proc.poll() is not None, 40.0)
            assert proc.wait(10.0) == 0, proc.output()
            spin_until(ex, lambda: len(got) >= len(want), 3.0)
            log = proc.output()
    finally:
        probe.close()
    assert got == want, log
    assert f'not installed, not played: {UNKNOWN_TOPIC} ({UNKNOWN_TYPE})' in log, log
    idle = [x for x in log.splitlines() if 'no subscriber on' in x]
    assert idle and '/truth' in idle[0] and topic not in idle[0], log
    assert 'not matched' not in log, log


@pytest.mark.parametrize('flag', ['--area-km', '--region-km'])
def test_negative_number_list_after_an_option(flag, capsys):
    base = ['plan', 'place', '--stations', '0,0,0;10,0,0;0,10,0', '--sigma-deg', '0.1',
            '--altitude', '1000', '--area-cells', '4', '--candidates', '4']
    if flag == '--region-km':
        base += ['--area-km', '0,5,0,5']
    area = [flag, '-5,5,-5,5'] if flag == '--area-km' else [flag, '-10,10,-10,10']
    attached = base + [f'{flag}={area[1]}']
    assert cli_main(base + area) == 0
    spaced = json.loads(capsys.readouterr().out)
    assert cli_main(attached) == 0
    assert json.loads(capsys.readouterr().out) == spaced
    # a list starting with a minus sign that is not a valid box: one clear line
    assert cli_main(base + [flag, '-5,5']) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and flag in err, err


def test_negative_station_coordinates(capsys):
    argv = ['plan', 'map', '--stations', '-10,0,0;10,0,0;0,10,0', '--sigma-deg', '0.1',
            '--altitude', '1000', '--extent-km', '5', '--resolution', '2500']
    assert cli_main(argv) == 0
    d = json.loads(capsys.readouterr().out)
    assert d['stations'][0]['position_m'] == [-10000.0, 0.0, 0.0]


@pytest.mark.parametrize('verb', ['play', 'process', 'info'])
def test_a_missing_bag_is_named_as_missing(verb, tmp_path, capsys):
    # A path that does not exist is not "not a directory"; a file is.
    afile = tmp_path / 'afile'
    afile.write_text('x')
    for path, words in ((tmp_path / 'nope', 'does not exist'), (afile, 'is not a directory')):
        assert cli_main(['bag', verb, str(path)]) == 2
        out, err = capsys.readouterr()
        assert out == '' and len(err.splitlines()) == 1 and words in err, err
