"""bearing_loc_ros.discovery_probe: the child process that watches discovered topics, and the
fusion node's side of it (a probe that dies, hangs or prints garbage is replaced, never
trusted, and always reaped)."""
import os
import signal
import sys
import time

from geometry_msgs.msg import PoseWithCovarianceStamped
import pytest
import rclpy

from bearing_loc_ros.core.bearings import Bearing
from bearing_loc_ros.discovery_probe import parse_command, ProbeProcess
from bearing_loc_ros.ros_common import keep_last_qos
from bearing_loc_ros.ros_conversions import bearing_to_msg

#: A stand-in probe: answers each command, reports the stations named in the
#: environment variable VALID (asked for or not) and prints garbage on the way.
FAKE = '''
import os, sys
valid = os.environ.get('VALID', '').split()
mode = os.environ.get('MODE', '')
answered = 0
for line in sys.stdin:
    n = line.split()[1]
    if mode == 'hang' or (mode == 'hang-later' and answered):
        continue
    answered += 1
    print('hello there', flush=True)
    print('valid', flush=True)
    for s in valid:
        print('valid', s, flush=True)
    print('ack', n, flush=True)
    if mode == 'die':
        sys.exit(3)
'''


def fake(monkeypatch, valid='', mode='', **kw):
    monkeypatch.setenv('VALID', valid)
    monkeypatch.setenv('MODE', mode)
    return ProbeProcess([], command=[sys.executable, '-c', FAKE], **kw)


def update_until(probe, candidates, predicate, timeout=10.0):
    """Call probe.update every 50 ms; the accumulated accepted stations once predicate()."""
    got = []
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        got += probe.update(candidates)
        if predicate(got):
            break
        time.sleep(0.05)
    return got


def test_parse_command():
    assert parse_command('watch 3 a b\n') == (3, {'a', 'b'})
    assert parse_command('watch 4\n') == (4, set())
    for bad in ('', 'watch', 'watch x a', 'look 1 a', '\x00\xff'):
        assert parse_command(bad) is None


def test_only_asked_stations_are_accepted_and_garbage_is_counted(monkeypatch):
    p = fake(monkeypatch, valid='s1 intruder s2')
    try:
        got = update_until(p, {'s1', 's2'}, lambda got: len(got) == 2)
        assert sorted(got) == ['s1', 's2']          # 'intruder' was never asked for
        assert p.garbage >= 2 and p.failures == 0 and p.starts == 1
        # A station no longer a candidate is not accepted.
        assert update_until(p, {'s3'}, lambda got: False, timeout=0.5) == []
    finally:
        p.stop()
    assert not p.running


def test_a_probe_that_dies_is_reaped_and_restarted(monkeypatch):
    p = fake(monkeypatch, valid='s1', mode='die', backoff=(0.0, 0.0))
    procs = []
    try:
        def seen(got):
            if p.proc is not None and p.proc not in procs:
                procs.append(p.proc)
            return p.starts >= 3
        update_until(p, {'s1'}, seen)
        assert p.starts >= 3 and p.failures >= 2
        # Every replaced probe was reaped (no zombie left behind).
        assert all(proc.returncode is not None for proc in procs[:-1])
    finally:
        p.stop()


def test_a_hung_probe_is_killed_and_the_restart_backs_off(monkeypatch):
    p = fake(monkeypatch, mode='hang', ack_timeout=0.3, backoff=(0.5, 60.0))
    try:
        p.update({'s1'})
        first = p.proc
        assert first is not None
        update_until(p, {'s1'}, lambda got: p.failures >= 1)
        assert p.failures == 1 and first.returncode is not None     # killed and reaped
        assert not p.running
        p.update({'s1'})
        assert not p.running                        # backing off: no restart at once
        update_until(p, {'s1'}, lambda got: p.running)
        assert p.starts == 2
    finally:
        p.stop()


def test_a_probe_that_hangs_after_answering_is_found_by_the_keep_alive(monkeypatch):
    # The candidate set does not change after the first answer: only the keep-alive can
    # find the hang.
    p = fake(monkeypatch, mode='hang-later', ack_timeout=0.4, backoff=(30.0, 60.0))
    try:
        update_until(p, {'s1'}, lambda got: p.failures >= 1, timeout=5.0)
        assert p.failures == 1 and not p.running
    finally:
        p.stop()


def test_stations_reported_valid_by_a_probe_that_then_died_are_accepted(monkeypatch):
    p = fake(monkeypatch, valid='s1', mode='die', backoff=(30.0, 60.0))
    try:
        got = update_until(p, {'s1'}, lambda got: p.failures >= 1 and got, timeout=5.0)
        assert got == ['s1'] and p.failures == 1
    finally:
        p.stop()


def test_a_probe_that_cannot_start_is_counted_not_raised(monkeypatch):
    p = ProbeProcess([], command=[os.path.join(os.sep, 'nonexistent', 'python')])
    assert p.update({'s1'}) == []
    assert p.failures == 1 and not p.running


@pytest.mark.ros
def test_the_real_probe_reports_a_valid_bearing_and_exits_when_idle(ros):
    """``python -m bearing_loc_ros.discovery_probe``: a topic whose publisher sends only an
    invalid bearing is not reported, one with a valid bearing is; with nothing to watch the
    probe exits by itself (code 0, not a failure); killed, it is started again."""
    node = rclpy.create_node('probe_test', namespace='/probe_ns', context=ros)
    qos = keep_last_qos(10, 'reliable')
    good = node.create_publisher(PoseWithCovarianceStamped, 'good/bearing', qos)
    bad = node.create_publisher(PoseWithCovarianceStamped, 'bad/bearing', qos)
    b = Bearing(station='x', stamp_ns=10 ** 9, position=[0.0, 0.0, 0.0], azimuth=0.5,
                elevation=0.1, sigma_azimuth=1e-2, sigma_elevation=1e-2, frame_id='map')
    wrong_frame = bearing_to_msg(b)
    wrong_frame.header.frame_id = 'odom'
    p = ProbeProcess(['--namespace', '/probe_ns', '--idle', '0.5'], backoff=(0.0, 0.0))
    try:
        got = []
        end = time.monotonic() + 30.0
        while time.monotonic() < end and not got:
            good.publish(bearing_to_msg(b))
            bad.publish(wrong_frame)
            got += p.update({'good', 'bad'})
            time.sleep(0.1)
        assert got == ['good']
        first = p.proc
        first.send_signal(signal.SIGKILL)          # dies: started again, counted
        update_until(p, {'bad'}, lambda got: p.starts == 2)
        assert p.starts == 2 and p.failures == 1 and first.returncode is not None
        update_until(p, set(), lambda got: not p.running, timeout=15.0)
        assert not p.running and p.failures == 1    # the idle exit is no failure
    finally:
        p.stop()
        node.destroy_node()
