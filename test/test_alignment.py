"""Time alignment without ROS: buffers, nearest/interpolated alignment, arrival rules, clocks.

Covers core/alignment.py and the alignment behaviour of core/fusion.FusionCore (late,
duplicate and out-of-order bearings, stale stations, time going backwards, triggers).
"""
import math

from hypothesis import given, settings, strategies as st
import numpy as np
import pytest

from bearing_loc_ros.core.alignment import (
    AlignmentConfig, DUPLICATE, INTERPOLATED, NEAREST, OUT_OF_ORDER, StationBuffer, align,
    interpolate_bearing)
from bearing_loc_ros.core.bearings import Bearing
from bearing_loc_ros.core.conventions import azimuth_elevation, wrap_angle
from bearing_loc_ros.core.fusion import FusionConfig, FusionCore, replay

S = 1_000_000_000
MS = 1_000_000


def brg(t_ns, az=0.3, station='s1', el=0.1, pos=(0.0, 0.0, 0.0), s_az=0.01, s_el=0.01):
    return Bearing(station=station, stamp_ns=int(t_ns), position=np.array(pos, dtype=float),
                   azimuth=az, elevation=el, sigma_azimuth=s_az,
                   sigma_elevation=s_el if np.isfinite(el) else float('nan'))


def filled(stamps, **kw):
    buf = StationBuffer('s1', size=50, age_ns=100 * S)
    for t in stamps:
        buf.push(brg(t, **kw))
    return buf


# ---------------------------------------------------------------- StationBuffer
def test_nearest_within_tolerance_and_ties_go_to_the_earlier():
    buf = filled([1 * S, 2 * S, 3 * S])
    assert buf.nearest(2 * S + 40 * MS, 50 * MS).stamp_ns == 2 * S
    assert buf.nearest(2 * S + 60 * MS, 50 * MS) is None
    # Exactly between two bearings 1 s apart with a 0.5 s tolerance: the earlier one.
    assert buf.nearest(2 * S + 500 * MS, 500 * MS).stamp_ns == 2 * S
    # after_ns excludes bearings already used.
    assert buf.nearest(2 * S, 50 * MS, after_ns=2 * S) is None
    assert buf.nearest(2 * S + 500 * MS, 500 * MS, after_ns=2 * S).stamp_ns == 3 * S


def test_duplicate_and_out_of_order_are_classified_and_refused():
    buf = filled([1 * S, 2 * S])
    assert buf.classify(2 * S) == DUPLICATE
    assert buf.classify(1 * S) == DUPLICATE
    assert buf.classify(1 * S + 1) == OUT_OF_ORDER
    assert buf.classify(2 * S + 1) is None
    with pytest.raises(ValueError, match='stamp_ns'):
        buf.push(brg(1 * S + 1))
    assert len(buf) == 2


def test_buffer_is_bounded_in_size_and_age():
    buf = StationBuffer('s1', size=3, age_ns=10 * S)
    evicted = sum(buf.push(brg(k * S)) for k in range(1, 6))
    assert evicted == 2 and [b.stamp_ns for b in buf.bearings] == [3 * S, 4 * S, 5 * S]
    assert buf.prune(14 * S + 1) == 2          # stamps < 4 s + 1 ns are older than 10 s
    assert [b.stamp_ns for b in buf.bearings] == [5 * S]


# ---------------------------------------------------------------- interpolation
def test_interpolation_is_linear_in_angle_position_and_sigma():
    b0 = brg(0, az=0.2, el=0.1, pos=(0, 0, 0), s_az=0.01, s_el=0.02)
    b1 = brg(4 * S, az=0.6, el=0.3, pos=(4, 8, 0), s_az=0.03, s_el=0.04)
    b = interpolate_bearing(b0, b1, 1 * S)
    assert b.stamp_ns == 1 * S and b.station == 's1'
    assert b.azimuth == pytest.approx(0.3)
    assert b.elevation == pytest.approx(0.15)
    np.testing.assert_allclose(b.position, [1, 2, 0])
    assert b.sigma_azimuth == pytest.approx(0.015)
    assert b.sigma_elevation == pytest.approx(0.025)


def test_interpolation_goes_the_short_way_across_the_wrap():
    # 3.1 rad to -3.1 rad is a 0.083 rad step through +-pi, not a 6.2 rad sweep through 0.
    b0, b1 = brg(0, az=3.1), brg(2 * S, az=-3.1)
    mid = interpolate_bearing(b0, b1, 1 * S)
    assert abs(abs(mid.azimuth) - math.pi) < 1e-12
    quarter = interpolate_bearing(b0, b1, S // 2)
    assert quarter.azimuth == pytest.approx(3.1 + 0.25 * (2 * math.pi - 6.2))
    back = interpolate_bearing(b1, brg(4 * S, az=3.1), 3 * S)
    assert abs(abs(back.azimuth) - math.pi) < 1e-12


@settings(max_examples=200, deadline=None)
@given(st.floats(-math.pi, math.pi), st.floats(-3.0, 3.0), st.floats(0.0, 1.0))
def test_interpolated_azimuth_lies_on_the_shorter_arc(a0, step, frac):
    b0, b1 = brg(0, az=a0), brg(1000, az=float(wrap_angle(a0 + step)))
    b = interpolate_bearing(b0, b1, int(round(frac * 1000)))
    f = round(frac * 1000) / 1000
    assert abs(wrap_angle(b.azimuth - (a0 + f * step))) < 1e-9
    assert -math.pi < b.azimuth <= math.pi


def test_mixed_1d_2d_pair_interpolates_azimuth_only():
    b = interpolate_bearing(brg(0, el=0.1), brg(2 * S, el=float('nan')), 1 * S)
    assert math.isnan(b.elevation) and math.isnan(b.sigma_elevation)
    with pytest.raises(ValueError, match='station'):
        interpolate_bearing(brg(0), brg(1, station='s2'), 0)
    with pytest.raises(ValueError, match='t0 < t1'):
        interpolate_bearing(brg(5), brg(5), 5)


def test_interpolation_tracks_a_moving_target_within_the_curvature_bound():
    # Target at constant velocity past a station; bearings every 0.5 s. Linear interpolation
    # error at the midpoint is at most gap²/8 · max|θ''| (the remainder of linear
    # interpolation); check it against that bound, and that nearest alignment is worse.
    station = np.zeros(3)
    v = np.array([-150.0, -1000.0, 0.0])
    x0 = np.array([3000.0, 4000.0, 2000.0])

    def true_angles(t):
        return azimuth_elevation(x0 + v * t - station)

    buf = StationBuffer('s1', size=50, age_ns=100 * S)
    for k in range(9):
        az, el = true_angles(0.5 * k)
        buf.push(brg(k * S // 2, az=float(az), el=float(el), s_az=1e-3, s_el=1e-3))
    cfg = AlignmentConfig(sync_tolerance_ns=300 * MS, interpolation=True,
                          max_interpolation_gap_ns=S)
    ts = np.linspace(0.0, 4.0, 4001)
    az_all = np.unwrap(true_angles(ts[:, None])[0])
    curv = np.max(np.abs(np.gradient(np.gradient(az_all, ts), ts)))
    bound = 0.5 ** 2 / 8 * curv * 1.05 + 1e-9
    for t in (0.25, 1.75, 3.25):
        b, how = align(buf, int(t * S), cfg)
        assert how == INTERPOLATED
        err = abs(wrap_angle(b.azimuth - true_angles(t)[0]))
        assert err <= bound
        nb, nhow = align(buf, int(t * S), cfg.replace(interpolation=False))
        assert nhow == NEAREST and abs(wrap_angle(nb.azimuth - true_angles(t)[0])) > err


def test_align_falls_back_to_nearest_outside_a_bracket_or_beyond_the_gap():
    buf = filled([1 * S, 3 * S])
    cfg = AlignmentConfig(sync_tolerance_ns=100 * MS, interpolation=True,
                          max_interpolation_gap_ns=1 * S)
    assert align(buf, 2 * S, cfg) == (None, None)            # gap 2 s > 1 s, none near
    b, how = align(buf, 3 * S + 50 * MS, cfg)                # newest edge: not bracketed
    assert how == NEAREST and b.stamp_ns == 3 * S
    b, how = align(buf, 3 * S, cfg)                          # exact stamp: that bearing
    assert how == NEAREST and b.stamp_ns == 3 * S
    b, how = align(buf, 2 * S, cfg.replace(max_interpolation_gap_ns=2 * S))
    assert how == INTERPOLATED and b.stamp_ns == 2 * S


def test_alignment_config_validation_names_the_field():
    with pytest.raises(ValueError, match='buffer_size'):
        AlignmentConfig(buffer_size=1).validate()
    with pytest.raises(ValueError, match='sync_tolerance'):
        AlignmentConfig(sync_tolerance_ns=-1).validate()


# ---------------------------------------------------------------- FusionCore alignment
STATIONS = {'s1': (0.0, 0.0, 0.0), 's2': (1000.0, 0.0, 0.0), 's3': (0.0, 1000.0, 10.0)}
TARGET = np.array([600.0, 700.0, 300.0])


def truth_bearing(station, t_ns, target=TARGET, sigma=1e-3):
    pos = np.array(STATIONS[station])
    az, el = azimuth_elevation(np.asarray(target) - pos)
    return Bearing(station=station, stamp_ns=int(t_ns), position=pos, azimuth=float(az),
                   elevation=float(el), sigma_azimuth=sigma, sigma_elevation=sigma)


def core(**kw):
    kw.setdefault('estimator', 'ls')
    return FusionCore(FusionConfig(**kw), stations=list(STATIONS))


def feed_round(c, t_ns, now_ns=None, stations=STATIONS):
    out = []
    for s in stations:
        out += c.add_bearing(truth_bearing(s, t_ns), now_ns if now_ns is not None else t_ns)
    return out


def test_event_trigger_fires_when_every_live_station_reported():
    c = core(trigger='event', station_timeout=2.0)
    # s2 and s3 have not reported yet but are waited for (added < station_timeout ago).
    assert c.add_bearing(truth_bearing('s1', 10 * S), 10 * S) == []
    assert c.add_bearing(truth_bearing('s2', 10 * S), 10 * S) == []
    eps = c.add_bearing(truth_bearing('s3', 10 * S), 10 * S)
    assert len(eps) == 1 and eps[0].ok and eps[0].stamp_ns == 10 * S
    np.testing.assert_allclose(eps[0].position, TARGET, atol=1e-6)
    assert sorted(eps[0].stations) == ['s1', 's2', 's3']
    eps = feed_round(c, 11 * S)
    assert len(eps) == 1 and eps[0].ok and eps[0].stamp_ns == 11 * S


def test_event_trigger_waits_for_a_silent_station_at_most_max_latency():
    c = core(trigger='event', station_timeout=2.0, max_latency=0.2)
    eps = feed_round(c, 10 * S, stations=['s1', 's2'])
    assert eps == [] and c.tick(10 * S + 100 * MS) == []
    eps = c.tick(10 * S + 200 * MS)   # s3 never reported: not waited for beyond max_latency
    assert len(eps) == 1 and eps[0].ok and sorted(eps[0].stations) == ['s1', 's2']
    assert eps[0].stamp_ns == 10 * S
    # The next cycle starting (s1 reports again) closes a pending epoch at once.
    eps = feed_round(c, 11 * S, stations=['s1', 's2']) + feed_round(c, 12 * S, stations=['s1'])
    assert [(e.stamp_ns, sorted(e.stations)) for e in eps] == [(11 * S, ['s1', 's2'])]


@pytest.mark.parametrize('offset_ms', [300, -300])
def test_a_station_clock_off_by_more_than_sync_tolerance_is_named_and_leaves_others_fused(
        offset_ms):
    # Four stations at 10 Hz, one whose clock runs 0.3 s ahead of (or behind) the others.
    # Ahead: its buffered future-stamped bearings used to count as "a station reports
    # again", which closed every epoch before the fourth station's bearing of that cycle
    # arrived (that station was fused in 1 of 200 epochs). Either way the station is named
    # in /diagnostics with its offset from the other stations'.
    stations = dict(STATIONS, s4=(1000.0, 1000.0, 5.0))
    c = FusionCore(FusionConfig(estimator='ls', trigger='event'), stations=list(stations))
    eps = []
    for k in range(1, 101):
        now = 1000 * S + k * 100 * MS
        eps += c.tick(now)
        for s, pos in stations.items():
            az, el = azimuth_elevation(TARGET - np.array(pos))
            stamp = now + (offset_ms * MS if s == 's3' else 0)
            eps += c.add_bearing(Bearing(s, stamp, np.array(pos), float(az), float(el),
                                         1e-3, 1e-3), now + MS)
    honest = [e for e in eps[-50:] if e.ok]
    assert honest and all({'s1', 's2', 's4'} <= set(e.stations) for e in honest)
    entries = {e.name: e for e in c.diagnostics(now)}
    s3 = entries['station s3']
    side = 'ahead of' if offset_ms > 0 else 'behind'
    assert s3.level == 'warn' and f"0.3 s {side} the other stations'" in s3.message
    assert all(entries[f'station {s}'].level == 'ok' for s in ('s1', 's2', 's4'))


def test_no_clock_warning_for_two_stations_or_a_mere_transport_delay():
    # Of two stations the data cannot say which clock is off (both were blamed, each for
    # half the offset); a station whose bearings arrive 80 ms later than the others', with
    # right stamps, is a delay the event trigger waits for (max_latency 0.2 s), not a clock.
    for delays in ({'s1': 0.0, 's2': 0.12}, {'s1': 0.01, 's2': 0.01, 's3': 0.09}):
        c = FusionCore(FusionConfig(estimator='ls'), stations=list(delays))
        for k in range(1, 21):
            t = 1000 * S + k * 100 * MS
            for s, d in delays.items():
                pos = STATIONS[s]
                az, el = azimuth_elevation(TARGET - np.array(pos))
                c.add_bearing(Bearing(s, t, np.array(pos), float(az), float(el), 1e-3, 1e-3),
                              t + int(d * S))
        entries = c.diagnostics(t + 200 * MS)
        assert not any('other stations' in e.message for e in entries)


def test_late_duplicate_and_out_of_order_bearings_are_dropped_and_counted():
    c = FusionCore(FusionConfig(estimator='ls', trigger='event'), stations=['s1', 's2'])
    feed_round(c, 10 * S, stations=['s1', 's2'])
    feed_round(c, 11 * S, stations=['s1', 's2'])
    assert c.add_bearing(truth_bearing('s1', 11 * S), 11 * S) == []          # duplicate
    c.add_bearing(truth_bearing('s2', 12 * S), 12 * S)
    c.add_bearing(truth_bearing('s2', 11 * S + 500 * MS), 12 * S)             # out of order
    # s3 joins with a bearing older than the last epoch (11 s) - sync_tolerance: too late.
    c.add_bearing(truth_bearing('s3', 10 * S + 500 * MS), 12 * S)
    st = c.station_stats
    assert st('s1').dropped['duplicate'] == 1
    assert st('s2').dropped['out_of_order'] == 1
    assert st('s3').dropped['too_late'] == 1
    assert dict(c.dropped) == {'duplicate': 1, 'out_of_order': 1, 'too_late': 1}
    values = c.diagnostics(12 * S)[0].values
    assert values['dropped.too_late'] == 1 and values['dropped.duplicate'] == 1
    # A bearing older than the buffer age is too late even before any epoch.
    c2 = core(buffer_age=5.0)
    c2.add_bearing(truth_bearing('s1', 1 * S), 10 * S)
    assert c2.station_stats('s1').dropped['too_late'] == 1


def test_stale_station_is_left_out_reported_and_comes_back():
    c = core(trigger='event', station_timeout=1.5)
    for k in range(10, 13):
        feed_round(c, k * S)
    # s3 stops; after 1.5 s without a bearing it is stale and the others fix on their own.
    eps = []
    for k in range(13, 16):
        eps += feed_round(c, k * S, stations=['s1', 's2'])
        eps += c.tick(k * S + 100 * MS)
    assert c.station_state('s3') == 'stale'
    ok = [e for e in eps if e.ok]
    assert ok and all(sorted(e.stations) == ['s1', 's2'] for e in ok)
    assert 's3' in ok[-1].stale
    assert any('s3 stale' in text for _, text in c.drain_events())
    diag = {d.name: d for d in c.diagnostics(16 * S)}
    assert diag['station s3'].values['state'] == 'stale' and diag['station s3'].level == 'warn'
    eps = feed_round(c, 16 * S)     # s1, s2 complete epoch 16 s before s3 is alive again
    assert c.station_state('s3') == 'alive'
    assert [sorted(e.stations) for e in eps] == [['s1', 's2']]
    eps = feed_round(c, 17 * S)
    assert len(eps) == 1 and sorted(eps[0].stations) == ['s1', 's2', 's3']
    assert any('s3 alive again' in text for _, text in c.drain_events())


def test_timer_trigger_processes_grid_epochs_after_max_latency():
    c = core(trigger='timer', rate=10.0, max_latency=0.2, sync_tolerance=0.05)
    for s in STATIONS:   # bearings 20 ms off the 0.1 s grid
        c.add_bearing(truth_bearing(s, 10 * S + 20 * MS), 10 * S + 30 * MS)
    eps = c.tick(10 * S + 150 * MS)             # only 9.9 s is due (10.0 needs now >= 10.2)
    assert [e.stamp_ns for e in eps] == [9 * S + 900 * MS]
    assert eps[0].reason == 'too_few_stations' and sorted(eps[0].missing) == list(STATIONS)
    eps = c.tick(10 * S + 210 * MS)
    assert [e.stamp_ns for e in eps] == [10 * S]
    assert eps[0].ok and len(eps[0].bearings) == 3
    # Missed ticks are backfilled on the grid; the used bearings are not used again.
    eps = c.tick(10 * S + 520 * MS)
    assert [e.stamp_ns for e in eps] == [10 * S + k * 100 * MS for k in (1, 2, 3)]
    assert all(e.reason == 'too_few_stations' and not e.bearings for e in eps)


def test_timer_with_interpolation_aligns_staggered_stations():
    c = core(trigger='timer', rate=10.0, max_latency=0.5, interpolation=True,
             max_interpolation_gap=1.0, sync_tolerance=0.0)
    offsets = {'s1': 0, 's2': 130 * MS, 's3': 270 * MS}
    items = sorted((10 * S + k * 400 * MS + off, truth_bearing(s, 10 * S + k * 400 * MS + off))
                   for k in range(3) for s, off in offsets.items())
    eps = list(replay(c, items + [(11 * S + 600 * MS, None)]))
    # s1 at 10.0/10.4/10.8, s2 at 10.13/10.53/10.93, s3 at 10.27/10.67/11.07 s: all three are
    # bracketed for t in [10.27, 10.8] s (grid 10.3 ... 10.8), two of them at 10.2 and 10.9.
    three = [e.stamp_ns for e in eps if e.ok and len(e.bearings) == 3]
    assert three == [10 * S + k * 100 * MS for k in range(3, 9)]
    two = [e.stamp_ns for e in eps if e.ok and len(e.bearings) == 2]
    assert two == [10 * S + 200 * MS, 10 * S + 900 * MS]
    for e in eps:
        if e.ok:
            np.testing.assert_allclose(e.position, TARGET, atol=1e-6)
    at_10_8 = [e for e in eps if e.stamp_ns == 10 * S + 800 * MS]
    assert at_10_8[0].how == {'s1': 'nearest', 's2': 'interpolated', 's3': 'interpolated'}


def test_time_going_backwards_clears_buffers_and_is_reported():
    c = core(trigger='event')
    feed_round(c, 100 * S)
    feed_round(c, 101 * S)
    c.drain_events()
    assert c.tick(5 * S) == []                   # a bag looped: now jumps back 96 s
    assert c.time_jumps == 1
    assert all(c.station_state(s) == 'waiting' for s in STATIONS)
    events = c.drain_events()
    assert any(level == 'warn' and 'time jumped back' in text for level, text in events)
    eps = feed_round(c, 6 * S)                   # fresh data after the jump fixes again
    assert eps[-1].ok and eps[-1].stamp_ns == 6 * S
    # A backward step within time_jump_tolerance is not a jump.
    c.tick(6 * S - 50 * MS)
    assert c.time_jumps == 1


def test_nearest_mode_uses_each_bearing_once():
    c = core(trigger='timer', rate=10.0, max_latency=0.0, sync_tolerance=0.05)
    for s in STATIONS:
        c.add_bearing(truth_bearing(s, 10 * S + 50 * MS), 10 * S)
    first = c.tick(10 * S)              # 10.0 and 10.1 are both 50 ms from the bearings
    second = c.tick(10 * S + 100 * MS)
    assert [e.ok for e in first + second] == [True, False]
    assert second[0].reason == 'too_few_stations'
