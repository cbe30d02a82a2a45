"""Simulator core (no ROS): scenario loading, statistics, timing, determinism, trajectories.

Statistical tests use fixed seeds and bounds from the sampling distribution at the
0.1 % / 99.9 % quantiles (two-sided 0.2 % false-alarm rate per check), never fitted to a run.
"""
import copy
import math
import os

import numpy as np
import pytest
from scipy import stats
import yaml

from bearing_loc_ros.core.conventions import wrap_angle
from bearing_loc_ros.core.simulation import (bearing_topic, load_scenario, observation_times_ns,
                                             parse_scenario, realize_targets, simulate,
                                             station_position, target_position, Trajectory,
                                             truth_topic)

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCEN = os.path.join(REPO, 'config', 'scenarios')
Q_LO, Q_HI = 0.001, 0.999


def chi2_ok(z):
    """Sum of squares of n N(0, 1) samples inside the χ²_n 0.1 %..99.9 % quantiles."""
    z = np.asarray(z, dtype=float).ravel()
    s = float(np.sum(z * z))
    return stats.chi2.ppf(Q_LO, z.size) < s < stats.chi2.ppf(Q_HI, z.size), s, z.size


def binom_ok(count, n, p):
    """``count`` successes of n Bernoulli(p) trials inside the 0.1 %..99.9 % quantiles."""
    return stats.binom.ppf(Q_LO, n, p) <= count <= stats.binom.ppf(Q_HI, n, p)


def static_scenario(**station_overrides):
    """Two 2D stations and a 1D one watching a static target; 200 Hz for 5 s = 1000 obs each."""
    st = dict(rate=200.0, sigma_az=0.01, sigma_el=0.02)
    st.update(station_overrides)
    return parse_scenario({
        'duration': 5.0,
        'stations': [dict(st, id='a', position=[0.0, 0.0, 0.0]),
                     dict(st, id='b', position=[3000.0, 0.0, 20.0]),
                     dict(st, id='c', position=[0.0, 3000.0, 10.0], dims=1)],
        'targets': [{'position': [1200.0, 1700.0, 400.0]}],
    })


# --- shipped scenarios ----------------------------------------------------------------------

def test_seed000_scenario_is_faithful_to_section_4():
    sc = load_scenario(os.path.join(SCEN, 'seed000.yaml'))
    pos = np.array([s.trajectory.position(0.0) for s in sc.stations])
    assert np.allclose(pos, [[30e3, -10e3, 100.0], [30e3, 20e3, 200.0], [-30e3, 5e3, 150.0]])
    assert all(s.sigma_az == 0.003 and s.sigma_el == 0.003 and s.dims == 2 for s in sc.stations)
    assert all(s.rate == 0.5 for s in sc.stations) and sc.duration == 100.0
    (tg,) = sc.targets
    assert tg.namespace == '' and tg.kind == 'constant_velocity'
    # start (58.5, 27.75) km at the chosen 5 km altitude, velocity (-150, -1000, 0) m/s
    assert np.allclose(target_position(tg, [0.0, 50.0]),
                       [[58500.0, 27750.0, 5000.0], [58500.0 - 7500.0, 27750.0 - 50e3, 5000.0]])
    sim = simulate(sc, seed=0)
    # a bearing every 2 s over [0, 100 s): t = 0, 2, ..., 98 -> 50 per station
    for s in sim.streams:
        assert len(s.t) == 50 and s.t[-1] == 98.0 and np.all(s.kept)
    assert len(sim.bearings) == 150


def test_seed003_scenario_line_array_random_sources_and_sigma_growth():
    sc = load_scenario(os.path.join(SCEN, 'seed003.yaml'))
    pos = np.array([s.trajectory.position(0.0) for s in sc.stations])
    assert np.allclose(pos[:, 0], np.linspace(-3000.0, 3000.0, 6)) and np.all(pos[:, 1:] == 0)
    (tg,) = sc.targets
    assert tg.kind == 'random_static'
    pts = np.array([target_position(realize_targets(sc, seed)[0], 0.0) for seed in range(400)])
    assert np.all(pts >= [-3000.0, 1000.0, -500.0]) and np.all(pts <= [3000.0, 7000.0, 500.0])
    # uniform on each axis: the sample mean is within 3.3 standard errors of the box centre
    half = np.array([3000.0, 3000.0, 500.0])
    se = half / np.sqrt(3.0) / np.sqrt(len(pts))
    assert np.all(np.abs(pts.mean(axis=0) - [0.0, 4000.0, 0.0]) < 3.3 * se)
    # σ(d) = 0.5° · clip(d / 1000 m, ., 6): 0.5° .. 3°, as in the experiments of Zong & Cui (2015)
    sim = simulate(sc, seed=4)
    for s in sim.streams:
        expect = np.radians(0.5) * np.minimum(s.range_ / 1000.0, 6.0)
        assert np.allclose(s.sigma_az_actual, expect) and np.allclose(s.sigma_el_actual, expect)
        assert np.allclose(s.sigma_az, np.radians(0.5))          # nominal σ is reported
        assert np.all(s.sigma_az_actual <= np.radians(3.0) + 1e-15)


def test_documented_example_scenario_parses():
    # The simulator section of the manual (README or docs/nodes.md) shows one full scenario.
    texts = []
    for page in ('README.md', os.path.join('docs', 'nodes.md')):
        if os.path.exists(os.path.join(REPO, page)):
            with open(os.path.join(REPO, page), encoding='utf-8') as f:
                texts.append(f.read())
    sections = [t.split('## Simulator: bearings without hardware')[1] for t in texts
                if '## Simulator: bearings without hardware' in t]
    assert sections
    block = sections[0].split('```yaml\n')[1].split('```')[0]
    sc = parse_scenario(yaml.safe_load(block), 'simulator.md')
    assert [s.trajectory.kind for s in sc.stations] == ['constant_velocity', 'static']
    assert [t.namespace for t in sc.targets] == ['', 'drone']
    assert {e.topic for e in simulate(sc, duration=1.0, seed=0).bearings} == {
        'observer/bearing', 'hill/bearing', 'drone/observer/bearing', 'drone/hill/bearing'}


def test_static3_test_scenario_loads():
    sc = load_scenario(os.path.join(SCEN, 'static3.yaml'))
    assert [s.id for s in sc.stations] == ['station_1', 'station_2', 'station_3']
    assert sc.stations[2].dims == 1 and math.isnan(sc.stations[2].sigma_el)
    assert sc.stations[1].sigma_az == pytest.approx(math.radians(1.0))


# --- statistics -----------------------------------------------------------------------------

def test_angle_errors_match_configured_sigma_chi2():
    sim = simulate(static_scenario(), seed=11)
    for s in sim.streams:
        assert np.all(s.kept) and not np.any(s.outlier)
        z_az = wrap_angle(s.azimuth - s.azimuth_true) / s.sigma_az
        ok, val, n = chi2_ok(z_az)
        assert ok, (s.station, 'azimuth', val, n)
        # zero mean: |mean| below the 99.9 % two-sided normal bound 3.29 / sqrt(n)
        assert abs(z_az.mean()) < 3.29 / math.sqrt(n)
        if s.station == 'c':
            assert np.all(np.isnan(s.elevation)) and np.all(np.isnan(s.sigma_el))
        else:
            ok, val, n = chi2_ok((s.elevation - s.elevation_true) / s.sigma_el)
            assert ok, (s.station, 'elevation', val, n)


def test_chi2_test_detects_a_wrong_sigma():
    # the check above could fail: with n = 1000, χ²_n has sd sqrt(2n) ≈ 45, and noise 20 %
    # larger than assumed scales the sum by 1.44 (≈ +440, ten sd past the 99.9 % bound)
    sim = simulate(static_scenario(), seed=11)
    s = sim.streams[0]
    ok, _, _ = chi2_ok(wrap_angle(s.azimuth - s.azimuth_true) / (s.sigma_az / 1.2))
    assert not ok


def test_sigma_growth_noise_scales_with_range_and_reports():
    base = dict(duration=2.0, targets=[{'position': [0.0, 4000.0, 300.0]}])
    growth = {'range_ref': 1000.0}
    for report, expect_actual in (('nominal', False), ('actual', True)):
        sc = parse_scenario(dict(base, stations=[
            {'id': 'a', 'position': [0.0, 0.0, 0.0], 'rate': 500.0, 'sigma_az': 0.002,
             'sigma_el': 0.001, 'sigma_growth': dict(growth, report=report)}]))
        s = simulate(sc, seed=5).streams[0]
        f = s.range_ / 1000.0                   # ≈ 4.01
        assert np.allclose(s.sigma_az_actual, 0.002 * f)
        assert np.allclose(s.sigma_az, 0.002 * f if expect_actual else 0.002)
        assert chi2_ok(wrap_angle(s.azimuth - s.azimuth_true) / s.sigma_az_actual)[0]
        assert chi2_ok((s.elevation - s.elevation_true) / s.sigma_el_actual)[0]


def test_dropout_and_outlier_rates_binomial():
    sim = simulate(static_scenario(dropout=0.2, outlier=0.05, outlier_size_deg=30.0), seed=3)
    size = math.radians(30.0)
    for s in sim.streams:
        n = len(s.t)
        assert binom_ok(int(np.sum(~s.kept)), n, 0.2), (s.station, np.sum(~s.kept))
        assert binom_ok(int(np.sum(s.outlier)), n, 0.05), (s.station, np.sum(s.outlier))
        err = wrap_angle(s.azimuth - s.azimuth_true)
        # an outlier's error is ±size plus the normal noise (|noise| < 5 σ, σ = 0.01 rad)
        assert np.all(np.abs(np.abs(err[s.outlier]) - size) < 5 * 0.01)
        assert chi2_ok(err[~s.outlier] / 0.01)[0]
        # outlier signs are fair: binomial bound on the positive count
        assert binom_ok(int(np.sum(err[s.outlier] > 0)), int(np.sum(s.outlier)), 0.5)
    kept_events = sum(int(np.sum(s.kept)) for s in sim.streams)
    assert len(sim.bearings) == kept_events
    assert all(not math.isnan(b.bearing.azimuth) for b in sim.bearings)


def test_clock_offset_drift_and_latency_exact_without_jitter():
    sim = simulate(static_scenario(clock_offset=-0.3, clock_drift_ppm=50.0, latency=0.125),
                   seed=0)
    sc = sim.scenario
    for s in sim.streams:
        assert np.array_equal(s.true_ns, sc.epoch_ns + observation_times_ns(sc.stations[0], 5.0))
        expect = np.round((-0.3 + 50e-6 * s.t) * 1e9).astype(np.int64)
        assert np.array_equal(s.stamp_ns - s.true_ns, expect)
        assert np.all(s.publish_ns - s.true_ns == 125_000_000)
    for ev in sim.bearings:
        assert ev.publish_ns == ev.true_ns + 125_000_000
        assert ev.bearing.stamp_ns < ev.true_ns       # the station clock runs 0.3 s behind
    assert [e.publish_ns for e in sim.bearings] == sorted(e.publish_ns for e in sim.bearings)


def test_clock_and_latency_jitter_statistics():
    sim = simulate(static_scenario(clock_offset=0.5, clock_jitter=0.002, latency=0.05,
                                   latency_jitter=0.005), seed=9)
    for s in sim.streams:
        c = (s.stamp_ns - s.true_ns) / 1e9 - 0.5
        assert chi2_ok(c / 0.002)[0]                    # 1 ns rounding is negligible
        lat = (s.publish_ns - s.true_ns) / 1e9
        assert np.all(lat >= 0.0)
        # latency 0.05 ± 0.005 s: clipping at 0 is 10 σ away, so the χ² bound applies
        assert chi2_ok((lat - 0.05) / 0.005)[0]


def test_stamps_and_ordering_with_jitter():
    sim = simulate(static_scenario(latency=0.01, latency_jitter=0.02), seed=2)
    pub = [e.publish_ns for e in sim.bearings]
    assert pub == sorted(pub)
    assert any(np.any(np.diff(s.publish_ns) < 0) for s in sim.streams)  # reordering happens
    assert sim.end_ns == max(sim.scenario.time_ns(5.0), pub[-1])


# --- determinism ----------------------------------------------------------------------------

def _signature(sim):
    return [(e.publish_ns, e.namespace, e.bearing.station, e.bearing.stamp_ns,
             e.bearing.azimuth, repr(e.bearing.elevation), tuple(e.bearing.position), e.true_ns,
             tuple(e.truth)) for e in sim.bearings]


def test_same_seed_same_bearings_different_seed_different():
    sc = load_scenario(os.path.join(SCEN, 'static3.yaml'))
    a, b, c = simulate(sc, seed=42), simulate(sc, seed=42), simulate(sc, seed=43)
    sa = _signature(a)
    assert sa == _signature(b) and len(sa) > 20
    assert sa != _signature(c)
    sc3 = load_scenario(os.path.join(SCEN, 'seed003.yaml'))
    assert _signature(simulate(sc3, seed=7)) == _signature(simulate(sc3, seed=7))
    assert not np.allclose(target_position(simulate(sc3, seed=7).targets[0], 0),
                           target_position(simulate(sc3, seed=8).targets[0], 0))


def test_streams_independent_of_duration_and_other_stations():
    sc = static_scenario(dropout=0.1, outlier=0.1, clock_jitter=0.001)
    full = simulate(sc, seed=5)
    short = simulate(sc, duration=1.0, seed=5)
    for sf, ss in zip(full.streams, short.streams):
        k = len(ss.t)
        assert k == 200
        for name in ('azimuth', 'elevation', 'stamp_ns', 'kept', 'outlier'):
            assert np.array_equal(getattr(sf, name)[:k], getattr(ss, name), equal_nan=True)
    # changing station b's settings leaves station a's bearings untouched
    raw = {'duration': 1.0, 'targets': [{'position': [1000.0, 1000.0, 100.0]}],
           'stations': [{'id': 'a', 'position': [0.0, 0.0, 0.0], 'rate': 50.0},
                        {'id': 'b', 'position': [2000.0, 0.0, 0.0], 'rate': 50.0}]}
    other = copy.deepcopy(raw)
    other['stations'][1].update(rate=7.0, dropout=0.5, sigma_az=0.1)
    s1 = simulate(parse_scenario(raw), seed=1).stream('a')
    s2 = simulate(parse_scenario(other), seed=1).stream('a')
    assert np.array_equal(s1.azimuth, s2.azimuth)


def test_seed_validation():
    sc = static_scenario()
    for bad in (-1, 1.5, 'x', True):
        with pytest.raises(ValueError, match='seed'):
            simulate(sc, seed=bad)
    with pytest.raises(ValueError, match='duration'):
        simulate(sc, duration=-1.0)
    # Too many bearings: the message names the station whose rate dominates.
    fast = parse_scenario({'duration': 10.0, 'stations': [
        {'id': 'slow', 'position': [0.0, 0.0, 0.0], 'sigma_az': 0.01, 'rate': 1.0},
        {'id': 'fast', 'position': [1e3, 0.0, 0.0], 'sigma_az': 0.01, 'rate': 1e6}],
        'targets': [{'position': [0.0, 1e3, 100.0]}]}, 'x.yaml')
    with pytest.raises(ValueError, match=r'duration: 10 s gives .* \(the largest rate: '
                                         r'station fast, 1e\+06 Hz\)'):
        simulate(fast)


# --- trajectories, moving stations, geodetic, namespaces --------------------------------------

def test_trajectories_vectorised():
    cv = Trajectory.constant_velocity([1.0, 2.0, 3.0], [10.0, 0.0, -1.0])
    assert np.allclose(cv.position(np.array([[0.0, 2.0]])), [[[1, 2, 3], [21, 2, 1]]])
    wp = parse_scenario({'duration': 1.0, 'stations': [{'id': 'a', 'position': [0, 0, 0]}],
                         'targets': [{'waypoints': [[0, 0, 0], [300, 0, 0], [300, 400, 0]],
                                      'speed': [100.0, 50.0], 'start_time': 1.0}]}).targets[0]
    assert wp.kind == 'waypoints'
    assert np.allclose(wp.trajectory.times, [1.0, 4.0, 12.0])
    t = np.array([0.0, 2.5, 4.0, 8.0, 20.0])
    assert np.allclose(target_position(wp, t),
                       [[0, 0, 0], [150, 0, 0], [300, 0, 0], [300, 200, 0], [300, 400, 0]])
    assert np.allclose(wp.trajectory.velocity_at(t),
                       [[0, 0, 0], [100, 0, 0], [0, 50, 0], [0, 50, 0], [0, 0, 0]])
    timed = parse_scenario({'duration': 1.0, 'stations': [{'id': 'a', 'position': [0, 0, 0]}],
                            'targets': [{'waypoints': [[0, 0, 0], [10, 0, 0]],
                                         'times': [0.0, 5.0]}]}).targets[0]
    assert np.allclose(target_position(timed, 2.5), [5, 0, 0])


def test_moving_station_seed001_geometry():
    # Lin et al. (TMA): observer at the origin moving (0, 250, 0) m/s; target from
    # (100, 100, 10) km at (-340, 80, -1.21) m/s; a bearing every 0.2 s for 100 s.
    sc = parse_scenario({
        'duration': 100.0,
        'stations': [{'id': 'observer', 'position': [0.0, 0.0, 0.0],
                      'velocity': [0.0, 250.0, 0.0], 'rate': 5.0, 'sigma_az': 1e-3}],
        'targets': [{'position': [100e3, 100e3, 10e3], 'velocity': [-340.0, 80.0, -1.21]}]})
    assert sc.stations[0].trajectory.kind == 'constant_velocity'
    sim = simulate(sc, seed=0)
    (s,) = sim.streams
    assert len(s.t) == 500 and np.allclose(s.t[:3], [0.0, 0.2, 0.4])
    assert np.allclose(s.station_position, np.outer(s.t, [0.0, 250.0, 0.0]))
    assert np.allclose(s.truth, [100e3, 100e3, 10e3] + np.outer(s.t, [-340.0, 80.0, -1.21]))
    d = s.truth - s.station_position
    assert np.allclose(s.azimuth_true, np.arctan2(d[:, 1], d[:, 0]))
    ev = sim.bearings[10]
    assert np.allclose(ev.bearing.position, station_position(sc.stations[0],
                                                             (ev.true_ns - sc.epoch_ns) / 1e9))


def test_geodetic_station_positions():
    origin = {'lat_deg': 31.8, 'lon_deg': 117.2, 'alt': 30.0}
    sc = parse_scenario({
        'duration': 1.0, 'geodetic_origin': origin,
        'stations': [{'id': 'o', 'geodetic': origin},
                     {'id': 'n', 'geodetic': {'lat_deg': 31.8 + 1.0 / 111.2, 'lon_deg': 117.2,
                                              'alt': 30.0}}],
        'targets': [{'position': [0.0, 500.0, 100.0]}]})
    assert np.allclose(sc.stations[0].trajectory.position(0.0), 0.0, atol=1e-6)
    p = sc.stations[1].trajectory.position(0.0)
    # 1/111.2 degree of latitude ≈ 998 m north (WGS84 meridian arc at 31.8°), slightly below
    assert abs(p[0]) < 1e-6 and 990.0 < p[1] < 1005.0 and -0.2 < p[2] < 0.0


def test_namespaces_topics_and_truth_events():
    sc = parse_scenario({
        'duration': 1.0, 'truth_rate': 4.0,
        'stations': [{'id': 'station_1', 'position': [0, 0, 0], 'rate': 2.0}],
        'targets': [{'position': [100.0, 0.0, 10.0]},
                    {'namespace': '/tgt_b/', 'position': [0.0, 100.0, 10.0]},
                    {'namespace': 'src', 'kind': 'random_static', 'count': 2,
                     'box_min': [0, 0, 0], 'box_max': [1, 1, 1]}]})
    assert [t.namespace for t in sc.targets] == ['', 'tgt_b', 'src_0', 'src_1']
    assert bearing_topic('', 'station_1') == 'station_1/bearing'
    assert truth_topic('') == 'truth' and truth_topic('tgt_b') == 'tgt_b/truth'
    sim = simulate(sc, seed=1)
    assert {e.topic for e in sim.bearings} == {'station_1/bearing', 'tgt_b/station_1/bearing',
                                               'src_0/station_1/bearing',
                                               'src_1/station_1/bearing'}
    assert len(sim.truth) == 4 * 4                     # 4 Hz over [0, 1 s) for 4 targets
    for e in sim.truth:
        tg = next(t for t in sim.targets if t.namespace == e.namespace)
        assert np.allclose(e.position, target_position(tg, (e.stamp_ns - sc.epoch_ns) / 1e9))
    for e in sim.bearings:
        tg = next(t for t in sim.targets if t.namespace == e.namespace)
        assert np.allclose(e.truth, target_position(tg, (e.true_ns - sc.epoch_ns) / 1e9))
    assert not np.allclose(target_position(sim.targets[2], 0), target_position(sim.targets[3], 0))


def test_unrealized_random_target_raises():
    sc = load_scenario(os.path.join(SCEN, 'seed003.yaml'))
    with pytest.raises(ValueError, match='not realized'):
        target_position(sc.targets[0], 0.0)


# --- bad scenarios ----------------------------------------------------------------------------

def _base():
    with open(os.path.join(SCEN, 'static3.yaml'), encoding='utf-8') as f:
        return yaml.safe_load(f)


BAD = [
    (lambda d: d.pop('duration'), 'duration: required'),
    (lambda d: d.update(duration=-1.0), 'duration: must be > 0'),
    (lambda d: d.update(durration=1.0), 'durration: unknown key'),
    (lambda d: d['stations'][1].update(sigma_az_deg=-1.0), 'stations[1].sigma_az_deg: must be'),
    (lambda d: d['stations'][0].update(sigma_az='big'), 'stations[0].sigma_az: expected a num'),
    (lambda d: d['stations'][0].update(sigma_az=0.1, sigma_az_deg=1.0),
     'stations[0].sigma_az_deg: give either'),
    (lambda d: d['stations'][0].update(rate=0.0), 'stations[0].rate: must be > 0'),
    # sigma_el of a 1D (dims: 1) station is unused but still checked (docs/nodes.md)
    (lambda d: d['stations'][2].update(sigma_el=-5), 'stations[2].sigma_el: must be > 0'),
    (lambda d: d['stations'][2].update(sigma_el='abc'), 'stations[2].sigma_el: expected a num'),
    (lambda d: d['stations'][2].update(sigma_el_deg=500.0),
     'stations[2].sigma_el_deg: must be within'),
    (lambda d: d['stations'][0].update(dropout=1.5), 'stations[0].dropout: must be <= 1'),
    (lambda d: d['stations'][0].update(dims=3), 'stations[0].dims: must be 1'),
    (lambda d: d['stations'][2].update(id='station_1'), 'stations[2].id: duplicate'),
    (lambda d: d['stations'][2].update(id='3rd'), 'stations[2].id: expected a ROS name'),
    (lambda d: d['stations'][0].pop('position'), 'stations[0].position: required'),
    (lambda d: d['stations'][0].update(position=[1, 2]), 'stations[0].position: expected a list'),
    (lambda d: d['stations'][0].update(geodetic={'lat_deg': 1.0, 'lon_deg': 2.0}),
     'stations[0].geodetic: give either'),
    (lambda d: d['stations'][0].update(sigma_growth={'max_factor': 2.0}),
     'stations[0].sigma_growth.range_ref: required'),
    (lambda d: d['stations'][0].update(clock_offset=-2000.0), 'stations[0].clock_offset'),
    (lambda d: d['targets'][0].update(waypoints=[[0, 0, 0], [1, 0, 0]]),
     'targets[0].position: not allowed together with waypoints'),
    (lambda d: d['targets'][0].update(kind='constant_velocity'),
     "targets[0].kind: 'constant_velocity' does not match"),
    (lambda d: d['targets'].append({'position': [0, 0, 0]}), 'duplicate target namespace'),
    (lambda d: d['targets'][0].update(namespace='bad ns'), 'targets[0].namespace: not a valid'),
    (lambda d: d.update(stations=[]), 'stations: expected a non-empty list'),
    (lambda d: d.update(station_defaults=0), 'station_defaults: expected a mapping, got int'),
    (lambda d: d.update(station_defaults=[]), 'station_defaults: expected a mapping, got list'),
    (lambda d: d['targets'][0].update(kind='random_static', box_min=[0, 0, 0],
                                      box_max=[1, 1, 1], count=10 ** 8),
     'targets[0].count: must be an integer in [1, 1000]'),
]


@pytest.mark.parametrize('mutate,expected', BAD)
def test_bad_scenario_names_the_key_and_file(tmp_path, mutate, expected):
    d = _base()
    mutate(d)
    path = tmp_path / 'bad.yaml'
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(ValueError) as exc:
        load_scenario(path)
    msg = str(exc.value)
    assert msg.startswith(f'{path}: ') and expected in msg, msg


def test_a_target_on_a_station_or_above_it_is_not_observed(tmp_path):
    # Its azimuth is undefined: atan2(0, 0) = 0 published "due East" with the station's σ.
    d = _base()
    p0 = d['stations'][0]['position']
    d['targets'] = [{'namespace': 'on', 'position': list(p0)},
                    {'namespace': 'above', 'position': [p0[0], p0[1], p0[2] + 500.0]}]
    path = tmp_path / 'on_station.yaml'
    path.write_text(yaml.safe_dump(d))
    sim = simulate(load_scenario(path), seed=1)
    first = d['stations'][0]['id']
    seen = {(e.bearing.station, e.namespace) for e in sim.bearings}
    assert not any(s == first for s, _ in seen)
    assert {n for s, n in seen} == {'on', 'above'}       # the other stations see both
    # ... and the run says so (bag simulate prints it, the simulator node logs it)
    scheduled = len(sim.stream(first, 'on').t) + len(sim.stream(first, 'above').t)
    assert sim.unobserved() == {first: scheduled}
    assert sim.unobserved_note().endswith(f'no azimuth): {first} {scheduled}')
    assert simulate(load_scenario(os.path.join(SCEN, 'static3.yaml'))).unobserved_note() == ''
    # with a survey error the published position is off, the true one still under the target
    d['stations'][0]['position_sigma'] = 1.0
    path.write_text(yaml.safe_dump(d))
    assert simulate(load_scenario(path), seed=1).unobserved() == {first: scheduled}


def test_bad_yaml_syntax_and_missing_file(tmp_path):
    p = tmp_path / 'syntax.yaml'
    p.write_text('duration: [1.0\nstations: {')
    with pytest.raises(ValueError, match=r'syntax.yaml: invalid YAML'):
        load_scenario(p)
    with pytest.raises(ValueError, match='cannot read scenario'):
        load_scenario(tmp_path / 'missing.yaml')
    p.write_text('')
    with pytest.raises(ValueError, match='empty scenario'):
        load_scenario(p)


# --- values beyond the documented bounds (docs/nodes.md "Scenario YAML") ----------------------

def _set(key, value, station=0):
    """Mutation setting top-level ``key`` (station None) or ``stations[station].key``."""
    def mutate(d):
        (d if station is None else d['stations'][station])[key] = value
    return mutate


# Each value made `bag simulate` overflow (OverflowError in the simulator or rosbags), run
# out of memory (truth_rate 1e9: a 745 GiB truth array) or silently write wrong data (every
# stamp 0, or bearings that fail validation) before the loader bounded it.
BEYOND = [
    ('epoch', None, 1e300), ('epoch', None, 1e10), ('phase', 0, 1e300), ('rate', 0, 1e-300),
    ('sigma_az', 0, 1e300), ('position_sigma', 0, 1e300), ('latency', 0, 1e12),
    ('truth_rate', None, 1e9), ('clock_offset', 0, 1e12), ('clock_jitter', 0, 1e300),
    ('position', 0, [1e300, 0.0, 0.0]),
    ('duration', None, 1e300), ('sigma_el_deg', 0, 1e300), ('clock_drift_ppm', 1, -1e300),
    ('latency_jitter', 1, 1e300), ('velocity', 2, [0.0, 1e300, 0.0]),
]


@pytest.mark.parametrize('key,station,value', BEYOND)
def test_values_beyond_the_bounds_name_the_key(tmp_path, key, station, value):
    d = _base()
    if key == 'sigma_el_deg':
        d['stations'][station].pop('sigma_el')
    _set(key, value, station)(d)
    path = tmp_path / 'beyond.yaml'
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(ValueError) as exc:
        load_scenario(path)
    where = key if station is None else f'stations[{station}].{key}'
    msg = str(exc.value)
    assert msg.startswith(f'{path}: {where}: ') and 'must be' in msg, msg


def test_truth_samples_are_bounded_by_rate_times_duration():
    d = _base()
    d.update(truth_rate=1e5, duration=100.0)    # 1e7 samples of ~0.5 kB each
    with pytest.raises(ValueError, match=r'^x.yaml: truth_rate: .*1e\+07 truth samples'):
        parse_scenario(d, 'x.yaml')
    d.update(truth_rate=1e4)
    assert parse_scenario(d, 'x.yaml').truth_rate == 1e4


def test_the_bounds_themselves_give_valid_ros_stamps(tmp_path):
    """At the largest epoch, clock offset, drift, jitters and latency every stamp still fits
    builtin_interfaces/Time (int32 s) and every bearing is valid."""
    d = _base()
    d.update(epoch=2e9, duration=2.0)
    d['stations'][0].update(clock_offset=1e8, clock_drift_ppm=1e5, clock_jitter=100.0,
                            latency=3600.0, latency_jitter=100.0, position_sigma=1e6,
                            position=[1e8, 0.0, 0.0], sigma_az=math.pi, sigma_el=1e-12)
    sim = simulate(parse_scenario(d, 'edge.yaml'), seed=1)
    assert sim.bearings
    for ev in sim.bearings:
        ev.bearing.validate()
        assert 0 <= ev.bearing.stamp_ns < 2 ** 31 * 10 ** 9
        assert 0 <= ev.publish_ns < 2 ** 31 * 10 ** 9


def test_bag_simulate_refuses_an_unbounded_scenario(tmp_path, capsys):
    """End to end through the CLI: exit 2, one line on stderr naming file and key, no bag."""
    from bearing_loc_ros.cli import main
    d = _base()
    d['stations'][1]['clock_jitter'] = 1e300      # wrote a bag with every stamp 0
    path = tmp_path / 'jitter.yaml'
    path.write_text(yaml.safe_dump(d))
    out = tmp_path / 'bag'
    assert main(['bag', 'simulate', '--scenario', str(path), '--duration', '10', '--out',
                 str(out)]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and f'{path}: stations[1].clock_jitter: must be' in lines[0], \
        captured.err
    assert captured.out == '' and not out.exists()


# --- overrides of a valid scenario (Python API and `bag simulate --duration`) -----------------

def _slow_scenario(**top):
    """One station at 1e-6 Hz (one bearing, at t = 0), no truth: only the duration matters."""
    return parse_scenario(dict({'duration': 10.0, 'truth_rate': 0.0,
                                'stations': [{'id': 'a', 'position': [0.0, 0.0, 0.0],
                                              'rate': 1e-6}],
                                'targets': [{'position': [100.0, 0.0, 0.0]}]}, **top), 'x.yaml')


def test_duration_override_has_the_scenario_bounds():
    """simulate(duration=...) is checked as the scenario's duration: MAX_TIME, the truth
    samples and the bearings of one run (each made a MemoryError or a multi-GB run)."""
    from bearing_loc_ros.core.scenario_loader import MAX_TIME, MAX_TRUTH_SAMPLES
    from bearing_loc_ros.core.simulation import MAX_SIMULATED_BEARINGS
    sc = _slow_scenario(epoch=2e9)
    for bad in (MAX_TIME * 1.001, 5e8, math.inf, math.nan, -1.0):
        with pytest.raises(ValueError, match=r'^duration: '):
            simulate(sc, duration=bad)
    assert simulate(sc, duration=MAX_TIME).duration == MAX_TIME     # the bound itself is valid
    truthy = _slow_scenario(truth_rate=1e4, duration=1.0)          # 1e4 samples: valid
    n = MAX_TRUTH_SAMPLES / 1e4
    with pytest.raises(ValueError, match=r'^duration: .*truth samples'):
        simulate(truthy, duration=2.0 * n)
    assert len(simulate(truthy, duration=n / 100.0).truth) == MAX_TRUTH_SAMPLES / 100.0
    fast = parse_scenario({'duration': 1.0, 'truth_rate': 0.0,
                           'stations': [{'id': 'a', 'position': [0.0, 0.0, 0.0], 'rate': 1e3}],
                           'targets': [{'position': [100.0, 0.0, 0.0]}]}, 'x.yaml')
    with pytest.raises(ValueError, match=r'^duration: .*bearings'):
        simulate(fast, duration=2.0 * MAX_SIMULATED_BEARINGS / 1e3)


def test_a_scenario_error_echoes_a_short_value():
    """A bad value was echoed whole: one line of 80 MB for a list of aliases."""
    d = _base()
    d['name'] = list(range(100_000))
    with pytest.raises(ValueError, match=r'name: expected a string, got \[0, 1, 2') as exc:
        parse_scenario(d, 'x.yaml')
    assert len(str(exc.value)) < 200


def test_a_station_whose_phase_is_past_the_end_is_an_error():
    """phase >= duration: the station would make no bearing (it silently made none)."""
    d = _base()
    d['stations'][1]['phase'] = d['duration']
    sc = parse_scenario(d, 'x.yaml')
    with pytest.raises(ValueError, match=r"^duration: 2 s ends before the first observation "
                                         r"of station \S+ \(phase 2 s\)"):
        simulate(sc)
    assert simulate(sc, duration=2.5).bearings                  # a longer run observes it


def test_bag_simulate_duration_override_is_bounded(tmp_path, capsys):
    """`bag simulate --duration` beyond MAX_TIME (a MemoryError building /clock at epoch 2e9)
    or giving more /clock messages than a bag holds: exit 2, one line naming duration."""
    from bearing_loc_ros.cli import main
    from bearing_loc_ros.core.simulation import MAX_CLOCK_TICKS
    path = tmp_path / 'slow.yaml'
    path.write_text(yaml.safe_dump({'duration': 10.0, 'epoch': 2e9, 'truth_rate': 0.0,
                                    'stations': [{'id': 'a', 'position': [0.0, 0.0, 0.0],
                                                  'rate': 1e-6}],
                                    'targets': [{'position': [100.0, 0.0, 0.0]}]}))
    ticks = 2.0 * MAX_CLOCK_TICKS / 100.0         # seconds of /clock at 100 Hz
    for duration in ('5e8', '1.0000001e7', f'{ticks:g}'):
        out = tmp_path / f'bag{duration}'
        assert main(['bag', 'simulate', '--scenario', str(path), '--duration', duration,
                     '--out', str(out)]) == 2
        captured = capsys.readouterr()
        lines = captured.err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith('bearing_loc bag: error: duration: '), \
            captured.err
        assert captured.out == '' and not out.exists()
    # a lower --clock-rate makes the same duration valid
    out = tmp_path / 'ok'
    assert main(['bag', 'simulate', '--scenario', str(path), '--duration', f'{ticks:g}',
                 '--clock-rate', '0.01', '--out', str(out)]) == 0
    assert 'clock messages' in capsys.readouterr().out and out.is_dir()


def test_range_grown_sigma_is_clipped_to_a_valid_bearing_sigma():
    """σ(r) = σ·clip(r/r_ref, min, max) with report: actual and no max_factor reached 1e4 rad
    (1e-15 rad at min_factor), outside core.bearings' [SIGMA_MIN, SIGMA_MAX]; it is capped
    at π (a wider σ carries no information) and floored at SIGMA_MIN."""
    from bearing_loc_ros.core.bearings import SIGMA_MIN
    sc = parse_scenario({
        'duration': 10.0,
        'stations': [{'id': 'far', 'position': [0.0, 0.0, 0.0], 'sigma_az': 0.01,
                      'sigma_growth': {'range_ref': 1.0, 'report': 'actual'}},
                     {'id': 'near', 'position': [1e6, 0.0, 0.0], 'sigma_az': 1e-12,
                      'sigma_growth': {'range_ref': 1e8, 'report': 'actual'}}],
        'targets': [{'position': [1e6, 1.0, 1.0]}]}, 'x.yaml')
    sim = simulate(sc, seed=3)
    far, near = sim.stream('far'), sim.stream('near')
    assert np.all(far.range_ > 1e5) and np.all(near.range_ < 2.0)
    for s, sigma in ((far, math.pi), (near, SIGMA_MIN)):
        for name in ('sigma_az', 'sigma_el', 'sigma_az_actual', 'sigma_el_actual'):
            assert np.all(getattr(s, name) == sigma), (s.station, name)
    assert len(sim.bearings) == 20
    for ev in sim.bearings:
        ev.bearing.validate()
