"""Robust fixes (core.robust), station trust (core.station_trust) and their fusion wiring.

Statistical checks use fixed seeds; bounds come from the statistics (χ² bands, binomial
counts), not from one run.
"""

import math

import numpy as np
import pytest
from scipy import stats

from bearing_loc_ros.core import evaluation as ev
from bearing_loc_ros.core import robust
from bearing_loc_ros.core.bearings import Bearing, BearingSet, simulate_bearings
from bearing_loc_ros.core.conventions import azimuth_elevation
from bearing_loc_ros.core.estimators import locate
from bearing_loc_ros.core.fusion import FusionConfig
from bearing_loc_ros.core.fusion.pipeline import make_core, replay
from bearing_loc_ros.core.simulation import load_scenario, simulate
from bearing_loc_ros.core.station_trust import StationTrust
from bearing_loc_ros.scenarios import resolve_scenario

S = 1_000_000_000
Q9999 = stats.chi2.ppf(0.9999, 3)


def trials(name, n, seed=0):
    return ev.trials_from_scenario(load_scenario(resolve_scenario(name)), n, seed)


def noisy(tr, sigma, seed, outliers=None):
    f = tr.sigma_factor()
    b = ev.noisy_bearings(tr, sigma * f, sigma * f, np.random.default_rng(seed), outliers)
    b.sigma_az = np.full_like(b.sigma_az, sigma)
    b.sigma_el = np.where(b.has_elevation, sigma, np.nan)
    return b


def nees(res, truth, mask):
    e = res.position[mask] - truth[mask]
    return np.einsum('mi,mij,mj->m', e, np.linalg.inv(res.covariance[mask]), e)


def test_calm_fixes_are_the_paper_estimate_and_ok():
    tr = trials('config/scenarios/six_station_const.yaml', 400)
    b = noisy(tr, math.radians(1.0), 1)
    plain = locate('mle', b)
    rob = locate('mle', b, robust=True)
    ok = rob.status == 'ok'
    # a consistent fix fails the 0.999 chi-square test with probability 1e-3: binomial bound
    assert ok.mean() >= 1 - stats.binom.ppf(0.9999, 400, 0.002) / 400
    calm = ok & ~np.any(rob.excluded, axis=(1, 2))
    same = np.all(rob.position[calm] == plain.position[calm], axis=1)
    assert same.mean() > 0.95
    n = nees(rob, tr.targets, ok)
    half = stats.norm.ppf(0.995) * math.sqrt(6.0 / n.size)
    assert abs(n.mean() - 3.0) < half * 1.5        # chi2_3 mean band (x1.5: nonlinearity)
    assert np.mean(n > Q9999) < 0.003


def test_outlier_bearings_are_excluded_and_named():
    tr = trials('config/scenarios/six_station_const.yaml', 300)
    sigma = math.radians(1.0)
    clean = locate('mle', noisy(tr, sigma, 2), robust=True)
    b = noisy(tr, sigma, 2, (0.1, math.radians(20), math.radians(90)))
    rob = locate('mle', b, robust=True)
    plain = locate('mle', b)
    ok = rob.status == 'ok'
    rmse_ok = np.sqrt(np.mean(np.sum((rob.position[ok] - tr.targets[ok]) ** 2, axis=1)))
    rmse_clean = np.sqrt(np.mean(np.sum((clean.position - tr.targets) ** 2, axis=1)))
    rmse_plain = np.sqrt(np.nanmean(np.sum((plain.position - tr.targets) ** 2, axis=1)))
    assert ok.mean() > 0.9
    assert rmse_ok < 1.3 * rmse_clean < rmse_plain
    # the excluded azimuths are the outliers: truth residual > 20 deg
    az_true, _ = azimuth_elevation(tr.targets[:, None, :] - tr.stations)
    big = np.abs(np.angle(np.exp(1j * (b.azimuth - az_true)))) > math.radians(15)
    exc = rob.excluded[..., 0][ok]
    assert np.all(exc[big[ok]])                     # every gross azimuth outlier excluded
    assert exc[~big[ok]].mean() < 0.01              # few good azimuths lost


def test_many_stations_in_one_problem_keep_a_bounded_consensus():
    # Leaving out each pair of N stations made N²/2 candidates scored over N stations: 3 GB
    # and 11 s at N = 400, a MemoryError at N = 1000. Above MAX_SUBSET_STATIONS the
    # candidates are the pairs of 16 spread stations, and one reflection is still named.
    from bearing_loc_ros.core.robust_consensus import _station_masks, MAX_SUBSET_STATIONS
    assert _station_masks(MAX_SUBSET_STATIONS).shape == (137, 16)      # 1 + 16 + 120
    masks = _station_masks(600)
    assert masks.shape == (121, 600) and set(masks[1:].sum(axis=1)) == {2.0}
    rng = np.random.default_rng(5)
    st = rng.uniform(-1e4, 1e4, (600, 3))
    st[:, 2] = 0.0
    b = simulate_bearings(np.array([[500.0, 700.0, 300.0]]), st, 0.01, rng=rng)
    b.azimuth[0, 0] += 0.5                                          # a 50σ reflection
    for one in (b, BearingSet(*(np.concatenate([a, a]) for a in (
            b.positions, b.azimuth, b.elevation, b.sigma_az, b.sigma_el)))):
        r = locate('mle', one)
        assert list(r.status) == ['ok'] * one.M
        assert np.flatnonzero(r.excluded[0, :, 0]).tolist() == [0]
        e = r.position - [500.0, 700.0, 300.0]         # within the χ²₃ 0.9999 ellipsoid
        assert np.all(np.einsum('mi,mij,mj->m', e, np.linalg.inv(r.covariance), e) < 21.1)


def test_wmle_never_runs_away_in_range():
    tr = trials('config/scenarios/seed003.yaml', 300)
    b = noisy(tr, math.radians(4.0), 3)
    plain = locate('wmle', b)
    rob = locate('wmle', b, robust=True)
    err_p = np.linalg.norm(plain.position - tr.targets, axis=1)
    err_r = np.linalg.norm(rob.position - tr.targets, axis=1)
    fixed = np.isin(rob.status, ('ok', 'low_confidence'))
    assert fixed.mean() > 0.95 and np.all(np.isfinite(err_r[fixed]))
    assert np.sqrt(np.mean(err_r[fixed] ** 2)) < np.sqrt(np.mean(err_p[fixed] ** 2))
    assert err_r[fixed].max() < 15e3          # the box spans ~9 km from the farthest station
    ok = rob.status == 'ok'
    if ok.any():
        assert np.mean(nees(rob, tr.targets, ok) > Q9999) < 0.05


def test_assess_flags_inconsistent_residuals():
    tr = trials('config/scenarios/six_station_const.yaml', 50)
    b = noisy(tr, math.radians(1.0), 4)
    b.sigma_az = b.sigma_az / 10.0         # a claim 10x too good: chi2 ~ 100 x dof
    b.sigma_el = b.sigma_el / 10.0
    rob = locate('mle', b, robust=True)
    assert np.mean(rob.status != 'ok') >= 0.85     # single fixes; the trust learns the rest


def test_nonlinearity_is_range_sigma_over_range():
    P = np.diag([1.0, 100.0 ** 2, 1.0])[None]
    u = np.array([[[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]])
    d = np.array([[1000.0, 2000.0]])
    nu = robust.nonlinearity(P, u, d, np.ones((1, 2), dtype=bool))
    assert nu[0] == pytest.approx(0.1)


def test_station_trust_inputs():
    with pytest.raises(ValueError, match='window'):
        StationTrust(window=0)
    with pytest.raises(ValueError, match='sigma_floor'):
        StationTrust(sigma_floor=-1.0)
    t = StationTrust(sigma_floor=1e-3, floors={'a': 5e-3})
    b = Bearing(station='a', stamp_ns=0, position=np.zeros(3), azimuth=0.1, elevation=0.1,
                sigma_azimuth=1e-4, sigma_elevation=1e-4)
    e = t.effective(b)
    assert e.sigma_azimuth == 5e-3 and e.sigma_elevation == 5e-3
    assert t.effective(b, 0.0).sigma_azimuth == 5e-3


TARGET = np.array([2500.0, 3000.0, 800.0])
POS = np.array([[0.0, 0.0, 0.0], [5000.0, 0.0, 20.0], [0.0, 6000.0, 40.0],
                [6000.0, 6000.0, 10.0], [-2000.0, 3000.0, 0.0]])
SIG = 3e-3


def spoof(off_deg, claim, fake=0.0, epochs=30, seed=0):
    """Four honest stations (σ = 3 mrad) and a liar s5 (bias, tiny claimed σ, fake position)."""
    rng = np.random.default_rng(seed)
    names = [f's{i + 1}' for i in range(5)]
    core = make_core(FusionConfig(trigger='timer', rate=1.0, max_latency=0.5), stations=names)
    items = []
    for k in range(epochs):
        t = (k + 1) * S
        for i, p in enumerate(POS):
            az, el = azimuth_elevation(TARGET - p)
            az, el = az + SIG * rng.standard_normal(), el + SIG * rng.standard_normal()
            liar = i == 4
            pos = p + np.array([fake, 0.0, 0.0]) if liar else p.copy()
            az += math.radians(off_deg) if liar else 0.0
            s = claim if liar else SIG
            items.append((t, Bearing(station=names[i], stamp_ns=t, position=pos,
                                     azimuth=float(az), elevation=float(el), sigma_azimuth=s,
                                     sigma_elevation=s)))
    items.append(((epochs + 3) * S, None))
    eps = list(replay(core, items))
    return eps, core.diagnostics((epochs + 3) * S)[0].values


@pytest.mark.parametrize('off_deg,claim,fake', [(0.5, 3e-4, 0.0), (1.0, 1e-5, 0.0),
                                                (5.0, 1e-6, 0.0), (0.0, 1e-5, 600.0)])
def test_a_lying_station_is_named_and_never_makes_a_confident_wrong_fix(off_deg, claim, fake):
    eps, diag = spoof(off_deg, claim, fake)
    ok = [e for e in eps if e.ok]
    assert len(ok) >= 25                                    # the honest four keep fixing
    for e in ok:
        d = e.position - TARGET
        assert d @ np.linalg.solve(e.covariance, d) < Q9999
        assert {'s1', 's2', 's3', 's4'} <= set(e.stations)  # honest stations never dropped
    assert diag['suspect_stations'] == 's5'


def test_honest_network_names_no_suspect():
    eps, diag = spoof(0.0, SIG)
    assert diag['suspect_stations'] == ''
    assert sum(e.ok for e in eps) >= 28


def test_evaluate_completes_at_ten_degrees_and_reports_statuses():
    from bearing_loc_ros.cli.evaluate import run_evaluation
    rows, meta = run_evaluation('config/scenarios/seed003.yaml', ['ls', 'wmle'], [10.0], 40,
                                sweep='none', robust=True, outliers=(0.1, 0.35, 1.57))
    assert meta['robust'] and len(rows) == 2
    for r in rows:
        total = r.ok_fraction + r.low_confidence_fraction + r.other_fraction
        assert total == pytest.approx(1.0)
        assert math.isfinite(r.p95_error) or r.converged == 0


def test_consistency_covers_the_bias_of_pseudo_linear_fixes():
    # ls at 5° on the six stations is biased (a mean error of 345 m in an RMSE of 710 m
    # here); its own covariance left 18 of 1985 ok fixes (0.9 %) confidently wrong, P + δδᵀ
    # leaves 5. At the acceptance rate of 0.1 % the count is Poisson(2): 8 or more has
    # probability 0.0011, so the bound fails a rate beyond the acceptance, not chance.
    from bearing_loc_ros.cli.evaluate import run_evaluation
    rows, _ = run_evaluation('six_station_const', ['ls'], [5.0], 2000, sweep='none')
    (r,) = rows
    assert r.ok_fraction > 0.98
    assert r.confident_wrong_fraction * r.ok_fraction * 2000 < 8


def test_one_fix_screen_and_lambda_max_agree_with_the_batch_screen():
    tr = trials('config/scenarios/six_station_const.yaml', 200)
    rng = np.random.default_rng(7)
    b = noisy(tr, math.radians(2.0), 5, (0.05, math.radians(5), math.radians(30)))
    plain = locate('mle', b, robust=False)
    data = robust.Data(b)
    batch = robust.screen(data, plain.position, plain.covariance)
    one = [robust.screen_one(b.problem(m), plain.position[m].tolist(), None,
                             plain.covariance[m]) for m in range(b.M)]
    assert batch.any() and not batch.all()
    assert list(batch) == one
    for _ in range(200):
        A = rng.standard_normal((3, 3)) * 10.0 ** rng.uniform(-3, 6)
        A = A @ A.T if rng.random() < 0.8 else np.diag(rng.uniform(0, 5, 3))
        lam = np.linalg.eigvalsh(A)[-1]
        assert robust._lambda_max(A.tolist()) == pytest.approx(lam, rel=1e-9, abs=1e-12 * lam)


def test_consensus_inverse_equals_safe_inverse_around_its_rank_threshold():
    # The ls candidates' rank test uses closed-form eigenvalues where they are clear: the
    # same decisions and the same inverse as crlb.safe_inverse, also for eigenvalue ratios
    # across rcond = 1e-12.
    from bearing_loc_ros.core.crlb import safe_inverse
    from bearing_loc_ros.core.robust_consensus import _psd_inverse
    rng = np.random.default_rng(3)
    B = rng.standard_normal((2000, 3, 3)) * 10.0 ** rng.uniform(-3, 4, (2000, 1, 1))
    spd = B @ B.transpose(0, 2, 1)
    v = rng.standard_normal((500, 3, 2))
    rank2 = v @ v.transpose(0, 2, 1)
    U = np.linalg.qr(rng.standard_normal((3000, 3, 3)))[0]
    lam = np.stack([np.ones(3000), 10.0 ** rng.uniform(-14, -10, 3000), np.full(3000, 3.0)],
                   axis=-1)
    near = np.einsum('mij,mj,mkj->mik', U, lam, U)
    near = 0.5 * (near + near.transpose(0, 2, 1))
    # Nearly rank one (the two smallest eigenvalues close: where the closed form is least
    # accurate, about sqrt(eps) of the largest).
    lam1 = np.stack([10.0 ** rng.uniform(-14, -7, 3000), 10.0 ** rng.uniform(-14, -7, 3000),
                     np.ones(3000)], axis=-1)
    rank1 = np.einsum('mij,mj,mkj->mik', U, lam1, U)
    rank1 = 0.5 * (rank1 + rank1.transpose(0, 2, 1))
    bad = spd[:40].copy()
    bad[:20, 1, 2] = np.nan
    bad[20:, 0, 0] = -bad[20:, 0, 0]
    scaled = np.eye(3) * np.array([0.0, 1e-3, 2.0, 7.0])[:, None, None]
    for A in (spd, rank2, near, rank1, bad, scaled):
        fast, ref = _psd_inverse(A), safe_inverse(A)
        assert np.array_equal(fast, ref, equal_nan=True)
    assert 0 < np.isinf(_psd_inverse(near)[:, 0, 0]).sum() < len(near)


def assert_one_fix_equals_batch(one, batch, m, stations):
    """A one-problem robust result equals row m of the batch result.

    Statuses and exclusions exactly. Positions within 1e-9 of the rms station range: the
    refit stops at a step below 1e-10 of it, and accepts steps within the rounding of its
    cost (robust_consensus.ACCEPT_TOL), so both runs iterate to the same optimum (measured
    ≤ 6.1e-11; with a strict cost comparison they stopped up to 7.3e-9 apart). Covariance
    (the inverse information at that point, widened for range-grown σ) and ν follow to
    1e-8 relative (measured ≤ 4.7e-10).
    """
    assert one.status[0] == batch.status[m]
    assert one.converged[0] == batch.converged[m]
    assert np.array_equal(one.excluded[0], batch.excluded[m])
    x, y = one.position[0], batch.position[m]
    if not np.all(np.isfinite(y)):
        assert np.array_equal(np.isfinite(x), np.isfinite(y))
        return
    scale = np.sqrt(np.mean(np.sum((y - stations) ** 2, axis=1)))
    np.testing.assert_allclose(x, y, rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(one.nonlinearity[0], batch.nonlinearity[m], rtol=1e-8)
    C, D = one.covariance[0], batch.covariance[m]
    if np.all(np.isfinite(D)) and np.isfinite(batch.nonlinearity[m]):
        # (ν NaN: the estimator's own fix was kept, with its own covariance.)
        np.testing.assert_allclose(C, D, rtol=0, atol=1e-8 * np.abs(D).max())


def test_robust_one_fix_path_gives_the_batch_result():
    tr = trials('config/scenarios/six_station_const.yaml', 60)
    b = noisy(tr, math.radians(3.0), 6, (0.1, math.radians(20), math.radians(90)))
    batch = locate('mle', b)                       # robust is the default of mle
    for m in range(b.M):
        assert_one_fix_equals_batch(locate('mle', b.problem(m)), batch, m, b.positions[m])


@pytest.mark.parametrize('sigma, outliers', [(1.0, None), (1.5, 0.1)])
def test_robust_wmle_one_fix_float_path_gives_the_batch_result(sigma, outliers):
    # Every robust wmle fix goes through steps 2-4; one problem per call runs them on
    # floats (core.robust_single), a batch on arrays: the same fixes, statuses, exclusions.
    from bearing_loc_ros.core import robust_single
    tr = trials('config/scenarios/seed003.yaml', 50)
    out = None if outliers is None else (outliers, math.radians(20), math.radians(90))
    b = noisy(tr, math.radians(sigma), 9, out)
    batch = locate('wmle', b, robust=True)
    statuses = set()
    floats = 0
    for m in range(b.M):
        one = b.problem(m)
        assert_one_fix_equals_batch(locate('wmle', one, robust=True), batch, m, b.positions[m])
        statuses.add(str(batch.status[m]))
        try:
            robust_single.refine(one, locate('wmle', one).position[0].tolist(), 1000.0)
            floats += 1
        except robust_single.Fallback:
            pass
    assert {'ok', 'low_confidence'} <= statuses
    assert floats >= 0.9 * b.M                  # the float path, not its fallback, is tested


def test_ill_conditioned_information_is_inverted_as_on_the_batch_path(monkeypatch):
    # Far targets and nearly collinear stations (σ 0.3-100 mrad, 15 % outliers) give Fisher
    # information that the closed forms cannot certify (κ possibly above 1e5): up to κ = 1e7
    # the compiled one-fix path inverts it with numpy's LAPACK, as the batch path does
    # (robust_single.MAX_CONDITION), instead of handing the fix to the batch path. The same
    # statuses, exclusions and fixes as the problem solved in a batch of two.
    from bearing_loc_ros.core import robust_single
    used = []
    real = robust_single._numpy_safe_inverse

    def counting(A):
        out = real(A)
        used.append(out[1])
        return out
    monkeypatch.setattr(robust_single, '_numpy_safe_inverse', counting)
    rng = np.random.default_rng(5)
    for k in range(60):
        n = int(rng.integers(3, 11))
        base = 10 ** rng.uniform(2, 3.5)
        if k % 2:
            t = rng.uniform(-base, base, n)
            xy = np.column_stack([t, 0.3 * t + rng.normal(0, base * 1e-3, n)])
        else:
            xy = rng.uniform(-base, base, (n, 2))
        pos = np.column_stack([xy, rng.uniform(0, 30, n)])
        r, ang = base * 10 ** rng.uniform(0.5, 3), rng.uniform(0, 2 * math.pi)
        d = np.array([r * math.cos(ang), r * math.sin(ang), rng.uniform(0, 0.2) * r]) - pos
        s = 10 ** rng.uniform(-3.5, -1)
        az = np.arctan2(d[:, 1], d[:, 0]) + rng.normal(0, s, n)
        el = np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])) + rng.normal(0, s, n)
        out = rng.random(n) < 0.15
        az[out] += rng.uniform(0.3, 1.5, out.sum()) * rng.choice([-1, 1], out.sum())
        el[1::3] = np.nan
        one = BearingSet.from_arrays(pos, az, el, s, s)
        two = BearingSet(*(np.concatenate([a, a]) for a in (
            one.positions, one.azimuth, one.elevation, one.sigma_az, one.sigma_el)))
        for name, opts in (('wmle', {'robust': True}), ('mle', {})):
            assert_one_fix_equals_batch(locate(name, one, **opts), locate(name, two, **opts),
                                        0, pos)
    assert sum(used) >= 20          # the LAPACK inverse ran (κ in (1e5, 1e7])


def test_robust_one_fix_fallback_is_the_batch_path(monkeypatch):
    # Where the floats cannot follow the batch path (robust_single.Fallback), the one-fix
    # call runs the vectorised steps: the batch result.
    from bearing_loc_ros.core import robust_single

    def fallback(*args, **kwargs):
        raise robust_single.Fallback('test')

    tr = trials('config/scenarios/seed003.yaml', 20)
    b = noisy(tr, math.radians(2.0), 4, (0.1, math.radians(20), math.radians(90)))
    batch = locate('wmle', b, robust=True)
    monkeypatch.setattr(robust_single, 'refine', fallback)
    for m in range(b.M):
        assert_one_fix_equals_batch(locate('wmle', b.problem(m), robust=True), batch, m,
                                    b.positions[m])


def test_low_snr_ok_fixes_are_never_grossly_wrong_and_nothing_runs_away():
    # Zong & Cui 2015 geometry at sigma_ref 4-5 deg: a subset of stations can fit a wrong
    # point near the stations (small range-grown sigma) and exclude good bearings. No ok
    # fix may be off by more than NEES 100 (chi2_3 probability ~1e-20), and no fix keeps the
    # paper iteration's max_iterations/diverged status (the run-aways are refitted).
    tr = trials('config/scenarios/seed003.yaml', 300)
    for sigma, seed in ((4.0, 11), (5.0, 12)):
        b = noisy(tr, math.radians(sigma), seed)
        rob = locate('wmle', b, robust=True)
        assert not np.isin(rob.status, ('max_iterations', 'diverged')).any()
        ok = rob.status == 'ok'
        if ok.any():
            assert nees(rob, tr.targets, ok).max() < 100.0
        fixed = np.isin(rob.status, ('ok', 'low_confidence'))
        err = np.linalg.norm(rob.position[fixed] - tr.targets[fixed], axis=1)
        assert err.max() < 15e3


def test_test_inversion_widens_only_the_major_axis():
    tr = trials('config/scenarios/seed003.yaml', 50)
    b = noisy(tr, math.radians(1.0), 13)
    data = robust.Data(b, 1000.0)
    X = tr.targets
    wa = np.ones_like(b.azimuth)
    we = b.has_elevation.astype(float)
    _, _, ga, ge, _, _, _ = data.evaluate(X)
    P = np.linalg.inv(robust.fisher(ga, ge, wa, we))
    W = robust.test_inversion_covariance(data, X, wa, we, P)
    D = W - P
    w = np.linalg.eigvalsh(D)
    scale = np.linalg.eigvalsh(P)[:, -1]
    assert np.all(w[:, :2] > -1e-9 * scale[:, None]) and np.all(w[:, :2] < 1e-9 * scale[:, None])
    assert np.all(w[:, 2] > 0)                     # the far side is always longer
    lam, V = np.linalg.eigh(P)
    u = np.linalg.eigh(D)[1][:, :, 2]
    assert np.all(np.abs(np.einsum('mi,mi->m', u, V[:, :, 2])) > 1 - 1e-6)


def test_range_grown_status_looks_at_the_region_of_a_confidently_wrong_fix():
    # wmle robust: the covariance is widened to the test-inversion level TEST_INVERSION_Z,
    # while ν (which decides ok) is taken over the region out to the confidently wrong
    # level STATUS_REGION_Z = sqrt(χ²₃ 0.9999 quantile), which is wider.
    from bearing_loc_ros.core.crlb import safe_inverse
    assert robust.STATUS_REGION_Z == pytest.approx(math.sqrt(Q9999), rel=1e-9)
    tr = trials('config/scenarios/seed003.yaml', 300)
    b = noisy(tr, math.radians(1.0), 17)
    res = locate('wmle', b, robust=True, reference_range=1000.0)
    fixed = np.isin(res.status, ('ok', 'low_confidence')) & np.isfinite(res.nonlinearity)
    idx = np.flatnonzero(fixed)
    data = robust.Data(b, 1000.0).take(idx)
    X = res.position[idx]
    wa = 1.0 - res.excluded[idx, :, 0]
    we = b.has_elevation[idx] & ~res.excluded[idx, :, 1]
    _, _, ga, ge, _, _, _ = data.evaluate(X)
    P0 = safe_inverse(robust.fisher(ga, ge, wa, we))
    cov = robust.test_inversion_covariance(data, X, wa, we, P0)
    np.testing.assert_allclose(res.covariance[idx], cov, rtol=1e-9,
                               atol=1e-9 * np.abs(cov).max())
    present = (wa + we) > 0
    rho = robust.horizontal_ranges(data, X)
    wide = robust.region_nonlinearity(
        robust.test_inversion_covariance(data, X, wa, we, P0, z=robust.STATUS_REGION_Z),
        rho, present)
    np.testing.assert_allclose(res.nonlinearity[idx], wide, rtol=1e-9)
    narrow = robust.region_nonlinearity(cov, rho, present)
    limit = robust.MAX_REGION_NONLINEARITY_GROWN
    # (Where the region has no far side both are capped at 10 × the largest range, and ν is
    # far above the limit in both.)
    assert np.all((wide >= narrow) | (np.minimum(wide, narrow) > 10 * limit))
    assert np.all(res.nonlinearity[res.status == 'ok'] <= limit)
    # The wider region decides: fixes whose covariance alone would pass are held back.
    assert np.count_nonzero((narrow <= limit) & (wide > limit)) >= 10
    assert np.all(res.status[idx[wide > limit]] == 'low_confidence')


def test_an_honest_three_station_network_is_never_scaled():
    # Wang, Zhang & Wu (2006) section 4 track: three honest stations (σ = 3 mrad as claimed).
    # With three stations the others' fix is weak (J P_(−k) Jᵀ up to ~100× the claimed
    # variance), so one excess sample scatters by ~±100× the claim; a scale must come only
    # from a window whose Σ d² exceeds its χ² 0.9999 quantile. Bound: s_k = 1 at every epoch
    # for every station (false alarm ≤ 1e-4 per station and epoch: ≤ 1.5 % over the 150
    # windows of this run, a fixed seed). The mean NEES of the 50 fixes (χ²_3 each,
    # independent noise) stays in the two-sided 99 % band χ²_150(0.005, 0.995) / 50.
    sc = load_scenario(resolve_scenario('seed000'))
    sim = simulate(sc, seed=0)
    names = sorted({e.bearing.station for e in sim.bearings})
    core = make_core(FusionConfig(), stations=names)
    trust = core.strategy.trust
    items = [(e.publish_ns, e.bearing) for e in sim.bearings] + [(sim.end_ns + 5 * S, None)]
    origin = round(sc.epoch * S)
    nees_values = []
    for e in replay(core, items):
        assert all(trust.scale(s) == 1.0 for s in names), (e.stamp_ns, trust.suspects())
        if e.ok:
            d = e.position - sc.targets[0].trajectory.position((e.stamp_ns - origin) / S)
            nees_values.append(d @ np.linalg.solve(e.covariance, d))
    n = len(nees_values)
    assert n >= 45
    lo, hi = stats.chi2.ppf([0.005, 0.995], 3 * n) / n
    assert lo < np.mean(nees_values) < hi
    assert trust.suspects() == []


def test_a_second_likelihood_optimum_makes_the_fix_low_confidence():
    # Zong & Cui 2015 geometry, σ_ref 5° (σ ≈ 30° at the target's range): the consensus
    # fits a point 0.85 km from the first station, 5.7 km short of the target at 6.2 km,
    # with a stated σ of 70 m (NEES 1e4). Refitted from the all-station ls fix, the full
    # likelihood has a second optimum near the target within the χ²₃ 0.9999 level, so
    # the likelihood-ratio region is not one ellipsoid: the fix is low_confidence.
    st = [[x, 0.0, 0.0] for x in (-3000.0, -1800.0, -600.0, 600.0, 1800.0, 3000.0)]
    az = [0.7026255418992083, 2.425751758640569, 2.4261049246351116, 3.043947805226523,
          2.2796326108613902, 2.874134103930627]
    el = [0.16608491878698725, 0.4565480201255526, 0.28166733688361356,
          -0.1725605113899137, 0.36163124914715694, -0.8687525105998355]
    s = math.radians(5.0)
    bs = BearingSet.from_arrays(st, az, el, s, s)
    res = locate('wmle', bs, robust=True, reference_range=1000.0)
    assert res.status[0] == 'low_confidence'
    data = robust.Data(bs, 1000.0)
    X = res.position
    wa = (~res.excluded[:, :, 0]).astype(float)
    we = ((~res.excluded[:, :, 1]) & bs.has_elevation).astype(float)
    assert robust.second_optimum(data, X, wa, we, res.covariance)[0]


def test_an_exclusion_that_does_not_hold_up_keeps_every_angle():
    # Wang, Zhang & Wu (2006) geometry at 1.5 mrad, a target ~100 km from the third station.
    # The paper's fix is 232 m from the target, its residual χ² above the 0.999 quantile,
    # so it goes to the consensus, which drops the third azimuth and lands 6 km off; that
    # exclusion is not decisive given the fix's own uncertainty. The fix must be the fit of
    # all the angles (the paper's optimum), low_confidence, with nothing excluded: on both
    # the one-problem path and the batch path.
    st = [[30000.0, -10000.0, 100.0], [30000.0, 20000.0, 200.0], [-30000.0, 5000.0, 150.0]]
    az = [-1.3079956163858633, -1.4047762498633978, -0.7551671248325064]
    el = [0.08783991355554505, 0.05127811008148017, 0.04564903037848992]
    truth = np.array([44610.0, -64850.0, 5000.0])
    one = BearingSet.from_arrays(st, az, el, 1.5e-3, 1.5e-3)
    paper = locate('mle', one, robust=False)
    assert paper.status[0] == 'ok'
    assert np.linalg.norm(paper.position[0] - truth) < 300.0
    two = BearingSet.from_arrays([st, st], [az, az], [el, el], 1.5e-3, 1.5e-3)
    for res in (locate('mle', one), locate('mle', two)):
        assert list(res.status) == ['low_confidence'] * res.position.shape[0]
        assert not res.excluded.any()
        # Both are the optimum of the same likelihood: equal within the LM's stopping
        # resolution (1e-10 of the rms range, ~70 km here).
        assert np.abs(res.position - paper.position[0]).max() < 1e-4
        e = res.position[0] - paper.position[0]
        assert e @ np.linalg.solve(paper.covariance[0], e) < 1e-6


def test_a_refit_of_all_angles_that_runs_out_in_range_is_not_kept():
    # Zong & Cui (2015) stations, σ_ref 4° in azimuth (0.5° in elevation): at the target's
    # 7 km range σ_az is 28°. The consensus excludes four azimuths; of the two refits of all
    # the angles, the one from the ls fix (on the baseline) leapt out to ~660 km and was
    # still on its way back when its iterations ended, 613 km out, at a slightly lower L
    # than the fit near the stations, with a χ² of 0.01 (σ(d) there covers any residual),
    # which passed the one-sided test. That run-away must not become the fix.
    st = [[x, 0.0, 0.0] for x in (-3000.0, -1800.0, -600.0, 600.0, 1800.0, 3000.0)]
    az = [1.60033800895946, 0.7013971710063017, 1.3818240234112038, 1.125059953616121,
          0.5667370426002434, 2.7768640412100893]
    el = [-0.06115676527375999, -0.0023071349490102824, 0.010833181589108887,
          0.05905812628858506, -0.009618005948192669, 0.001306786674582075]
    sa, se = math.radians(4.0), math.radians(0.5)
    one = BearingSet.from_arrays(st, az, el, sa, se)
    two = BearingSet.from_arrays([st, st], [az, az], [el, el], sa, se)
    got = [locate('wmle', b, robust=True, reference_range=1000.0) for b in (one, two)]
    for res in got:
        assert res.status[0] == 'low_confidence'
        assert np.linalg.norm(res.position[0]) < 10e3      # the stations span ±3 km
    assert np.abs(got[0].position[0] - got[1].position[0]).max() < 1e-6


def test_second_optimum_check_is_silent_at_moderate_snr():
    # Six stations, constant σ 2°: the likelihood has one optimum over the region, so the
    # check (level 1e-4 per fix) flags none of 300 fixes (expected count ≤ 0.03).
    tr = trials('config/scenarios/six_station_const.yaml', 300)
    b = noisy(tr, math.radians(2.0), 21)
    res = locate('mle', b, robust=False)
    data = robust.Data(b)
    wa = np.ones_like(b.azimuth)
    we = b.has_elevation.astype(float)
    assert not robust.second_optimum(data, res.position, wa, we, res.covariance).any()


@pytest.mark.parametrize('scenario,estimator,sigma_deg,seed', [
    ('config/scenarios/six_station_const.yaml', 'mle', 4.0, 31),
    ('config/scenarios/seed003.yaml', 'wmle', 1.0, 32)])
def test_confidently_wrong_ok_fixes_are_rarer_than_a_tenth_of_a_percent(scenario, estimator,
                                                                        sigma_deg, seed):
    # Acceptance criterion of the robust fixes: among ok fixes, NEES above the χ²₃ 0.9999
    # quantile below 0.1 %. 2000 trials: the count of such fixes must not be significantly
    # above what a rate of 1e-3 gives (Poisson, one-sided 1 %); the measured rate is 4e-4.
    tr = trials(scenario, 2000, seed)
    b = noisy(tr, math.radians(sigma_deg), seed)
    opts = {'reference_range': 1000.0} if estimator == 'wmle' else {}
    res = locate(estimator, b, robust=True, **opts)
    ok = res.status == 'ok'
    assert ok.sum() > 200
    k = int(np.count_nonzero(nees(res, tr.targets, ok) > Q9999))
    assert stats.poisson.sf(k - 1, 1e-3 * ok.sum()) > 0.01, (k, ok.sum())


def test_lambda_max_of_huge_or_tiny_covariances_is_lapacks():
    # The closed-form cubic overflows (1e110 m²) or divides by an underflowed r³ (1e-110 m²);
    # the screen must then get LAPACK's eigenvalue, not an exception.
    from bearing_loc_ros.core.robust import _lambda_max
    for scale in (1e110, 1e-110, 1.0):
        m = np.array([[1.0, 0.1, 0.0], [0.1, 2.0, 0.0], [0.0, 0.0, 1.0]]) * scale
        assert _lambda_max(m.tolist()) == pytest.approx(np.linalg.eigvalsh(m)[-1], rel=1e-12)
    assert math.isnan(_lambda_max([[1e300, 0.0, 1e300], [0.0, math.inf, 0.0],
                                   [1e300, 0.0, 1.0]]))


def test_a_singular_problem_does_not_change_the_refit_of_the_others_in_its_batch():
    # np.linalg.solve raises for the whole batch when one information matrix is singular;
    # the other problems' refit must still be what each gives alone (bit for bit).
    from bearing_loc_ros.core import robust_consensus
    st = [[x, 0.0, 0.0] for x in (-3000.0, -1800.0, -600.0, 600.0, 1800.0, 3000.0)]
    truth = np.array([[400.0, 4000.0, 200.0], [-900.0, 2500.0, -100.0]])
    az, el = azimuth_elevation(truth[:, None, :] - np.array(st))
    rng = np.random.default_rng(3)
    s = math.radians(1.0)
    bs = BearingSet.from_arrays([st, st], az + s * rng.standard_normal(az.shape),
                                el + s * rng.standard_normal(el.shape), s, s)
    for d_ref in (None, 1000.0):
        data = robust.Data(bs, d_ref)
        X0 = truth + 300.0
        wa = np.ones((2, 6))
        we = np.ones((2, 6))
        wa[1] = we[1] = 0.0            # no angle kept: a zero information matrix
        both = robust_consensus._refit(data, X0, wa, we)
        alone = robust_consensus._refit(data.take([0]), X0[:1], wa[:1], we[:1])
        assert np.array_equal(both[0], alone[0])
        assert np.linalg.norm(alone[0] - X0[0]) > 1.0     # it did move


@pytest.mark.parametrize('d_ref', [None, 1000.0])
def test_batch_refit_gives_each_problem_its_own_result(d_ref):
    # The batch refit drops the problems it has finished from its arrays; each problem's
    # result must still be, to the bit, what the refit of that problem alone gives (slow
    # and fast problems mixed: σ from 2 mrad to 60 mrad, one in five with an outlier).
    from bearing_loc_ros.core.robust_consensus import _refit
    from bearing_loc_ros.core.robust_model import Data
    rng = np.random.default_rng(17)
    M, N = 60, 5
    st = np.column_stack([rng.uniform(-20e3, 20e3, (N, 2)), rng.uniform(0.0, 200.0, N)])
    tgt = np.column_stack([rng.uniform(-30e3, 30e3, (M, 2)), rng.uniform(500.0, 8e3, M)])
    s = rng.uniform(2e-3, 60e-3, M)[:, None] * np.ones(N)
    az, el = azimuth_elevation(tgt[:, None, :] - st[None])
    az = az + s * rng.standard_normal((M, N))
    az[::5, 0] += 0.8
    el = el + s * rng.standard_normal((M, N))
    bs = BearingSet(np.broadcast_to(st, (M, N, 3)).copy(), az, el, s, s)
    data = Data(bs, d_ref)
    X0 = tgt + rng.normal(0.0, 2e3, (M, 3))
    wa, we = np.ones((M, N)), np.ones((M, N))
    batch = _refit(data, X0, wa, we)
    alone = np.array([_refit(data.take([m]), X0[m:m + 1], wa[m:m + 1], we[m:m + 1])[0]
                      for m in range(M)])
    assert np.array_equal(batch, alone)
    assert np.all(np.isfinite(batch))
    assert not np.array_equal(batch, X0)


def _one(bs, k):
    """Problem k of ``bs`` as a one-problem BearingSet (the one-fix path)."""
    fields = (bs.positions, bs.azimuth, bs.elevation, bs.sigma_az, bs.sigma_el)
    return BearingSet(*(a[k:k + 1] for a in fields))


def test_target_above_a_station_is_not_confidently_wrong():
    # A target 1.8 m beside the vertical axis of an azimuth-only station, 1.5 km up: every
    # azimuth fits near that axis, where the azimuth information grows as 1/ρ² and the
    # covariance collapses. ν is taken over the horizontal range ρ (the azimuth's curvature
    # scale), so such fixes are not ok; with the slant range 40 of 151 ok fixes were
    # confidently wrong.
    S = np.array([[0, 0, 0], [4000, 0, 0], [0, 4000, 0], [-3000, -3000, 0], [3000, -2000, 0]],
                 dtype=float)
    T = np.array([1.5, 1.0, 1500.0])
    bs = simulate_bearings(np.tile(T, (200, 1)), S, 5e-3,
                           has_elevation=[False, True, True, True, True],
                           rng=np.random.default_rng(0))
    for res, idx in ((locate('mle', bs), np.arange(200)),
                     *((locate('mle', _one(bs, k)), [k]) for k in range(20))):
        ok = res.status == 'ok'
        e = res.position[ok] - T
        m2 = np.einsum('mi,mi->m', e, np.linalg.solve(res.covariance[ok], e[..., None])[..., 0])
        assert np.all(m2 <= Q9999), (idx, m2.max())


def test_three_angles_must_fit_exactly_to_be_ok():
    # Two stations, one elevation: three angles for three unknowns (dof 0, no χ² test).
    # The refit stops 6 km from the truth with azimuth residuals of 426σ and −333σ; it was
    # reported ok (both paths) and is now low_confidence.
    S = [[3292.612314091666, -4757.544318202028, 0], [-4451.283220341735, 4641.734893425179, 0]]
    bs = BearingSet.from_arrays(S, [0.5861478494678765, -0.8824241124102877],
                                [np.nan, 0.0016181228901217771], 1e-3, 1e-3)
    two = BearingSet(*(np.concatenate([a, a]) for a in (
        bs.positions, bs.azimuth, bs.elevation, bs.sigma_az, bs.sigma_el)))
    for res in (locate('mle', bs), locate('mle', two)):
        assert set(res.status) == {'low_confidence'}


def _line_of_fifty(sigma=0.05, seed=50):
    S = np.c_[np.linspace(-5000, 5000, 50), np.zeros(50), np.zeros(50)]
    return simulate_bearings([8000.0, 0.0, 1000.0], S, sigma, rng=np.random.default_rng(seed))


def test_consistency_marks_gross_failures_of_the_closed_forms():
    # Fifty stations on a 10 km line, the target 8 km off it, σ 0.05 rad: ls ends with a
    # Mahalanobis error² of 261, ctls and ctls_am stop at spurious minima (6e4, 3e5); mle
    # is ok with 2.1. The check after one Gauss-Newton step marks the three low_confidence.
    bs = _line_of_fifty()
    truth = np.array([8000.0, 0.0, 1000.0])
    for name in ('ls', 'ctls', 'ctls_am'):
        r = locate(name, bs)
        e = r.position[0] - truth
        assert e @ np.linalg.solve(r.covariance[0], e) > 100, name
        assert r.status[0] == 'low_confidence' and not r.converged[0], name
        assert locate(name, bs, consistency=False).status[0] == 'ok', name
        batch = locate(name, BearingSet(*(np.concatenate([a, a]) for a in (
            bs.positions, bs.azimuth, bs.elevation, bs.sigma_az, bs.sigma_el))))
        assert list(batch.status) == ['low_confidence'] * 2, name
    assert locate('mle', bs).status[0] == 'ok'


def test_consistency_keeps_honest_fixes_ok():
    # Wang, Zhang & Wu (2006) stations, σ 1.5 mrad, 2000 trials per target. The checks
    # reject an honest fix with probability ≈ 0.1 % (χ²) + < 0.1 % (plausibility) + 6 ×
    # 0.01 % (outliers) ≈ 0.25 %: 5 expected of 2000; ≥ 98.9 % ok (22 or more rejections)
    # has Poisson probability below 1e-6.
    S = np.array([[30.0, -10.0, 0.1], [30.0, 20.0, 0.2], [-30.0, 5.0, 0.15]]) * 1e3
    for tgt in ([20e3, 40e3, 5e3], [-40e3, -30e3, 5e3], [10e3, 20e3, 5e3]):
        bs = simulate_bearings(np.tile(tgt, (2000, 1)), S, 1.5e-3, rng=np.random.default_rng(1))
        for name in ('ls', 'tls', 'ctls', 'ctls_am'):
            assert np.mean(locate(name, bs).status == 'ok') >= 0.989, (tgt, name)


def test_consistency_one_fix_equals_the_batch():
    rng = np.random.default_rng(7)
    for N, sigma in ((3, 2e-3), (4, 0.02), (6, 0.08), (10, 0.02)):
        st = rng.uniform(-5e3, 5e3, (N, 3))
        st[:, 2] = rng.uniform(0.0, 100.0, N)
        tg = rng.uniform([-8e3, -8e3, 200.0], [8e3, 8e3, 3e3], (100, 3))
        bs = simulate_bearings(tg, st, sigma, has_elevation=np.arange(N) % 3 != 1, rng=rng)
        for name in ('ls', 'tls', 'ctls', 'ctls_am'):
            batch = locate(name, bs).status
            one = [locate(name, _one(bs, k)).status[0] for k in range(100)]
            assert list(batch) == one, (N, sigma, name)


def test_consistency_option_is_validated():
    bs = _line_of_fifty()
    with pytest.raises(ValueError, match='options.consistency'):
        locate('ls', bs, consistency='yes')
    with pytest.raises(ValueError, match='consistency'):
        locate('mle', bs, consistency=False)        # mle has option robust instead
