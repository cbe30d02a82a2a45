"""The Foxglove view server, live: simulator + fusion + view_node as processes on loopback, and
a client of the Foxglove WebSocket protocol (test/view_client.py) that decodes what it
serves and compares it with what the fusion node publishes over DDS."""
import asyncio
import json
import math
import os
import re
import threading

from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import OccupancyGrid
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from visualization_msgs.msg import MarkerArray

from bearing_loc_ros import msgdefs
from bearing_loc_ros.core import geodesy
from bearing_loc_ros.ros_conversions import fix_from_msg
from ros_helpers import REPO, seed000_variant, spin_until, start_node
from view_client import FoxgloveClient, geojson_payload

pytestmark = pytest.mark.ros

ORIGIN = [48.137, 11.575, 520.0]
TYPES = ['geometry_msgs/msg/PoseWithCovarianceStamped', 'sensor_msgs/msg/NavSatFix',
         'visualization_msgs/msg/MarkerArray', 'nav_msgs/msg/OccupancyGrid',
         'nav_msgs/msg/Odometry', 'diagnostic_msgs/msg/DiagnosticArray',
         'rosgraph_msgs/msg/Clock', 'geometry_msgs/msg/PoseStamped']


@pytest.mark.parametrize('msgtype', TYPES)
def test_ros2msg_schema_matches_the_typestore(msgtype):
    """Each flattened definition parses (rosbags' .msg parser) into the same fields as the
    Jazzy typestore, dependency by dependency."""
    from rosbags.typesys import get_types_from_msg
    from bearing_loc_ros import bagio
    text = msgdefs.message_definition(msgtype)
    sections = text.split(msgdefs.SEPARATOR + '\n')
    names = [msgtype] + [s.splitlines()[0][len('MSG: '):] for s in sections[1:]]
    bodies = [sections[0]] + ['\n'.join(s.splitlines()[1:]) for s in sections[1:]]
    assert len(set(names)) == len(names)
    ts = bagio.typestore()
    for name, body in zip(names, bodies):
        pkg, typ = msgdefs.split_type(name)
        full = f'{pkg}/msg/{typ}'
        parsed = get_types_from_msg(body, full)[full]
        assert [f[0] for f in parsed[1]] == [f[0] for f in ts.fielddefs[full][1]], full


@pytest.fixture
def scenario_file(tmp_path):
    return seed000_variant(tmp_path, 'seed000_view.yaml', 1.0, 60.0)


class Listener:
    """In-test rclpy subscriber (raw CDR) of /fix, /markers, /accuracy_map, in a thread."""

    def __init__(self):
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node('view_test_listener', context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.fix, self.markers, self.maps = [], [], []
        rel = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.node.create_subscription(PoseWithCovarianceStamped, '/fix', self.fix.append, rel,
                                      raw=True)
        self.node.create_subscription(MarkerArray, '/markers', self.markers.append, rel,
                                      raw=True)
        self.node.create_subscription(OccupancyGrid, '/accuracy_map', self.maps.append,
                                      latched, raw=True)
        self.thread = None

    def start(self):
        self.thread = threading.Thread(target=self.ex.spin, daemon=True)
        self.thread.start()

    def close(self):
        self.ex.shutdown()
        if self.thread:
            self.thread.join(5)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


async def crowd(url, n=20, abort=10):
    """n clients at once: each subscribes to /fix and /map_geojson and receives; ``abort``
    of them drop the TCP connection without a close frame, the others close politely."""
    clients = await asyncio.gather(*(FoxgloveClient(url).connect() for _ in range(n)))
    await asyncio.gather(*(c.pump(3.0, lambda c: '/fix' in c.by_topic) for c in clients))
    for c in clients:
        await c.subscribe(['/fix', '/map_geojson'])
    await asyncio.gather(*(c.pump(5.0, lambda c: len(c.messages.get('/fix', ())) >= 2)
                           for c in clients))
    got = [len(c.messages.get('/fix', ())) for c in clients]
    for k, c in enumerate(clients):
        if k < abort:
            c.ws.transport.abort()
        else:
            await c.close()
    return got


async def slow_client(url):
    """Subscribes to everything and then never reads (its socket buffers fill up)."""
    c = await FoxgloveClient(url).connect()
    await c.pump(3.0, lambda c: '/fix' in c.by_topic)
    await c.subscribe(list(c.by_topic))
    return c


async def session(url, sim):
    a = await FoxgloveClient(url).connect()
    topics = {'/fix', '/markers', '/accuracy_map', '/map_geojson'}
    # Generous: on a loaded machine discovery of the fusion's publishers can take seconds.
    assert await a.pump(30.0, lambda c: topics <= set(c.by_topic)), sorted(a.by_topic)
    await a.subscribe(['/fix', '/markers', '/accuracy_map', '/map_geojson', '/clock',
                       '/view/fix_stats'])
    slow = await slow_client(url)
    await sim.start()
    # The crowd connects once fixes flow: a loaded machine may take seconds to start the
    # simulator, and the crowd's own wait must not race that start-up.
    await a.pump(30.0, lambda c: '/fix' in c.messages)
    crowd_task = asyncio.create_task(crowd(url))
    await a.pump(60.0, lambda c: sim.done())
    counts = await crowd_task
    await a.pump(1.5)                       # the last fixes and pictures in flight
    late = await FoxgloveClient(url).connect()
    await late.pump(3.0, lambda c: '/accuracy_map' in c.by_topic)
    await late.subscribe(['/accuracy_map', '/map_geojson'])
    await late.pump(5.0, lambda c: '/accuracy_map' in c.messages and '/map_geojson' in
                    c.messages)
    slow.ws.transport.abort()
    await a.close()
    await late.close()
    return a, late, counts


class Sim:
    """Starts the simulator on demand from the asyncio side, once ``ready()`` (the view's
    /fix reader is in the graph: fixes published before it matches would reach the test's
    listener but not the view) and 1 s more for matching to settle."""

    def __init__(self, args, ready=lambda: True):
        self.args, self.proc, self.ready = args, None, ready

    async def start(self):
        for _ in range(150):
            if self.ready():
                break
            await asyncio.sleep(0.1)
        await asyncio.sleep(1.0)
        self.proc = start_node('bearing_loc_ros.simulator_node', self.args)

    def done(self):
        return self.proc is not None and self.proc.proc.poll() is not None


def test_live_view_serves_what_the_fusion_publishes(scenario_file):
    stations = '["station_1","station_2","station_3"]'
    origin = '[' + ','.join(map(str, ORIGIN)) + ']'
    fusion_args = ['-p', f'stations:={stations}', '-p', 'use_sim_time:=true',
                   '-p', 'estimator:=mle', '-p', f'geodetic_origin:={origin}']
    view_args = ['-p', 'port:=0', '-p', 'use_sim_time:=true', '-p', f'geodetic_origin:={origin}',
                 '-p', 'geojson_period:=0.2', '-p', 'discovery_period:=0.2']
    listener = Listener()
    sim = Sim(['-p', f'scenario:={scenario_file}', '-p', 'seed:=7', '-p', 'time_scale:=10.0',
               '-p', 'start_delay:=10.0'],
              ready=lambda: listener.node.count_subscribers('/fix') >= 2)   # it and the view
    try:
        with start_node('bearing_loc_ros.fusion_node', fusion_args) as fusion, \
                start_node('bearing_loc_ros.view_node', view_args) as view:
            assert spin_until(listener.ex, lambda: listener.node.count_publishers('/fix') > 0
                              and re.search(r'ws://127\.0\.0\.1:(\d+)', view.output()), 20.0), \
                fusion.output() + view.output()
            port = int(re.search(r'ws://127\.0\.0\.1:(\d+)', view.output()).group(1))
            listener.start()
            a, late, counts = asyncio.run(session(f'ws://127.0.0.1:{port}', sim))
            assert sim.proc.stop() == 0, sim.proc.output()
            assert view.running(), view.output()      # survived aborts and the slow client
            assert view.stop() == 0, view.output()
            assert fusion.stop() == 0, fusion.output()
    finally:
        if sim.proc is not None:
            sim.proc.stop()
        listener.close()

    # Fixes: every fix the fusion published reached the client, byte for byte.
    dds = {fix_from_msg(deserialize_message(r, PoseWithCovarianceStamped))[0]: bytes(r)
           for r in listener.fix}
    ws = {fix_from_msg(deserialize_message(p, PoseWithCovarianceStamped))[0]: p
          for _, p in a.messages['/fix']}
    assert len(dds) >= 50 and set(ws) == set(dds)
    assert all(ws[k] == dds[k] for k in dds)
    # Markers: decoded, and every one served is one the fusion published.
    served = [p for _, p in a.messages['/markers']]
    assert served and set(served) <= {bytes(r) for r in listener.markers}
    assert deserialize_message(served[-1], MarkerArray).markers
    # Accuracy map: the live subscriber and the late joiner get the latched map.
    assert listener.maps and a.messages['/accuracy_map']
    assert late.messages['/accuracy_map'][-1][1] == bytes(listener.maps[-1])
    grid = deserialize_message(late.messages['/accuracy_map'][-1][1], OccupancyGrid)
    assert grid.info.width > 0 and len(grid.data) == grid.info.width * grid.info.height
    # GeoJSON: the last picture shows the stations, their rays and a fix the fusion published.
    fc = json.loads(geojson_payload(a.messages['/map_geojson'][-1][1]))
    kinds = [f['properties']['kind'] for f in fc['features']]
    assert kinds.count('station') == 3 and kinds.count('bearing') == 3
    assert 'ellipse' in kinds
    fix = [f for f in fc['features'] if f['properties']['kind'] == 'fix'][0]
    stamp = fix['properties']['stamp_ns']
    assert stamp in dds
    _, pos, _ = fix_from_msg(deserialize_message(dds[stamp], PoseWithCovarianceStamped))
    lat, lon, _ = geodesy.enu_to_geodetic(pos, ORIGIN)
    assert fix['geometry']['coordinates'][:2] == pytest.approx([float(lon), float(lat)],
                                                               abs=2e-9)
    assert late.messages['/map_geojson']
    # Server time is the simulated clock (scenario epoch 1000 s), not the wall clock.
    assert a.times and all(1000e9 <= t <= 1100e9 for t in a.times)
    assert np.all(np.diff(a.times) >= 0)
    # The plot channel: σ of each fix and the fix rate (1 Hz bearings -> 1 Hz fixes).
    assert a.by_topic['/view/fix_stats']['schemaName'] == 'bearing_loc_ros.FixStats'
    stats = [json.loads(p) for _, p in a.messages['/view/fix_stats']]
    assert len(stats) == len(dds)
    for st in stats:
        _, _, cov = fix_from_msg(deserialize_message(dds[st['stamp_ns']],
                                                     PoseWithCovarianceStamped))
        assert st['sigma_horizontal_m'] == pytest.approx(np.sqrt(cov[0, 0] + cov[1, 1]))
    assert stats[-1]['fix_rate_hz'] == pytest.approx(1.0, rel=0.05)
    # 20 clients at once all received fixes.
    assert len(counts) == 20 and min(counts) >= 2, counts


def test_view_refuses_a_polar_or_too_high_origin_and_a_busy_port():
    with start_node('bearing_loc_ros.view_node',
                    ['-p', 'port:=0', '-p', 'geodetic_origin:=[89.9,0.0,0.0]']) as bad:
        assert bad.wait(20.0) == 1
        assert 'polar' in bad.output() and 'Traceback' not in bad.output()
    with start_node('bearing_loc_ros.view_node',
                    ['-p', 'port:=0', '-p', 'geodetic_origin:=[48.0,11.0,1e12]']) as high:
        assert high.wait(20.0) == 1                  # was accepted
        assert "parameter 'geodetic_origin'" in high.output() and 'altitude' in high.output()
    import socket
    s = socket.socket()
    s.bind(('127.0.0.1', 0))
    s.listen(1)
    try:
        port = s.getsockname()[1]
        with start_node('bearing_loc_ros.view_node', ['-p', f'port:={port}']) as busy:
            assert busy.wait(20.0) == 1
            assert "parameter 'port'" in busy.output(), busy.output()
    finally:
        s.close()
    # A host that is not an address of this machine, or does not resolve, is blamed on
    # host, not port.
    from bearing_loc_ros.view_node import _blamed
    assert _blamed('192.0.2.1', RuntimeError('Failed to bind port: Cannot assign requested '
                                             'address (os error 99)')) == 'host'
    assert _blamed('127.0.0.1', RuntimeError('Address already in use (os error 98)')) == 'port'
    with start_node('bearing_loc_ros.view_node', ['-p', 'host:=not.a.host.invalid',
                                                  '-p', 'port:=0']) as nohost:
        assert nohost.wait(20.0) == 1
        assert "parameter 'host'" in nohost.output(), nohost.output()


def test_shipped_layout_is_the_generated_one_and_plots_served_fields():
    from bearing_loc_ros import foxglove_layout
    from bearing_loc_ros.foxglove_view import STATS_SCHEMA, STATS_TOPIC
    with open(os.path.join(REPO, 'config', 'foxglove_layout.json'), encoding='utf-8') as f:
        text = f.read()
    assert text == foxglove_layout.layout_json()
    doc = json.loads(text)
    panels = {k.split('!')[0] for k in doc['configById']}
    assert panels == {'map', '3D', 'Plot'}

    def leaves(node):
        if isinstance(node, str):
            return [node]
        return leaves(node['first']) + leaves(node['second'])
    assert sorted(leaves(doc['layout'])) == sorted(doc['configById'])
    three = doc['configById']['3D!bearingloc']['topics']
    assert three['/markers']['visible'] and three['/accuracy_map']['visible']
    for path in doc['configById']['Plot!bearingloc']['paths']:
        topic, _, field = path['value'].rpartition('.')
        assert topic == STATS_TOPIC and field in STATS_SCHEMA['properties']


def test_view_serves_a_bag_directly(tmp_path):
    """``bearing_loc view --bag SIM FIXES``: both bags merged, server time from /clock, the
    GeoJSON picture at the end shows the last fix of the processed bag."""
    import subprocess
    import sys
    cli = [sys.executable, '-c',
           'import sys; from bearing_loc_ros.cli import main; sys.exit(main())']
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    for args in (['bag', 'simulate', '--scenario', 'config/scenarios/static3.yaml', '--out',
                  str(tmp_path / 'sim')],
                 ['bag', 'process', str(tmp_path / 'sim'), '--out', str(tmp_path / 'fix')]):
        subprocess.run(cli + args, cwd=REPO, env=env, check=True, capture_output=True,
                       timeout=120)
    from bearing_loc_ros.processes import ChildProcess
    origin = [str(v) for v in ORIGIN]
    with ChildProcess(cli + ['view', '--bag', str(tmp_path / 'sim'), str(tmp_path / 'fix'),
                             '--port', '0', '--rate', '4', '--loop', '--origin', *origin],
                      env=env, cwd=REPO) as view:
        deadline = 20.0
        while deadline > 0 and not re.search(r'ws://127\.0\.0\.1:(\d+)', view.output()):
            threading.Event().wait(0.1)
            deadline -= 0.1
        port = int(re.search(r'ws://127\.0\.0\.1:(\d+)', view.output()).group(1))

        async def watch():
            c = await FoxgloveClient(f'ws://127.0.0.1:{port}').connect()
            # Generous: a loaded machine may take seconds to open the bags and advertise.
            assert await c.pump(30.0, lambda c: '/fix' in c.by_topic), view.output()
            await c.subscribe(list(c.by_topic) + ['/map_geojson'])
            for _ in range(6):
                if await c.pump(5.0, lambda c: '/fix' in c.messages):
                    break
                await c.subscribe(['/fix'], again=True)     # (view_client.subscribe)
            await c.pump(30.0, lambda c: len(c.messages.get('/fix', ())) >= 5
                         and 'replaying again' in view.output())
            await c.pump(0.5)
            await c.close()
            return c
        c = asyncio.run(watch())
        assert view.running()
    assert c.messages['/fix'] and c.times
    fc = json.loads(geojson_payload(c.messages['/map_geojson'][-1][1]))
    stamps = [fix_from_msg(deserialize_message(p, PoseWithCovarianceStamped))[0]
              for _, p in c.messages['/fix']]
    fix = [f for f in fc['features'] if f['properties']['kind'] == 'fix'][0]
    # A fix of the bag (each pass starts the picture afresh: test_bag_loop_picture_follows_
    # every_pass; the last fix of a pass is the newest).
    assert fix['properties']['stamp_ns'] in stamps
    from bearing_loc_ros import bagio
    with bagio.BagReader(tmp_path / 'sim') as r:
        lo, hi = r.start_time_ns, r.end_time_ns
    assert all(lo <= t <= hi for t in c.times)       # the bag's /clock, not the wall clock


# ------------------------------------------------------------------ the view's input rules
FIX_TYPE = 'geometry_msgs/msg/PoseWithCovarianceStamped'


def fix_cdr(sec, pos=(1000.0, 2000.0, 100.0), cov=None, frame='map', nanosec=0):
    from rclpy.serialization import serialize_message
    m = PoseWithCovarianceStamped()
    m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id = sec, nanosec, frame
    m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z = pos
    m.pose.pose.orientation.w = 1.0
    c = np.zeros((6, 6))
    c[:3, :3] = np.diag([100.0, 400.0, 900.0]) if cov is None else cov
    m.pose.covariance = c.ravel().tolist()
    return serialize_message(m)


def bearing_cdr(sec, frame='map', station_x=0.0):
    """A station_1 bearing message (azimuth 0.5 rad from (x, -3 km, 0)); ``station_x`` may
    be non-finite (set after the conversion, which refuses it)."""
    from rclpy.serialization import serialize_message
    from bearing_loc_ros.core.bearings import Bearing
    from bearing_loc_ros.ros_conversions import bearing_to_msg
    msg = bearing_to_msg(Bearing('station_1', sec * 10**9, np.array([0.0, -3000.0, 0.0]), 0.5,
                                 frame_id=frame))
    msg.pose.pose.position.x = station_x
    return serialize_message(msg)


@pytest.fixture
def view():
    """An in-process view (loopback, any port, Munich origin); its log lines in ``.lines``."""
    from bearing_loc_ros.foxglove_view import FoxgloveView
    lines = []
    v = FoxgloveView(port=0, origin=ORIGIN, geojson_period=0.0, log=lines.append)
    v.lines = lines
    yield v
    v.stop()


def geojson_text_of(v):
    """The GeoJSON text of the picture the view last sent on /map_geojson."""
    from bearing_loc_ros.foxglove_view import GEOJSON_TOPIC
    channel, msg, _ = v._latched[v._geo_channel.id()]
    assert channel.topic() == GEOJSON_TOPIC
    return geojson_payload(bytes(msg.encode()))


def shown_fix_stamp_s(v):
    """Stamp (s) of the fix in the picture the view last sent on /map_geojson, or None."""
    fc = json.loads(geojson_text_of(v))
    fixes = [f for f in fc['features'] if f['properties']['kind'] == 'fix']
    return fixes[0]['properties']['stamp_ns'] / 1e9 if fixes else None


def test_view_rejects_non_finite_fixes_and_the_map_goes_on(view):
    """One NaN/inf fix used to enter the trail; every later picture then failed ('geojson:
    enu: expected finite coordinates', logged per fix). Now it is counted and logged (once
    per reason and 10 s), and the map follows the good fixes."""
    view.forward('/fix', FIX_TYPE, fix_cdr(1), 1)
    assert shown_fix_stamp_s(view) == 1.0
    bad = [fix_cdr(2, pos=(math.nan, 0.0, 0.0)), fix_cdr(2, pos=(0.0, math.inf, 0.0)),
           fix_cdr(2, cov=np.diag([math.nan, 1.0, 1.0])), fix_cdr(2, pos=(1e300, 0.0, 0.0))]
    for _ in range(25):
        for raw in bad:
            view.forward('/fix', FIX_TYPE, raw, 2)
    view.forward('/station_1/bearing', FIX_TYPE, bearing_cdr(2, station_x=math.nan), 2)
    for k in range(3, 13):
        view.forward('/fix', FIX_TYPE, fix_cdr(k, pos=(1000.0 + 100 * k, 2000.0, 100.0)), k)
        assert shown_fix_stamp_s(view) == k
    st = view.stats()
    assert st['rejected'] == {'bad_fix': 100, 'bad_position': 1} and st['dropped'] == 101
    assert len(view.lines) == 2, view.lines              # throttled: one line per reason
    assert 'bad_fix' in view.lines[0] and 'finite' in view.lines[0]
    assert not any('geojson' in line for line in view.lines)
    fc = json.loads(geojson_text_of(view))
    track = [f for f in fc['features'] if f['properties']['kind'] == 'track'][0]
    assert track['properties']['fixes'] == 11
    # /view/fix_stats only for the fixes used, and the live fix draws no invented provenance.
    fix = [f for f in fc['features'] if f['properties']['kind'] == 'fix'][0]
    assert not {'status', 'estimator', 'stations'} & set(fix['properties'])


def test_view_draws_only_fixes_and_bearings_in_its_world_frame(view):
    """A fix in base_link or with an empty frame_id was drawn as if in the origin's ENU
    frame; now only frame 'map' (the view's frame_id) is drawn."""
    view.forward('/fix', FIX_TYPE, fix_cdr(1, frame='base_link', pos=(5.0, 0.0, 0.0)), 1)
    view.forward('/fix', FIX_TYPE, fix_cdr(2, frame='', pos=(7.0, 0.0, 0.0)), 2)
    view.forward('/station_1/bearing', FIX_TYPE, bearing_cdr(2, frame='odom'), 2)
    assert view.picture.fix is None and not view.picture.bearings
    assert view.stats()['rejected'] == {'wrong_frame': 3}
    assert len(view.lines) == 1 and "'base_link'" in view.lines[0] and "'map'" in view.lines[0]
    assert not view._spaces[''].fix_rate.stamps                   # no σ plotted for them either
    view.forward('/fix', FIX_TYPE, fix_cdr(3), 3)
    view.forward('/station_1/bearing', FIX_TYPE, bearing_cdr(3), 3)
    fc = json.loads(geojson_text_of(view))
    kinds = [f['properties']['kind'] for f in fc['features']]
    assert kinds == ['station', 'bearing', 'ellipse', 'fix']
    assert fc['features'][-1]['properties']['position_enu_m'] == [1000.0, 2000.0, 100.0]


def test_view_node_reports_its_counters_on_diagnostics():
    # The view's rejections were visible only in throttled warnings.
    from diagnostic_msgs.msg import DiagnosticStatus
    from rclpy.parameter import Parameter
    from bearing_loc_ros.view_node import ViewNode
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = ViewNode(context=ctx, parameter_overrides=[
        Parameter('port', value=0), Parameter('geodetic_origin', value=list(ORIGIN))])
    try:
        assert node.diagnostic_status().level == DiagnosticStatus.OK
        node.view.forward('/fix', FIX_TYPE, fix_cdr(1), 1)
        node.view.forward('/fix', FIX_TYPE, fix_cdr(2, frame='base_link'), 2)
        st = node.diagnostic_status()
        values = {kv.key: kv.value for kv in st.values}
        assert st.level == DiagnosticStatus.WARN and st.name == 'view: view'
        assert values['dropped'] == '1' and values['rejected.wrong_frame'] == '1'
        assert node.diagnostic_status().level == DiagnosticStatus.OK     # nothing new
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def test_view_frame_id_selects_the_world_frame_drawn():
    # A fusion node running in another world frame (its frame_id) is drawn when the view is
    # told that frame (view_node frame_id, bearing_loc view --frame-id).
    from bearing_loc_ros.foxglove_view import FoxgloveView
    lines = []
    v = FoxgloveView(port=0, origin=ORIGIN, geojson_period=0.0, log=lines.append,
                     frame_id='enu_site')
    try:
        v.forward('/fix', FIX_TYPE, fix_cdr(1), 1)                          # frame 'map'
        v.forward('/fix', FIX_TYPE, fix_cdr(2, frame='enu_site'), 2)
        assert shown_fix_stamp_s(v) == 2.0 and v.stats()['rejected'] == {'wrong_frame': 1}
    finally:
        v.stop()
    from bearing_loc_ros.cli import main
    assert main(['view', '--frame-id', 'my map', '--port', '0']) == 2


def test_view_survives_a_future_stamp_and_bounds_its_fix_rate_memory(view):
    """One fix stamped 2^31-1 s froze the map for good (older fixes were dropped) and the
    fix-rate stamps grew without bound; a stamp back by more than CLOCK_JUMP_NS is now a
    clock restart, by less an out-of-order drop (counted)."""
    from bearing_loc_ros.core import gis
    view.forward('/fix', FIX_TYPE, fix_cdr(1), 1)
    view.forward('/fix', FIX_TYPE, fix_cdr(2**31 - 1), 2)
    for k in range(3, 13):
        view.forward('/fix', FIX_TYPE, fix_cdr(k, pos=(1000.0 + 100 * k, 2000.0, 100.0)), k)
        assert shown_fix_stamp_s(view) == k
    view.forward('/fix', FIX_TYPE, fix_cdr(11), 13)          # 1 s late: out of order
    assert shown_fix_stamp_s(view) == 12
    st = view.stats()
    assert st['clock_restarts'] == 1 and st['rejected'] == {'out_of_order': 1}
    assert any('clock restart' in line for line in view.lines)
    view.geojson_period = 3600.0                                 # no picture per fix
    raw = fix_cdr(0)
    for k in range(gis.RATE_MAX_STAMPS + 500):                  # all stamped 0 (restart)
        view.forward('/fix', FIX_TYPE, raw, k)
    assert len(view._spaces[''].fix_rate.stamps) <= gis.RATE_MAX_STAMPS
    assert view.publish_geojson(0, force=True) and shown_fix_stamp_s(view) == 0.0
    assert view.stats()['clock_restarts'] == 2


def test_fix_stats_channel_has_a_stable_schema_name(view):
    from bearing_loc_ros.foxglove_view import STATS_SCHEMA, STATS_SCHEMA_NAME
    channel = view._spaces[''].stats_channel
    assert channel.schema_name() == STATS_SCHEMA_NAME == 'bearing_loc_ros.FixStats'
    schema = channel.schema()
    assert schema.encoding == 'jsonschema' and json.loads(bytes(schema.data)) == STATS_SCHEMA


def test_a_gone_clients_send_errors_are_throttled_per_client():
    """foxglove-sdk logs one 'Broken pipe' line per queued message of a client that went away
    (up to 512 per stalled client); the view lets one per client and 10 s through."""
    import logging
    from bearing_loc_ros import foxglove_view as fv
    fv.throttle_sdk_client_errors()
    fv.throttle_sdk_client_errors()
    logger = logging.getLogger(fv.SDK_CLIENT_LOGGER)
    assert logger.filters.count(fv._CLIENT_FILTER) == 1
    flt = fv._ClientErrorFilter()

    def record(client):
        return logging.LogRecord(fv.SDK_CLIENT_LOGGER, logging.ERROR, 'x', 1,
                                 f'Error sending message to client {client}: IO error: '
                                 'Broken pipe (os error 32)', None, None)
    passed = [flt.filter(record('127.0.0.1:40260')) for _ in range(512)]
    assert passed.count(True) == 1 and passed[0]
    assert flt.filter(record('127.0.0.1:40266'))
    t = [0.0]
    flt.throttle.clock = lambda: t[0]
    flt.throttle._last.clear()
    assert flt.filter(record('[::1]:1'))
    assert not flt.filter(record('[::1]:1'))
    t[0] = fv.LOG_THROTTLE_S
    rec = record('[::1]:1')
    assert flt.filter(rec) and '(1 similar lines left out)' in rec.getMessage()


def test_bag_loop_picture_follows_every_pass(tmp_path):
    """``bearing_loc view --bag ... --loop`` kept showing the first pass's last fix: the
    stamps start again with each pass. Every pass now starts the picture afresh; a 2 s bag
    (shorter than the clock-restart jump) too."""
    from bearing_loc_ros import bagio
    from bearing_loc_ros.core.bearings import Bearing
    from bearing_loc_ros.foxglove_view import FoxgloveView, serve_bag
    bag = tmp_path / 'short'
    t0 = 1000 * 10**9
    with bagio.BagWriter(bag) as w:
        w.add_topic('/fix', FIX_TYPE)
        w.add_topic('/station_1/bearing', FIX_TYPE)
        for k in range(10):
            t = t0 + k * 2 * 10**8
            w.write('/station_1/bearing', t, bagio.bearing_message(
                Bearing('station_1', t, np.array([0.0, -3000.0, 0.0]), 0.5)))
            w.write('/fix', t, bagio.fix_message([100.0 * k, 0.0, 0.0], np.eye(3), t))
    v = FoxgloveView(port=0, origin=ORIGIN, geojson_period=0.0, log=lambda text: None)
    passes, seen = [1], []
    stop = threading.Event()
    forward = v.forward

    def watch(topic, msgtype, raw, log_time_ns):
        forward(topic, msgtype, raw, log_time_ns)
        if topic == '/fix':
            seen.append((passes[0], log_time_ns, v.picture.fix.stamp_ns,
                         shown_fix_stamp_s(v)))

    def on_pass(text):
        passes[0] += 1
        if passes[0] > 3:
            stop.set()
    v.forward = watch
    try:
        serve_bag(v, [str(bag)], rate=1000.0, loop=True, stop=stop, log=on_pass)
    finally:
        v.stop()
    assert [p for p, *_ in seen] == [1] * 10 + [2] * 10 + [3] * 10
    for _, sent, held, shown in seen:
        assert held == sent and shown == sent / 1e9
    assert v.stats()['rejected'] == {}


def test_a_bag_with_nothing_to_serve_is_an_error_not_a_busy_loop(tmp_path):
    """``view --bag EMPTY --loop`` (or ``--topics`` naming a topic the bag lacks) spun
    replaying nothing, about 100 passes a second, and Ctrl-C could not stop it (the stop
    event was only looked at between messages). Nothing to serve is now an error before
    the first pass; a requested topic the bag lacks is named in a warning."""
    import subprocess
    import sys
    from bearing_loc_ros import bagio
    from bearing_loc_ros.core.bearings import Bearing
    from bearing_loc_ros.foxglove_view import FoxgloveView, serve_bag
    empty, full = tmp_path / 'empty', tmp_path / 'full'
    with bagio.BagWriter(empty) as w:
        w.add_topic('/station_1/bearing', FIX_TYPE)
    with bagio.BagWriter(full) as w:
        w.add_topic('/station_1/bearing', FIX_TYPE)
        w.write('/station_1/bearing', 10**9, bagio.bearing_message(
            Bearing('station_1', 10**9, np.array([0.0, 0.0, 0.0]), 0.5)))
    lines = []

    def log(text):              # the old loop would call it for ever: fail instead
        lines.append(text)
        assert len(lines) < 5, lines
    v = FoxgloveView(port=0, log=lambda text: None)
    try:
        with pytest.raises(ValueError, match='holds no message to serve'):
            serve_bag(v, [str(empty)], rate=1000.0, loop=True, log=log)
        with pytest.raises(ValueError, match=r'no message on the topics /typo .*no bag has '
                                             r'/typo'):
            serve_bag(v, [str(full)], rate=1000.0, loop=True, topics={'/typo'}, log=log)
        assert lines == []
        stop = threading.Event()
        stop.set()              # Ctrl-C before a pass: no pass at all
        assert serve_bag(v, [str(full)], loop=True, stop=stop, log=log) == 0
        sent = serve_bag(v, [str(full)], rate=1000.0, topics={'/typo', '/station_1/bearing'},
                         log=log)
        assert sent == 1 and lines == ['view: warning: no bag has the requested topic(s) '
                                       '/typo; they are not served']
    finally:
        v.stop()
    cli = [sys.executable, '-c',
           'import sys; from bearing_loc_ros.cli import main; sys.exit(main())']
    proc = subprocess.run(cli + ['view', '--bag', str(empty), '--loop', '--port', '0'],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and 'holds no message to serve' in proc.stderr, proc
    assert 'serving' not in proc.stdout


def test_latched_messages_reach_each_new_client_once_and_no_one_else(view):
    """Every new subscriber of a latched topic made the server broadcast its last message,
    so the first of 4 clients got 4 copies of /accuracy_map (and of /map_geojson and
    /station_1/navsat); /fix/navsat was latched by accident (/fix/bearing read as a station
    'fix'). Now each client gets the latched messages once, on its own, and /fix/navsat is
    not latched. A message broadcast after the last subscription, received by every client,
    orders the check: whatever was sent before it has arrived."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import NavSatFix
    view.forward('/accuracy_map', 'nav_msgs/msg/OccupancyGrid',
                 serialize_message(OccupancyGrid()), 1)
    view.forward('/station_1/bearing', FIX_TYPE, bearing_cdr(1), 1)
    view.forward('/fix', FIX_TYPE, fix_cdr(1), 1)
    view.forward('/fix/navsat', 'sensor_msgs/msg/NavSatFix', serialize_message(NavSatFix()), 1)
    view.advertise('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray')
    latched = ['/accuracy_map', '/map_geojson', '/station_1/navsat']
    url = f'ws://127.0.0.1:{view.port}'

    async def clients(n=4):
        cs = []
        for _ in range(n):
            c = await FoxgloveClient(url).connect()
            await c.pump(10.0, lambda c: all(t in c.by_topic for t in latched + ['/diagnostics']))
            await c.subscribe(latched + ['/fix/navsat', '/diagnostics'])
            await c.pump(10.0, lambda c: all(c.messages.get(t) for t in latched))
            cs.append(c)
        view.forward('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray', b'\0\1\0\0', 2)
        await asyncio.gather(*(c.pump(10.0, lambda c: c.messages.get('/diagnostics'))
                               for c in cs))
        for c in cs:
            await c.close()
        return cs
    cs = asyncio.run(clients())
    for c in cs:
        assert c.messages.get('/diagnostics')
        assert {t: len(c.messages.get(t, ())) for t in latched + ['/fix/navsat']} == \
            {'/accuracy_map': 1, '/map_geojson': 1, '/station_1/navsat': 1, '/fix/navsat': 0}


def test_each_channel_namespace_has_its_own_picture(view):
    """The fusion node's channels publish /<ch>/fix and read /<ch>/<station>/bearing: the
    view drew them all in one picture, a station of two channels as one ('a') with the
    last ray of either, and the fixes of both emitters in one trail. Each namespace now
    has its own picture on <ns>/map_geojson (stations named with their namespace) and its
    own fix statistics on <ns>/view/fix_stats."""
    from rclpy.serialization import serialize_message
    from bearing_loc_ros.core.bearings import Bearing
    from bearing_loc_ros.ros_conversions import bearing_to_msg
    for k in range(1, 5):
        for ch, az, pos in (('uhf', 0.5, (10000.0, 5000.0, 0.0)),
                            ('vhf', 2.0, (-20000.0, 8000.0, 0.0))):
            b = Bearing('a', k * 10**9, np.array([0.0, 0.0, 0.0]), az)
            view.forward(f'/{ch}/a/bearing', FIX_TYPE, serialize_message(bearing_to_msg(b)),
                         k * 10**9)
            view.forward(f'/{ch}/fix', FIX_TYPE, fix_cdr(k, pos=pos), k * 10**9)
    assert sorted(view._spaces) == ['', 'uhf', 'vhf']
    assert view.picture.fix is None and not view.picture.bearings
    for ch, az, x in (('uhf', 0.5, 10000.0), ('vhf', 2.0, -20000.0)):
        space = view._spaces[ch]
        assert space.geo_channel.topic() == f'/{ch}/map_geojson'
        assert space.stats_channel.topic() == f'/{ch}/view/fix_stats'
        _, msg, _ = view._latched[space.geo_channel.id()]
        fc = json.loads(geojson_payload(bytes(msg.encode())))
        rays = [f['properties'] for f in fc['features'] if f['properties']['kind'] == 'bearing']
        assert [r['station'] for r in rays] == [f'{ch}/a']
        assert rays[0]['azimuth_rad'] == pytest.approx(az, abs=1e-12)
        fixes = [f['properties'] for f in fc['features'] if f['properties']['kind'] == 'fix']
        assert [f['position_enu_m'][0] for f in fixes] == [x]
        track = [f['properties'] for f in fc['features'] if f['properties']['kind'] == 'track']
        assert track[0]['fixes'] == 4
        assert len(space.fix_rate.stamps) == 4
    assert view.stats()['rejected'] == {}
    assert {'/uhf/a/navsat', '/vhf/a/navsat'} <= set(view._channels)
