"""Estimators (core/estimators.py, core/constrained_tls.py): exactness, maths, options, bad input.

Statistical (Monte Carlo) acceptance tests live in test_estimators_mc.py.
"""
import numpy as np
import pytest

from bearing_loc_ros.core.bearings import BearingSet, simulate_bearings
from bearing_loc_ros.core.crlb import crlb_for
from bearing_loc_ros.core.constrained_tls import ctls_cost, ctls_covariance, ctls_derivatives
from bearing_loc_ros.core.estimators import (DEFAULT_ESTIMATOR, ESTIMATORS, FixResult, locate,
                                             noise_model_crlb, pseudo_linear_system,
                                             range_scaled_sigmas, STATUSES, tls)

ALL = sorted(ESTIMATORS)


def random_problems(rng, M, N, spread=10e3, sigma=2e-3, noise=False):
    """M random geometries of N stations (mixed 1D/2D, at least one 2D) around a target.

    Stations within ±spread horizontally and ±spread/20 vertically of a random origin offset,
    the target 0.2..1 spread away horizontally and 0.05..0.5 spread above the stations.
    """
    offset = rng.uniform(-50e3, 50e3, size=(M, 1, 3))
    pos = offset + rng.uniform(-1, 1, size=(M, N, 3)) * [spread, spread, spread / 20]
    ang = rng.uniform(-np.pi, np.pi, M)
    rad = rng.uniform(0.2, 1.0, M) * spread
    tgt = offset[:, 0] + np.column_stack([rad * np.cos(ang), rad * np.sin(ang),
                                          rng.uniform(0.05, 0.5, M) * spread])
    has_el = rng.random((M, N)) < 0.5
    has_el[:, 0] = True
    bs = simulate_bearings(tgt, pos, sigma, rng=rng if noise else None)
    el = np.where(has_el, bs.elevation, np.nan)
    return tgt, BearingSet.from_arrays(bs.positions, bs.azimuth, el, bs.sigma_az, bs.sigma_el)


def seed000_stations():
    return np.array([[30.0, -10.0, 0.1], [30.0, 20.0, 0.2], [-30.0, 5.0, 0.15]]) * 1e3


@pytest.mark.parametrize('N', [3, 4, 6, 10])
@pytest.mark.parametrize('method', ALL)
def test_noise_free_bearings_recover_the_target(method, N):
    rng = np.random.default_rng(100 + N)
    tgt, bs = random_problems(rng, 40, N)
    r = locate(method, bs)
    assert isinstance(r, FixResult) and r.method == method
    assert r.position.shape == (40, 3) and r.covariance.shape == (40, 3, 3)
    assert np.all(r.converged) and np.all(r.status == 'ok')
    scale = np.sqrt(np.mean(np.sum((tgt[:, None] - bs.positions) ** 2, axis=-1), axis=1))
    rel = np.linalg.norm(r.position - tgt, axis=1) / scale
    assert rel.max() < 1e-6


@pytest.mark.parametrize('method', ALL)
def test_batch_equals_problem_by_problem(method):
    rng = np.random.default_rng(7)
    _, bs = random_problems(rng, 12, 5, noise=True, sigma=0.01)
    batch = locate(method, bs)
    for m in range(bs.M):
        one = locate(method, bs.problem(m))
        assert one.status[0] == batch.status[m]
        np.testing.assert_allclose(one.position[0], batch.position[m], rtol=1e-9, atol=1e-6)
        np.testing.assert_allclose(one.covariance[0], batch.covariance[m], rtol=1e-6)


@pytest.mark.parametrize('method', ALL)
def test_results_are_well_formed_on_noisy_hard_input(method):
    # Large noise, short baselines, mixed 1D/2D: whatever happens, a converged result has a
    # finite position and a finite symmetric positive definite covariance; NaN only for
    # degenerate_geometry.
    rng = np.random.default_rng(11)
    _, bs = random_problems(rng, 300, 3, spread=2e3, sigma=0.15, noise=True)
    r = locate(method, bs)
    assert set(np.unique(r.status)) <= set(STATUSES)
    assert np.array_equal(r.converged, r.status == 'ok')
    ok = r.converged
    assert np.all(np.isfinite(r.position[ok])) and np.all(np.isfinite(r.covariance[ok]))
    assert np.all(np.linalg.eigvalsh(r.covariance[ok])[:, 0] > 0)
    nan_rows = ~np.all(np.isfinite(r.position), axis=1)
    assert np.all(r.status[nan_rows] == 'degenerate_geometry')
    assert r.iterations.shape == (300,) and r.iterations.dtype.kind == 'i'


def test_tls_is_the_smallest_right_singular_vector_of_minus_y_h():
    # Wang, Zhang & Wu (2006) eq. (5): X_TLS = v4(2:4) / v4(1), v4 of [−Y H] (absent elevation
    # rows dropped).
    rng = np.random.default_rng(5)
    _, bs = random_problems(rng, 20, 6, noise=True, sigma=0.02)
    H, Y, mask = pseudo_linear_system(bs)
    r = tls(bs)
    for m in range(bs.M):
        rows = mask[m].reshape(-1)
        C = np.concatenate([-Y[m][..., None], H[m]], axis=-1).reshape(-1, 4)[rows]
        v = np.linalg.svd(C)[2][-1]
        np.testing.assert_allclose(r.position[m], v[1:] / v[0], rtol=1e-9)


@pytest.mark.parametrize('weighting', ['paper', 'am'])
def test_ctls_gradient_and_hessian_match_finite_differences(weighting):
    # Wang, Zhang & Wu (2006) appendix A: T_n and H_n are the derivatives of f of eq. (11)
    # (mixed 1D/2D).
    rng = np.random.default_rng(3)
    tgt, bs = random_problems(rng, 1, 6, spread=5e3, sigma=0.02, noise=True)
    X = tgt + rng.normal(size=(1, 3)) * 300.0
    f, T, Hn, _ = ctls_derivatives(X, bs, weighting)
    assert f[0] == pytest.approx(ctls_cost(X, bs, weighting)[0])
    h = 1e-2
    T_num = np.zeros(3)
    H_num = np.zeros((3, 3))
    for i in range(3):
        e = np.zeros((1, 3))
        e[0, i] = h
        T_num[i] = (ctls_cost(X + e, bs, weighting) - ctls_cost(X - e, bs, weighting))[0] / (2 * h)
        H_num[:, i] = (ctls_derivatives(X + e, bs, weighting)[1]
                       - ctls_derivatives(X - e, bs, weighting)[1])[0] / (2 * h)
    np.testing.assert_allclose(T[0], T_num, rtol=1e-6, atol=1e-8 * np.abs(T_num).max())
    np.testing.assert_allclose(Hn[0], H_num, rtol=1e-5, atol=1e-7 * np.abs(H_num).max())


def test_ctls_am_covariance_is_the_crlb_and_paper_ctls_is_not_smaller():
    # Eq. (30) with G⁻¹ = P_E collapses to [H*ᵀ(H_X P_E H_Xᵀ)⁻¹H*]⁻¹ = J⁻¹; any other
    # weighting (the paper's G) gives a sandwich that is ≥ the CRLB in the PSD sense.
    rng = np.random.default_rng(9)
    tgt, bs = random_problems(rng, 30, 5)
    bound = crlb_for(tgt, bs)
    np.testing.assert_allclose(ctls_covariance(tgt, bs, 'am'), bound, rtol=1e-7)
    P = ctls_covariance(tgt, bs, 'paper')
    assert np.all(np.linalg.eigvalsh(P - bound)[:, 0] > -1e-9 * np.trace(bound, axis1=1,
                                                                         axis2=2))


def test_mle_covariance_is_the_crlb_at_the_estimate():
    rng = np.random.default_rng(13)
    _, bs = random_problems(rng, 25, 6, noise=True, sigma=0.01)
    r = locate('mle', bs)
    np.testing.assert_allclose(r.covariance, crlb_for(r.position, bs), rtol=1e-9)


def test_origin_and_unit_dependence_of_ctls_and_invariance_of_the_others():
    st = seed000_stations()
    tgt = np.array([20e3, 40e3, 5e3])
    rng = np.random.default_rng(21)
    bs = simulate_bearings(np.tile(tgt, (20, 1)), st, 4.5e-3, rng=rng)
    shift = np.array([-300e3, 400e3, 0.0])

    def shifted(scale, origin):
        return BearingSet((bs.positions - origin) / scale, bs.azimuth, bs.elevation,
                          bs.sigma_az, bs.sigma_el)

    # The iterations stop once a step is < 1e-5 standard deviations (~3 mm here): agreement
    # to 1 cm is invariance up to the convergence tolerance.
    for method in ('mle', 'ctls_am', 'wmle'):
        base = locate(method, bs).position
        np.testing.assert_allclose(locate(method, shifted(1.0, shift)).position + shift, base,
                                   rtol=0, atol=1e-2)
        np.testing.assert_allclose(locate(method, shifted(1e3, 0)).position * 1e3, base,
                                   rtol=0, atol=1e-2)
    base = locate('ctls', bs).position
    moved = locate('ctls', shifted(1.0, shift)).position + shift
    # The paper's CTLS moves by a sizeable fraction of its own error (~300 m here).
    assert np.median(np.linalg.norm(moved - base, axis=1)) > 10.0


def test_wmle_estimate_does_not_depend_on_reference_range_only_its_covariance_does():
    # σ(d) = σ_ref d / d_ref scales every weight by the same (d_ref'/d_ref)², so the
    # minimiser of eq. (3) with W of eq. (11) is unchanged; the covariance scales by the
    # inverse factor.
    rng = np.random.default_rng(17)
    _, bs = random_problems(rng, 10, 6, noise=True, sigma=0.01)
    a = locate('wmle', bs, reference_range=1000.0)
    b = locate('wmle', bs, reference_range=4000.0)
    np.testing.assert_allclose(a.position, b.position, rtol=1e-9, atol=1e-5)
    np.testing.assert_allclose(a.covariance, 16.0 * b.covariance, rtol=1e-6)
    np.testing.assert_allclose(a.covariance,
                               noise_model_crlb('wmle', a.position, bs, reference_range=1000.0),
                               rtol=1e-8)
    saz, sel = range_scaled_sigmas(bs, a.position, 1000.0)
    d = np.linalg.norm(a.position[:, None] - bs.positions, axis=-1)
    np.testing.assert_allclose(saz, bs.sigma_az * d / 1000.0)
    assert np.array_equal(np.isnan(sel), ~bs.has_elevation)


def test_mle_handles_azimuth_wrap_behind_the_stations():
    # Target due West of two stations: true azimuths ±π; noisy values straddle the wrap.
    st = np.array([[1000.0, 300.0, 0.0], [1200.0, -400.0, 10.0], [900.0, 50.0, 5.0]])
    tgt = np.array([-5000.0, 0.0, 800.0])
    rng = np.random.default_rng(2)
    bs = simulate_bearings(np.tile(tgt, (200, 1)), st, 0.01, rng=rng)
    assert np.any(bs.azimuth > 3.0) and np.any(bs.azimuth < -3.0)
    r = locate('mle', bs)
    assert np.all(r.converged)
    err = np.linalg.norm(r.position - tgt, axis=1)
    assert np.median(err) < 3 * np.sqrt(np.trace(crlb_for(tgt[None], bs.problem(0))[0]))


def test_mle_from_a_terrible_start_never_increases_cost_into_nan():
    st = seed000_stations()
    tgt = np.array([10e3, 20e3, 5e3])
    bs = simulate_bearings(np.tile(tgt, (50, 1)), st, 3e-3, rng=np.random.default_rng(4))
    starts = np.random.default_rng(5).uniform(-1e6, 1e6, size=(50, 3))
    r = locate('mle', bs, initial=starts, max_iterations=200)
    ok = r.converged
    assert np.all(np.isfinite(r.position[ok]))
    assert np.all(r.status[~ok] != 'ok')
    # Most starts (even 1000 km away) still reach the ML fix near the target.
    assert np.mean(np.linalg.norm(r.position[ok] - tgt, axis=1) < 2e3) * ok.mean() > 0.5


def test_default_estimator_is_registered():
    assert DEFAULT_ESTIMATOR == 'mle' and DEFAULT_ESTIMATOR in ESTIMATORS
    bs = simulate_bearings([1e3, 2e3, 300.0], seed000_stations() / 10, 1e-3)
    assert locate(None, bs).method == DEFAULT_ESTIMATOR


# ---------------------------------------------------------------------------------------------
# Options and bad input


def _one():
    return simulate_bearings([1e3, 2e3, 300.0], seed000_stations() / 10, 1e-3)


@pytest.mark.parametrize('method', ALL)
def test_unknown_option_is_named(method):
    with pytest.raises(ValueError, match=r'^options\.bogus: unknown option'):
        locate(method, _one(), bogus=1)


@pytest.mark.parametrize('kwargs, field', [
    ({'max_iterations': 0}, 'max_iterations'),
    ({'max_iterations': 2.5}, 'max_iterations'),
    ({'tolerance': -1.0}, 'tolerance'),
    ({'tolerance': float('nan')}, 'tolerance'),
    ({'initial': [1.0, 2.0]}, 'initial'),
    ({'initial': [1.0, np.nan, 2.0]}, 'initial'),
])
def test_bad_option_values_are_named(kwargs, field):
    with pytest.raises(ValueError, match=rf'^options\.{field}:'):
        locate('mle', _one(), **kwargs)


def test_method_specific_options():
    with pytest.raises(ValueError, match=r'^options\.reference_range'):
        locate('mle', _one(), reference_range=1000.0)
    with pytest.raises(ValueError, match=r'^options\.reference_range: must be'):
        locate('wmle', _one(), reference_range=0.0)
    with pytest.raises(ValueError, match=r'^options\.step_decay: must be'):
        locate('ctls', _one(), step_decay=1.5)
    r = locate('ctls', _one(), step_decay=0.9, max_iterations=200)
    assert r.converged[0]
    assert locate('ls', _one(), max_iterations=3).converged[0]     # common options accepted
    with pytest.raises(ValueError, match=r'^method: unknown estimator'):
        locate('nope', _one())


def test_initial_option_is_used():
    bs = _one()
    r = locate('mle', bs, initial=[1e3 + 5.0, 2e3 - 5.0, 310.0], max_iterations=1)
    assert r.iterations[0] == 1


def test_degenerate_target_on_baseline_of_two_stations():
    st = np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0]])
    for tgt in ([3000.0, 0.0, 0.0], [500.0, 0.0, 0.0]):
        bs = simulate_bearings(tgt, st, 1e-3)
        for method in ALL:
            r = locate(method, bs)
            assert not r.converged[0], method
            assert r.status[0] == 'degenerate_geometry', method
            assert np.all(np.isnan(r.position[0])) and np.all(np.isinf(r.covariance[0]))


def test_degenerate_parallel_bearings():
    st = np.array([[0.0, 0.0, 0.0], [0.0, 500.0, 0.0], [0.0, -500.0, 0.0]])
    bs = BearingSet.from_arrays(st, [0.0, 0.0, 0.0], [0.1, 0.1, 0.1], 1e-3, 1e-3)
    for method in ALL:
        r = locate(method, bs)
        assert not r.converged[0] and r.status[0] != 'ok', method
        assert not (np.all(np.isfinite(r.position)) and r.converged[0])


@pytest.mark.parametrize('method', ALL)
def test_bad_bearings_raise_value_error(method):
    st = seed000_stations()
    with pytest.raises(ValueError, match='at least two'):
        locate(method, BearingSet.from_arrays(st[:1], [0.1], [0.1], 1e-3, 1e-3,
                                              validate=False))
    fn = ESTIMATORS[method]   # the estimators validate on their own too
    for field, kw in (('azimuth', dict(azimuth=[0.1, np.nan, 0.2])),
                      ('sigma_azimuth', dict(sigma_az=[1e-3, 0.0, 1e-3])),
                      ('sigma_azimuth', dict(sigma_az=[1e-3, -1.0, 1e-3])),
                      ('sigma_elevation', dict(sigma_el=[1e-3, 1e-3, 0.0])),
                      ('position', dict(positions=np.where([[0], [1], [0]], np.nan, st)))):
        args = dict(positions=st, azimuth=[0.1, 0.2, 0.3], elevation=[0.1, 0.1, 0.1],
                    sigma_az=1e-3, sigma_el=1e-3)
        args.update(kw)
        bad = BearingSet.from_arrays(validate=False, **args)
        with pytest.raises(ValueError, match=field):
            fn(bad)


LINE6 = np.array([[x, 0.0, 0.0] for x in (-3000.0, -1800.0, -600.0, 600.0, 1800.0, 3000.0)])


def test_ctls_reports_ok_at_the_optimum():
    # Reproducer: near the optimum the Newton step stayed just above the step tolerance while
    # every trial step changed f only by rounding, and ctls_am reported 'diverged'.
    az = [1.2562628378752143, 1.4816822655121202, 1.836490202495151, 2.085604082097399,
          2.2973901203210922, 2.4230327098401045]
    el = [-0.04270575270023212, -0.04147015854570912, -0.04361847555358538,
          -0.07486902956512079, -0.06399036476559718, -0.03181500347586877]
    s = np.deg2rad(1.0)
    bs = BearingSet.from_arrays(LINE6, az, el, s, s)
    ref = locate('mle', bs)
    assert ref.status[0] == 'ok'
    np.testing.assert_allclose(ref.position[0], [-1609.55, 3940.76, -222.46], atol=0.01)
    info = np.linalg.inv(crlb_for(ref.position, bs)[0])
    for method in ('ctls_am', 'ctls'):
        r = locate(method, bs)
        assert r.status[0] == 'ok' and r.converged[0], method
        loose = locate(method, bs, tolerance=1e-6)
        d = r.position[0] - loose.position[0]
        assert d @ info @ d < 1e-12, method            # the looser run agrees to 1e-6 CRLB σ
    d = locate('ctls_am', bs).position[0] - ref.position[0]
    assert d @ info @ d < 1e-4                          # ctls_am ≈ mle: 1 % of the CRLB σ


@pytest.mark.slow
@pytest.mark.parametrize('sigma_deg', [1.0, 3.0])
def test_ctls_never_reports_a_correct_fix_as_not_converged(sigma_deg):
    # 10^4 trials of the six-station line (targets uniform in the Zong & Cui 2015 box): every
    # ctls / ctls_am fix not reported ok must stay not ok with tolerance=1e-6 (before the
    # rounding stop, 112 of 40,000 fixes were 'diverged'/'max_iterations' at the answer).
    rng = np.random.default_rng([12, int(sigma_deg * 1000)])
    tgt = rng.uniform([-3000.0, 1000.0, -500.0], [3000.0, 7000.0, 500.0], (10000, 3))
    bs = simulate_bearings(tgt, LINE6, np.deg2rad(sigma_deg), rng=rng)
    for method in ('ctls', 'ctls_am'):
        r = locate(method, bs)
        bad = np.flatnonzero(r.status != 'ok')
        if bad.size:
            sub = BearingSet(bs.positions[bad], bs.azimuth[bad], bs.elevation[bad],
                             bs.sigma_az[bad], bs.sigma_el[bad])
            again = locate(method, sub, tolerance=1e-6)
            assert not np.any(again.status == 'ok'), (method, bad[again.status == 'ok'])


@pytest.mark.parametrize('method', ['mle', 'wmle', 'ctls_am'])
def test_one_problem_path_gives_the_batch_paths_results(method):
    # M = 1 runs the iteration on Python floats (core/ml_single.py, core/ctls_single.py); the
    # same problem twice in one batch runs the vectorised iteration. Same statuses,
    # iterations and fixes to rounding, also for starts, iteration limits, azimuth-only
    # stations and N = 2-12.
    rng = np.random.default_rng(21)
    cases = []
    for N in (2, 3, 5, 8, 12):
        _, bs = random_problems(rng, 30, N, noise=True)
        cases += [(bs.problem(m), {}) for m in range(bs.M)]
    _, bs = random_problems(rng, 10, 4, noise=True)
    cases += [(bs.problem(m), {'max_iterations': 1}) for m in range(5)]
    cases += [(bs.problem(m), {'initial': [5e4, -3e4, 9e3], 'tolerance': 1e-6})
              for m in range(5, 10)]
    if method == 'wmle':
        cases = [(b, dict(o, reference_range=700.0)) for b, o in cases]
    if method == 'mle':
        # The paper's iteration on both paths (option robust, on by default, would turn the
        # max_iterations cases into low_confidence refits; tested in test_robust.py).
        cases = [(b, dict(o, robust=False)) for b, o in cases]
    if method == 'ctls_am':
        cases += [(b, dict(o, step_decay=0.8)) for b, o in cases[60:80]]     # N = 5
    statuses = set()
    for one, opts in cases:
        fast = locate(method, one, **opts)
        two = BearingSet(*(np.concatenate([a, a]) for a in (
            one.positions, one.azimuth, one.elevation, one.sigma_az, one.sigma_el)))
        plain = locate(method, two, **opts)
        if opts.get('step_decay', 1.0) < 1.0:
            # μ^n shrinks the steps until trial costs differ only by rounding, so where the
            # iteration ends is decided by rounding; both end at the same point, ok or not.
            assert (fast.status[0] == 'ok') == (plain.status[0] == 'ok')
        else:
            assert fast.status[0] == plain.status[0]
            assert fast.iterations[0] == plain.iterations[0]
        # Both stop within `tolerance` of the optimum (ctls takes its last small step).
        scale = np.max(np.abs(plain.position[0]))
        np.testing.assert_allclose(fast.position[0], plain.position[0], rtol=0,
                                   atol=opts.get('tolerance', 1e-9) * scale)
        np.testing.assert_allclose(fast.covariance[0], plain.covariance[0], rtol=0,
                                   atol=10 * opts.get('tolerance', 1e-10)
                                   * np.max(np.abs(plain.covariance[0])))
        statuses.add(str(fast.status[0]))
    assert {'ok', 'max_iterations'} <= statuses


@pytest.mark.parametrize('method', ['ls', 'tls'])
def test_closed_form_one_problem_path_gives_the_batch_paths_results(method):
    # M = 1 computes ls/tls on Python floats (core/pseudo_linear_single.py); the same problem
    # twice in one batch runs the vectorised closed form. Same statuses (including the
    # consistency check's low_confidence at high noise) and fixes to rounding, for N = 2-12,
    # mixed azimuth-only stations, parallel bearings and a solution on a station (the last
    # two are handed to the batch path).
    from bearing_loc_ros.core.pseudo_linear_single import solve_one
    rng = np.random.default_rng(22)
    cases = []
    for N, sigma in ((2, 2e-3), (3, 2e-3), (5, 2e-2), (8, 0.1), (12, 2e-3)):
        _, bs = random_problems(rng, 40, N, sigma=sigma, noise=True)
        cases += [bs.problem(m) for m in range(bs.M)]
    st = np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0], [2000.0, 0.0, 0.0]])
    cases.append(BearingSet.from_arrays(st[None], np.zeros((1, 3)), np.full((1, 3), 0.1),
                                        np.full((1, 3), 1e-3), np.full((1, 3), 1e-3)))
    cases.append(simulate_bearings([[0.0, 0.0, 0.0]], st + [[0, 0, 0], [0, 0, 0], [1, 2, 3]],
                                   1e-3))
    statuses, fast = set(), 0
    for one in cases:
        fast += solve_one(method, one) is not None
        res = locate(method, one)
        two = locate(method, BearingSet(*(np.concatenate([a, a]) for a in (
            one.positions, one.azimuth, one.elevation, one.sigma_az, one.sigma_el))))
        assert res.status[0] == two.status[0]
        statuses.add(str(res.status[0]))
        if np.all(np.isfinite(two.position[0])):
            np.testing.assert_allclose(res.position[0], two.position[0], rtol=0,
                                       atol=1e-12 * np.max(np.abs(two.position[0])))
            np.testing.assert_allclose(res.covariance[0], two.covariance[0], rtol=0,
                                       atol=1e-11 * np.max(np.abs(two.covariance[0])))
        else:
            assert not np.any(np.isfinite(res.position[0]))
    assert {'ok', 'low_confidence', 'degenerate_geometry'} <= statuses
    assert fast >= 0.95 * (len(cases) - 2)      # the float path, not its fallback, is tested


def test_one_problem_path_hands_ieee_cases_to_the_batch_path():
    # A start on a station's vertical axis divides by zero on floats: the batch path (inf
    # and NaN arithmetic) answers instead, identically to a batch of two.
    st = np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0], [0.0, 1000.0, 0.0]])
    bs = simulate_bearings([[300.0, 400.0, 500.0]], st, 1e-3, rng=np.random.default_rng(2))
    for method in ('mle', 'wmle', 'ctls', 'ctls_am'):
        one = locate(method, bs, initial=[0.0, 0.0, 700.0])
        two = locate(method, BearingSet(*(np.concatenate([a, a]) for a in (
            bs.positions, bs.azimuth, bs.elevation, bs.sigma_az, bs.sigma_el))),
            initial=[0.0, 0.0, 700.0])
        assert one.status[0] == two.status[0]
        np.testing.assert_array_equal(one.position[0], two.position[0])


def _screen_by_definition(data, X, P, c2, probability, max_nu):
    """The robust screen written out plainly: residuals, per-row χ² band, ν from eigvalsh."""
    from bearing_loc_ros.core.robust_model import chi2_band, region_nonlinearity
    ra, re, _, _, _, _, _ = data.evaluate(X)
    qa, qe = ra * ra, re * re
    chi2 = (qa + qe).sum(axis=-1)
    lo, hi = chi2_band(data.az.shape[1] + data.has_el.sum(axis=-1) - 3, probability)
    rho = np.hypot(*(X[:, None, :2] - data.pos[..., :2]).transpose(2, 0, 1))
    nu = region_nonlinearity(P, rho, np.ones_like(rho, dtype=bool))
    with np.errstate(invalid='ignore'):
        calm = ((qa.max(axis=-1) <= c2) & (qe.max(axis=-1) <= c2) & (chi2 >= lo)
                & (chi2 <= hi) & (nu <= max_nu))
    return ~calm


@pytest.mark.parametrize('same_elevations', [True, False])
def test_robust_screen_equals_its_definition(same_elevations):
    # The batch screen (no eigenvalues, reductions through transposed copies) decides as the
    # plain definition: residual outliers, χ² below and above its band, ν on either side of
    # its bound, mixed elevation patterns, and non-finite fixes and covariances.
    from bearing_loc_ros.core import robust
    rng = np.random.default_rng(11)
    M, N = 3000, 5
    _, bs = random_problems(rng, M, N, noise=True, sigma=np.radians(1.0))
    if same_elevations:
        bs = BearingSet.from_arrays(bs.positions, bs.azimuth,
                                    np.where(np.arange(N) % 2 == 0, bs.elevation, np.nan),
                                    bs.sigma_az, bs.sigma_el)
    # Claimed σ 0.3-3 × the true 1°: χ² above, inside and below its band.
    bs.sigma_az[:] = bs.sigma_el[:] = np.radians(rng.uniform(0.3, 3.0, M))[:, None]
    bs.sigma_el[~bs.has_elevation] = np.nan
    # One azimuth 3-8 σ off in a fifth of the rows: single angles around the outlier bound.
    rows = np.flatnonzero(rng.random(M) < 0.2)
    bs.azimuth[rows, 1] += rng.uniform(3.0, 8.0, rows.size) * bs.sigma_az[rows, 1]
    plain = locate('mle', bs, robust=False)
    X, P = plain.position.copy(), plain.covariance.copy()
    # Covariances scaled so that ν spreads on both sides of its bound 0.2.
    P *= np.exp(rng.uniform(-2.0, 7.0, M))[:, None, None]
    X[:5] = [np.nan, 0.0, 0.0]
    X[5:10, 1] = np.inf
    P[10:15, 2, 2] = np.inf
    P[15:20, 0, 1] = P[15:20, 1, 0] = np.nan
    data = robust.Data(bs)
    fast = robust.screen(data, X, P)
    plain_def = _screen_by_definition(data, X, P, robust.outlier_c2(),
                                      robust.CONSISTENCY_PROBABILITY,
                                      robust.MAX_REGION_NONLINEARITY)
    np.testing.assert_array_equal(fast, plain_def)
    assert fast[:20].all()
    assert 0.1 < fast.mean() < 0.9              # both decisions are well represented


def test_cofactor_inverses_match_lapack_or_decline():
    # The covariance of mle/wmle: solvers.spd_inverse3 (batch) and single_floats.inverse3
    # (one fix) use cofactors only for positive definite matrices with tr(A) tr(A⁻¹) ≤ 1e3
    # and then agree with numpy's inverse and with each other bit for bit; the float path
    # declines (None) the others, the batch path hands them to crlb.safe_inverse.
    from bearing_loc_ros.core.crlb import safe_inverse
    from bearing_loc_ros.core.single_floats import inverse3
    from bearing_loc_ros.core.solvers import INVERSE3_MAX_CONDITION, spd_inverse3
    rng = np.random.default_rng(5)
    M = 3000
    Q, _ = np.linalg.qr(rng.standard_normal((M, 3, 3)))
    w = 10.0 ** rng.uniform(-8, 8, (M, 1)) * 10.0 ** rng.uniform(0, 4, (M, 3))
    w[:200, 0] = -w[:200, 0]                        # indefinite
    w[200:300, 0] = 0.0                             # singular
    w[300:310] = [1e-15, 1.0, 1.0]                  # beyond safe_inverse's 1e-12 as well
    A = np.einsum('mij,mj,mkj->mik', Q, w, Q)
    A = 0.5 * (A + np.swapaxes(A, 1, 2))
    A[310:315, 0, 0] = np.nan
    A[315:320, 1, 2] = A[315:320, 2, 1] = np.inf
    batch = spd_inverse3(A)
    with np.errstate(divide='ignore'):
        bound = np.trace(A, axis1=1, axis2=2) * np.sum(1.0 / w, axis=1)
    bound[:320] = np.inf                           # no bound: not positive definite or finite
    answered = 0
    for m in range(M):
        (a00, a01, a02), (_, a11, a12), (_, _, a22) = A[m].tolist()
        got = inverse3(a00, a01, a02, a11, a12, a22)
        if got is None:
            assert not bound[m] < 0.5 * INVERSE3_MAX_CONDITION
            lapack = safe_inverse(A[m:m + 1])[0]
            np.testing.assert_array_equal(np.isinf(batch[m]), np.isinf(lapack))
            np.testing.assert_allclose(batch[m][np.isfinite(lapack)],
                                       lapack[np.isfinite(lapack)], rtol=1e-12)
            continue
        answered += 1
        assert bound[m] < 2.0 * INVERSE3_MAX_CONDITION
        np.testing.assert_array_equal(batch[m], got)
        ref = np.linalg.inv(A[m])
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-11 * np.max(np.abs(ref)))
    assert 300 < answered < 2500
    assert np.all(np.isinf(batch[200:320]))


def test_robust_mle_screens_with_the_iterations_residuals_as_from_the_bearings():
    # mle hands the residual statistics of its last evaluation to the robust screen
    # (screen_decision); the result equals confident_result screening from the bearings
    # (robust.screen), field by field, on calm fixes, outliers, χ² outside the band and
    # large confidence regions.
    from bearing_loc_ros.core.robust import confident_result
    rng = np.random.default_rng(3)
    _, bs = random_problems(rng, 400, 5, noise=True, sigma=np.radians(1.0))
    rows = np.flatnonzero(rng.random(400) < 0.2)
    bs.azimuth[rows, 2] += rng.uniform(3.0, 30.0, rows.size) * bs.sigma_az[rows, 2]
    bs.sigma_az[:] = bs.sigma_el[:] = np.radians(rng.uniform(0.3, 3.0, 400))[:, None]
    bs.sigma_el[~bs.has_elevation] = np.nan
    fast = locate('mle', bs)
    plain = confident_result(locate('mle', bs, robust=False), bs)
    for f in ('position', 'covariance', 'iterations', 'converged', 'status', 'excluded',
              'nonlinearity'):
        np.testing.assert_array_equal(getattr(fast, f), getattr(plain, f), err_msg=f)
    assert 0.05 < np.mean(~np.isnan(fast.nonlinearity)) < 0.95     # both paths taken


@pytest.mark.parametrize('weighting', ['paper', 'am'])
def test_ctls_covariance_is_symmetric_and_paths_agree(weighting):
    # Two stations nearly in line with the target: A of eq. (30) is ill-conditioned and the
    # rounding of A⁻¹BA⁻¹ made P[0, 2] = 989.04 against P[2, 0] = 989.94 (``ctls``, relative
    # asymmetry 8e-5). Symmetrised in the batch path and the one-problem path (ctls_am, M = 1).
    from bearing_loc_ros.core.constrained_tls import constrained_tls
    st = np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0]])
    bs = simulate_bearings([3000.0, 0.0, 200.0], st, 1e-3, rng=np.random.default_rng(5))
    one = constrained_tls(bs, weighting)
    P = one.covariance[0]
    assert one.status[0] == 'ok'
    np.testing.assert_array_equal(P, P.T)
    rep = BearingSet.from_arrays(*(np.repeat(a, 3, axis=0) for a in (
        bs.positions, bs.azimuth, bs.elevation, bs.sigma_az, bs.sigma_el)))
    batch = constrained_tls(rep, weighting)
    np.testing.assert_array_equal(batch.covariance, np.swapaxes(batch.covariance, 1, 2))
    np.testing.assert_allclose(batch.covariance[0], P, rtol=1e-9)
