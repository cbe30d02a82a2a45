"""Optimal cut angle of Wang, Su, Bai & Zhong (2009) (core/cutangle.py).

Checks eq. (6), its link to the CRLB, and the optimum.
"""
import numpy as np
import pytest

from bearing_loc_ros.core.crlb import crlb
from bearing_loc_ros.core.cutangle import (boundary_limits, cut_angle_derivatives,
                                           cut_angle_f, cut_angle_table, optimal_cut_angle,
                                           pure_bearing_stationary_points, pure_bearing_theta1,
                                           two_sensor_geometry)


def _random_cases(rng, n):
    """Well-conditioned random (θ1, θ2, ε1, k1, k2): target off the baseline and sensors."""
    t1 = rng.uniform(0.1, np.pi - 0.4, n)
    phi = rng.uniform(0.2, np.pi - t1 - 0.1)
    return (t1, t1 + phi, rng.uniform(-1.2, 1.2, n), rng.uniform(0.05, 5.0, n),
            rng.uniform(0.01, 5.0, n))


def test_eq6_equals_crlb_trace_for_random_geometry():
    # Three angles fix three coordinates, so the first-order covariance of eqs. (1)-(3) is the
    # CRLB of the same measurements: trace(CRLB) = D² σ²_θ2 f to rounding (1e-9 relative).
    rng = np.random.default_rng(4)
    t1, t2, el, k1, k2 = _random_cases(rng, 300)
    D, sigma = 25e3, 2e-3
    targets = np.array([two_sensor_geometry(a, b, e, D, z1=120.0, z2=-40.0)[1]
                        for a, b, e in zip(t1, t2, el)])
    positions = two_sensor_geometry(0.3, 1.0, 0.0, D, z1=120.0, z2=-40.0)[0]
    saz = np.stack([np.sqrt(k1) * sigma, np.full_like(k1, sigma)], axis=1)
    sel = np.stack([np.sqrt(k2) * sigma, np.full_like(k2, np.nan)], axis=1)
    P = crlb(targets, positions, saz, sel, np.array([True, False]))
    tr = np.trace(P, axis1=1, axis2=2)
    f = cut_angle_f(t1, t2, el, k1, k2)
    np.testing.assert_allclose(tr, D ** 2 * sigma ** 2 * f, rtol=1e-9)


def test_geometry_reproduces_the_measured_angles():
    # Eqs. (1)-(3): the target seen from sensor 1 at (θ1, ε1) and from sensor 2 at θ2.
    pos, tgt = two_sensor_geometry(0.4, 2.1, 0.3, 10.0, z1=2.0)
    d1, d2 = tgt - pos[0], tgt - pos[1]
    assert np.arctan2(d1[1], d1[0]) == pytest.approx(0.4)
    assert np.arctan2(d1[2], np.hypot(d1[0], d1[1])) == pytest.approx(0.3)
    assert np.arctan2(d2[1], d2[0]) == pytest.approx(2.1)


def test_analytic_gradient_and_hessian_match_finite_differences():
    rng = np.random.default_rng(7)
    t1, t2, el, k1, k2 = _random_cases(rng, 20)
    h = 1e-6
    for a, b, e, p, q in zip(t1, t2, el, k1, k2):
        f, g, H = cut_angle_derivatives(a, b, e, p, q)
        assert f == pytest.approx(cut_angle_f(a, b, e, p, q), rel=1e-13)
        num_g = [(cut_angle_f(a + h, b, e, p, q) - cut_angle_f(a - h, b, e, p, q)) / (2 * h),
                 (cut_angle_f(a, b + h, e, p, q) - cut_angle_f(a, b - h, e, p, q)) / (2 * h)]
        num_H = np.array([
            (cut_angle_derivatives(a + h, b, e, p, q)[1]
             - cut_angle_derivatives(a - h, b, e, p, q)[1]) / (2 * h),
            (cut_angle_derivatives(a, b + h, e, p, q)[1]
             - cut_angle_derivatives(a, b - h, e, p, q)[1]) / (2 * h)])
        # Central differences: truncation O(h²) ~ 1e-12 relative, rounding ~ 1e-16 / h.
        np.testing.assert_allclose(g, num_g, rtol=1e-6, atol=1e-8 * abs(f))
        np.testing.assert_allclose(H, num_H, rtol=1e-5, atol=1e-7 * np.abs(H).max())


def test_equal_accuracy_bearings_give_arccos_minus_one_third():
    # k1 = 1, k2 = 0, ε1 = 0: by symmetry θ2 = π − θ1, f = 1/(8 sin²θ1 cos⁴θ1), minimal at
    # cos²θ1 = 2/3, i.e. φ = arccos(−1/3) ≈ 109.47° and f = 27/32.
    r = optimal_cut_angle(1.0, 0.0, 0.0)
    assert r.feasible
    assert r.cut_angle == pytest.approx(np.arccos(-1.0 / 3.0), abs=1e-9)
    assert np.degrees(r.cut_angle) == pytest.approx(109.47, abs=0.005)
    assert r.theta1 == pytest.approx(np.arccos(np.sqrt(2.0 / 3.0)), abs=1e-9)
    assert r.theta2 == pytest.approx(np.pi - r.theta1, abs=1e-9)
    assert r.f_min == pytest.approx(27.0 / 32.0, rel=1e-12)
    assert r.gradient_norm < 1e-9


@pytest.mark.parametrize('k1', [0.1, 0.3, 0.5])
def test_pure_bearing_k1_up_to_half_is_infeasible(k1):
    # Near sensor 2 (θ1 = ρβ..., target at distance ρD in direction π/2 + β) f ≈ k1 + k1β²
    # − 4k1ρβ + (2k1 + 1)ρ²: a local minimum at the sensor iff det = k1(1 − 2k1) > 0, so no
    # interior optimum for k1 ≤ 1/2 (Wang, Su, Bai & Zhong (2009), section 5.2.1, says the same).
    r = optimal_cut_angle(k1, 0.0, 0.0)
    assert not r.feasible and 'sensor 2' in r.reason
    assert (np.degrees(r.theta1), np.degrees(r.theta2)) == pytest.approx((0.0, 90.0))
    assert np.degrees(r.cut_angle) == pytest.approx(90.0)
    assert r.f_min == pytest.approx(k1)
    assert r.local_minima == []


def test_pure_bearing_feasible_just_above_half_and_symmetric_in_k1():
    r = optimal_cut_angle(0.51, 0.0, 0.0)
    assert r.feasible and r.f_min < 0.51 and 0 < r.theta1 < np.radians(10)
    # Swapping the two 1D sensors maps k1 to 1/k1 and θ1 to π − θ2, with f scaled by 1/k1.
    for k1 in (0.6, 0.8, 0.9):
        a, b = optimal_cut_angle(k1), optimal_cut_angle(1.0 / k1)
        assert b.feasible
        assert b.theta1 == pytest.approx(np.pi - a.theta2, abs=1e-8)
        assert b.cut_angle == pytest.approx(a.cut_angle, abs=1e-8)
        assert b.f_min == pytest.approx(a.f_min / k1, rel=1e-10)
    r = optimal_cut_angle(2.0)
    assert not r.feasible and 'sensor 1' in r.reason and r.f_min == pytest.approx(1.0)


@pytest.mark.parametrize('k1', [0.6, 0.8, 1.0])
def test_newton_optimum_agrees_with_eqs_8_to_11(k1):
    # Independent solver: eq. (10) gives θ1(θ2) on eq. (8); ∂f/∂θ1 = 0 is then solved along it.
    r = optimal_cut_angle(k1, 0.0, 0.0)
    assert np.sin(2 * r.theta1) + k1 * np.sin(2 * r.theta2) == pytest.approx(0.0, abs=1e-10)
    assert np.min(np.abs(pure_bearing_theta1(r.theta2, k1) - r.theta1)) < 1e-8
    pts = [p for p in pure_bearing_stationary_points(k1) if p[2] < 1.0]
    assert pts, 'eqs. (8)-(11) found no stationary point'
    best = min(pts, key=lambda p: p[2])
    assert best[0] == pytest.approx(r.theta1, abs=1e-7)
    assert best[1] == pytest.approx(r.theta2, abs=1e-7)
    assert best[2] == pytest.approx(r.f_min, rel=1e-10)


@pytest.mark.parametrize('k1,k2,el_deg', [(0.3, 0.2, 0.0), (1.2, 0.5, 20.0), (0.8, 0.8, 35.0),
                                          (2.5, 0.1, 10.0), (0.4, 0.0, 0.0)])
def test_optimum_is_the_global_minimum_of_a_dense_grid(k1, k2, el_deg):
    el = np.radians(el_deg)
    r = optimal_cut_angle(k1, k2, el)
    a = np.linspace(1e-3, np.pi - 1e-3, 700)
    T1, T2 = np.meshgrid(a, a, indexing='ij')
    F = np.where(T2 > T1 + 1e-3, cut_angle_f(T1, T2, el, k1, k2), np.inf)
    # Feasible or not, f_min is the infimum of f over the domain: no grid point is lower,
    # and the grid comes close to it (near the optimum, or near the limit point).
    assert r.f_min <= F.min() * (1 + 1e-12)
    assert F.min() <= r.f_min * (1 + 1e-2)
    lim = min(v[0] for v in boundary_limits(k1, k2, el).values())
    if r.feasible:
        assert r.f_min < lim
    else:
        assert r.f_min == pytest.approx(lim)


def test_section_5_claims():
    # 5.2.2 (2): with an elevation measurement (k2 > 0) k1 <= 0.5 has a feasible optimum.
    assert optimal_cut_angle(0.3, 0.2, 0.0).feasible
    # 5.2.1 (1), 5.2.2 (1), 5.2.3 (1): every feasible optimum has φ >= 90°.
    rows = cut_angle_table([0.2, 0.6, 1.0, 1.5], [0.0, 0.2, 0.8], np.radians(20.0), grid=60)
    assert any(r.feasible for r in rows)
    assert all(np.degrees(r.cut_angle) >= 90.0 - 1e-9 for r in rows if r.feasible)
    # 5.2.3 (3): k1 = 0.3, k2 = 0.8 has no feasible optimum above ~40° elevation; k1 = 1.2,
    # k2 = 0.3 still has one at 60°.
    assert optimal_cut_angle(0.3, 0.8, np.radians(30)).feasible
    assert not optimal_cut_angle(0.3, 0.8, np.radians(50)).feasible
    assert optimal_cut_angle(1.2, 0.3, np.radians(60)).feasible
    # 5.2.2 (3): for fixed k2, large k1 drives the optimum to sensor 1 (θ1 -> 90°, θ2 -> 180°).
    r = optimal_cut_angle(3.0, 0.2, 0.0)
    assert not r.feasible and np.degrees(r.theta2) == pytest.approx(180.0)


@pytest.mark.parametrize('kwargs,field', [({'k1': 0.0}, 'k1'), ({'k1': np.nan}, 'k1'),
                                          ({'k1': 1.0, 'k2': -0.1}, 'k2'),
                                          ({'k1': 1.0, 'elevation': np.radians(89.5)},
                                           'elevation')])
def test_bad_input_names_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        optimal_cut_angle(**kwargs)


def test_as_dict_is_plain_json_types():
    import json
    d = optimal_cut_angle(0.8).as_dict()
    assert json.loads(json.dumps(d)) == d
    assert set(d) >= {'theta1_deg', 'theta2_deg', 'cut_angle_deg', 'f_min', 'feasible'}
    assert d['feasible'] is True
