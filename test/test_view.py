"""The Foxglove view server, live: simulator + fusion + view_node as processes on loopback, and
a client of the Foxglove WebSocket protocol (test/view_client.py) that decodes what it
serves and compares it with what the fusion node publishes over DDS."""
import asyncio
import json
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
    stats = [json.loads(p) for _, p in a.messages['/view/fix_stats']]
    assert len(stats) == len(dds)
    for st in stats:
        _, _, cov = fix_from_msg(deserialize_message(dds[st['stamp_ns']],
                                                     PoseWithCovarianceStamped))
        assert st['sigma_horizontal_m'] == pytest.approx(np.sqrt(cov[0, 0] + cov[1, 1]))
    assert stats[-1]['fix_rate_hz'] == pytest.approx(1.0, rel=0.05)
    # 20 clients at once all received fixes.
    assert len(counts) == 20 and min(counts) >= 2, counts


def test_view_refuses_a_polar_origin_and_a_busy_port():
    with start_node('bearing_loc_ros.view_node',
                    ['-p', 'port:=0', '-p', 'geodetic_origin:=[89.9,0.0,0.0]']) as bad:
        assert bad.wait(20.0) == 1
        assert 'polar' in bad.output() and 'Traceback' not in bad.output()
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
    assert fix['properties']['stamp_ns'] == max(stamps)     # newest fix, also after a loop
    from bearing_loc_ros import bagio
    with bagio.BagReader(tmp_path / 'sim') as r:
        lo, hi = r.start_time_ns, r.end_time_ns
    assert all(lo <= t <= hi for t in c.times)       # the bag's /clock, not the wall clock
