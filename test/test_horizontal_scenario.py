"""The mobile fox-hunt scenario: reflections 20-90° off, azimuth only, a car on waypoints;
through bag process's pipeline with the window mode."""

import dataclasses
import math
import os

import numpy as np
from scipy.stats import binom

from bearing_loc_ros.core.conventions import wrap_angle
from bearing_loc_ros.core.evaluation import nees_values
from bearing_loc_ros.core.fusion import FusionConfig, make_core, MODE_WINDOW, replay
from bearing_loc_ros.core.simulation import load_scenario, simulate

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENARIO = os.path.join(REPO, 'config', 'scenarios', 'mobile_foxhunt.yaml')


def test_scenario_matches_its_description():
    sc = load_scenario(SCENARIO)
    (car,) = sc.stations
    assert car.dims == 1 and car.trajectory.kind == 'waypoints'
    assert 3.0 <= math.degrees(car.sigma_az) <= 5.0
    sim = simulate(sc, seed=3)
    events = sim.bearings
    pos = np.array([e.bearing.position for e in events])
    truth = np.array([e.truth for e in events])
    d = np.linalg.norm((truth - pos)[:, :2], axis=1)
    assert 2000.0 <= d.min() and d.max() <= 5000.0
    assert np.all(np.isnan([e.bearing.elevation for e in events]))
    out = np.array([e.outlier for e in events])
    n = len(events)
    lo, hi = binom.ppf([0.0005, 0.9995], n, 0.1)
    assert lo <= out.sum() <= hi
    true_az = np.arctan2(truth[:, 1] - pos[:, 1], truth[:, 0] - pos[:, 0])
    off = np.degrees(np.abs(wrap_angle(np.array([e.bearing.azimuth for e in events])
                                       - true_az)))
    # reflections: 20-90° plus the 4° noise (6 σ); the others within 6 σ
    assert np.all((off[out] > 20.0 - 6 * 4.0) & (off[out] < 90.0 + 6 * 4.0))
    assert np.all(off[~out] < 6 * 4.0)
    # magnitudes spread over the range (uniform): both halves are populated
    assert np.any(off[out] < 50.0) and np.any(off[out] > 60.0)


def test_reflection_range_leaves_the_other_bearings_unchanged():
    sc = load_scenario(SCENARIO)
    fixed = dataclasses.replace(sc, stations=[dataclasses.replace(sc.stations[0],
                                                                  outlier_size_max=None)])
    a = simulate(sc, seed=1, duration=100.0).bearings
    b = simulate(fixed, seed=1, duration=100.0).bearings
    for x, y in zip(a, b):
        assert x.outlier == y.outlier
        if not x.outlier:
            assert x.bearing.azimuth == y.bearing.azimuth


def run_window(sc, seed, duration=None):
    cfg = FusionConfig.from_parameters({'target_altitude': [10.0], 'trigger': 'timer',
                                        'rate': 0.05, 'window': 600.0, 'buffer_age': 30.0})
    core = make_core(cfg, stations=['car'], mode=MODE_WINDOW)
    sim = simulate(sc, seed=seed, duration=duration)
    eps = [e for e in replay(core, [(ev.publish_ns, ev.bearing) for ev in sim.bearings])
           if e.ok]
    truth = sc.targets[0].trajectory.position(0.0)
    return core, eps, truth


def test_window_mode_converges_on_the_scenario():
    """Through the bag process pipeline (make_core + replay): fixes converge as the car
    drives and the last one is consistent with its covariance (χ²₂ 99.9 %)."""
    sc = load_scenario(SCENARIO)
    core, eps, truth = run_window(sc, seed=4)
    assert len(eps) >= 10
    err = np.array([np.linalg.norm(e.position[:2] - truth[:2]) for e in eps])
    sig = np.array([math.sqrt(np.trace(e.covariance[:2, :2])) for e in eps])
    assert sig[-1] < 0.5 * sig[0]
    v, dof = nees_values(eps[-1].position - truth, eps[-1].covariance)
    assert dof[0] == 2 and v[0] < 13.8
    assert err[-1] < 4.0 * sig[-1]
    assert core.station_stats('car').outliers > 0


def test_evaluate_reports_rmse_over_crlb_and_nees_for_an_azimuth_only_scenario():
    """seed000_azimuth_only (dims: 1, altitude from the scenario): the horizontal bound and
    NEES with 2 dof. mle's RMSE/CRLB within 4 standard errors of 1 (+2 % for the
    nonlinearity at ~200 m errors), its mean NEES inside the χ²_{2n}/n 99.9 % band."""
    from scipy.stats import chi2
    from bearing_loc_ros.cli.evaluate import run_evaluation
    n = 2000
    rows, meta = run_evaluation('seed000_azimuth_only', ['ls', 'mle'], [0.0859437], n,
                                seed=5, sweep='none')
    assert meta['dimension'] == 'auto' and meta['target_altitude_m'] == 'truth'
    mle = next(r for r in rows if r.estimator == 'mle')
    assert abs(mle.rmse_over_crlb - 1.0) < 4 * mle.rmse_se / mle.crlb + 0.02
    lo, hi = chi2.ppf([0.0005, 0.9995], 2 * n) / n
    assert lo < mle.mean_nees < hi
    ls = next(r for r in rows if r.estimator == 'ls')
    # (ls's option consistency rejects an honest fix with probability ≈ 0.2 %)
    assert ls.rmse >= mle.rmse and ls.convergence_rate >= 0.99
