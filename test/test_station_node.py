"""station_node end to end: raw_bearing topic, UDP datagrams, moving platform, diagnostics,
parameter failures (exit code 1) and one node in its own process talking over DDS.

In-process tests follow tf2_ros: the station nodes and a probe node share one
SingleThreadedExecutor (own rclpy Context) stepped with spin_once. Expected bearings come from
the geometry (target − station, Wang, Zhang & Wu (2006) eq. (1)) and each reading is what
the sensor would report in its own reference, so the node is checked against the definitions.
"""

import json
import math
import os
import socket
import subprocess
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped, Vector3Stamped
from nav_msgs.msg import Odometry
import numpy as np
import pytest
from rclpy.parameter import Parameter
from ros_helpers import free_udp_port, node_env, Probe, REPO, spin_until, start_node
from scipy.spatial.transform import Rotation

from bearing_loc_ros.core.conventions import azimuth_elevation, wrap_angle
from bearing_loc_ros.ros_conversions import bearing_from_msg, ns_to_time
from bearing_loc_ros.station_node import INPUT_QOS, OUTPUT_QOS, StationNode

pytestmark = pytest.mark.ros

TOL = 1e-9  # rad; float64 angles through a few trig calls and a quaternion
T0 = 1_700_000_000_000_000_000  # an observation time, ns
STATION = [100.0, -50.0, 10.0]
TARGET = np.array([900.0, 400.0, 300.0])


def _send(port, obj):
    data = obj if isinstance(obj, bytes) else json.dumps(obj).encode()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.sendto(data, ('127.0.0.1', port))


def _truth(position, target=TARGET):
    az, el = azimuth_elevation(np.asarray(target) - np.asarray(position))
    return float(az), float(el)


class Harness:
    """Station nodes (one per configuration) + a probe node in one executor."""

    CONFIGS = {
        # ENU sensor on the raw topic in degrees, 2D, mounting offset +5°.
        'enu': dict(position=STATION, measures_elevation=True, input_units='deg',
                    azimuth_offset_deg=5.0, sigma_azimuth_deg=1.0, sigma_elevation_deg=2.0,
                    diagnostics_period=0.1),
        # Compass receiver over UDP (and the raw topic in rad), 1D, offset −12°.
        'compass': dict(position=STATION, azimuth_reference='compass',
                        azimuth_offset_deg=-12.0, udp_port='free', position_covariance=[
                            1.0, 0.5, 0.0, 0.5, 2.0, 0.0, 0.0, 0.0, 3.0]),
        # Compass-referenced 2D array on a moving platform (relative bearings from the bow).
        'boat': dict(platform_odometry='/boat/odom', azimuth_reference='compass',
                     measures_elevation=True, azimuth_offset_deg=3.0, udp_port='free',
                     odometry_tolerance=0.05, frame_id='map'),
        # UDP re-stamped on receipt with the node clock.
        'restamp': dict(position=STATION, udp_port='free', udp_stamp='receive'),
        # Bearings published reliable (for reliable subscribers).
        'reliable': dict(position=STATION, qos_reliability='reliable', qos_depth=50),
    }

    def __init__(self):
        self._probe = Probe('probe')
        self.context, self.executor = self._probe.context, self._probe.executor
        self.probe = self._probe.node
        self.stations, self.ports, self.raw_pubs, self.received = {}, {}, {}, {}
        self.diagnostics = []
        for name, cfg in self.CONFIGS.items():
            cfg = dict(cfg)
            if cfg.get('udp_port') == 'free':
                cfg['udp_port'] = self.ports[name] = free_udp_port()
            overrides = [Parameter(k, value=v) for k, v in cfg.items()]
            node = StationNode(context=self.context, namespace=f'/st_{name}',
                               parameter_overrides=overrides)
            self.executor.add_node(node)
            self.stations[name] = node
            self.received[name] = []
            self.probe.create_subscription(
                PoseWithCovarianceStamped, f'/st_{name}/bearing',
                lambda m, n=name: self.received[n].append(m), OUTPUT_QOS)
            self.raw_pubs[name] = self.probe.create_publisher(
                Vector3Stamped, f'/st_{name}/raw_bearing', 10)
        self.odom_pub = self.probe.create_publisher(Odometry, '/boat/odom', 50)
        self.probe.create_subscription(DiagnosticArray, '/diagnostics',
                                       self.diagnostics.append, 50)
        pubs = list(self.raw_pubs.values()) + [self.odom_pub]
        assert spin_until(self.executor, lambda: all(p.get_subscription_count() for p in pubs)
                          and all(n.pub.get_subscription_count()
                                  for n in self.stations.values()), 10.0)

    def raw(self, name, stamp_ns, x, y=math.nan):
        msg = Vector3Stamped()
        msg.header.stamp = ns_to_time(stamp_ns)
        msg.header.frame_id = 'df_array'
        msg.vector.x, msg.vector.y = float(x), float(y)
        self.raw_pubs[name].publish(msg)

    def wait_for(self, name, count, timeout=5.0):
        spin_until(self.executor, lambda: len(self.received[name]) >= count, timeout)
        return [bearing_from_msg(m, name) for m in self.received[name]]

    def close(self):
        self._probe.close(self.stations.values())


@pytest.fixture(scope='module')
def h():
    harness = Harness()
    yield harness
    harness.close()


def test_enu_raw_topic_with_offset(h):
    theta, psi = _truth(STATION)
    raw_az = math.degrees(theta) - 5.0  # the sensor reads the offset short
    h.raw('enu', T0, raw_az, math.degrees(psi))
    h.raw('enu', T0 + 1, raw_az, math.nan)  # no elevation this time: azimuth-only
    got = h.wait_for('enu', 2)
    assert len(got) == 2
    b = got[0]
    assert b.stamp_ns == T0 and b.frame_id == 'map'
    np.testing.assert_array_equal(b.position, STATION)
    assert abs(wrap_angle(b.azimuth - theta)) < TOL and abs(b.elevation - psi) < TOL
    assert b.sigma_azimuth == pytest.approx(math.radians(1.0), rel=1e-12)
    assert b.sigma_elevation == pytest.approx(math.radians(2.0), rel=1e-12)
    assert got[1].stamp_ns == T0 + 1 and not got[1].has_elevation


def test_compass_udp_and_raw_topic(h):
    theta, _ = _truth(STATION)
    compass_deg = 90.0 - math.degrees(theta) + 12.0  # reads 12° long: offset −12°
    _send(h.ports['compass'], {'t': 1700000000.25, 'azimuth_deg': compass_deg,
                               'elevation_deg': 30.0, 'sigma_deg': 0.5})
    got = h.wait_for('compass', 1)
    assert len(got) == 1
    b = got[0]
    assert b.stamp_ns == 1_700_000_000_250_000_000
    assert abs(wrap_angle(b.azimuth - theta)) < TOL
    assert not b.has_elevation  # a 1D station ignores elevations
    assert b.sigma_azimuth == pytest.approx(math.radians(0.5), rel=1e-12)
    np.testing.assert_array_equal(b.position_covariance,
                                  [[1.0, 0.5, 0.0], [0.5, 2.0, 0.0], [0.0, 0.0, 3.0]])
    # The same station's raw topic (radians, default input_units).
    h.raw('compass', T0 + 7, math.radians(compass_deg))
    got = h.wait_for('compass', 2)
    assert got[1].stamp_ns == T0 + 7 and abs(wrap_angle(got[1].azimuth - theta)) < TOL


def test_malformed_input_is_counted_and_never_stops_the_node(h):
    node = h.stations['compass']
    before = dict(node.rejected)
    for bad in (b'garbage', b'[1]', b'{"t": 1}', b'{"azimuth_deg": 3}',
                b'{"t": 5, "azimuth_deg": "x"}'):
        _send(h.ports['compass'], bad)
    h.raw('compass', 0, 0.1)             # stamp not set
    h.raw('compass', T0, math.nan)       # no azimuth
    n = len(h.received['compass'])
    _send(h.ports['compass'], {'t': 1700000001, 'azimuth_deg': 45.0})
    got = h.wait_for('compass', n + 1)
    assert len(got) == n + 1 and got[-1].stamp_ns == 1_700_000_001 * 10 ** 9
    spin_until(h.executor, lambda: sum(node.rejected.values()) - sum(before.values()) >= 7,
               2.0)
    delta = {k: node.rejected[k] - before.get(k, 0) for k in node.rejected}
    assert delta == {'bad_json': 1, 'not_object': 1, 'missing_azimuth': 1, 'missing_t': 1,
                     'bad_azimuth': 2, 'bad_stamp': 1}


def _odom(stamp_ns, position, yaw, pitch=0.0):
    msg = Odometry()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.header.frame_id, msg.child_frame_id = 'map', 'boat/base_link'
    p = msg.pose.pose.position
    p.x, p.y, p.z = (float(v) for v in position)
    q = Rotation.from_euler('ZYX', [yaw, pitch, 0.0]).as_quat()
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = (float(v) for v in q)
    return msg


def test_moving_platform(h):
    """Odometry at 1 s and 2 s (moving 10 m East and turning 40°); a reading at 1.25 s must
    use the pose interpolated to 1.25 s (linear position, slerp yaw)."""
    node = h.stations['boat']
    t1, t2 = T0, T0 + 10 ** 9
    p1, p2 = np.array([0.0, 0.0, 1.0]), np.array([10.0, 0.0, 1.0])
    yaw1, yaw2 = math.radians(10.0), math.radians(50.0)
    h.odom_pub.publish(_odom(t1, p1, yaw1, 0.1))
    h.odom_pub.publish(_odom(t2, p2, yaw2, 0.1))
    assert spin_until(h.executor, lambda: len(node.poses) == 2, 5.0)
    t = t1 + 250_000_000
    pose_pos = 0.75 * p1 + 0.25 * p2
    R = Rotation.from_euler('ZYX', [0.75 * yaw1 + 0.25 * yaw2, 0.1, 0.0])
    theta, psi = _truth(pose_pos)
    u_b = R.inv().apply(TARGET - pose_pos)
    theta_b, psi_b = (float(v) for v in azimuth_elevation(u_b))
    relative_deg = -math.degrees(theta_b) - 3.0  # clockwise from the bow, reads 3° short
    # t written as an exact decimal JSON number (a float t / 1e9 would be 200 ns off).
    _send(h.ports['boat'], (f'{{"t": {t // 10**9}.{t % 10**9:09d}, "azimuth_deg": '
                            f'{relative_deg!r}, "elevation_deg": {math.degrees(psi_b)!r}}}'
                            ).encode())
    got = h.wait_for('boat', 1)
    assert len(got) == 1
    b = got[0]
    assert b.stamp_ns == t
    np.testing.assert_allclose(b.position, pose_pos, rtol=0, atol=1e-12)
    assert abs(wrap_angle(b.azimuth - theta)) < TOL and abs(b.elevation - psi) < TOL
    # Outside the buffered interval by more than the 50 ms tolerance: dropped and counted.
    before = node.rejected['after_odometry'], node.rejected['before_odometry']
    _send(h.ports['boat'], {'t': (t2 + 60_000_000) / 1e9, 'azimuth_deg': 1.0})
    _send(h.ports['boat'], {'t': (t1 - 60_000_000) / 1e9, 'azimuth_deg': 1.0})
    spin_until(h.executor, lambda: (node.rejected['after_odometry'],
                                    node.rejected['before_odometry']) ==
               (before[0] + 1, before[1] + 1), 3.0)
    assert node.rejected['after_odometry'] == before[0] + 1
    assert node.rejected['before_odometry'] == before[1] + 1
    assert len(h.received['boat']) == 1
    # A late (reordered) odometry message is dropped and counted; the buffer stays.
    h.odom_pub.publish(_odom(t2 - 500_000_000, p1, yaw1))
    spin_until(h.executor, lambda: node.rejected['odometry_late'] == 1, 3.0)
    assert node.rejected['odometry_late'] == 1 and len(node.poses) == 2
    assert node.received['odometry_resets'] == 0
    # Odometry in another frame is rejected, not used.
    bad = _odom(t2 + 1, p2, yaw2)
    bad.header.frame_id = 'odom'
    h.odom_pub.publish(bad)
    spin_until(h.executor, lambda: node.rejected['odometry_wrong_frame'] == 1, 3.0)
    assert node.rejected['odometry_wrong_frame'] == 1 and len(node.poses) == 2


def test_udp_restamp_on_receipt(h):
    node = h.stations['restamp']
    before = node.get_clock().now().nanoseconds
    _send(h.ports['restamp'], {'azimuth_deg': 20.0})  # no t needed when re-stamping
    got = h.wait_for('restamp', 1)
    after = node.get_clock().now().nanoseconds
    assert len(got) == 1 and before <= got[0].stamp_ns <= after
    assert got[0].azimuth == pytest.approx(math.radians(20.0), abs=TOL)


def test_diagnostics(h):
    node = h.stations['enu']
    n = len(h.received['enu'])
    h.raw('enu', T0 + 50, 10.0)
    assert len(h.wait_for('enu', n + 1)) == n + 1
    h.diagnostics.clear()
    h.raw('enu', T0 + 99, math.inf)  # rejected: bad_azimuth

    def warned():
        for arr in h.diagnostics:
            for st in arr.status:
                if st.hardware_id == 'st_enu' and st.level == DiagnosticStatus.WARN:
                    return st
        return None
    st = spin_until(h.executor, warned, 3.0)
    assert st is not None
    values = {kv.key: kv.value for kv in st.values}
    assert values['station'] == 'st_enu' and values['frame_id'] == 'map'
    assert int(values['published']) == node.published >= 1
    assert values['rejected_bad_azimuth'] == '1'
    assert '/st_enu/raw_bearing' in values['sources']
    assert int(values['last_stamp_ns']) == T0 + 50
    assert 'rejected' in st.message
    # The next report, with nothing new rejected, is OK again.
    h.diagnostics.clear()
    ok = spin_until(h.executor, lambda: [s for a in h.diagnostics for s in a.status
                                         if s.hardware_id == 'st_enu'], 3.0)
    assert ok and ok[-1].level == DiagnosticStatus.OK


# ------------------------------------------------------------------ separate processes

BAD_PARAMS = [
    ('sigma_azimuth_deg: -1.0', 'sigma_azimuth_deg'),
    ('geodetic_position: [95.0, 7.0, 100.0]\n    geodetic_origin: [46.0, 7.0, 0.0]',
     'geodetic_position'),
    ('position: [1.0, 2.0, 3.0]\n    azimuth_reference: north', 'azimuth_reference'),
    ('position: [1.0, 2.0, 3.0]\n    position_covariance: [1.0, 2.0]', 'position_covariance'),
    # Receiver inputs: each error names the parameter that is wrong.
    ('position: [1.0, 2.0, 3.0]\n    input: kraken_xml_http\n    kraken:\n'
     '      url: http://127.0.0.1:abc/doa.xml', 'kraken.url'),
    ('position: [1.0, 2.0, 3.0]\n    input: kraken_xml_http\n    kraken:\n'
     '      url: http://127.0.0.1:9/doa.xml\n      position_source: gps', 'position'),
    ('position: [1.0, 2.0, 3.0]\n    input: kraken_json_post\n    kraken:\n'
     '      post_address: 192.0.2.1', 'kraken.post_address'),
    ('position: [1.0, 2.0, 3.0]\n    input: kraken_json_post\n    kraken:\n'
     '      stamp: receive\n      max_age: 5.0', 'kraken.max_age'),
    ('position: [1.0, 2.0, 3.0]\n    udp_port: 5005\n    udp_address: 192.0.2.1',
     'udp_address'),
]
#: Parameters a start-up error must not blame (they were not set).
NOT_SET = ('platform_odometry', 'kraken.post_port', 'udp_port')


def test_bad_parameter_files_exit_1_naming_the_parameter(tmp_path):
    procs = []
    for k, (body, name) in enumerate(BAD_PARAMS):
        path = tmp_path / f'bad{k}.yaml'
        path.write_text(f'/**:\n  ros__parameters:\n    {body}\n')
        procs.append((name, subprocess.Popen(
            [sys.executable, '-m', 'bearing_loc_ros.station_node', '--ros-args',
             '-r', '__ns:=/bad', '--params-file', str(path)], cwd=REPO, env=node_env(),
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)))
    results = []
    try:
        for name, proc in procs:
            try:
                out, err = proc.communicate(timeout=30)
            except subprocess.TimeoutExpired:       # still running: not a start-up error
                out, err = '', 'still running after 30 s'
            results.append((name, proc.returncode, out, err))
    finally:                                        # every node is reaped, whatever failed
        for _, proc in procs:
            proc.kill()
            proc.wait()
    for name, code, out, err in results:
        assert code == 1, (name, out, err)
        assert f"error: parameter '{name}'" in err, err
        assert not any(other in err for other in NOT_SET), err


def test_separate_process_over_dds():
    """The node in its own process (example config/station.yaml, UDP on) talking over DDS."""
    port = free_udp_port()
    dds = Probe('dds_probe')
    probe, ex = dds.node, dds.executor
    got = []
    probe.create_subscription(PoseWithCovarianceStamped, '/station_9/bearing', got.append,
                              OUTPUT_QOS)
    raw_pub = probe.create_publisher(Vector3Stamped, '/station_9/raw_bearing', INPUT_QOS)
    node = start_node('bearing_loc_ros.station_node', ros_args=[
        '-r', '__ns:=/station_9', '--params-file', os.path.join(REPO, 'config', 'station.yaml'),
        '-p', f'udp_port:={port}'])
    try:
        with node:
            assert spin_until(ex, lambda: raw_pub.get_subscription_count() > 0
                              and probe.count_publishers('/station_9/bearing') > 0, 20.0), \
                node.output()
            # Compass 90° = due East from the example's position; raw topic in degrees.
            msg = Vector3Stamped()
            msg.header.stamp = ns_to_time(T0)
            msg.vector.x = 90.0
            deadline = time.monotonic() + 10.0
            while not got and time.monotonic() < deadline:
                raw_pub.publish(msg)
                spin_until(ex, lambda: got, 0.5)
            assert got, node.output()
            b = bearing_from_msg(got[0], 'station_9', expected_frame='map')
            assert b.stamp_ns == T0 and abs(b.azimuth) < TOL and not b.has_elevation
            np.testing.assert_array_equal(b.position, [120.0, -35.5, 4.0])
            assert b.sigma_azimuth == pytest.approx(math.radians(2.0), rel=1e-12)
            n = len(got)
            deadline = time.monotonic() + 10.0
            while len(got) == n and time.monotonic() < deadline:
                _send(port, {'t': 1700000002.5, 'azimuth_deg': 0.0})  # due North
                spin_until(ex, lambda: len(got) > n, 0.5)
            b = bearing_from_msg(got[-1], 'station_9')
            assert b.stamp_ns == 1_700_000_002_500_000_000, node.output()
            assert b.azimuth == pytest.approx(math.pi / 2, abs=TOL)
        assert node.proc.returncode == 0, node.output()
    finally:
        dds.close()


def test_unparsable_ros_args_exit_1_with_one_line():
    """rcl rejects a malformed -p override; the node says so in one line, exit code 1."""
    proc = subprocess.run([sys.executable, '-m', 'bearing_loc_ros.station_node', '--ros-args',
                           '-p', 'udp_address:=::'], capture_output=True, text=True,
                          timeout=60, stdin=subprocess.DEVNULL)
    assert proc.returncode == 1
    assert 'error: invalid command line:' in proc.stderr, proc.stderr
    assert 'Traceback' not in proc.stderr


def test_bearings_are_published_best_effort_unless_reliable_is_asked(h):
    from rclpy.qos import ReliabilityPolicy
    info = {n: h.probe.get_publishers_info_by_topic(f'/st_{n}/bearing')
            for n in ('enu', 'reliable')}
    assert [i.qos_profile.reliability for i in info['enu']] == [ReliabilityPolicy.BEST_EFFORT]
    assert [i.qos_profile.reliability for i in info['reliable']] == [ReliabilityPolicy.RELIABLE]
