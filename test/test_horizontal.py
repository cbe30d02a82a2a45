"""Horizontal solve (target altitude stated): exactness, bound, bad input, dimension selection.

Statistical checks live in test_horizontal_mc.py.
"""
import numpy as np
import pytest

from bearing_loc_ros.core.bearings import BearingSet
from bearing_loc_ros.core.crlb import crlb, fisher_information
from bearing_loc_ros.core.cutangle import optimal_cut_angle
from bearing_loc_ros.core.fix import FixResult
from bearing_loc_ros.core.horizontal import (ESTIMATORS, height_observed, locate,
                                             locate_horizontal, select_dimension,
                                             simulate_bearings)
from bearing_loc_ros.core.horizontal_crlb import (horizontal_crlb, horizontal_crlb_for,
                                                  horizontal_gdop,
                                                  optimal_cut_angle_two_azimuth,
                                                  two_azimuth_crlb_trace)
from bearing_loc_ros.core.horizontal_ctls import PlaneCTLS
from bearing_loc_ros.core.horizontal_robust import nonlinearity
from bearing_loc_ros.core.horizontal_estimators import prepare

METHODS = sorted(ESTIMATORS)


def _random_geometry(rng, N):
    """N stations in a 10 km square (heights 0-100 m), a target 200 m from every station."""
    while True:
        st = np.column_stack([rng.uniform(-5e3, 5e3, (N, 2)), rng.uniform(0.0, 100.0, N)])
        tgt = np.array([*rng.uniform(-4e3, 4e3, 2), rng.uniform(200.0, 800.0)])
        if np.min(np.hypot(*(st[:, :2] - tgt[:2]).T)) > 200.0:
            return st, tgt


@pytest.mark.parametrize('with_elevations', [False, True])
def test_noise_free_sets_are_recovered_exactly_by_every_estimator(with_elevations):
    # Random geometries of 2 to 10 stations (seeded); some 2D stations when with_elevations.
    rng = np.random.default_rng(100 + with_elevations)
    for N in range(2, 11):
        for _ in range(3):
            st, tgt = _random_geometry(rng, N)
            mask = rng.random(N) < 0.5 if with_elevations else False
            bs = simulate_bearings(tgt, st, 2e-3, 3e-3, has_elevation=mask)
            for sigma_z in (0.0, 25.0):
                for method in METHODS:
                    r = locate_horizontal(method, bs, tgt[2], sigma_z)
                    assert r.status[0] == 'ok', (N, method, sigma_z, r.status)
                    assert np.allclose(r.position[0], tgt, rtol=0, atol=1e-6), (N, method)
                    assert np.all(r.solve == 'horizontal')
                    P = r.covariance[0]
                    assert np.all(np.isfinite(P)) and np.allclose(P, P.T)
                    if np.any(mask) and method in ('mle', 'wmle'):
                        # The posterior of z: the elevations add height information.
                        assert P[2, 2] <= sigma_z ** 2 * (1 + 1e-12)
                    else:
                        assert P[2, 2] == pytest.approx(sigma_z ** 2, rel=1e-9, abs=0)
                    if not np.any(mask):
                        # Azimuths alone: z = z0 exactly, no x-y/z correlation at all.
                        assert r.position[0, 2] == tgt[2]
                        assert np.all(P[:2, 2] == 0.0) and np.all(P[2, :2] == 0.0)


def test_batch_equals_problem_by_problem():
    rng = np.random.default_rng(7)
    st, tgt = _random_geometry(rng, 4)
    bs = simulate_bearings(np.tile(tgt, (5, 1)), st, 3e-3, has_elevation=[True, False] * 2,
                           rng=rng)
    for method in METHODS:
        batch = locate_horizontal(method, bs, tgt[2], 10.0)
        for m in range(bs.M):
            one = locate_horizontal(method, bs.problem(m), tgt[2], 10.0)
            assert np.allclose(batch.position[m], one.position[0], rtol=1e-9, atol=1e-6)


def test_crlb_is_the_3d_information_with_the_altitude_prior():
    rng = np.random.default_rng(3)
    st, tgt = _random_geometry(rng, 5)
    saz, sel = np.array([1e-3, 2e-3, 3e-3, 2e-3, 1e-3]), 2e-3
    has_el = np.array([True, False, True, False, False])
    J = fisher_information(tgt[None], st, saz, sel, has_el)[0]
    for sz in (0.5, 20.0, 1e4):
        P = horizontal_crlb(tgt, st, saz, sel, has_el, sz)[0]
        assert np.allclose(P, np.linalg.inv(J + np.diag([0, 0, sz ** -2])), rtol=1e-7)
        assert abs(P[0, 2]) + abs(P[1, 2]) > 0          # elevations correlate z with x, y
    # σ_z = 0: z fixed, the 2 × 2 problem with the elevations' range information.
    P0 = horizontal_crlb(tgt, st, saz, sel, has_el, 0.0)[0]
    assert np.allclose(P0[:2, :2], np.linalg.inv(J[:2, :2]), rtol=1e-9)
    assert np.all(P0[2] == 0) and np.all(P0[:, 2] == 0)
    # A weak prior tends to the 3D bound of crlb.py (height observed by the elevations).
    P3 = crlb(tgt[None], st, saz, sel, has_el)[0]
    assert np.allclose(horizontal_crlb(tgt, st, saz, sel, has_el, 1e7)[0], P3, rtol=1e-5)


def test_azimuth_only_crlb_is_the_sum_of_cross_range_information():
    # Independent form: J_h = Σ u⊥u⊥ᵀ / (ρ² σ²), u⊥ = (−sin θ, cos θ); z block σ_z², no cross.
    st = np.array([[0.0, 0.0, 5.0], [3000.0, 0.0, 0.0], [0.0, 4000.0, 12.0]])
    tgt = np.array([2500.0, 3000.0, 150.0])
    sig = np.array([1e-3, 2e-3, 4e-3])
    d = tgt[:2] - st[:, :2]
    rho2 = np.sum(d * d, axis=1)
    u = np.column_stack([-d[:, 1], d[:, 0]]) / np.sqrt(rho2)[:, None]
    Jh = np.einsum('n,ni,nj->ij', 1.0 / (rho2 * sig ** 2), u, u)
    P = horizontal_crlb(tgt, st, sig, sigma_z=30.0)[0]
    assert np.allclose(P[:2, :2], np.linalg.inv(Jh), rtol=1e-10)
    assert P[2, 2] == 900.0 and np.all(P[:2, 2] == 0) and np.all(P[2, :2] == 0)
    assert horizontal_gdop(P) == pytest.approx(np.sqrt(np.trace(np.linalg.inv(Jh))))


def test_ctls_gradient_and_hessian_match_finite_differences():
    rng = np.random.default_rng(5)
    st, tgt = _random_geometry(rng, 4)
    bs = simulate_bearings(tgt, st, 3e-3, has_elevation=[True, False, True, False], rng=rng)
    for weighting in ('paper', 'am'):
        prob = PlaneCTLS(prepare(bs, tgt[2]), weighting)
        X = tgt[None, :2] + np.array([[40.0, -25.0]])
        f, T, Hn, _ = prob.derivatives(X)
        h = 1e-3
        for k in range(2):
            e = np.zeros((1, 2))
            e[0, k] = h
            fp, Tp, _, _ = prob.derivatives(X + e)
            fm, Tm, _, _ = prob.derivatives(X - e)
            assert (fp - fm)[0] / (2 * h) == pytest.approx(T[0, k], rel=1e-5, abs=1e-9 * f[0])
            assert np.allclose((Tp - Tm)[0] / (2 * h), Hn[0, :, k], rtol=1e-4,
                               atol=1e-6 * np.abs(Hn).max())


def test_elevations_give_range_when_stations_and_target_share_a_line():
    # Stations on the x axis, target on it too: azimuths alone are degenerate, but with the
    # altitude known an elevation gives the horizontal range, ρ = (z0 − z_i)/tan ψ_i.
    st = np.array([[0.0, 0.0, 0.0], [2000.0, 0.0, 10.0], [-3000.0, 0.0, 0.0]])
    tgt = np.array([6000.0, 0.0, 400.0])
    bs = simulate_bearings(tgt, st, 1e-3, has_elevation=[True, False, False])
    for method in METHODS:
        r = locate_horizontal(method, bs, 400.0)
        assert r.status[0] == 'ok' and np.allclose(r.position[0], tgt, atol=1e-6), method
        no_el = locate_horizontal(method, bs, 400.0, use_elevations=False)
        assert no_el.status[0] == 'degenerate_geometry', method
        assert np.all(np.isnan(no_el.position[0])) and np.all(np.isinf(no_el.covariance[0]))


def test_ignored_elevations_mean_the_horizontal_solve():
    # use_elevations=False (ground emitters, multipath-spoiled elevations): with auto the
    # elevations can no longer observe the height, so the set is solved horizontally with
    # the stated altitude (before, auto went 3D and used the spoiled elevations); 3d is an
    # error naming the option, and without an altitude the error says why it is needed.
    st = np.array([[0.0, 0.0, 0.0], [4000.0, 0.0, 10.0], [0.0, 5000.0, 20.0]])
    tgt = np.array([3000.0, 3500.0, 300.0])
    bs = simulate_bearings(tgt, st, 1e-3, has_elevation=True, rng=np.random.default_rng(5))
    bs.elevation[0, 1] += 0.2                          # a spoiled elevation
    assert locate('mle', bs).solve[0] == '3d'
    auto = locate('mle', bs, target_altitude=300.0, use_elevations=False)
    forced = locate('mle', bs, dimension='horizontal', target_altitude=300.0,
                    use_elevations=False)
    assert auto.solve[0] == 'horizontal' and auto.status[0] == 'ok'
    np.testing.assert_array_equal(auto.position, forced.position)
    assert np.linalg.norm(auto.position[0] - tgt) < 4 * np.sqrt(np.trace(auto.covariance[0]))
    with pytest.raises(ValueError, match='^use_elevations:'):
        locate('mle', bs, dimension='3d', use_elevations=False)
    with pytest.raises(ValueError, match='^target_altitude: required because use_elevations'):
        locate('mle', bs, use_elevations=False)
    # The fusion node's epoch gate: the spoiled elevation does not get station 1 dropped.
    from bearing_loc_ros.core.bearings import Bearing
    from bearing_loc_ros.core.fusion.gating import solve_epoch
    epoch = [Bearing(f's{i}', 0, st[i], float(bs.azimuth[0, i]), float(bs.elevation[0, i]),
                     1e-3, 1e-3) for i in range(3)]
    for flag in (False, np.False_):                  # a numpy bool from a Python caller too
        e = solve_epoch(epoch, 'mle', {'target_altitude': 300.0, 'use_elevations': flag})
        assert e.ok and not e.rejected and len(e.bearings) == 3
        np.testing.assert_allclose(e.position, auto.position[0], rtol=0, atol=1e-6)


def test_collinear_stations_with_the_target_on_the_line_never_give_a_confident_fix():
    st = np.array([[0.0, 0.0, 0.0], [2000.0, 0.0, 10.0], [-3000.0, 0.0, 0.0]])
    for tgt in ([6000.0, 0.0, 400.0], [500.0, 0.0, 400.0]):       # beyond / between stations
        for rng in (None, np.random.default_rng(9)):
            bs = simulate_bearings(np.tile(tgt, (200, 1)), st, 1e-3, rng=rng)
            for method in METHODS:
                r = locate_horizontal(method, bs, 400.0)
                # χ² tail 1e-6 per problem: P(any of 200 problems escapes) ≈ 2e-4.
                assert np.all(r.status == 'degenerate_geometry'), method
                assert np.all(np.isnan(r.position)) and np.all(np.isinf(r.covariance))
    # Off the line by 40 m (χ² ≈ 160 against the 1e-6 quantile 30.7), the same stations fix.
    off = simulate_bearings([6000.0, 40.0, 400.0], st, 1e-3)
    assert locate_horizontal('mle', off, 400.0, robust=False).status[0] == 'ok'
    # The robust default fixes it too, as low_confidence: 40 m off the line the parallax
    # is a few σ, so the range is loosely bound and the region far from an ellipse (ν > 0.2).
    fix = locate_horizontal('mle', off, 400.0)
    assert fix.status[0] == 'low_confidence' and np.all(np.isfinite(fix.position))
    assert nonlinearity(fix.position, fix.covariance, off.positions)[0] > 0.2


@pytest.mark.parametrize('kwargs, field', [
    (dict(target_altitude=None), 'target_altitude'),
    (dict(target_altitude=float('nan')), 'target_altitude'),
    (dict(target_altitude=float('inf')), 'target_altitude'),
    (dict(target_altitude='high'), 'target_altitude'),
    (dict(target_altitude=True), 'target_altitude'),
    (dict(target_altitude=[1.0, 2.0, 3.0]), 'target_altitude'),
    (dict(target_altitude=100.0, target_altitude_sigma=-1.0), 'target_altitude_sigma'),
    (dict(target_altitude=100.0, target_altitude_sigma=float('nan')), 'target_altitude_sigma'),
    (dict(target_altitude=100.0, target_altitude_sigma=float('inf')), 'target_altitude_sigma'),
    (dict(target_altitude=100.0, use_elevations='yes'), 'use_elevations'),
    (dict(target_altitude=100.0, max_iterations=0), 'options.max_iterations'),
    (dict(target_altitude=100.0, initial=[1.0]), 'options.initial'),
    (dict(target_altitude=100.0, initial=[np.nan, 0.0]), 'options.initial'),
    (dict(target_altitude=100.0, bogus=1), 'options.bogus'),
])
def test_bad_input_names_the_field(kwargs, field):
    st = np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0]])
    bs = simulate_bearings([500.0, 800.0, 100.0], st, 1e-3)
    kwargs = dict(kwargs)
    z0 = kwargs.pop('target_altitude')
    with pytest.raises(ValueError, match=f'^{field}'):
        locate_horizontal('mle', bs, z0, **kwargs)


def test_bad_bearings_name_the_field():
    st = np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0]])
    one = BearingSet.from_arrays(st[:1], [0.3], validate=False)
    with pytest.raises(ValueError, match='^bearings: 1 azimuth'):
        locate_horizontal('ls', one, 100.0)
    ok = simulate_bearings([500.0, 800.0, 100.0], st, 1e-3)
    for name, attr, value in (('azimuth', 'azimuth', np.nan), ('position', 'positions', np.inf),
                              ('sigma_azimuth', 'sigma_az', -1.0),
                              ('elevation', 'elevation', 2.0)):
        bad = BearingSet(ok.positions.copy(), ok.azimuth.copy(), ok.elevation.copy(),
                         ok.sigma_az.copy(), np.full_like(ok.sigma_az, 1e-3))
        getattr(bad, attr).flat[0] = value
        with pytest.raises(ValueError, match=f'^{name}'):
            locate_horizontal('mle', bad, 100.0)
    with pytest.raises(ValueError, match='^bearings'):
        locate_horizontal('mle', 'not bearings', 100.0)
    with pytest.raises(ValueError, match='^method'):
        locate_horizontal('magic', ok, 100.0)


def test_dimension_selection():
    st = np.array([[0.0, 0.0, 0.0], [4000.0, 500.0, 20.0], [-2000.0, 3000.0, 5.0]])
    tgt = np.array([1500.0, 2500.0, 600.0])
    az_only = simulate_bearings(tgt, st, 1e-3)
    one_el = simulate_bearings(tgt, st, 1e-3, has_elevation=[True, False, False])
    assert list(select_dimension(az_only)) == ['horizontal']
    assert list(select_dimension(one_el)) == ['3d']
    assert list(select_dimension(one_el, 'horizontal')) == ['horizontal']
    # One vertical plane holds every station and the target: one elevation constrains only a
    # combination of the along-line position and the height (rank-2 information); two
    # elevations triangulate in that plane.
    line = np.array([[0.0, 0.0, 0.0], [2000.0, 0.0, 10.0], [-3000.0, 0.0, 0.0]])
    on_line = np.array([6000.0, 0.0, 400.0])
    single = simulate_bearings(on_line, line, 1e-3, has_elevation=[True, False, False])
    double = simulate_bearings(on_line, line, 1e-3, has_elevation=[True, True, False])
    assert list(height_observed(single)) == [False]
    assert list(height_observed(double)) == [True]
    with pytest.raises(ValueError, match='^dimension'):
        select_dimension(az_only, '2.5d')


def test_locate_dispatches_and_merges_a_mixed_batch():
    st = np.array([[0.0, 0.0, 0.0], [4000.0, 500.0, 20.0], [-2000.0, 3000.0, 5.0]])
    tgt = np.array([1500.0, 2500.0, 600.0])
    rng = np.random.default_rng(2)
    mixed = simulate_bearings(np.tile(tgt, (6, 1)), st, 2e-3, rng=rng, has_elevation=True)
    mixed.elevation[::2] = np.nan                      # problems 0, 2, 4: azimuth only
    mixed.sigma_el[::2] = np.nan
    with pytest.raises(ValueError, match='^target_altitude'):
        locate('mle', mixed)
    r = locate('mle', mixed, target_altitude=600.0, target_altitude_sigma=5.0)
    assert isinstance(r, FixResult)
    assert list(r.solve) == ['horizontal', '3d'] * 3
    h = locate_horizontal('mle', mixed.problem(0), 600.0, 5.0)
    assert np.allclose(r.position[0], h.position[0])
    assert np.allclose(r.covariance[0], h.covariance[0])
    assert r.target_altitude_sigma[0] == 5.0 and np.isnan(r.target_altitude[1])
    three_d = locate('mle', mixed.problem(1), dimension='3d')
    assert np.allclose(r.position[1], three_d.position[0]) and three_d.solve[0] == '3d'
    single = r.single(0)
    assert single['solve'] == 'horizontal' and single['target_altitude'] == 600.0
    assert r.single(1)['solve'] == '3d'
    with pytest.raises(ValueError, match='^target_altitude'):
        locate('ls', mixed.problem(0), dimension='horizontal')


def test_two_azimuth_cut_angle_closed_form():
    # Equal accuracies on a fixed baseline: cos φ* = −1/3 (109.47°, an isosceles triangle).
    r = optimal_cut_angle_two_azimuth(2e-3, 2e-3)
    assert r.feasible and np.cos(r.cut_angle) == pytest.approx(-1.0 / 3.0, abs=1e-12)
    assert r.theta1 == pytest.approx(np.pi - r.theta2, abs=1e-12)
    t1, t2 = np.meshgrid(np.linspace(1e-3, np.pi - 1e-3, 1201),
                         np.linspace(1e-3, np.pi - 1e-3, 1201))
    inside = t2 > t1 + 1e-3
    with np.errstate(divide='ignore'):
        for k in (0.3, 0.6, 0.8, 1.0, 1.5, 2.5):
            r = optimal_cut_angle_two_azimuth(np.sqrt(k), 1.0)
            grid = np.where(inside, two_azimuth_crlb_trace(t1, t2, np.sqrt(k), 1.0), np.inf)
            assert r.f == pytest.approx(grid.min(), rel=1e-4)            # global minimum
            assert r.feasible == (0.5 < k < 2.0)
            assert two_azimuth_crlb_trace(r.theta1, r.theta2, np.sqrt(k), 1.0) == \
                pytest.approx(r.f, rel=1e-9)
            ref = optimal_cut_angle(k)                                  # Newton on eq. (7)
            assert ref.feasible == r.feasible
            assert r.cut_angle == pytest.approx(ref.cut_angle, abs=1e-6)
    # The trace formula is the 2 × 2 CRLB of the geometry.
    t1, t2, D = 0.6, 2.1, 5000.0
    r1, r2 = D * np.sin(t2) / np.sin(t2 - t1), D * np.sin(t1) / np.sin(t2 - t1)
    tgt = np.array([r1 * np.cos(t1), r1 * np.sin(t1), 0.0])
    st = np.array([[0.0, 0.0, 0.0], [D, 0.0, 0.0]])
    P = horizontal_crlb(tgt, st, np.array([1e-3, 3e-3]))[0]
    assert np.trace(P) == pytest.approx(two_azimuth_crlb_trace(t1, t2, 1e-3, 3e-3, D), rel=1e-9)
    assert np.hypot(*(tgt[:2] - st[1, :2])) == pytest.approx(r2)
    # At fixed ranges (r1, r2) the CRLB trace (r1²σ1² + r2²σ2²)/sin²φ is smallest at 90° for
    # any σ: target at the origin, sensors at r1 (1, 0) and r2 (cos φ, sin φ).
    phis = np.linspace(0.3, np.pi - 0.3, 721)
    for s1, s2 in ((1e-3, 1e-3), (1e-3, 3e-3)):
        st = np.zeros((phis.size, 2, 3))
        st[:, 0, 0] = 2000.0
        st[:, 1, 0], st[:, 1, 1] = 5000.0 * np.cos(phis), 5000.0 * np.sin(phis)
        tr = horizontal_gdop(horizontal_crlb(np.zeros((phis.size, 3)), st,
                                             np.array([s1, s2]))) ** 2
        assert np.allclose(tr, (2000.0 ** 2 * s1 ** 2 + 5000.0 ** 2 * s2 ** 2)
                           / np.sin(phis) ** 2, rtol=1e-9)
        assert phis[np.argmin(tr)] == pytest.approx(np.pi / 2, abs=1e-9)
    with pytest.raises(ValueError, match='^sigma1'):
        optimal_cut_angle_two_azimuth(0.0, 1.0)


def test_horizontal_crlb_for_uses_the_set():
    st = np.array([[0.0, 0.0, 0.0], [4000.0, 500.0, 20.0], [-2000.0, 3000.0, 5.0]])
    tgt = np.array([1500.0, 2500.0, 600.0])
    bs = simulate_bearings(tgt, st, [1e-3, 2e-3, 3e-3], 2e-3, has_elevation=[True, 0, 0])
    a = horizontal_crlb_for(tgt[None], bs, 10.0)
    b = horizontal_crlb(tgt, st, [1e-3, 2e-3, 3e-3], 2e-3, [True, False, False], 10.0)
    assert np.allclose(a, b)
    c = horizontal_crlb_for(tgt[None], bs, 10.0, use_elevations=False)
    assert c[0, 2, 2] == 100.0 and np.all(c[0, :2, 2] == 0)
