"""fusion_node accuracy_map: an in-process FusionNode (test_fusion_node.Harness,
simulated /clock) publishes the expected-accuracy OccupancyGrid of its live stations; a late
transient-local subscriber gets it, its cells follow the documented mapping of
core.planning.occupancy_error_map, and a station going stale triggers exactly one recompute
(never one per bearing)."""
from nav_msgs.msg import OccupancyGrid
import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from bearing_loc_ros.core.planning import error_to_occupancy, GridSpec, occupancy_error_map, \
    Stations
from test_fusion_node import POSITIONS, S

pytestmark = pytest.mark.ros

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
SIGMA = 1e-3                                   # test_fusion_node.truth_bearing's σ
MAP = {'accuracy_map.size': 12000.0, 'accuracy_map.resolution': 300.0,
       'accuracy_map.center': [3000.0, 3000.0], 'accuracy_map.altitude': 800.0}


def late_map(h, count=1):
    """A new transient-local subscriber; spin until it has received ``count`` maps."""
    got = []
    sub = h.node.create_subscription(OccupancyGrid, 'accuracy_map', got.append, LATCHED)
    assert h.spin(lambda: len(got) >= count), 'no accuracy_map for a late subscriber'
    h.node.destroy_subscription(sub)
    return got[-1]


def expected(names):
    """The core map of stations ``names`` on the configured grid (default 0..100 m linear)."""
    st = Stations.from_arrays([POSITIONS[s] for s in names], SIGMA, SIGMA, names=list(names))
    grid = GridSpec(3000.0 - 6000.0, 3000.0 - 6000.0, 300.0, 40, 40, 800.0)
    return grid, occupancy_error_map(st, grid, 'crlb', 'linear', 0.0, 100.0)


def check_map(msg, names):
    grid, om = expected(names)
    assert msg.header.frame_id == 'map'
    info = msg.info
    assert (info.width, info.height) == (grid.width, grid.height)
    assert info.resolution == pytest.approx(grid.resolution)
    assert (info.origin.position.x, info.origin.position.y, info.origin.position.z) == \
        pytest.approx((grid.origin_x, grid.origin_y, grid.altitude))
    data = np.array(msg.data, dtype=np.int8)
    np.testing.assert_array_equal(data, om.data)
    # the documented default mapping: value = round(ε / 1 m) clipped to 0..100, NaN -> -1
    np.testing.assert_array_equal(data, error_to_occupancy(om.error, 0.0, 100.0).ravel())
    fin = np.isfinite(om.error.ravel())
    np.testing.assert_array_equal(data[fin], np.clip(np.rint(om.error.ravel()[fin]), 0, 100))
    assert 0 < np.count_nonzero(data < 100) and np.ptp(data[data >= 0]) > 5   # not constant
    return om


class MapLog:
    """Stands in for the node's logger: keeps the accuracy_map info lines."""

    def __init__(self, logger):
        self.logger, self.lines = logger, []

    def info(self, text, **kw):
        if text.startswith('accuracy_map:'):
            self.lines.append(text)
        return self.logger.info(text, **kw)

    def __getattr__(self, name):
        return getattr(self.logger, name)


def test_late_subscriber_gets_the_map_and_stale_station_recomputes(harness):
    h = harness(station_timeout=2.0, **MAP)
    log = MapLog(h.fusion.get_logger())
    h.fusion.get_logger = lambda: log
    for k in range(100, 103):
        h.set_clock(k * S)
        h.send_round(k * S)
    assert h.spin(lambda: h.fusion.accuracy_maps >= 1)
    msg = late_map(h)
    om3 = check_map(msg, ['s1', 's2', 's3'])
    # three rounds of bearings, ticks at 10 Hz: still one map (never per bearing)
    assert h.fusion.accuracy_maps == 1
    # s3 goes silent -> stale -> exactly one recompute with s1, s2
    for k in range(103, 107):
        h.set_clock(k * S)
        h.send_round(k * S, stations=('s1', 's2'), wait_fix=False)
    assert h.spin(lambda: h.fusion.core.station_state('s3') == 'stale')
    assert h.spin(lambda: h.fusion.accuracy_maps == 2)
    msg = late_map(h)
    om2 = check_map(msg, ['s1', 's2'])
    assert np.nanmean(om2.error[np.isfinite(om2.error)]) > \
        np.nanmean(om3.error[np.isfinite(om3.error)])   # coverage got worse
    # each new station set is logged at once, within the 10 s of the previous line
    sets = [line.split(' (')[1].split(')')[0] for line in log.lines]
    assert sets == ['s1, s2, s3', 's1, s2']
    for k in range(107, 109):                        # same two stations: no recompute
        h.set_clock(k * S)
        h.send_round(k * S, stations=('s1', 's2'), wait_fix=False)
    h.spin(lambda: False, timeout=0.3)
    assert h.fusion.accuracy_maps == 2
    d = h.diag(lambda d: {kv.key: kv.value for kv in d['fusion'].values}
               .get('accuracy_maps') == '2')
    values = {kv.key: kv.value for kv in d['fusion'].values}
    assert float(values['accuracy_map_ms']) > 0.0 and values['mode'] == 'multistation'


def test_auto_grid_and_disabled_map(harness):
    h = harness()                                   # automatic centre, size and resolution
    h.set_clock(100 * S)
    h.send_round(100 * S)
    h.set_clock(100 * S + S // 2)                   # the map comes with the next tick
    msg = late_map(h)
    pos = np.array([POSITIONS[s] for s in ('s1', 's2', 's3')])
    c = pos[:, :2].mean(axis=0)
    side = 3.0 * np.max(np.hypot(*(pos[:, :2] - c).T))
    assert (msg.info.width, msg.info.height) == (100, 100)
    assert msg.info.resolution == pytest.approx(side / 100, rel=1e-6)
    assert msg.info.origin.position.x == pytest.approx(c[0] - side / 2)
    assert msg.info.origin.position.z == 0.0
    off = harness(**{'accuracy_map.enabled': False})
    assert off.fusion.map_pub is None and off.fusion.accuracy_map is None
