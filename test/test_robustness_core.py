"""Robustness of the numerical core: extreme but valid inputs return a status (never NaN
reported as converged, never an exception other than a ValueError naming the field), and
the fusion core counts malformed bearings instead of raising."""
import math
import re

import numpy as np
import pytest

from bearing_loc_ros.core import estimators as est
from bearing_loc_ros.core import tma as tma_core
from bearing_loc_ros.core.bearings import Bearing, BearingSet, simulate_bearings
from bearing_loc_ros.core.conventions import azimuth_elevation
from bearing_loc_ros.core.fusion import FusionConfig, FusionCore, TmaFusionCore

S = 1_000_000_000
STATIONS = np.array([[0.0, 0.0, 0.0], [10000.0, 0.0, 0.0], [0.0, 10000.0, 0.0]])
TARGET = np.array([3000.0, 4000.0, 2000.0])
METHODS = sorted(est.ESTIMATORS)


def assert_honest(res):
    """A converged fix is finite; a NaN position only with status degenerate_geometry."""
    finite = np.all(np.isfinite(res.position), axis=1)
    assert not np.any(res.converged & ~finite)
    assert np.all(finite | (res.status == est.STATUS_DEGENERATE))
    assert set(res.status) <= set(est.STATUSES)


def extreme_sets():
    rng = np.random.default_rng(0)
    return {
        'far_1e7': simulate_bearings([1e7, 1e7, 5000.0], STATIONS, 0.002, rng=rng),
        'far_1e7_exact': simulate_bearings([1e7, 1e7, 5000.0], STATIONS, 0.002),
        'colocated': simulate_bearings(TARGET, np.tile([1234.5, 5678.9, 90.0], (3, 1)), 0.002,
                                       rng=rng),
        'sigma_1e-9': simulate_bearings(TARGET, STATIONS, 1e-9, rng=rng),
        'sigma_0.5': simulate_bearings(TARGET, STATIONS, 0.5, rng=rng),
        'near_zenith': simulate_bearings([1.0, 1.0, 1e7], STATIONS, 0.002),
        'near_nadir': simulate_bearings([1.0, 1.0, -1e7], STATIONS, 0.002),
        'n2_one_2d': simulate_bearings(TARGET, STATIONS[:2], 0.002, has_elevation=[True, False],
                                       rng=rng),
        'on_baseline': simulate_bearings([5000.0, 0.0, 0.0], STATIONS[:2], 0.002),
        'target_on_station': simulate_bearings(STATIONS[0] + 1e-9, STATIONS, 0.002),
    }


@pytest.mark.parametrize('name', sorted(extreme_sets()))
@pytest.mark.parametrize('method', METHODS)
def test_extreme_geometry_returns_a_status(name, method):
    res = est.locate(method, extreme_sets()[name])
    assert_honest(res)


@pytest.mark.parametrize('method', ['ls', 'tls'])
def test_colocated_stations_are_degenerate_not_a_confident_fix(method):
    # Bug: every ray starts at one point, the pseudo-linear solution is that point with a
    # ~1e-13 m² covariance and status ok. It must be degenerate_geometry.
    bs = simulate_bearings(TARGET, np.tile([1234.5, 5678.9, 90.0], (3, 1)), 0.002,
                           rng=np.random.default_rng(0))
    res = est.locate(method, bs)
    assert res.status[0] == est.STATUS_DEGENERATE and not res.converged[0]
    assert np.all(np.isnan(res.position[0]))


def test_empty_batch_returns_empty_results():
    bs = simulate_bearings(TARGET, STATIONS, 0.002)
    empty = BearingSet(bs.positions[:0], bs.azimuth[:0], bs.elevation[:0], bs.sigma_az[:0],
                       bs.sigma_el[:0])
    for method in METHODS:
        res = est.locate(method, empty)
        assert res.position.shape == (0, 3) and res.status.shape == (0,)
    t = np.zeros((0, 4))
    for method in sorted(tma_core.TMA_FUNCTIONS):
        assert tma_core.tma(method, empty.subset(np.arange(3)), t[:, :3], 100.0).M == 0


@pytest.mark.parametrize('sigma', [1e-300, 1e-13, 1e4, 1e300])
def test_sigma_outside_the_numeric_range_is_a_named_error(sigma):
    # Bug: sigma 1e-300 overflowed 1/sigma^2 (TMA: "Eigenvalues did not converge" with
    # RuntimeWarnings; mle: overflow warnings, diverged).
    with pytest.raises(ValueError, match='sigma_azimuth'):
        simulate_bearings(TARGET, STATIONS, sigma)
    b = Bearing('s1', 0, STATIONS[0], 0.1, 0.1, sigma, 0.01)
    with pytest.raises(ValueError, match='sigma_azimuth'):
        b.validate()


def test_tma_extremes_return_a_status():
    t = np.arange(20) * 5.0
    obs = np.stack([np.zeros(20), 100.0 * t, np.zeros(20)], 1)
    cases = [([1e7, 1e7, 3000.0], obs, t, 1e-3), ([2e4, 2e4, 3000.0], obs, t, 1e-12),
             ([2e4, 2e4, 3000.0], obs, t, 0.5), ([2e4, 2e4, 3000.0], obs[:2], t[:2], 1e-3),
             ([2e4, 2e4, 3000.0], obs, np.zeros(20), 1e-3),
             ([2e4, 2e4, 3000.0], np.zeros((20, 3)), t, 1e-3)]
    for p0, o, tt, sig in cases:
        bs, times = tma_core.simulate_tma(tt, p0, [200.0, 0.0, 0.0], o, sig,
                                          rng=np.random.default_rng(1))
        for method in sorted(tma_core.TMA_FUNCTIONS):
            res = tma_core.tma(method, bs, times, 200.0, speed_reference='ground')
            d = res.single(0)
            assert not (d['converged'] and not np.all(np.isfinite(d['position'])))


# ------------------------------------------------------------------------------ fusion core

def good_bearing(station, stamp):
    p = STATIONS[int(station[1:]) - 1]
    az, el = azimuth_elevation(TARGET - p)
    return Bearing(station, stamp, p.copy(), float(az), float(el), 0.002, 0.002)


BAD_FIELDS = [('azimuth', math.nan), ('elevation', math.inf), ('elevation', 2.0),
              ('sigma_azimuth', -1.0), ('sigma_azimuth', math.nan), ('sigma_elevation', -0.1),
              ('position', None), ('position', 'abc'), ('position', np.zeros(2)),
              ('azimuth', None), ('azimuth', 'x'), ('stamp_ns', math.nan),
              ('stamp_ns', None), ('stamp_ns', 'x'), ('stamp_ns', 1.5), ('stamp_ns', 10 ** 30),
              ('station', None), ('station', ''), ('position_covariance', None),
              ('position_covariance', -np.eye(3)), ('position_covariance', np.full((3, 3),
                                                                                   np.nan))]


@pytest.mark.parametrize('core_cls,extra', [(FusionCore, {'estimator': 'mle'}),
                                            (TmaFusionCore, {'estimator': 'tma_ctls',
                                                             'target_speed': 100.0})])
@pytest.mark.parametrize('trigger', ['event', 'timer'])
def test_fusion_core_counts_malformed_bearings_and_keeps_fixing(core_cls, extra, trigger):
    # Bugs: position None -> IndexError, stamp NaN/None/'x' -> int() error, station None
    # registered as a station, position_covariance None -> crash in the epoch (timer mode).
    core = core_cls(FusionConfig(trigger=trigger, **extra), stations=['s1', 's2', 's3'])
    now = 100 * S
    for field_name, value in BAD_FIELDS:
        now += S // 10
        for st in ('s1', 's2', 's3'):
            core.add_bearing(good_bearing(st, now - S // 100), now)
        b = good_bearing('s1', now)
        setattr(b, field_name, value)
        assert core.add_bearing(b, now) == []
        core.tick(now)
    # Two bearings have no usable station id: counted globally, not under a station.
    assert core.station_stats('s1').bad['invalid_bearing'] == len(BAD_FIELDS) - 2
    assert set(core.stations) == {'s1', 's2', 's3'}
    if core_cls is FusionCore:
        assert core.bad_messages == len(BAD_FIELDS)
        assert core.fixes > 0
    core.diagnostics(now)


def test_fusion_core_far_future_stamp_does_not_block_its_station():
    # Bug: one bearing stamped 1e6 s ahead was buffered, so every later bearing of that
    # station was dropped as out_of_order (forever, no time jump ever cleared it).
    core = FusionCore(FusionConfig(estimator='mle'), stations=['s1', 's2', 's3'])
    now = 100 * S
    assert core.add_bearing(good_bearing('s1', now + 10 ** 6 * S), now) == []
    assert core.dropped['from_future'] == 1
    for _ in range(10):
        now += S // 10
        for st in ('s1', 's2', 's3'):
            core.add_bearing(good_bearing(st, now - S // 100), now)
    assert core.station_stats('s1').accepted == 10
    assert core.dropped['out_of_order'] == 0
    diag = {d.name: d.values for d in core.diagnostics(now)}
    assert diag['fusion']['dropped.from_future'] == 1


def test_before_ros_time_starts_one_stations_future_stamps_do_not_become_now():
    """Simulated time before the first /clock: the node has no clock and the bearing's own
    stamp stood in. One station stamping a day ahead made every honest bearing after it a
    clock jump back: every buffer cleared, every cycle, and no from_future counted."""
    core = FusionCore(FusionConfig(estimator='mle'), stations=['s1', 's2', 's3'])
    t, day = 100 * S, 86400 * S
    fixes = 0
    for k in range(20):
        t += S // 5
        for st in ('s1', 's2', 's3'):
            fixes += len(core.add_bearing(good_bearing(st, t + (day if st == 's2' else 0)),
                                          None))
    assert core.time_jumps <= 1                     # at most the very first cycle's
    assert core.dropped['from_future'] >= 19
    assert core.station_stats('s1').accepted == core.station_stats('s3').accepted == 20
    # a station that falls silent does not hold "now" back for the others: at most the
    # bearings until it leaves the median are dropped
    from bearing_loc_ros.core.fusion.stations import RECENT_ARRIVALS_PER_STATION
    for st_silent in (['s2'], ['s2', 's3']):
        core = FusionCore(FusionConfig(estimator='mle'), stations=['s1', 's2', 's3'])
        t = 100 * S
        for k in range(50):
            t += S // 5
            for st in ('s1', 's2', 's3'):
                if k < 5 or st not in st_silent:
                    core.add_bearing(good_bearing(st, t), None)
        s1 = core.station_stats('s1')
        assert s1.accepted >= 50 - 3 * RECENT_ARRIVALS_PER_STATION, core.dropped
        assert s1.last_stamp_ns == t                     # and the last ones are accepted
    # alone, a station's stamp is the clock, as before
    one = FusionCore(FusionConfig(estimator='mle'), stations=['s1'])
    assert one.registry.stand_in_now(good_bearing('s1', 5 * day)) == 5 * day


def test_a_station_whose_position_teleports_is_dropped_not_fused():
    """A station reporting its real position and one 100 km away on alternate bearings (its
    bearings always from the real place): the far ones made confidently wrong ok fixes
    63 km off with three stations, and the gate blamed an honest station."""
    core = FusionCore(FusionConfig(estimator='mle'), stations=['s1', 's2', 's3'])
    t = 100 * S
    errors = []
    for k in range(40):
        t += S // 5
        for st in ('s1', 's2', 's3'):
            b = good_bearing(st, t)
            if st == 's2' and k % 2:
                b.position = b.position + np.array([100_000.0, 0.0, 0.0])
            for ep in core.add_bearing(b, t):
                if ep.ok:
                    errors.append(np.linalg.norm(ep.position - TARGET))
    assert core.station_stats('s2').dropped['implausible_position'] == 20
    assert len(errors) >= 38 and max(errors) < 100.0
    events = ' '.join(text for _, text in core.drain_events())
    assert 's2: position moved 100000 m in 0.2 s, faster than max_station_speed 1000' in events
    # a station that really moved stays at its new place: taken as relocated
    for k in range(5):
        t += S // 5
        b = good_bearing('s2', t)
        b.position = b.position + np.array([5000.0, 0.0, 0.0])
        core.add_bearing(b, t)
    assert core.station_stats('s2').dropped['implausible_position'] == 22
    assert 'taken as a relocated station' in ' '.join(x for _, x in core.drain_events())
    # 0 turns the check off
    off = FusionCore(FusionConfig(estimator='mle', max_station_speed=0.0), stations=['s1'])
    for k in range(2):
        b = good_bearing('s1', (k + 1) * S)
        b.position = b.position + k * np.array([1e6, 0.0, 0.0])
        off.add_bearing(b, (k + 1) * S)
    assert off.station_stats('s1').dropped['implausible_position'] == 0


def test_diagnostics_print_stamps_exactly():
    """A stamp of exactly ...163.604 s printed as ...163.604000092 (float seconds)."""
    core = FusionCore(FusionConfig(estimator='mle'), stations=['s1', 's2', 's3'])
    t = 1_796_534_163_604_000_000
    for st in ('s1', 's2', 's3'):
        core.add_bearing(good_bearing(st, t), t)
    diag = {d.hardware_id or d.name: d.values for d in core.diagnostics(t)}
    assert diag['s1']['last_stamp'] == '1796534163.604000000'
    assert diag['fusion']['last_fix_stamp'] == '1796534163.604000000'


def test_fusion_core_clock_going_back_repeatedly_is_counted():
    core = FusionCore(FusionConfig(estimator='mle', trigger='timer'), stations=['s1', 's2'])
    now = 1000 * S
    for k in range(10):
        now -= 5 * S
        core.tick(now)
        core.add_bearing(good_bearing('s1', now), now)
    assert core.time_jumps == 9          # the first tick sets the clock
    for stamp in (-5 * S, 2 ** 62):
        assert core.add_bearing(good_bearing('s2', stamp), now) == []
    assert core.dropped['too_late'] == 1 and core.dropped['from_future'] == 1
    core.tick(2 ** 62)
    core.diagnostics(2 ** 62)


@pytest.mark.parametrize('field, value, message', [
    ('azimuth', 1e300, 'azimuth: |azimuth| must be <= 10000 rad'),
    ('azimuth', -2e4, 'azimuth: |azimuth| must be <= 10000 rad'),
    ('position', 1e300, 'position: |coordinate| must be <= 1e+12 m'),
    ('azimuth', float('nan'), 'azimuth: non-finite value'),
])
def test_huge_or_nan_angles_and_positions_are_named_errors(field, value, message):
    """An azimuth beyond 1e4 rad keeps no direction after wrapping, and a coordinate beyond
    1e12 m overflows the estimators' sums: both are named errors, never a fix (one problem
    takes the fast validation path, two problems the vectorised one)."""
    for M in (1, 2):
        pos = np.tile(np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0], [0.0, 1000.0, 5.0]]),
                      (M, 1, 1))
        az = np.tile(np.array([0.8, 2.3, -0.8]), (M, 1))
        el = np.tile(np.array([0.01, 0.01, np.nan]), (M, 1))
        if field == 'azimuth':
            az[-1, 1] = value
        else:
            pos[-1, 2, 0] = value
        bs = BearingSet(pos, az, el, np.full((M, 3), 0.01), np.full((M, 3), 0.01))
        with pytest.raises(ValueError, match=re.escape(message)):
            bs.validate()
