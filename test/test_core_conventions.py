"""Conventions of DESIGN.md: wrapping, compass, line of sight, quaternions, validation."""
import math

import numpy as np
import pytest

from bearing_loc_ros.core import bearings as bearings_module
from bearing_loc_ros.core.bearings import Bearing, BearingSet, simulate_bearings
from bearing_loc_ros.core.conventions import (azel_from_quaternion,
                                              azel_from_quaternion_scalar, azimuth_elevation,
                                              compass_to_enu, enu_to_compass, los_vector,
                                              quaternion_from_azel, quaternion_from_azel_scalar,
                                              wrap_angle, wrap_angle_scalar)
from bearing_loc_ros.core.crlb import crlb, fisher_information, gdop


def test_wrap_angle_half_open_interval():
    a = np.array([np.pi, -np.pi, 3 * np.pi, 0.5, -0.5 - 4 * np.pi, 7.0])
    w = wrap_angle(a)
    assert np.all(w > -np.pi) and np.all(w <= np.pi)
    assert w[0] == pytest.approx(np.pi) and w[1] == pytest.approx(np.pi)
    assert np.allclose(np.exp(1j * w), np.exp(1j * a))


def test_compass_round_trip_and_cardinal_points():
    # North (compass 0) is ENU +y (pi/2); East (compass pi/2) is ENU 0.
    assert compass_to_enu(0.0) == pytest.approx(np.pi / 2)
    assert compass_to_enu(np.pi / 2) == pytest.approx(0.0)
    assert compass_to_enu(np.pi) == pytest.approx(-np.pi / 2)
    c = np.linspace(0, 2 * np.pi, 37, endpoint=False)
    assert np.allclose(enu_to_compass(compass_to_enu(c)), c)


def test_los_vector_matches_azimuth_elevation():
    rng = np.random.default_rng(1)
    d = rng.normal(size=(100, 3))
    az, el = azimuth_elevation(d)
    assert np.allclose(los_vector(az, el), d / np.linalg.norm(d, axis=1, keepdims=True))


def test_quaternion_round_trip_and_rotates_x_onto_los():
    rng = np.random.default_rng(2)
    az = rng.uniform(-np.pi, np.pi, 200)
    el = rng.uniform(-1.5, 1.5, 200)
    q = quaternion_from_azel(az, el)
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0)
    az2, el2, roll = azel_from_quaternion(q)
    assert np.allclose(wrap_angle(az2 - az), 0, atol=1e-12)
    assert np.allclose(el2, el, atol=1e-12)
    assert np.allclose(roll, 0, atol=1e-12)


HALF_PI = math.pi / 2.0
EDGE_ANGLES = [0.0, -0.0, math.pi, -math.pi, math.nextafter(-math.pi, 0.0),
               math.nextafter(math.pi, 4.0), 2 * math.pi, -3 * math.pi, 1e17, -1e300,
               math.nextafter(HALF_PI, 0.0), -math.nextafter(HALF_PI, 0.0), 5e-324]


def _bits(values):
    return np.asarray(values, dtype=float).view(np.int64)


def _ulps(a, b):
    """|a − b| in units in the last place of the larger magnitude (0 when equal, NaN = NaN)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    both_nan = np.isnan(a) & np.isnan(b)
    scale = np.spacing(np.maximum(np.abs(a), np.abs(b)))
    return np.where(both_nan, 0.0, np.abs(a - b) / scale)


def test_wrap_angle_scalar_is_bit_identical():
    """Same formula and folds: identical bits, including the sign of zero and ±π edges."""
    rng = np.random.default_rng(10)
    a = np.concatenate([rng.uniform(-50.0, 50.0, 20000), EDGE_ANGLES])
    scalar = [wrap_angle_scalar(v) for v in a.tolist()]
    assert np.array_equal(_bits(scalar), _bits(wrap_angle(a)))
    assert all(-math.pi < v <= math.pi for v in scalar)
    assert wrap_angle_scalar(-0.0) == 0.0 and math.copysign(1.0, wrap_angle_scalar(-0.0)) > 0
    for bad in (math.nan, math.inf, -math.inf):
        with np.errstate(invalid='ignore'):
            assert math.isnan(wrap_angle_scalar(bad)) and math.isnan(wrap_angle(bad))


def test_quaternion_from_azel_scalar_is_bit_identical():
    """Same expressions in the same order, and math.sin/cos == np.sin/cos on this input."""
    rng = np.random.default_rng(11)
    az = np.concatenate([rng.uniform(-4.0, 4.0, 20000), EDGE_ANGLES])
    el = np.concatenate([rng.uniform(-HALF_PI, HALF_PI, 20000), EDGE_ANGLES])
    scalar = [quaternion_from_azel_scalar(a, e) for a, e in zip(az.tolist(), el.tolist())]
    assert np.array_equal(_bits(scalar), _bits(quaternion_from_azel(az, el)))
    # NaN elevation counts as 0 and ±inf as ±max float (np.nan_to_num), inf azimuth -> NaN.
    for a, e in [(0.3, math.nan), (0.3, math.inf), (0.3, -math.inf), (math.inf, 0.1),
                 (math.nan, 0.1)]:
        with np.errstate(invalid='ignore'):
            vec = quaternion_from_azel(a, e)
        assert np.array_equal(quaternion_from_azel_scalar(a, e), vec, equal_nan=True)
    assert quaternion_from_azel_scalar(0.3) == quaternion_from_azel_scalar(0.3, math.nan)


def test_azel_from_quaternion_scalar_agrees_to_one_ulp():
    """Same maths; numpy evaluates arctan2/arcsin/hypot with its own SIMD routines where the
    CPU has them, which round differently from the C library on some inputs (both are
    accurate to within 1 ulp of the true value), so the bound is 1 ulp and exactly equal
    elsewhere. Inputs: bearings (roll 0) up to within rounding of the vertical, and random
    (rolled, non-unit) quaternions."""
    rng = np.random.default_rng(12)
    n = 20000
    el = rng.uniform(-HALF_PI, HALF_PI, n)
    el[::5] = np.sign(el[::5]) * (HALF_PI - 10.0 ** rng.uniform(-16, -3, el[::5].size))
    q_bearings = quaternion_from_azel(rng.uniform(-math.pi, math.pi, n), el)
    q_random = rng.normal(size=(n, 4)) * rng.uniform(0.5, 2.0, (n, 1))
    for q in (q_bearings, q_random):
        vec = np.stack(azel_from_quaternion(q), axis=-1)
        scalar = np.array([azel_from_quaternion_scalar(*row) for row in q.tolist()])
        assert np.all(_ulps(scalar, vec) <= 1.0)
        # Azimuths stay in [−π, π], elevations in [−π/2, π/2], as atan2 guarantees.
        assert np.all(np.abs(scalar[:, 0]) <= math.pi)
        assert np.all(np.abs(scalar[:, 1]) <= HALF_PI)
    # Degenerate inputs behave like the vectorised version: NaN, not an exception.
    for q in ([0.0, 0.0, 0.0, 0.0], [math.nan, 0.0, 0.0, 1.0], [math.inf, 0.0, 0.0, 1.0]):
        with np.errstate(invalid='ignore', divide='ignore'):
            vec = np.array(azel_from_quaternion(np.array(q)))
        assert np.array_equal(np.isnan(azel_from_quaternion_scalar(*q)), np.isnan(vec))


def test_bearing_set_validation_names_the_field():
    pos = np.array([[0, 0, 0], [1000, 0, 0], [0, 1000, 0.0]])
    good = dict(positions=pos, azimuth=[0.1, 0.2, 0.3], elevation=[0.1, np.nan, 0.2],
                sigma_az=0.01, sigma_el=0.01)
    BearingSet.from_arrays(**good)
    for field_, value, word in [('azimuth', [np.nan, 0.2, 0.3], 'azimuth'),
                                ('elevation', [2.0, np.nan, 0.2], 'elevation'),
                                ('sigma_az', -0.01, 'sigma_azimuth'),
                                ('sigma_el', 0.0, 'sigma_elevation'),
                                ('elevation', None, 'elevation')]:
        bad = dict(good, **{field_: value})
        with pytest.raises(ValueError, match=word):
            BearingSet.from_arrays(**bad)
    with pytest.raises(ValueError, match='two'):
        BearingSet.from_arrays(pos[:1], [0.1], [0.1], 0.01, 0.01)
    with pytest.raises(ValueError, match='position'):
        Bearing('s', 0, np.array([np.nan, 0, 0]), 0.1).validate()


def _full_check(b):
    """The vectorised field check alone (what validate did before its scalar fast path)."""
    try:
        bearings_module._check_bearing_fields(
            np.asarray(b.position, dtype=float)[None, None, :],
            np.array([[b.azimuth]], dtype=float), np.array([[b.elevation]], dtype=float),
            np.array([[b.sigma_azimuth]], dtype=float),
            np.array([[b.sigma_elevation]], dtype=float))
    except ValueError as exc:
        return str(exc)
    return None


def _assert_validate_agrees(obj, expected):
    """obj.validate() returns obj when ``expected`` is None, else raises ValueError with the
    message ``expected`` (any message for 'counts', the batch check's count failure)."""
    if expected is None:
        assert obj.validate() is obj
    else:
        with pytest.raises(ValueError) as info:
            obj.validate()
        assert expected == 'counts' or str(info.value) == expected


def test_bearing_validate_fast_path_agrees_with_full_check():
    """validate() accepts exactly what the vectorised check accepts and raises its message.

    Every field takes good, boundary and bad values (NaN, ±inf, 0, negatives, |ψ| = π/2 and
    the float just below it), in Python floats, numpy float64/float32, ints and lists, over
    4000 seeded random combinations."""
    rng = np.random.default_rng(13)
    below = math.nextafter(HALF_PI, 0.0)
    pos_choices = [np.array([1.0, 2.0, 3.0]), [1.0, 2.0, 3.0], (0, 0, 5),
                   np.array([1.0, np.nan, 3.0]), [np.inf, 0.0, 0.0], np.zeros((1, 3)),
                   np.zeros(2), np.array([1, 2, 3], dtype=np.float32), np.zeros(3, dtype=int)]
    angle_choices = [0.3, -3.0, math.nan, math.inf, -math.inf, np.float64(0.2), 1,
                     np.float32(0.1), HALF_PI, -HALF_PI, below, -below]
    sigma_choices = [0.01, 0.0, -0.01, math.nan, math.inf, np.float64(1e-300), 2, 5e-324]
    for _ in range(4000):
        pick = [pos_choices[rng.integers(len(pos_choices))]] + [
            angle_choices[rng.integers(len(angle_choices))] for _ in range(2)] + [
            sigma_choices[rng.integers(len(sigma_choices))] for _ in range(2)]
        b = Bearing('s', 0, *pick)
        _assert_validate_agrees(b, _full_check(b))


def _set_full_check(bs):
    """BearingSet.validate without its one-problem fast path: None or the message."""
    try:
        bearings_module._check_bearing_fields(bs.positions, bs.azimuth, bs.elevation,
                                              bs.sigma_az, bs.sigma_el)
        n_el = np.sum(bs.has_elevation, axis=1)
        if bs.N < 2 or np.any(n_el == 0) or np.any(bs.N + n_el < 3):
            return 'counts'
    except ValueError as exc:
        return str(exc)
    return None


def test_bearing_set_one_problem_fast_path_agrees_with_full_check():
    """A one-problem BearingSet passes validate() exactly when the vectorised check passes it,
    and gets that check's message otherwise (the fast path only ever says 'certainly valid').

    3000 seeded sets of N = 1-5 bearings whose fields take good, boundary and bad values."""
    rng = np.random.default_rng(17)
    below = math.nextafter(HALF_PI, 0.0)
    coords = [0.0, 1e3, -2e4, math.nan, math.inf, -math.inf, 1e308]
    angles = [0.3, -3.0, math.nan, math.inf, -math.inf, HALF_PI, -HALF_PI, below, 7.0]
    sigmas = [0.01, 0.0, -0.01, math.nan, math.inf, 1e-12, 1e-13, 1e3, 1.0001e3]
    for _ in range(3000):
        N = int(rng.integers(1, 6))
        pos = rng.uniform(-1e4, 1e4, (1, N, 3))
        az, el = rng.uniform(-3, 3, (1, N)), rng.uniform(-1, 1, (1, N))
        saz, sel = np.full((1, N), 0.01), np.full((1, N), 0.01)
        el[0, rng.random(N) < 0.4] = np.nan
        for arr, choices in ((pos, coords), (az, angles), (el, angles), (saz, sigmas),
                             (sel, sigmas)):
            if rng.random() < 0.3:
                arr.flat[rng.integers(arr.size)] = choices[rng.integers(len(choices))]
        bs = BearingSet(pos, az, el, saz, sel)
        _assert_validate_agrees(bs, _set_full_check(bs))


def test_crlb_equals_inverse_fisher_and_matches_monte_carlo_linearisation():
    pos = np.array([[30e3, -10e3, 100], [30e3, 20e3, 200], [-30e3, 5e3, 150.0]])
    tgt = np.array([[10e3, 40e3, 5e3]])
    J = fisher_information(tgt, pos, 1.5e-3)
    C = crlb(tgt, pos, 1.5e-3)
    assert np.allclose(C[0] @ J[0], np.eye(3), atol=1e-9)
    # Numerical Jacobian of the angles confirms the analytic gradients inside J.
    eps = 1e-3
    rows = []
    for k in range(3):
        dp = np.zeros(3)
        dp[k] = eps
        a1, e1 = azimuth_elevation(tgt[0] + dp - pos)
        a0, e0 = azimuth_elevation(tgt[0] - dp - pos)
        rows.append(np.concatenate([a1 - a0, e1 - e0]) / (2 * eps))
    G = np.array(rows).T / 1.5e-3
    assert np.allclose(G.T @ G, J[0], rtol=1e-6)
    assert gdop(C)[0] > 0


def test_simulate_bearings_noise_free_is_exact():
    pos = np.array([[0, 0, 0], [1000, 0, 0.0]])
    bs = simulate_bearings([500, 500, 100], pos, 0.01, has_elevation=[True, False])
    assert bs.azimuth[0, 0] == pytest.approx(np.pi / 4)
    assert np.isnan(bs.elevation[0, 1]) and np.isnan(bs.sigma_el[0, 1])


def test_simulate_bearings_clips_elevation_past_the_zenith():
    # The target 2e-6 rad from station 0's zenith with σ_ψ = 0.01: about half the draws cross
    # ±π/2, which raised ValueError('elevation: |elevation| must be < pi/2'). Clipped to
    # ±MAX_ELEVATION as the simulator and core.evaluation do; the other draws are unchanged.
    from bearing_loc_ros.core.scenario_model import MAX_ELEVATION
    assert bearings_module.MAX_ELEVATION is MAX_ELEVATION       # one rule, one constant
    st = np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0]])
    tgt = np.tile([0.01, 0.0, 5000.0], (1000, 1))
    bs = simulate_bearings(tgt, st, 1e-3, 1e-2, rng=np.random.default_rng(0))
    el = bs.elevation[:, 0]
    assert np.all(np.abs(el) <= MAX_ELEVATION) and np.any(el == MAX_ELEVATION)
    raw = math.atan2(5000.0, 0.01) + 1e-2 * np.random.default_rng(0).standard_normal(
        (2, 1000, 2))[1, :, 0]
    np.testing.assert_array_equal(el, np.minimum(raw, MAX_ELEVATION))
    overhead = simulate_bearings([0.0, 0.0, 100.0], st, 1e-3)      # noise-free, exactly above
    assert overhead.elevation[0, 0] == MAX_ELEVATION


def test_bearing_covariance6_layout():
    from bearing_loc_ros.core.conventions import (bearing_covariance6, IDX_AZ_VAR, IDX_EL_VAR,
                                                  NO_ELEVATION_VARIANCE)
    pcov = np.array([[1.0, 0.1, 0.2], [0.1, 2.0, 0.3], [0.2, 0.3, 3.0]])
    c = bearing_covariance6(pcov, 0.02, 0.05).reshape(6, 6)
    np.testing.assert_array_equal(c[:3, :3], pcov)
    assert c.flat[IDX_EL_VAR] == c[4, 4] == 0.05 ** 2
    assert c.flat[IDX_AZ_VAR] == c[5, 5] == 0.02 ** 2
    rest = c.copy()
    rest[:3, :3] = 0.0
    rest[4, 4] = rest[5, 5] = 0.0
    assert not rest.any()
    c1 = bearing_covariance6(pcov, 0.02)
    assert c1[IDX_EL_VAR] == NO_ELEVATION_VARIANCE == -1.0 and c1.shape == (36,)
