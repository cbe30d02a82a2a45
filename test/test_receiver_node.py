"""Station nodes with a KrakenSDR input, end to end over loopback HTTP.

A fake KrakenSDR web server inside the test serves one ``doa.xml`` per station; the test
sets each frame's documents and steps one executor holding the station nodes (and, where
the fusion has an azimuth-only mode, the fusion node) and a probe. Expected bearings come
from the geometry, independently of the node: the receiver reports DOA = H − β (the
default ``inverted`` sense, β the true compass bearing of the transmitter, H the array
front) and the published ENU azimuth must be θ = 90° − β.
"""

import math
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from http_fakes import LoopbackHTTP
import numpy as np
import pymap3d
import pytest
from rclpy.parameter import Parameter
from ros_helpers import Probe, spin_until
from scipy.stats import chi2

from bearing_loc_ros.core import parameters as schema
from bearing_loc_ros.core.bearings import BearingSet
from bearing_loc_ros.core.conventions import wrap_angle
from bearing_loc_ros.core.horizontal import locate_horizontal
from bearing_loc_ros.ros_conversions import bearing_from_msg, fix_from_msg
from bearing_loc_ros.station_node import OUTPUT_QOS, StationNode

pytestmark = pytest.mark.ros

FREQ_MHZ = 433.92
SIGMA_DEG = 1.5
#: name -> (ENU position m, array front heading deg clockwise from North)
STATIONS = {'north': ([0.0, 2000.0, 0.0], 10.0), 'west': ([-1500.0, -500.0, 0.0], 250.0),
            'east': ([1800.0, -300.0, 0.0], 95.0)}
TX = np.array([300.0, 400.0, 0.0])
HAS_HORIZONTAL = any(p.name == 'dimension' for p in schema.schema('fusion_node'))
#: The fusion node's azimuth-only settings for a transmitter at altitude 0.
HORIZONTAL = {} if not HAS_HORIZONTAL else {
    'dimension': 'horizontal', 'target_altitude': (
        [0.0] if schema.param('fusion_node', 'target_altitude').type.endswith('array')
        else 0.0)}


def xml_doc(t_ms, doa_deg, station='rx', conf=0.95, lat=None, lon=None, heading=None,
            speed=None, freq_mhz=FREQ_MHZ):
    """A KrakenSDR doa.xml (field specification of the receiver's web output)."""
    loc = ''
    if lat is not None:
        loc = (f'<LOCATION><LATITUDE>{lat!r}</LATITUDE><LONGITUDE>{lon!r}</LONGITUDE>'
               f'<HEADING>{heading!r}</HEADING><SPEED>{speed!r}</SPEED></LOCATION>')
    return (f'<?xml version="1.0" encoding="UTF-8"?><DATA><STATION_ID>{station}</STATION_ID>'
            f'<TIME>{t_ms}</TIME><GPS_TIME>0</GPS_TIME><FREQUENCY>{freq_mhz}</FREQUENCY>{loc}'
            f'<DOA>{doa_deg!r}</DOA><PWR>60</PWR><CONF>{int(round(conf * 100))}</CONF>'
            '<LATENCY>100</LATENCY><PROCESSING_TIME>20</PROCESSING_TIME>'
            '<ADC_OVERDRIVE>0</ADC_OVERDRIVE><NUM_CORRELATED_SOURCES>1'
            '</NUM_CORRELATED_SOURCES><SNR_DB>15</SNR_DB></DATA>').encode()


def compass_deg(frm, to):
    """True compass bearing (deg, clockwise from North) from ``frm`` to ``to`` (ENU)."""
    return math.degrees(math.atan2(to[0] - frm[0], to[1] - frm[1]))


class FakeKrakens(LoopbackHTTP):
    """KrakenSDR web servers on one loopback port: ``docs[path]`` is served at ``path``
    (404 else). ``stop()`` closes the socket (the receivers die), ``start()`` binds the same
    port again."""

    def __init__(self):
        super().__init__()
        self.docs = {}
        self.lock = threading.Lock()

    def respond(self, handler):
        with self.lock:
            body = self.docs.get(handler.path)
        handler.send_response(404 if body is None else 200)
        handler.send_header('Content-Length', str(len(body or b'')))
        handler.end_headers()
        handler.wfile.write(body or b'')

    def set(self, path, body):
        with self.lock:
            self.docs[path] = body

    def url(self, station):
        return f'http://127.0.0.1:{self.port}/{station}/doa.xml'


class Net:
    """Station nodes, an optional fusion node and a probe in one executor."""

    def __init__(self):
        self._probe = Probe('probe')
        self.context, self.executor = self._probe.context, self._probe.executor
        self.probe = self._probe.node
        self.nodes, self.received, self.diagnostics, self.fixes = {}, {}, {}, []
        # receiver TIME of frame 0 (ms): the wall clock, as a live fusion node expects
        self.t0_ms = int(time.time() * 10) * 100
        self.probe.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 100)

    def _on_diag(self, arr):
        for st in arr.status:
            level = st.level[0] if isinstance(st.level, bytes) else int(st.level)
            self.diagnostics[st.name] = (level, st.message,
                                         {kv.key: kv.value for kv in st.values})

    def station(self, name, topics=('bearing',), **params):
        params.setdefault('diagnostics_period', 0.1)
        node = StationNode(context=self.context, namespace=f'/{name}', parameter_overrides=[
            Parameter(k, value=v) for k, v in params.items()])
        self.executor.add_node(node)
        self.nodes[name] = node
        for t in topics:
            topic = f'/{name}/bearing' if t == 'bearing' else t
            self.received[topic] = []
            self.probe.create_subscription(PoseWithCovarianceStamped, topic,
                                           self.received[topic].append, OUTPUT_QOS)
        return node

    def add(self, node):
        self.executor.add_node(node)
        self.nodes[node.get_name()] = node
        return node

    def spin(self, predicate, timeout=5.0):
        return spin_until(self.executor, predicate, timeout)

    def diag(self, name):
        """(level, message, values) of station ``name``'s newest DiagnosticStatus."""
        return self.diagnostics.get(f'station_node: {name}')

    def close(self):
        self._probe.close(self.nodes.values())


@pytest.fixture
def net():
    n = Net()
    yield n
    n.close()


@pytest.fixture
def fake():
    f = FakeKrakens().start()
    yield f
    f.stop()


def kraken_params(url, **kw):
    p = {'input': 'kraken_xml_http', 'kraken.url': url, 'kraken.poll_rate': 50.0,
         'kraken.timeout': 0.5, 'kraken.sigma_conf1_deg': SIGMA_DEG,
         'kraken.sigma_conf0_deg': SIGMA_DEG}
    p.update(kw)
    return p


def three_stations(net, fake, fusion=False):
    for s, (pos, heading) in STATIONS.items():
        net.station(s, **kraken_params(fake.url(s), position=pos,
                                       **{'kraken.array_heading_deg': heading}))
    if fusion:
        from bearing_loc_ros.fusion_node import FusionNode
        node = net.add(FusionNode(context=net.context, parameter_overrides=[
            Parameter('stations', value=sorted(STATIONS)), Parameter('min_stations', value=3),
            *(Parameter(k, value=v) for k, v in HORIZONTAL.items())]))
        net.probe.create_subscription(PoseWithCovarianceStamped, '/fix', net.fixes.append, 50)
        assert net.spin(lambda: all(n.pubs[''].get_subscription_count() >= 2 for k, n in
                                    net.nodes.items() if k in STATIONS)), 'not discovered'
        return node
    return None


def serve_frame(net, fake, rng=None):
    """The next frame of every station, stamped with the wall clock (strictly increasing):
    the transmitter's compass bearing (+ noise) as DOA. Returns (stamp ms, truth θ rad)."""
    net.last_ms = max(getattr(net, 'last_ms', 0) + 1, int(time.time() * 1000))
    truth = {}
    for s, (pos, heading) in STATIONS.items():
        beta = compass_deg(pos, TX) + (rng.normal(0.0, SIGMA_DEG) if rng else 0.0)
        doa = (heading - beta) % 360.0
        fake.set(f'/{s}/doa.xml', xml_doc(net.last_ms, doa, station=s))
        truth[s] = math.radians(90.0 - (heading - doa))
    return net.last_ms, truth


def test_three_stations_publish_the_expected_enu_azimuths(net, fake):
    three_stations(net, fake)
    for k in range(5):
        t_ms, truth = serve_frame(net, fake)
        assert net.spin(lambda: all(len(net.received[f'/{s}/bearing']) > k
                                    for s in STATIONS)), f'frame {k}'
        for s, (pos, _) in STATIONS.items():
            b = bearing_from_msg(net.received[f'/{s}/bearing'][k], s)
            assert b.stamp_ns == t_ms * 10 ** 6
            assert abs(wrap_angle(b.azimuth - truth[s])) < 1e-9
            assert abs(wrap_angle(b.azimuth - math.radians(90.0 - compass_deg(pos, TX)))) \
                < 1e-9
            assert b.position.tolist() == pos and math.isnan(b.elevation)
            assert b.sigma_azimuth == pytest.approx(math.radians(SIGMA_DEG))
    net.spin(lambda: False, 0.3)            # the same documents polled again: unchanged
    assert all(len(net.received[f'/{s}/bearing']) == 5 for s in STATIONS)
    level, _, values = net.diag('north')
    assert int(values['published']) == 5 and int(values['rejected']) == 0
    assert values['kraken_state'] == 'ok' and int(values['kraken_unchanged']) > 0
    assert level == 0


def _frames_to_fixes(received):
    """Per frame, the horizontal MLE of the three stations' published bearings (z = 0)."""
    out = []
    for msgs in zip(*(received[f'/{s}/bearing'] for s in STATIONS)):
        bs = [bearing_from_msg(m, s) for m, s in zip(msgs, STATIONS)]
        assert len({b.stamp_ns for b in bs}) == 1
        f = locate_horizontal('mle', BearingSet.from_arrays(
            np.array([b.position for b in bs]), np.array([b.azimuth for b in bs]),
            sigma_az=np.array([b.sigma_azimuth for b in bs]), validate=False), 0.0)
        out.append((f.position[0], f.covariance[0]))
    return out


def _nees_sum_in_band(fixes, truth, alpha=1e-3):
    """Σ of the horizontal Mahalanobis distances² of n independent consistent fixes is
    χ²(2n): the two-sided 1 − alpha band."""
    d2 = [float((x[:2] - truth[:2]) @ np.linalg.solve(c[:2, :2], x[:2] - truth[:2]))
          for x, c in fixes]
    n = len(d2)
    lo, hi = chi2.ppf(alpha / 2, 2 * n), chi2.ppf(1 - alpha / 2, 2 * n)
    return lo < sum(d2) < hi, (sum(d2), lo, hi, max(d2))


@pytest.mark.parametrize('with_fusion', [
    False, pytest.param(True, marks=pytest.mark.skipif(
        not HAS_HORIZONTAL, reason='the fusion node has no azimuth-only mode (dimension) '
        'yet'))])
def test_noisy_frames_localize_the_transmitter_within_covariance(net, fake, with_fusion):
    three_stations(net, fake, fusion=with_fusion)
    rng = np.random.default_rng(14)
    n = 25
    for k in range(n):
        serve_frame(net, fake, rng)
        assert net.spin(lambda: all(len(net.received[f'/{s}/bearing']) > k
                                    for s in STATIONS)), f'frame {k}'
    fixes = _frames_to_fixes(net.received)
    if with_fusion:
        assert net.spin(lambda: len(net.fixes) >= n)
        net.spin(lambda: False, 0.2)
        assert len(net.fixes) == n                      # one fix per frame, no other
        fixes = [fix_from_msg(m)[1:] for m in net.fixes]
    ok, figures = _nees_sum_in_band(fixes, TX)
    assert len(fixes) == n and ok, figures
    # the figure for the report: mean horizontal error against the mean 1-sigma size
    err = np.mean([np.linalg.norm(x[:2] - TX[:2]) for x, _ in fixes])
    size = np.mean([math.sqrt(np.trace(c[:2, :2])) for _, c in fixes])
    print(f'fixes {n}: mean error {err:.1f} m, mean sqrt(tr P) {size:.1f} m, '
          f'NEES sum {figures[0]:.1f} in ({figures[1]:.1f}, {figures[2]:.1f})')


def test_dead_or_garbage_receiver_never_stops_the_node_and_recovers(net, fake):
    three_stations(net, fake)
    serve_frame(net, fake)
    assert net.spin(lambda: all(len(net.received[f'/{s}/bearing']) == 1 for s in STATIONS))

    fake.stop()                                     # the receivers die
    assert net.spin(lambda: (net.diag('north') or (0, '', {}))[2].get('kraken_state')
                    == 'unreachable')
    level, message, values = net.diag('north')
    assert level == 1 and 'unreachable' in message
    fake.start()                                    # same port: automatic recovery
    serve_frame(net, fake)
    assert net.spin(lambda: all(len(net.received[f'/{s}/bearing']) == 2 for s in STATIONS),
                    15.0)
    assert net.spin(lambda: int(net.diag('north')[2].get('kraken_source_recoveries', 0)) >= 1
                    and net.diag('north')[2]['kraken_state'] == 'ok')

    for body, reason in ((b'\x00garbage <DATA', 'malformed_xml'),
                         (xml_doc(net.t0_ms + 500, math.nan, 'north'), 'not_finite'),
                         (xml_doc(net.t0_ms + 600, 12.0, 'north', freq_mhz=-5),
                          'out_of_range'),
                         (xml_doc(net.t0_ms - 1000, 12.0, 'north'), 'old_time'),
                         (b'<DATA>' + b'x' * 300_000 + b'</DATA>', 'too_large')):
        fake.set('/north/doa.xml', body)
        assert net.spin(lambda: int(net.diag('north')[2].get(f'rejected_{reason}', 0)) > 0), \
            reason
        assert net.diag('north')[0] == 1            # WARN while readings are rejected
    serve_frame(net, fake)                       # good documents again
    assert net.spin(lambda: all(len(net.received[f'/{s}/bearing']) == 3 for s in STATIONS))
    assert net.spin(lambda: net.diag('north')[0] == 0 and int(net.diag('north')[2][
        'published']) == 3)


def test_vehicle_gps_heading_on_a_circle_holds_the_heading_below_min_speed(net, fake):
    """A vehicle drives a 150 m circle at 10 m/s, then stops; the GPS heading it reports
    while stopped is junk (90° off): the node must use the last good heading, and count it.
    Expected azimuths: the transmitter's direction from the vehicle's GPS position, taken
    by pymap3d in the vehicle's own ENU axes (the receiver's frame) and rotated into the
    origin's; tolerance 1e-4 rad covers the 1e-5 rad mixing of local and origin North in
    the vehicle's heading."""
    origin = (48.137, 11.575, 520.0)
    tx_geo = [float(v) for v in pymap3d.enu2geodetic(*TX, *origin)]
    net.station('car', **kraken_params(
        fake.url('car'), geodetic_origin=list(origin),
        **{'kraken.heading_source': 'gps', 'kraken.position_source': 'gps',
           'kraken.min_speed': 2.0, 'kraken.array_heading_deg': 30.0}))
    r, frames, slow = 150.0, 24, 6
    expected, held_h = [], None
    for k in range(frames + slow):
        a = 2 * math.pi * min(k, frames - 1) / frames
        p = np.array([r * math.cos(a), r * math.sin(a), 0.0])
        h_true = math.degrees(math.atan2(-math.sin(a), math.cos(a)))  # CCW motion, compass
        moving = k < frames
        held_h = h_true if moving else held_h
        lat, lon, alt = (float(v) for v in pymap3d.enu2geodetic(*p, *origin))
        e, n_, _ = pymap3d.geodetic2enu(*tx_geo, lat, lon, alt)
        beta = math.degrees(math.atan2(e, n_))       # in the vehicle's local North
        doa = (h_true + 30.0 - beta) % 360.0
        fake.set('/car/doa.xml', xml_doc(
            net.t0_ms + 200 * k, doa, lat=lat, lon=lon,
            heading=(h_true if moving else h_true + 90.0) % 360.0,
            speed=10.0 if moving else 0.3))
        expected.append(math.atan2(TX[1] - p[1], TX[0] - p[0]))
        assert net.spin(lambda: len(net.received['/car/bearing']) > k), f'frame {k}'
    got = [bearing_from_msg(m, 'car') for m in net.received['/car/bearing']]
    err = [abs(wrap_angle(b.azimuth - t)) for b, t in zip(got, expected)]
    assert max(err) < 1e-4, max(err)
    assert np.allclose(got[frames - 1].position[:2], [r * math.cos(2 * math.pi * (frames - 1)
                                                                   / frames),
                                                      r * math.sin(2 * math.pi * (frames - 1)
                                                                   / frames)], atol=1e-6)
    assert net.spin(lambda: int(net.diag('car')[2].get('kraken_heading_held', 0)) == slow)
    values = net.diag('car')[2]
    assert int(values['kraken_heading_gps']) == frames
    assert 'kraken_heading_fixed' not in values


TX2 = {'uhf': (TX, 433.92e6), 'vhf': (np.array([-400.0, 900.0, 0.0]), 145.5e6)}


@pytest.mark.skipif(not HAS_HORIZONTAL, reason='the fusion node has no azimuth-only mode '
                    '(dimension) yet')
def test_two_channels_two_transmitters_one_fusion_process(net, fake):
    """Each receiver serves DOA_value.html with one line per channel; the station nodes
    publish /<channel>/<station>/bearing, the fusion node (channels uhf, vhf) fixes each
    transmitter on /<channel>/fix within its covariance."""
    from bearing_loc_ros.core import kraken
    from bearing_loc_ros.fusion_node import FusionNode
    bands = {'kraken.channels': ['uhf', 'vhf'],
             'kraken.channel_bands_mhz': [430.0, 440.0, 144.0, 146.0]}
    for s, (pos, heading) in STATIONS.items():
        net.station(s, topics=[f'/{c}/{s}/bearing' for c in TX2], **kraken_params(
            fake.url(s).replace('doa.xml', 'DOA_value.html'), input='kraken_csv_http',
            position=pos, **{'kraken.array_heading_deg': heading}, **bands))
    host = net.add(FusionNode(context=net.context, parameter_overrides=[
        Parameter('stations', value=sorted(STATIONS)), Parameter('min_stations', value=3),
        *(Parameter(k, value=v) for k, v in HORIZONTAL.items()),
        Parameter('channels', value=list(TX2))]))
    fixes = {c: [] for c in TX2}
    for c in TX2:
        net.probe.create_subscription(PoseWithCovarianceStamped, f'/{c}/fix',
                                      fixes[c].append, 50)
    assert net.spin(lambda: len(host.channel_host.nodes) == 2 and all(
        n.pubs[c].get_subscription_count() >= 2 for k, n in net.nodes.items()
        if k in STATIONS for c in TX2)), 'channel nodes not subscribed'
    rng = np.random.default_rng(15)
    n = 20
    for k in range(n):
        net.last_ms = max(getattr(net, 'last_ms', 0) + 1, int(time.time() * 1000))
        for s, (pos, heading) in STATIONS.items():
            lines = []
            for c, (tx, freq) in TX2.items():
                doa = (heading - compass_deg(pos, tx) - rng.normal(0.0, SIGMA_DEG)) % 360.0
                lines.append(kraken.csv_line(kraken.KrakenRecord(
                    net.last_ms * 10 ** 6, s, freq, doa, (360.0 - doa) % 360.0, 0.95, -40.0)))
            fake.set(f'/{s}/DOA_value.html', ('\n'.join(lines) + '\n').encode())
        assert net.spin(lambda: all(len(net.received[f'/{c}/{s}/bearing']) > k
                                    for s in STATIONS for c in TX2)), f'frame {k}'
    assert net.spin(lambda: all(len(fixes[c]) >= n for c in TX2))
    for c, (tx, _) in TX2.items():
        ok, figures = _nees_sum_in_band([fix_from_msg(m)[1:] for m in fixes[c]], tx)
        assert len(fixes[c]) == n and ok, (c, figures)
        print(f'channel {c}: NEES sum {figures[0]:.1f} in ({figures[1]:.1f}, '
              f'{figures[2]:.1f}), largest {figures[3]:.1f}')
    # /diagnostics is periodic: the last one received may predate the last fixes.
    assert net.spin(lambda: all(
        int(net.diagnostics.get(f'{c}/fusion: fusion', (0, '', {'fixes': -1}))[2]['fixes'])
        == n for c in TX2))
    values = net.diagnostics['uhf/fusion: fusion'][2]
    assert int(values['fixes']) == n and values['live_stations'].count(',') == 2


def test_file_input_live_equals_bag_import_then_bag_process(net, tmp_path):
    """The station nodes' file input (kraken_csv_file, followed while the test appends one
    frame at a time) and a live fusion node on /clock give the same bearings as ``bag
    import`` of the same logs, bit for bit, and (with the azimuth-only solve) the same
    fixes as ``bag process`` of that bag: stamps come from the files and the pipeline is
    the same, so only the arrival times differ, and those change no fix (event trigger,
    every frame's bearings in before the next)."""
    from rclpy.serialization import serialize_message
    from rosgraph_msgs.msg import Clock
    from test_kraken_bag import params as log_params, STATIONS as LOG_STATIONS, write_logs

    from bearing_loc_ros import bagio
    from bearing_loc_ros.bag_import import import_logs
    from bearing_loc_ros.bag_process import fusion_params, process_bag
    from bearing_loc_ros.fusion_node import FusionNode
    from bearing_loc_ros.ros_conversions import fix_to_msg, ns_to_time
    channels = ['uhf', 'vhf']
    logs = write_logs(tmp_path, np.random.default_rng(3))
    import_logs(logs, tmp_path / 'bag', log_params(), clock_rate=10.0)
    fusion = {'min_stations': 3, **HORIZONTAL}
    offline = {c: process_bag(tmp_path / 'bag', None, fusion_params(None, [
        f'{k}={v}' for k, v in fusion.items()]), namespace=c)['epoch_list'] for c in channels}

    frames = {}     # station -> [lines of frame k]
    for s, path in logs.items():
        groups = []
        for line in path.read_text().splitlines(keepends=True):
            head = line.split(',')[0]
            if groups and (not head.isdigit() or abs(int(head) - groups[-1][0]) < 500):
                groups[-1][1].append(line)
            else:
                groups.append((int(head), [line]))
        frames[s] = groups
    live_dir = tmp_path / 'live'
    live_dir.mkdir()
    common = log_params()['/**']['ros__parameters']['kraken']
    for s, (pos, heading) in LOG_STATIONS.items():
        (live_dir / f'{s}.csv').write_text('')
        net.station(s, topics=[f'/{c}/{s}/bearing' for c in channels], position=pos, **{
            'input': 'kraken_csv_file', 'kraken.file': str(live_dir / f'{s}.csv'),
            'kraken.array_heading_deg': heading, **{f'kraken.{k}': v
                                                    for k, v in common.items()}})
    host = net.add(FusionNode(context=net.context, parameter_overrides=[
        *(Parameter(k, value=v) for k, v in fusion.items()),
        Parameter('stations', value=sorted(LOG_STATIONS)), Parameter('channels', value=channels),
        Parameter('use_sim_time', value=True)]))
    live = {c: [] for c in channels}
    for c in channels:
        net.probe.create_subscription(PoseWithCovarianceStamped, f'/{c}/fix',
                                      live[c].append, 100)
    clock = net.probe.create_publisher(Clock, '/clock', 10)
    assert net.spin(lambda: len(host.channel_host.nodes) == 2 and all(
        n.pubs[c].get_subscription_count() >= 2 for k, n in net.nodes.items()
        if k in LOG_STATIONS for c in channels)), 'not connected'
    n_frames = len(frames['north'])
    for k in range(n_frames):
        t_ns = max(frames[s][k][0] for s in LOG_STATIONS) * 10 ** 6
        clock.publish(Clock(clock=ns_to_time(t_ns)))
        assert net.spin(lambda: all(n.get_clock().now().nanoseconds >= t_ns for n in
                                    host.channel_host.nodes.values()))
        for s in LOG_STATIONS:
            with open(live_dir / f'{s}.csv', 'a') as f:
                f.writelines(frames[s][k][1])
        assert net.spin(lambda: all(len(net.received[f'/{c}/{s}/bearing']) > k
                                    for s in LOG_STATIONS for c in channels)), f'frame {k}'
    clock.publish(Clock(clock=ns_to_time(t_ns + 10 ** 9)))
    net.spin(lambda: False, 0.3)

    with bagio.BagReader(tmp_path / 'bag') as r:
        for c in channels:
            for s in LOG_STATIONS:
                topic = f'/{c}/{s}/bearing'
                want = [m.raw for m in r.messages([topic])]
                got = [serialize_message(m) for m in net.received[topic]]
                assert got == want, topic          # the same bytes
    if not HAS_HORIZONTAL:
        return
    for c in channels:
        want = [fix_from_msg(fix_to_msg(e.position, e.covariance, e.stamp_ns, 'map'))
                for e in offline[c] if e.ok]
        got = [fix_from_msg(m) for m in live[c]]
        assert len(got) == len(want) == n_frames
        for (ts, xs, cs), (tw, xw, cw) in zip(got, want):
            assert ts == tw and np.array_equal(xs, xw) and np.array_equal(cs, cw)
