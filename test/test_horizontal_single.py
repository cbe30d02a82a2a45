"""One-problem float path of the horizontal mle/wmle and its robust screen against the batch path.

A one-problem call (M = 1) runs core/horizontal_single.py; the same problem twice in one
batch (M = 2) runs the vectorised iteration of core/horizontal_ml.py. Both must give the same
statuses, iterations and excluded bearings, and the same fixes to rounding.
"""
import numpy as np
import pytest

from bearing_loc_ros.core.bearings import BearingSet
from bearing_loc_ros.core.horizontal import locate_horizontal, screen_passed, simulate_bearings
from bearing_loc_ros.core.horizontal_estimators import prepare
from bearing_loc_ros.core.horizontal_robust import screen_one


def _twice(one):
    return BearingSet(*(np.concatenate([a, a]) for a in (
        one.positions, one.azimuth, one.elevation, one.sigma_az, one.sigma_el)))


def _azimuths(positions, azimuth):
    """An azimuth-only one-problem set, σ 1 mrad."""
    n = len(azimuth)
    return BearingSet.from_arrays(positions, np.array(azimuth, dtype=float), np.full(n, np.nan),
                                  np.full(n, 1e-3), np.full(n, np.nan), require_elevation=False)


def _problems(rng, count, N, sigma=2e-3, outliers=False):
    """One-problem sets: stations within ±20 km, targets 0.5-7 km high, 1D/2D mix."""
    out = []
    for _ in range(count):
        st = np.column_stack([rng.uniform(-20e3, 20e3, (N, 2)), rng.uniform(0.0, 200.0, N)])
        tgt = np.array([*rng.uniform(-10e3, 10e3, 2), rng.uniform(500.0, 7e3)])
        mask = rng.random(N) < 0.5
        bs = simulate_bearings(tgt, st, sigma, sigma, has_elevation=mask, rng=rng)
        if outliers and N >= 4:
            bs.azimuth[0, rng.integers(N)] += rng.choice([-1.0, 1.0]) * rng.uniform(3, 40) * sigma
        out.append((bs, tgt[2]))
    return out


def _assert_same(fast, plain, position_tol=1e-12, covariance_tol=1e-10):
    assert fast.status[0] == plain.status[0]
    assert fast.iterations[0] == plain.iterations[0]
    assert fast.converged[0] == plain.converged[0]
    for name in ('position', 'covariance'):
        a, b = getattr(fast, name)[0], getattr(plain, name)[0]
        assert np.array_equal(np.isfinite(a), np.isfinite(b)), name
        assert np.array_equal(a[~np.isfinite(a)], b[~np.isfinite(b)], equal_nan=True), name
    fin = np.isfinite(plain.position[0])
    if fin.any():
        # The float path's atan2 (C library) and numpy's differ in the last bit on a few
        # per cent of arguments, so the iterates differ by rounding: on well-posed problems
        # positions within 1e-12 of their scale, covariances within 1e-10 of their largest
        # entry (the inverse of the information amplifies its rounding by the condition
        # number, up to ~1e4 on these geometries; measured 1e-12 at most).
        scale = np.max(np.abs(plain.position[0]))
        np.testing.assert_allclose(fast.position[0], plain.position[0], rtol=0,
                                   atol=position_tol * scale)
        P = plain.covariance[0]
        np.testing.assert_allclose(fast.covariance[0], P, rtol=0,
                                   atol=covariance_tol * np.max(np.abs(P[np.isfinite(P)])))
    assert np.array_equal(fast.solve, plain.solve[:1])
    if plain.nonlinearity is not None:
        # ν as the status took it: on floats where the one-problem screen decides.
        np.testing.assert_allclose(fast.nonlinearity, plain.nonlinearity[:1],
                                   rtol=covariance_tol)


@pytest.mark.parametrize('method', ['mle', 'wmle'])
def test_one_problem_path_gives_the_batch_paths_results(method):
    rng = np.random.default_rng(61)
    cases = []
    for N in (2, 3, 4, 6, 10):
        for bs, z0 in _problems(rng, 12, N):
            for sz in (0.0, 10.0):
                cases.append((bs, z0, sz, True, {}))
                cases.append((bs, z0, sz, False, {}))
    for bs, z0 in _problems(rng, 6, 4):
        cases.append((bs, z0, 10.0, True, {'max_iterations': 1}))
        # Without robust the status max_iterations stays (the robust solve makes it
        # low_confidence), so both paths are compared on it too.
        cases.append((bs, z0, 10.0, True, {'max_iterations': 1, 'robust': False}))
        cases.append((bs, z0, 10.0, True, {'initial': [3e4, -2e4, 900.0], 'tolerance': 1e-6}))
        cases.append((bs, z0, 0.0, True, {'initial': [3e4, -2e4]}))
    if method == 'wmle':
        cases = [c[:4] + (dict(c[4], reference_range=700.0),) for c in cases]
    statuses = set()
    for bs, z0, sz, use_el, opts in cases:
        fast = locate_horizontal(method, bs, z0, sz, use_el, **opts)
        plain = locate_horizontal(method, _twice(bs), z0, sz, use_el, **opts)
        _assert_same(fast, plain)
        statuses.add(str(fast.status[0]))
    assert {'ok', 'max_iterations'} <= statuses


def test_degenerate_problems_give_the_batch_paths_results():
    # Collinear stations with the target on their line (azimuth-only: degenerate on both
    # paths), a target on a station's vertical axis and parallel bearings (the float path
    # hands IEEE cases to the batch path), and a start on a station.
    rng = np.random.default_rng(62)
    line = np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 5.0], [2500.0, 0.0, 0.0]])
    cases = [
        (simulate_bearings([4000.0, 0.0, 100.0], line, 1e-3, rng=rng), {}),
        (simulate_bearings([4000.0, 0.0, 100.0], line, 1e-3), {}),
        (simulate_bearings([1000.0, 2000.0, 100.0], line, 1e-3, rng=rng), {}),
        (simulate_bearings([1000.0, 2000.0, 100.0], line, 1e-3, rng=rng),
         {'initial': [1000.0, 0.0]}),
        (_azimuths(line[:2], [0.5, 0.5]), {}),
        (_azimuths(line[:2], [0.0, np.pi]), {}),
    ]
    # Nearly parallel azimuths: a start exists, the information at the fix may not (the float
    # path reports degenerate_geometry itself at cuts near 1.7e-6 rad).
    tri = np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0], [300.0, 800.0, 0.0]])
    cases += [(_azimuths(tri, [0.3, 0.3 + c, 0.3 - 0.5 * c]), {})
              for c in (1e-5, 1.7012542798525892e-06, 1.6e-6, 1e-6)]
    on_station = simulate_bearings([1000.0, 0.0, 300.0], np.vstack([line, [[0, 900, 0]]]),
                                   1e-3)
    cases.append((on_station, {}))
    statuses = set()
    for bs, opts in cases:
        for method in ('mle', 'wmle'):
            for sz in (0.0, 10.0):
                fast = locate_horizontal(method, bs, 100.0, sz, **opts)
                plain = locate_horizontal(method, _twice(bs), 100.0, sz, **opts)
                # Nearly singular problems: rounding decides where within the stopping
                # tolerance (1e-9 of the rms range) the iteration ends.
                _assert_same(fast, plain, 1e-9, 1e-6)
                statuses.add(str(fast.status[0]))
    assert 'degenerate_geometry' in statuses and 'ok' in statuses


def test_bad_one_problem_input_names_the_same_field_as_a_batch():
    bs = simulate_bearings([1000.0, 2000.0, 100.0], np.array(
        [[0.0, 0.0, 0.0], [3000.0, 0.0, 0.0], [0.0, 3000.0, 0.0]]), 1e-3)
    bad = []
    for field, value in (('azimuth', np.nan), ('sigma_az', -1.0), ('sigma_az', np.inf),
                         ('elevation', 2.0), ('elevation', np.inf)):
        b = BearingSet(*(a.copy() for a in (bs.positions, bs.azimuth, bs.elevation,
                                            bs.sigma_az, bs.sigma_el)))
        getattr(b, field)[0, 1] = value
        if field == 'elevation':
            b.sigma_el[0, 1] = 1e-3
        bad.append((b, 100.0, 0.0, True))
    pos = bs.positions.copy()
    pos[0, 0, 0] = np.nan
    bad.append((BearingSet(pos, bs.azimuth, bs.elevation, bs.sigma_az, bs.sigma_el),
                100.0, 0.0, True))
    bad += [(bs, np.nan, 0.0, True), (bs, 100.0, -1.0, True), (bs, True, 0.0, True),
            (bs, np.array([np.inf]), 0.0, True), (bs, 100.0, np.array([-2.0]), True),
            (bs, 10 ** 400, 0.0, True),
            (bs, 100.0, np.inf, True), (bs, 100.0, 0.0, 1), (bs, 'high', 0.0, True)]
    for b, z0, sz, use_el in bad:
        with pytest.raises(ValueError) as one:
            locate_horizontal('mle', b, z0, sz, use_el)
        with pytest.raises(ValueError) as two:
            locate_horizontal('mle', _twice(b), z0, sz, use_el)
        assert str(one.value) == str(two.value)


def test_one_problem_prepare_builds_the_batch_arrays():
    rng = np.random.default_rng(63)
    for bs, z0 in _problems(rng, 5, 5):
        for z, sz, use_el in ((z0, 0.0, True), (z0, 7.5, False),
                              (np.array([z0]), np.float64(2.0), np.bool_(True)),
                              (int(z0), np.array(3), False)):
            fast, full = prepare(bs, z, sz, use_el), prepare(_twice(bs), z, sz, use_el)
            for name in ('px', 'py', 'pz', 'az', 'el', 'saz', 'sel', 'use_el', 'z0', 'sz'):
                a, b = getattr(fast, name), getattr(full, name)[:1]
                assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), name


@pytest.mark.parametrize('method', ['mle', 'wmle'])
def test_robust_one_fix_gives_the_batch_paths_results(method):
    # Clean sets (the screen keeps the fix) and sets with one bad azimuth (the consensus and
    # refit run, every refit itself a one-problem solve). wmle's σ is σ_ref at d_ref: d_ref
    # 15 km keeps the outliers (3-40 σ_ref) outliers at these ranges.
    opts = {} if method == 'mle' else {'reference_range': 15e3}
    rng = np.random.default_rng(64)
    cases = _problems(rng, 25, 4) + _problems(rng, 25, 8, outliers=True)
    cases += _problems(rng, 10, 10, outliers=True)
    excluded = 0
    for bs, z0 in cases:
        fast = locate_horizontal(method, bs, z0, 10.0, robust=True, **opts)
        plain = locate_horizontal(method, _twice(bs), z0, 10.0, robust=True, **opts)
        _assert_same(fast, plain)
        assert np.array_equal(fast.excluded[0], plain.excluded[0])
        excluded += int(fast.excluded[0].any())
    assert excluded >= 10


def test_float_screen_agrees_with_the_vectorised_screen():
    # Fixes moved off the optimum by growing amounts cross the screen's thresholds; the
    # float screen decides as screen_passed or defers (None) near a threshold.
    rng = np.random.default_rng(65)
    decided = {True: 0, False: 0}
    for bs, z0 in _problems(rng, 40, 5) + _problems(rng, 20, 8, outliers=True):
        for d_ref in (None, 900.0):
            method = 'mle' if d_ref is None else 'wmle'
            opts = {} if d_ref is None else {'reference_range': d_ref}
            res = locate_horizontal(method, bs, z0, 10.0, **opts)
            p = prepare(bs, z0, 10.0)
            for shift in (0.0, 3.0, 30.0, 300.0):
                moved = type(res)(res.position + [shift, -shift, 0.0], res.covariance,
                                  res.iterations, res.converged, res.status, res.method)
                got = screen_one(bs, moved, p.use_el[0], d_ref)
                want = bool(screen_passed(bs, moved, p, d_ref)[0])
                if got is not None:
                    assert got == want
                    decided[got] += 1
    assert decided[True] >= 20 and decided[False] >= 20


# The batch path computes with 1/σ_z² = inf and reports the fix as not converged; numpy
# warns about it on the way.
@pytest.mark.filterwarnings('ignore::RuntimeWarning')
def test_an_altitude_sigma_whose_square_underflows_goes_to_the_batch_path():
    # σ_z = 1e-170 is a valid, positive σ, but 1/σ_z² overflows on floats: the one-problem
    # path must hand the problem over instead of raising ZeroDivisionError.
    rng = np.random.default_rng(5)
    tri = np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0], [300.0, 800.0, 0.0]])
    bs = simulate_bearings([500.0, 400.0, 100.0], tri, 1e-3, rng=rng)
    for method in ('mle', 'wmle'):
        fast = locate_horizontal(method, bs, 100.0, 1e-170)
        plain = locate_horizontal(method, _twice(bs), 100.0, 1e-170)
        assert str(fast.status[0]) == str(plain.status[0])
