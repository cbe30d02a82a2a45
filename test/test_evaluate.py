"""Monte Carlo evaluation (core.evaluation, ``bearing_loc evaluate``; README "Evaluation").

Statistical assertions use fixed seeds and tolerances built from the standard errors the
evaluation itself reports (SE(RMSE) by the delta method on mean |e|², SE(mean NEES) =
sd/sqrt(n)): a claim "A beats B" must hold by more than 3 combined standard errors
sqrt(SE_A² + SE_B²) (one-sided 0.13 % chance of a false failure for independent draws; the
draws are shared between estimators, which only makes the test more conservative).
"""
import csv
import io
import json
import math
import os

import numpy as np
import pytest

from bearing_loc_ros.cli import main as cli_main
from bearing_loc_ros.cli.evaluate import Progress
from bearing_loc_ros.core import evaluation as ev
from bearing_loc_ros.core.estimators import FixResult
from bearing_loc_ros.core.simulation import load_scenario, realize_targets

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SEED003 = os.path.join(REPO, 'config', 'scenarios', 'seed003.yaml')
STATIC3 = os.path.join(REPO, 'config', 'scenarios', 'static3.yaml')
K = 3.0   # standard errors


def fix(position, covariance, converged=None):
    position = np.asarray(position, dtype=float)
    M = position.shape[0]
    conv = np.ones(M, bool) if converged is None else np.asarray(converged, bool)
    return FixResult(position, np.asarray(covariance, dtype=float), np.zeros(M, int), conv,
                     np.where(conv, 'ok', 'diverged'), 'test')


def test_error_statistics_exact_values():
    truth = np.zeros((4, 3))
    est = np.array([[3.0, 0, 0], [0, 4.0, 0], [0, 0, 0], [100.0, 0, 0]])
    cov = np.array([np.eye(3) * v for v in (9.0, 4.0, 1.0, 1.0)])
    crlb = np.array([np.eye(3) * 2.0] * 4)          # trace 6 -> CRLB sqrt(6)
    lvl = ev.noise_levels([1.0], 'joint')[0]
    s = ev.error_statistics('x', 'joint', lvl, truth, fix(est, cov, [1, 1, 1, 0]), crlb, 0.4)
    # the diverged 4th trial is excluded from RMSE, bias, NEES; counted in the rate
    assert s.converged == 3 and s.convergence_rate == pytest.approx(0.75)
    assert s.rmse == pytest.approx(math.sqrt((9 + 16 + 0) / 3))
    assert s.bias_vector == pytest.approx([1.0, 4 / 3, 0.0])
    assert s.bias == pytest.approx(math.hypot(1.0, 4 / 3))
    assert s.crlb == pytest.approx(math.sqrt(6.0))
    assert s.rmse_over_crlb == pytest.approx(s.rmse / math.sqrt(6.0))
    assert s.mean_nees == pytest.approx((9 / 9 + 16 / 4 + 0) / 3)
    assert s.time_per_fix_s == pytest.approx(0.1)
    assert s.median_error == pytest.approx(3.0)
    assert s.sigma_az_deg == 1.0 and s.sigma_el_deg == 1.0


def test_rmse_over_crlb_divides_by_the_bound_of_the_same_trials():
    # Only the near target converges: its 1 m error against the 1 m bound of that target is
    # ratio 1, not 1 / sqrt(mean(3, 3 * 100**2) / 3) of every trial's bound (was 0.014).
    truth = np.zeros((2, 3))
    crlb = np.array([np.eye(3) / 3.0, np.eye(3) * 1e4 / 3.0])     # traces 1 and 1e4 m²
    lvl = ev.noise_levels([1.0], 'joint')[0]
    s = ev.error_statistics('x', 'joint', lvl, truth,
                            fix([[1.0, 0, 0], [50.0, 0, 0]], [np.eye(3)] * 2, [1, 0]), crlb, 0.0)
    assert s.crlb == pytest.approx(math.sqrt((1.0 + 1e4) / 2))
    assert s.rmse_over_crlb == pytest.approx(1.0)
    # a converged trial whose bound is infinite (unobservable) is left out of both sides
    s = ev.error_statistics('x', 'joint', lvl, np.zeros((3, 3)),
                            fix([[1.0, 0, 0], [2.0, 0, 0], [50.0, 0, 0]], [np.eye(3)] * 3),
                            np.array([np.eye(3) / 3.0, np.eye(3) * 4 / 3.0,
                                      np.full((3, 3), np.inf)]), 0.0)
    assert s.rmse_over_crlb == pytest.approx(1.0)


def test_error_statistics_never_reports_nan_as_a_value():
    lvl = ev.noise_levels([1.0], 'joint')[0]
    s = ev.error_statistics('x', 'joint', lvl, np.zeros((2, 3)),
                            fix(np.full((2, 3), np.nan), np.full((2, 3, 3), np.inf), [0, 0]),
                            np.full((2, 3, 3), np.inf), 0.0)
    assert s.converged == 0 and s.convergence_rate == 0.0
    for v in (s.rmse, s.bias, s.crlb, s.rmse_over_crlb, s.mean_nees, s.median_error):
        assert math.isnan(v)
    # a converged fix with a singular covariance counts for RMSE but not for NEES
    s = ev.error_statistics('x', 'joint', lvl, np.zeros((2, 3)),
                            fix([[1.0, 0, 0], [0, 1.0, 0]], [np.eye(3), np.zeros((3, 3))]),
                            np.array([np.eye(3)] * 2), 0.0)
    assert s.rmse == pytest.approx(1.0) and s.mean_nees == pytest.approx(1.0)


def test_noise_levels_sweeps_and_validation():
    j, a, e = (ev.noise_levels([0.5, 2.0], sw, 0.5) for sw in ev.SWEEPS)
    assert [(x.sigma_az_deg, x.sigma_el_deg) for x in j] == [(0.5, 0.5), (2.0, 2.0)]
    assert [(x.sigma_az_deg, x.sigma_el_deg) for x in a] == [(0.5, 0.5), (2.0, 0.5)]
    assert [(x.sigma_az_deg, x.sigma_el_deg) for x in e] == [(0.5, 0.5), (0.5, 2.0)]
    assert a[1].sigma_az == pytest.approx(math.radians(2.0))
    for bad, field in [(([0.0],), 'sigma_deg'), (([1.0], 'x'), 'sweep'),
                       (([1.0], 'joint', -1.0), 'fixed_sigma_deg')]:
        with pytest.raises(ValueError, match=field):
            ev.noise_levels(*bad)


def test_trials_use_the_simulator_target_sampling_and_sigma_growth():
    sc = load_scenario(SEED003)
    tr = ev.trials_from_scenario(sc, 20, seed=5)
    assert tr.M == 20 and tr.stations.shape == (20, 6, 3)
    for m in (0, 7, 19):        # trial m == simulator seed 5 + m
        assert np.array_equal(tr.targets[m], realize_targets(sc, 5 + m)[0].trajectory.points[0])
    assert np.all(tr.targets >= [-3000, 1000, -500]) and np.all(tr.targets <= [3000, 7000, 500])
    r = np.linalg.norm(tr.targets[:, None] - tr.stations, axis=-1)
    assert np.allclose(tr.sigma_factor(), np.clip(r / 1000.0, 1e-3, 6.0))
    assert tr.reference_range() == 1000.0
    assert np.allclose(ev.trials_from_scenario(sc, 3, range_ref=0).sigma_factor(), 1.0)
    assert np.allclose(ev.trials_from_scenario(sc, 3, 5, range_ref=2000).sigma_factor(),
                       np.clip(np.linalg.norm(tr.targets[:3, None] - tr.stations[:3], axis=-1)
                               / 2000.0, 1e-3, 6.0))
    # a 1D station and a moving target (static3 has both kinds of station)
    tr3 = ev.trials_from_scenario(load_scenario(STATIC3), 4)
    assert tr3.has_elevation.tolist() == [True, True, False]
    with pytest.raises(ValueError, match='trials'):
        ev.trials_from_scenario(sc, 0)


def test_consistent_estimator_meets_the_crlb_with_nees_three():
    """mle with the true σ (constant) is efficient: RMSE = CRLB and mean NEES = 3 within K SE.

    The bound itself carries no Monte Carlo error (it is averaged over the same targets).
    """
    sc = load_scenario(SEED003)
    tr = ev.trials_from_scenario(sc, 400, seed=1, range_ref=0)
    rows = ev.evaluate(['mle', 'ls'], tr, [0.5], ('joint',), seed=3)
    mle, ls = rows
    assert abs(mle.rmse - mle.crlb) < K * mle.rmse_se
    assert abs(mle.mean_nees - ev.NEES_DOF) < K * mle.nees_se
    assert mle.convergence_rate == 1.0 and ls.convergence_rate == 1.0
    assert ls.time_per_fix_s > 0 and mle.time_per_fix_s > 0
    # the test can fail: the same data with a 2x wrong reported sigma gives NEES ~ 12
    lv = ev.noise_levels([0.5], 'joint')[0]
    lv_wrong = ev.NoiseLevel(lv.sigma_az / 2, lv.sigma_el / 2, 0.5, 0.25, 0.25)
    tr2 = ev.trials_from_scenario(sc, 400, seed=1, range_ref=0)
    tr2.report_actual[:] = False
    true_f = tr2.sigma_factor
    tr2.sigma_factor = lambda: 2.0 * true_f()
    bad = ev.run_level(['mle'], tr2, lv_wrong, ev.level_rng(3, 'joint', 0))[0]
    assert bad.mean_nees - ev.NEES_DOF > K * bad.nees_se


def test_deterministic_for_a_seed_and_independent_of_the_estimator_set():
    tr = ev.trials_from_scenario(load_scenario(SEED003), 60, seed=2)

    def strip(rows):
        # (NaN as None: a statistic of fewer than two ok fixes is NaN, and NaN != NaN)
        return [{k: None if isinstance(v, float) and math.isnan(v) else v
                 for k, v in r.row().items() if k != 'time_per_fix_s'} for r in rows]

    a = ev.evaluate(['ls', 'mle'], tr, [1.0, 2.0], ('joint', 'azimuth'), seed=9)
    b = ev.evaluate(['ls', 'mle'], tr, [1.0, 2.0], ('joint', 'azimuth'), seed=9)
    c = ev.evaluate(['mle'], tr, [2.0], ('azimuth',), seed=9)
    d = ev.evaluate(['ls', 'mle'], tr, [1.0, 2.0], ('joint', 'azimuth'), seed=10)
    assert strip(a) == strip(b)
    # the noise of a level depends on (seed, sweep, sigma index), so a subset run gives the
    # same numbers only for the same sigma index: [2.0] is index 0 here, index 1 above
    assert strip(c)[0]['rmse'] != strip(a)[7]['rmse']
    assert strip(ev.evaluate(['mle'], tr, [1.0], ('joint',), seed=9))[0] == strip(a)[1]
    assert strip(a) != strip(d)


@pytest.fixture(scope='module')
def seed003_csv(tmp_path_factory):
    """`bearing_loc evaluate` on Zong & Cui (2015) (seed003), 300 trials (the docs use 1000)."""
    out = tmp_path_factory.mktemp('eval')
    argv = ['evaluate', '--scenario', SEED003, '--estimator', 'ls,mle,wmle',
            '--sigma-deg', '0.5,1,3', '--trials', '300', '--seed', '0', '--out', str(out),
            '--quiet', '--paper']
    assert cli_main(argv) == 0
    with open(out / 'evaluation.csv', encoding='utf-8') as f:
        rows = list(csv.DictReader(f))
    table = {}
    for r in rows:
        x = float(r['sigma_el_deg'] if r['sweep'] == 'elevation' else r['sigma_az_deg'])
        table[(r['sweep'], x, r['estimator'])] = {k: _num(v) for k, v in r.items()}
    return out, rows, table


def _num(v):
    try:
        return float(v)
    except ValueError:
        return v


def _better(t, a, b):
    """RMSE of row a below RMSE of row b by more than K combined standard errors."""
    return t[b]['rmse'] - t[a]['rmse'] > K * math.hypot(t[a]['rmse_se'], t[b]['rmse_se'])


def test_seed003_csv_table_is_complete(seed003_csv):
    out, rows, table = seed003_csv
    assert len(rows) == 3 * 3 * 3
    for col in ('rmse', 'bias', 'crlb', 'rmse_over_crlb', 'mean_nees', 'convergence_rate',
                'time_per_fix_s', 'rmse_se', 'nees_se'):
        assert col in rows[0]
    for r in table.values():
        assert r['trials'] == 300 and r['convergence_rate'] >= 0.99
        assert r['time_per_fix_s'] > 0
        # the CRLB bounds every estimator's RMSE (within Monte Carlo error)
        assert r['rmse'] + K * r['rmse_se'] >= r['crlb']
    with open(out / 'evaluation.json', encoding='utf-8') as f:
        doc = json.load(f)
    assert doc['trials'] == 300 and doc['sweeps'] == ['joint', 'azimuth', 'elevation']
    assert doc['options'] == {'ls': {'consistency': False}, 'mle': {'robust': False},
                              'wmle': {'reference_range': 1000.0, 'robust': False}}
    assert len(doc['rows']) == len(rows)
    assert doc['findings']['ranking']['elevation@3'][-1] == 'ls'
    for name in ('eval_rmse_joint.png', 'eval_rmse_azimuth.png', 'eval_rmse_elevation.png',
                 'eval_az_vs_el.png'):
        p = out / name
        assert p.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and p.stat().st_size < 300_000


def test_seed003_estimator_ordering(seed003_csv):
    """Zong & Cui (2015), sec. 3.2, conclusion 1: PLE (ls) worst, MLE/WMLE near the CRLB.

    Reproduced wherever the Monte Carlo resolves it: the joint sweep up to σ = 1° and the
    elevation sweep at σ = 1° and 3°. (At σ_ref = 3° with σ growing to 18° at long range the
    ML estimates have a heavy tail and the ordering reverses; README "Evaluation".)
    """
    _, _, t = seed003_csv
    for key in (('joint', 1.0), ('elevation', 1.0), ('elevation', 3.0)):
        for good in ('mle', 'wmle'):
            assert _better(t, key + (good,), key + ('ls',)), (key, good)
    for x in (0.5, 1.0):
        r = t[('joint', x, 'wmle')]
        assert r['rmse'] - r['crlb'] < K * r['rmse_se'] + 0.1 * r['crlb']
    # Zong & Cui's (2015) motivation for WMLE: MLE's constant σ misstates its accuracy (NEES >> 3),
    # WMLE's range-grown σ gives a consistent covariance (NEES = 3) at small σ
    w, m = t[('joint', 0.5, 'wmle')], t[('joint', 0.5, 'mle')]
    assert abs(w['mean_nees'] - ev.NEES_DOF) < K * w['nees_se']
    assert m['mean_nees'] - ev.NEES_DOF > K * m['nees_se'] + 10.0


def test_seed003_azimuth_error_costs_more_than_elevation_error(seed003_csv):
    """Zong & Cui (2015), sec. 3.2, conclusion 2 compares figs. 3 and 4 (one angle's σ varied).

    Its text names the dominant angle inconsistently (σφ is azimuth in its eq. (7) and
    figure description, elevation in section 1). For its geometry (stations on the x axis,
    sources 1-7 km in front) the CRLB, which no estimator can beat, is ~3x larger when the
    azimuth σ grows than when the elevation σ grows, and the efficient estimators follow it.
    """
    _, _, t = seed003_csv
    for x in (1.0, 3.0):
        assert t[('azimuth', x, 'mle')]['crlb'] > 1.5 * t[('elevation', x, 'mle')]['crlb']
    assert t[('azimuth', 3.0, 'mle')]['crlb'] > 2.5 * t[('elevation', 3.0, 'mle')]['crlb']
    for est in ('mle', 'wmle'):
        assert _better(t, ('elevation', 3.0, est), ('azimuth', 3.0, est))


def test_progress_bar_plain_text_and_silent_when_disabled():
    buf = io.StringIO()
    p = Progress(True, width=10, stream=buf)
    p(3, 6)
    p(6, 6)
    text = buf.getvalue()
    assert '\r[#####.....]    3/6' in text and '[##########]    6/6' in text
    assert text.endswith('\n')
    buf = io.StringIO()
    Progress(False, stream=buf)(1, 2)
    assert buf.getvalue() == ''


def test_evaluate_cli_bad_input_names_the_field(capsys, tmp_path):
    base = ['evaluate', '--scenario', SEED003, '--trials', '5', '--quiet']
    for extra, field in [(['--estimator', 'ls,nope'], '--estimator'),
                         (['--sigma-deg', '1,-2'], '--sigma-deg'),
                         (['--sigma-deg', 'a,b'], '--sigma-deg'),
                         (['--sigma-deg', '1,2,1'], '--sigma-deg'),
                         (['--sigma-deg', '1,,2'], '--sigma-deg'),
                         (['--estimator', 'ls,'], '--estimator'),
                         (['--trials', '0'], '--trials'),
                         (['--seed', '-1'], '--seed'),
                         (['--range-ref', '-5'], '--range-ref'),
                         (['--fixed-sigma-deg', '0'], '--fixed-sigma-deg'),
                         (['--fixed-sigma-deg', '100'], '--fixed-sigma-deg')]:
        assert cli_main(base + extra) == 2
        err = capsys.readouterr().err
        assert f'error: {field}: ' in err and err.count('\n') == 1, err
    assert cli_main(['evaluate', '--scenario', str(tmp_path / 'no.yaml')]) == 2
    assert 'scenario' in capsys.readouterr().err
    # no progress bar when stderr is not a TTY (pytest captures it)
    assert cli_main(['evaluate', '--scenario', SEED003, '--trials', '5', '--estimator', 'ls',
                     '--sigma-deg', '1', '--sweep', 'none']) == 0
    cap = capsys.readouterr()
    assert cap.err == '' and 'joint' in cap.out and 'RMSE/CRLB' in cap.out


def test_an_unused_target_altitude_is_warned_about(capsys):
    # A 3D scenario fixes the height from its elevations: the stated altitude was silently
    # unused (locate says so in the same case).
    base = ['evaluate', '--scenario', SEED003, '--trials', '5', '--quiet', '--estimator',
            'ls', '--sigma-deg', '1', '--sweep', 'none', '--target-altitude', '1000']
    assert cli_main(base) == 0
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'warning: --target-altitude not used' in err
    assert cli_main(base + ['--dimension', 'horizontal']) == 0
    assert 'warning' not in capsys.readouterr().err


def test_azimuth_only_scenario_runs_the_joint_sweep_only(capsys):
    # Its azimuth sweep would repeat the joint rows and its elevation sweep vary an angle no
    # station measures: the default --sweep both runs the joint sweep, with a note.
    assert cli_main(['evaluate', '--scenario', 'seed000_azimuth_only', '--trials', '20',
                     '--estimator', 'mle', '--sigma-deg', '1', '--quiet']) == 0
    cap = capsys.readouterr()
    rows = [line.split()[0] for line in cap.out.splitlines()[3:] if line.strip()]
    assert rows == ['joint'] and 'only the joint sweep' in cap.err


def test_track_crlb_statistics():
    from bearing_loc_ros.core.crlb import crlb
    rng = np.random.default_rng(3)
    stations = np.array([[0.0, 0.0, 0.0], [5e3, 0.0, 10.0], [0.0, 5e3, 20.0]])
    saz, sel = [2e-3, 2e-3, 3e-3], [2e-3, math.nan, 3e-3]
    truth = np.array([10e3, 8e3, 500.0]) + rng.normal(0.0, 1e3, (20, 3))
    C = crlb(truth, stations, saz, sel)
    # estimates drawn from the bound itself: RMSE / CRLB near 1
    est = truth + np.einsum('kij,kj->ki', np.linalg.cholesky(C), rng.normal(size=(20, 3)))
    P = 4.0 * C
    s = ev.track_crlb_statistics(est, P, truth, stations, saz, sel)
    e = np.linalg.norm(est - truth, axis=1)
    np.testing.assert_allclose(s['error'], e)
    np.testing.assert_allclose(s['predicted'], 2.0 * np.sqrt(np.trace(C, axis1=1, axis2=2)))
    np.testing.assert_allclose(s['crlb'], np.sqrt(np.trace(C, axis1=1, axis2=2)))
    assert s['rmse'] == pytest.approx(math.sqrt(np.mean(e ** 2)))
    assert s['crlb_rms'] == pytest.approx(math.sqrt(np.mean(np.trace(C, axis1=1, axis2=2))))
    assert s['ratio'] == pytest.approx(s['rmse'] / s['crlb_rms'])
    assert s['mean_predicted'] == pytest.approx(2.0 * s['crlb_rms'])


def test_confidently_wrong_uses_the_quantile_of_the_nees_degrees_of_freedom():
    from bearing_loc_ros.core import chisq
    assert ev.CONFIDENT_WRONG_NEES == pytest.approx(float(chisq.ppf(0.9999, 3)), rel=1e-7)
    assert ev.CONFIDENT_WRONG_NEES_2D == pytest.approx(float(chisq.ppf(0.9999, 2)), rel=1e-7)
    # NEES 19.5: above the χ²₂ 0.9999 quantile (18.4), below the χ²₃ one (21.1).
    e = math.sqrt(19.5)
    flat = np.diag([1.0, 1.0, 0.0])               # horizontal fix, altitude stated exactly
    lvl = ev.noise_levels([1.0], 'joint')[0]
    for cov, wrong in ((flat, 1.0), (np.eye(3), 0.0)):
        s = ev.error_statistics('x', 'joint', lvl, np.zeros((1, 3)),
                                fix([[e, 0.0, 0.0]], [cov]), np.array([np.eye(3)]), 0.1)
        assert s.nees_ok == pytest.approx(19.5)
        assert s.confident_wrong_fraction == wrong


def test_evaluate_warns_when_no_trial_is_observable(capsys, tmp_path):
    path = tmp_path / 'coloc.yaml'
    path.write_text('duration: 10\nstations:\n  - id: a\n    position: [0, 0, 0]\n'
                    '  - id: b\n    position: [0, 0, 0]\ntargets:\n'
                    '  - position: [1000, 1000, 100]\n')
    assert cli_main(['evaluate', '--scenario', str(path), '--trials', '5', '--sigma-deg', '1',
                     '--estimator', 'ls', '--sweep', 'none', '--quiet']) == 0
    assert 'warning: the CRLB is infinite for every trial' in capsys.readouterr().err


def test_a_stated_altitude_sigma_is_drawn_so_rmse_crlb_and_nees_agree():
    # --target-altitude-sigma S: the altitude stated to the horizontal solve must be a draw
    # from N(true altitude, S²). It used to be the exact truth while the bound counted S²
    # and NEES 3 dof, so the estimator "beat" the bound (RMSE/CRLB 0.47 at S = 2 km, NEES 2).
    from bearing_loc_ros.cli.evaluate import run_evaluation
    S = 2000.0
    rows, meta = run_evaluation('seed000_azimuth_only', ['mle'], [0.5], 2000, seed=0,
                                sweep='none', target_altitude_sigma=S)
    r = rows[0]
    assert meta['target_altitude_m'] == 'truth' and meta['target_altitude_sigma_m'] == S
    assert r.convergence_rate > 0.99
    # RMSE over the bound of the same trials: 1 within K standard errors (mle is efficient
    # at 0.5°; SE(RMSE) from the evaluation itself)
    assert abs(r.rmse_over_crlb - 1.0) < K * r.rmse_se / (r.rmse / r.rmse_over_crlb)
    assert abs(r.mean_nees - ev.NEES_DOF) < K * r.nees_se          # 3 dof with σ_z > 0
    # the altitude error is the stated one: |e_z| ~ S, so the 3D RMSE exceeds S
    assert r.rmse > S and abs(r.bias_vector[2]) < K * S / math.sqrt(r.converged)
    again = run_evaluation('seed000_azimuth_only', ['mle'], [0.5], 2000, seed=0,
                           sweep='none', target_altitude_sigma=S)[0][0]
    assert again.rmse == r.rmse                                       # seeded draws
    exact = run_evaluation('seed000_azimuth_only', ['mle'], [0.5], 2000, seed=0,
                           sweep='none', target_altitude_sigma=0.0)[0][0]
    assert abs(exact.mean_nees - 2.0) < K * exact.nees_se and exact.rmse < r.rmse


def test_trials_times_targets_times_stations_is_bounded(capsys, tmp_path):
    # A random_static count of 1000 makes every trial 1000 problems: --trials 20000 ended in
    # a MemoryError traceback after 112 s, the default 1000 trials took 41 s and 1.6 GB.
    from bearing_loc_ros.cli.evaluate import MAX_BEARINGS
    path = tmp_path / 'many.yaml'
    path.write_text('duration: 10\nstations:\n  - {id: a, position: [0, 0, 0]}\n'
                    '  - {id: b, position: [5000, 0, 0]}\n  - {id: c, position: [0, 5000, 0]}\n'
                    'targets:\n  - {kind: random_static, box_min: [1000, 1000, 100], '
                    'box_max: [4000, 4000, 500], count: 1000}\n')
    most = MAX_BEARINGS // 3000
    for trials in (None, '20000', str(most + 1)):
        extra = [] if trials is None else ['--trials', trials]
        assert cli_main(['evaluate', '--scenario', str(path), '--quiet'] + extra) == 2
        cap = capsys.readouterr()
        assert cap.out == '' and cap.err.count('\n') == 1
        assert 'error: --trials: ' in cap.err and f'use --trials {most} or fewer' in cap.err


def test_a_target_on_or_above_a_station_drops_that_bearing_as_the_simulator_does(
        capsys, tmp_path):
    # Its azimuth is undefined: evaluate fed the estimators atan2(0, 0) = due East with the
    # station's σ and printed an all-NaN table blaming the station layout. The simulator
    # makes no such bearing (core.simulation.MIN_HORIZONTAL_RANGE); evaluate now solves
    # (and bounds) those problems with the other stations' bearings, and says so.
    path = tmp_path / 'above.yaml'
    path.write_text('duration: 10\nstations:\n  - {id: a, position: [0, 0, 0]}\n'
                    '  - {id: b, position: [5000, 0, 0]}\n  - {id: c, position: [0, 5000, 0]}\n'
                    'targets:\n  - {namespace: above, position: [0, 0, 800]}\n'
                    '  - {namespace: aside, position: [3000, 4000, 500]}\n')
    out = tmp_path / 'out'
    assert cli_main(['evaluate', '--scenario', str(path), '--trials', '300', '--estimator',
                     'ls,mle', '--sigma-deg', '1', '--sweep', 'none', '--quiet', '--no-plots',
                     '--paper', '--out', str(out)]) == 0      # --paper: every fix counts
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'target on or straight above the station' in err
    assert err.rstrip().endswith('of 600 problems per level: a 300')
    doc = json.loads((out / 'evaluation.json').read_text())
    assert doc['unobserved_bearings'] == {'a': 300}
    for r in doc['rows']:
        assert r['convergence_rate'] == 1.0 and r['crlb'] > 0
        # mle is efficient here: RMSE over the bound of the same trials is 1 within K SE
        if r['estimator'] == 'mle':
            assert abs(r['rmse_over_crlb'] - 1.0) < K * r['rmse_se'] * r['rmse_over_crlb'] \
                / r['rmse']
    # two stations, the target above one of them: a single bearing is no fix
    path.write_text('duration: 10\nstations:\n  - {id: a, position: [0, 0, 0]}\n'
                    '  - {id: b, position: [5000, 0, 0]}\n'
                    'targets:\n  - {position: [0, 0, 800]}\n')
    assert cli_main(['evaluate', '--scenario', str(path), '--trials', '5', '--estimator',
                     'mle', '--sigma-deg', '1', '--sweep', 'none', '--quiet']) == 0
    cap = capsys.readouterr()
    assert 'too few bearings left where the target is on or above a station' in cap.err
    assert ' 0.0 ' in cap.out.splitlines()[-1]                  # conv % 0
