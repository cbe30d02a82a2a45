"""Horizontal solve through the registry: solve-level options, bound, robust fix, bad input."""

import numpy as np
import pytest

from bearing_loc_ros.core import registry
from bearing_loc_ros.core.bearings import BearingSet
from bearing_loc_ros.core.horizontal import simulate_bearings
from bearing_loc_ros.core.horizontal_crlb import horizontal_crlb
from bearing_loc_ros.core.robust import _c2

# Wang, Zhang & Wu section 4 station layout (azimuth only here), target at a known altitude.
STATIONS = np.array([[0.0, 0.0, 0.0], [20e3, 0.0, 0.0], [20e3, 20e3, 0.0]])
TARGET = np.array([10e3, 30e3, 500.0])


def az_only(rng=None, sigma=0.0015, target=TARGET, stations=STATIONS):
    return simulate_bearings(target, stations, sigma, rng=rng)


def test_solve_reports_the_solve_and_the_stated_altitude():
    res = registry.solve('mle', az_only(), target_altitude=500.0, target_altitude_sigma=20.0)
    assert list(res.solve) == ['horizontal']
    np.testing.assert_allclose(res.position[0], TARGET, atol=1e-6)
    one = res.single()
    assert one['solve'] == 'horizontal'
    assert one['target_altitude'] == 500.0 and one['target_altitude_sigma'] == 20.0
    # z variance is the stated σ², no x-y/z correlation for an azimuth-only set
    assert res.covariance[0, 2, 2] == pytest.approx(400.0)
    assert np.all(res.covariance[0, :2, 2] == 0.0)


def test_3d_set_without_altitude_keeps_the_3d_solve():
    bs = simulate_bearings(TARGET, STATIONS, 0.0015, has_elevation=True)
    res = registry.solve('mle', bs)
    assert list(res.solve) == ['3d']
    assert 'target_altitude' not in res.single()


@pytest.mark.parametrize('options, field', [
    ({}, 'target_altitude'),
    ({'dimension': 'horizontal'}, 'target_altitude'),
    ({'target_altitude': float('nan')}, 'options.target_altitude'),
    ({'target_altitude': float('inf')}, 'options.target_altitude'),
    ({'target_altitude': 0.0, 'target_altitude_sigma': -1.0}, 'options.target_altitude_sigma'),
    ({'target_altitude': 0.0, 'dimension': '2d'}, 'options.dimension'),
    ({'target_altitude': 0.0, 'use_elevations': 'yes'}, 'options.use_elevations'),
    ({'target_altitude': 'high'}, 'options.target_altitude'),
])
def test_bad_solve_options_are_named_errors(options, field):
    with pytest.raises(ValueError, match=f'^{field}:'):
        registry.solve('mle', az_only(), **options)


def test_check_accepts_solve_options_for_multistation_only():
    kw = registry.check('ls', {'dimension': 'horizontal', 'target_altitude': 3.0})
    assert kw == {'dimension': 'horizontal', 'target_altitude': 3.0}
    assert registry.scoped_options('tma_mle', {'dimension': 'auto'}) == {}


@pytest.mark.parametrize('name', ['ls', 'tls', 'ctls', 'ctls_am', 'mle', 'wmle'])
def test_collinear_target_on_the_station_line_is_degenerate(name):
    st = np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0], [2500.0, 0.0, 0.0]])
    bs = az_only(target=np.array([4000.0, 0.0, 0.0]), stations=st)
    res = registry.solve(name, bs, target_altitude=0.0)
    assert list(res.status) == ['degenerate_geometry']
    assert np.all(np.isnan(res.position)) and not res.converged[0]


def test_noise_crlb_of_horizontal_solves_is_the_horizontal_bound():
    bs = az_only()
    res = registry.solve('mle', bs, target_altitude=500.0, target_altitude_sigma=5.0)
    bound = registry.noise_crlb('mle', res.position, bs, solve=res.solve,
                                target_altitude=500.0, target_altitude_sigma=5.0)
    ref = horizontal_crlb(TARGET, STATIONS, 0.0015, sigma_z=5.0)
    np.testing.assert_allclose(bound, ref, rtol=1e-9)
    # wmle: σ grown with range (Zong & Cui 2015 eqs. (9)-(10)) before the bound
    w = registry.noise_crlb('wmle', res.position, bs, solve=res.solve, target_altitude=500.0,
                            reference_range=1000.0)
    d = np.linalg.norm(TARGET - STATIONS, axis=1)
    np.testing.assert_allclose(w, horizontal_crlb(TARGET, STATIONS, 0.0015 * d / 1000.0),
                               rtol=1e-9)


def test_azimuth_only_set_passes_the_field_checks_only():
    bs = az_only()
    with pytest.raises(ValueError, match='^elevation:'):
        bs.validate()
    assert bs.validate(require_elevation=False) is bs
    bad = BearingSet(bs.positions, bs.azimuth * np.nan, bs.elevation, bs.sigma_az, bs.sigma_el)
    with pytest.raises(ValueError, match='^azimuth:'):
        bad.validate(require_elevation=False)


def _track(N):
    t = np.linspace(0.0, 1.0, N)
    return np.column_stack([4000.0 * t, 600.0 * np.sin(3.0 * t), np.zeros(N)])


def test_robust_horizontal_fix_excludes_reflections():
    """Many bearings, 10 % of them 20-90° off: the robust fix excludes exactly the bad ones
    (each is > 5 σ off) and its error is consistent with its covariance (χ²₂ 99.9 % gate)."""
    rng = np.random.default_rng(7)
    N, sigma = 200, np.radians(4.0)
    target = np.array([2000.0, 3000.0, 0.0])
    bs = simulate_bearings(target, _track(N), sigma, rng=rng)
    bad = np.zeros(N, dtype=bool)
    bad[rng.choice(N, N // 10, replace=False)] = True
    off = np.radians(rng.uniform(20, 90, bad.sum())) * rng.choice([-1, 1], bad.sum())
    bs.azimuth[0, bad] += off
    plain = registry.solve('mle', bs, target_altitude=0.0, robust=False)
    res = registry.solve('mle', bs, target_altitude=0.0, robust=True)
    assert res.status[0] == 'ok'
    ex = res.excluded[0, :, 0]
    assert np.all(ex[bad])
    # good bearings excluded only as the Gaussian tail beyond c² allows (expected < 0.02)
    assert np.count_nonzero(ex & ~bad) <= 2
    err = res.position[0, :2] - target[:2]
    d2 = err @ np.linalg.solve(res.covariance[0, :2, :2], err)
    assert d2 < 13.8
    # the fix is the full-likelihood fit of the kept bearings
    kept = registry.solve('mle', bs.subset(~ex), target_altitude=0.0, robust=False)
    np.testing.assert_allclose(res.position, kept.position, atol=1e-3)
    np.testing.assert_allclose(res.covariance, kept.covariance, rtol=1e-3)
    assert plain.excluded is None


def test_robust_keeps_a_clean_fix_unchanged():
    rng = np.random.default_rng(3)
    bs = simulate_bearings(np.array([2000.0, 3000.0, 0.0]), _track(60), np.radians(3.0),
                           rng=rng)
    plain = registry.solve('mle', bs, target_altitude=0.0, robust=False)
    res = registry.solve('mle', bs, target_altitude=0.0, robust=True)
    d2 = ((bs.azimuth[0] - np.arctan2(3000.0 - bs.positions[0, :, 1],
                                      2000.0 - bs.positions[0, :, 0])) / np.radians(3.0)) ** 2
    if np.all(d2 < _c2()):
        np.testing.assert_array_equal(res.position, plain.position)
    assert not res.excluded.any() or res.status[0] == 'ok'


def test_robust_is_refused_by_estimators_without_it():
    with pytest.raises(ValueError, match='^options.robust:'):
        registry.solve('ls', az_only(), target_altitude=0.0, robust=True)


def _locate(tmp_path, capsys, doc, *flags):
    import json
    from bearing_loc_ros.cli import main
    path = tmp_path / 'in.json'
    path.write_text(json.dumps(doc))
    capsys.readouterr()
    code = main(['locate', str(path), *flags])
    out, err = capsys.readouterr()
    return code, (json.loads(out) if out else None), err


def _json_bearings(bs):
    return [{'station': f's{i}', 'position': bs.positions[0, i].tolist(),
             'azimuth': float(bs.azimuth[0, i]), 'sigma_azimuth': float(bs.sigma_az[0, i])}
            for i in range(bs.N)]


def test_cli_locate_azimuth_only(tmp_path, capsys):
    """locate: flags and JSON options, the solve and the stated altitude in the output,
    the CRLB of the horizontal solve; clear errors for no altitude, NaN, collinear."""
    doc = {'estimator': 'mle', 'bearings': _json_bearings(az_only())}
    code, res, err = _locate(tmp_path, capsys, doc, '--target-altitude', '500',
                             '--target-altitude-sigma', '5')
    assert code == 0, err
    assert res['solve'] == 'horizontal' and res['target_altitude'] == 500.0
    np.testing.assert_allclose(res['position'], TARGET, atol=1e-6)
    np.testing.assert_allclose(res['crlb'], horizontal_crlb(TARGET, STATIONS, 0.0015,
                                                            sigma_z=5.0)[0], rtol=1e-9)
    doc['options'] = {'target_altitude': 500.0, 'dimension': 'horizontal'}
    code, res, _ = _locate(tmp_path, capsys, doc)
    assert code == 0 and res['solve'] == 'horizontal'
    doc.pop('options')
    code, res, err = _locate(tmp_path, capsys, doc)
    assert code == 2 and res is None and err.strip().endswith(
        'target_altitude: required because the bearings do not observe the height (no usable '
        'elevation geometry); state the target altitude (m, world frame) and its standard '
        'deviation')
    code, res, err = _locate(tmp_path, capsys, doc, '--target-altitude', 'nan')
    assert code == 2 and 'options.target_altitude: must be finite' in err
    st = np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0], [2500.0, 0.0, 0.0]])
    doc = {'bearings': _json_bearings(az_only(target=np.array([4000.0, 0.0, 0.0]),
                                              stations=st))}
    code, res, err = _locate(tmp_path, capsys, doc, '--target-altitude', '0')
    assert code == 0 and res['status'] == 'degenerate_geometry' and res['position'] == [None] * 3


def test_planning_maps_of_azimuth_only_layouts():
    """The accuracy map and placement of an azimuth-only layout: the horizontal GDOP
    sqrt(P_xx + P_yy) of core.horizontal_crlb at z = the map altitude."""
    from bearing_loc_ros.core.horizontal_crlb import horizontal_gdop
    from bearing_loc_ros.core.planning import (accuracy_map, GridSpec, place_station,
                                               position_error, Stations)
    st = Stations.from_arrays(STATIONS, 0.0015, has_elevation=False)
    pts = np.array([[10e3, 30e3, 500.0], [-5e3, 12e3, 500.0], [40e3, -3e3, 500.0]])
    err = position_error(pts, st)
    ref = horizontal_gdop(horizontal_crlb(pts, STATIONS, 0.0015))
    np.testing.assert_allclose(err, ref, rtol=1e-9)
    assert np.all(np.isinf(position_error(pts, st, dimension='3d')))
    with pytest.raises(ValueError, match='^model:'):
        position_error(pts, st, model='ctls', dimension='horizontal')
    assert np.all(np.isinf(position_error(pts, st, model='ctls')))   # auto: the 3D model
    grid = GridSpec(-10e3, -10e3, 1000.0, 40, 50, 500.0)
    amap = accuracy_map(st, grid)
    assert amap.solve == 'horizontal'
    assert amap.stats()['finite_cells'] > 0.9 * amap.error.size
    two = Stations.from_arrays(STATIONS[:2], 0.0015, has_elevation=False)
    area = GridSpec(0.0, 5e3, 1000.0, 20, 20, 500.0)
    res = place_station(two, area, (-10e3, 30e3, -10e3, 40e3), has_elevation=False,
                        candidates=9)
    assert np.isfinite(res.after) and res.after < res.before


def test_plan_cli_azimuth_only(capsys):
    import json
    from bearing_loc_ros.cli import main
    assert main(['plan', 'map', '--stations', '0,0,0,1d;20,0,0,1d;20,20,0,1d',
                 '--altitude', '500', '--sigma-deg', '0.1', '--extent-km', '-20,40,-20,40',
                 '--resolution', '2000']) == 0
    out = json.loads(capsys.readouterr().out)
    assert out['solve'] == 'horizontal' and out['stats']['finite_cells'] > 0
    assert main(['plan', 'cut-angle', '--sigmas-deg', '1', '1']) == 0
    out = json.loads(capsys.readouterr().out)
    assert out['cut_angle_deg'] == pytest.approx(np.degrees(np.arccos(-1.0 / 3.0)))


def test_one_newton_iteration_serves_2d_and_3d():
    """core.solvers.newton_backtracking on a convex quadratic f = ½(X − c)ᵀQ(X − c): the
    minimiser in one full step, in 2 and 3 dimensions; a non-finite start is diverged."""
    from bearing_loc_ros.core.solvers import newton_backtracking, solve2

    class Quadratic:
        def __init__(self, Q, c):
            self.Q, self.c = Q, c

        def take(self, idx):
            return Quadratic(self.Q[idx], self.c[idx])

        def cost(self, X):
            d = X - self.c
            return 0.5 * np.einsum('mi,mij,mj->m', d, self.Q, d) + 1.0

        def derivatives(self, X):
            T = np.einsum('mij,mj->mi', self.Q, X - self.c)
            return self.cost(X), T, self.Q, self.Q

    rng = np.random.default_rng(0)
    for d in (2, 3):
        R = rng.standard_normal((5, d, d))
        Q = R @ np.swapaxes(R, 1, 2) + np.eye(d)
        c = rng.standard_normal((5, d)) * 100.0
        X0 = np.zeros((5, d))
        X0[4] = np.nan
        X, it, conv, div = newton_backtracking(Quadratic(Q, c), X0, 1.0, 1e-12, 20,
                                               np.full(5, 1e-12), lambda s, X: np.ones(len(X)))
        np.testing.assert_allclose(X[:4], c[:4], rtol=1e-9, atol=1e-9)
        assert conv[:4].all() and div[4] and np.isnan(X[4]).all()
    A = np.array([[[2.0, 1.0], [1.0, 3.0]], [[1.0, 2.0], [2.0, 1.0]]])
    x = solve2(A, np.array([[3.0, 4.0], [1.0, 1.0]]))
    np.testing.assert_allclose(x[0], [1.0, 1.0])
    assert np.isnan(x[1]).all()          # det < 0: not positive definite


def test_mle_is_robust_by_default_in_the_plane_as_in_3d():
    bs = az_only(np.random.default_rng(2))
    default = registry.solve('mle', bs, target_altitude=TARGET[2])
    assert default.excluded is not None                    # the robust path ran
    assert registry.solve('mle', bs, target_altitude=TARGET[2], robust=False).excluded is None
    assert registry.solve('wmle', bs, target_altitude=TARGET[2]).excluded is None


def test_three_azimuths_never_blame_one_of_them():
    # Any two of three azimuths intersect exactly: with one 30° off the data cannot tell
    # which one is wrong. The fix is the fit of all three, low_confidence, nothing excluded.
    bs = az_only()
    bs.azimuth[0, 1] += np.radians(30.0)
    plain = registry.solve('mle', bs, target_altitude=TARGET[2], robust=False)
    res = registry.solve('mle', bs, target_altitude=TARGET[2])
    assert res.status[0] == 'low_confidence' and not res.excluded.any()
    np.testing.assert_array_equal(res.position, plain.position)


def test_a_decisive_outlier_among_five_azimuths_is_excluded():
    stations = np.array([[0.0, 0.0, 0.0], [20e3, 0.0, 0.0], [20e3, 20e3, 0.0],
                         [-5e3, 25e3, 0.0], [0.0, 40e3, 0.0]])
    bs = az_only(np.random.default_rng(4), stations=stations)
    bs.azimuth[0, 3] += np.radians(30.0)
    res = registry.solve('mle', bs, target_altitude=TARGET[2])
    assert res.status[0] == 'ok'
    np.testing.assert_array_equal(res.excluded[0, :, 0], np.arange(5) == 3)
    err = res.position[0, :2] - TARGET[:2]
    assert err @ np.linalg.solve(res.covariance[0, :2, :2], err) < 13.8     # χ²₂ 99.9 %


def test_a_banana_region_is_low_confidence_and_every_ok_fix_has_a_small_nu():
    # σ 4° on the Wang, Zhang & Wu stations, azimuth only (config/scenarios/
    # seed000_azimuth_only.yaml): ν of the calm fixes spreads over 0.1-0.4.
    from bearing_loc_ros.core.horizontal_robust import nonlinearity
    from bearing_loc_ros.core.robust_model import MAX_REGION_NONLINEARITY
    st = np.array([[30e3, -10e3, 100.0], [30e3, 20e3, 200.0], [-30e3, 5e3, 150.0]])
    rng = np.random.default_rng(8)
    targets = np.column_stack([rng.uniform(40e3, 60e3, 400), rng.uniform(-20e3, 30e3, 400),
                               np.full(400, 5000.0)])
    bs = simulate_bearings(targets, st, np.radians(4.0), rng=rng)
    res = registry.solve('mle', bs, target_altitude=5000.0)
    nu = nonlinearity(res.position, res.covariance, bs.positions)
    np.testing.assert_allclose(res.nonlinearity, nu, rtol=1e-12)     # reported with the fix
    ok = res.status == 'ok'
    assert 0.1 * len(ok) < np.count_nonzero(ok) < 0.9 * len(ok)
    assert np.all(nu[ok] <= MAX_REGION_NONLINEARITY)
    assert np.all((res.status == 'ok') | (res.status == 'low_confidence'))
    assert not res.excluded.any()                   # three azimuths: nothing is blamed


def test_a_mixed_batch_keeps_the_exclusions_of_its_horizontal_problems():
    from bearing_loc_ros.core.horizontal import locate
    st = np.array([[0, 0, 0], [20e3, 0, 0], [20e3, 20e3, 0.], [0, 20e3, 0]])
    T = np.array([[10e3, 5e3, 3000.], [10e3, 5e3, 3000.]])
    bs = simulate_bearings(T, st, 0.01, 0.01, has_elevation=True, rng=np.random.default_rng(0))
    bs.elevation[1], bs.sigma_el[1] = np.nan, np.nan          # problem 1: azimuth only
    bs.azimuth[1, 2] += 0.5                                     # an outlier there
    mixed = locate('mle', bs, target_altitude=3000.0)
    alone = locate('mle', bs.problem(1), target_altitude=3000.0)
    assert list(mixed.solve) == ['3d', 'horizontal']
    np.testing.assert_array_equal(mixed.excluded[1], alone.excluded[0])
    assert mixed.excluded[1, 2, 0] and mixed.status[1] == alone.status[0]
    assert np.isnan(mixed.nonlinearity[1]) or mixed.nonlinearity[1] == alone.nonlinearity[0]


def test_decisive_with_a_station_under_the_fix_is_false_without_a_warning():
    import warnings
    from bearing_loc_ros.core.horizontal_robust import decisive
    st = np.array([[0.0, 0.0, 0.0], [20e3, 0.0, 0.0], [20e3, 20e3, 0.0], [-5e3, 25e3, 0.0]])
    bs = az_only(np.random.default_rng(1), stations=st)
    x = np.array([10e3, 30e3, 500.0])
    bs.positions[0, 3, :2] = x[:2]
    excluded = np.arange(4) == 3
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        assert decisive(bs, x, np.eye(3), excluded, np.zeros(4, bool)) is False
        # Away from the stations: an inlier's exclusion is not decisive, a 0.5 rad error is.
        first = np.arange(4) == 0
        assert decisive(bs, x, np.eye(3), first, np.zeros(4, bool)) is False
        bs.azimuth[0, 0] += 0.5
        assert decisive(bs, x, np.eye(3), first, np.zeros(4, bool)) is True


def _range_grown_azimuths(sigma_ref, n, noise_seed):
    """Zong & Cui (2015) section 3 trials (config/scenarios/seed003.yaml: σ grows with range,
    d_ref 1000 m), azimuths only, bearings stating σ_ref."""
    import math
    from bearing_loc_ros.core import evaluation as ev
    from bearing_loc_ros.core.simulation import load_scenario
    from bearing_loc_ros.scenarios import resolve_scenario
    tr = ev.trials_from_scenario(load_scenario(resolve_scenario('seed003')), n, 0)
    s = math.radians(sigma_ref)
    f = tr.sigma_factor()
    b = ev.noisy_bearings(tr, s * f, s * f, np.random.default_rng(noise_seed))
    nan = np.full_like(b.elevation, np.nan)
    return tr, BearingSet(b.positions, b.azimuth, nan, np.full_like(b.sigma_az, s), nan)


def test_range_grown_wmle_in_the_plane_is_never_confidently_short():
    # Azimuths only with σ growing with range: a fix that lands near the stations (where σ
    # is small) looks precise. Its covariance is widened to the test-inversion level and it is
    # ok only when the region is an ellipse out to 4.59σ, also along the direction in which
    # the near stations' σ grow. Trial 260 at σ_ref 5° landed 0.5 km from the stations, the
    # truth 5 km out, with a stated σ of 65 m (NEES 601).
    tr, bs = _range_grown_azimuths(5.0, 2000, 100)
    m = 260
    one = registry.solve('wmle', bs.problem(m), target_altitude=tr.targets[m, 2], robust=True,
                         reference_range=1000.0)
    assert one.status[0] == 'low_confidence' and one.nonlinearity[0] > 0.1
    # σ_ref 1°, 600 trials: about one fix in eight is ok (σ_ref 2° and above: none).
    tr, bs = _range_grown_azimuths(1.0, 600, 7)
    res = registry.solve('wmle', bs, target_altitude=tr.targets[:, 2], robust=True,
                         reference_range=1000.0)
    plain = registry.solve('wmle', bs, target_altitude=tr.targets[:, 2], robust=False,
                           reference_range=1000.0)
    ok = res.status == 'ok'
    assert np.count_nonzero(ok) >= 30
    e = (res.position - tr.targets)[:, :2]
    nees = np.einsum('mi,mij,mj->m', e, np.linalg.inv(res.covariance[:, :2, :2]), e)
    assert np.count_nonzero(ok & (nees > 18.42)) == 0
    assert np.all(res.nonlinearity[ok] <= 0.1)
    # The covariance is the estimator's widened along one axis, never narrowed.
    same = np.all(res.position == plain.position, axis=1)
    D = res.covariance[same, :2, :2] - plain.covariance[same, :2, :2]
    assert np.all(np.linalg.eigvalsh(D) > -1e-9 * np.abs(plain.covariance[same]).max())


@pytest.mark.parametrize('estimator', ['mle', 'wmle'])
def test_robust_horizontal_fixes_end_ok_low_confidence_or_degenerate(estimator):
    # σ 15° on the stations of the banana test: some iterations end on the likelihood's pole
    # at a station (max_iterations) or run off. As in 3D, the robust solve leaves no
    # max_iterations or diverged fix: a finite one is low_confidence, else degenerate; and
    # it never loses a finite fix the estimator had.
    st = np.array([[30e3, -10e3, 100.0], [30e3, 20e3, 200.0], [-30e3, 5e3, 150.0]])
    rng = np.random.default_rng(9)
    targets = np.column_stack([rng.uniform(40e3, 60e3, 600), rng.uniform(-20e3, 30e3, 600),
                               np.full(600, 5000.0)])
    bs = simulate_bearings(targets, st, np.radians(15.0), rng=rng)
    plain = registry.solve(estimator, bs, target_altitude=5000.0, robust=False)
    assert np.isin(plain.status, ('max_iterations', 'diverged')).any()    # the case exists
    res = registry.solve(estimator, bs, target_altitude=5000.0, robust=True)
    assert set(res.status) <= {'ok', 'low_confidence', 'degenerate_geometry'}
    finite = np.all(np.isfinite(res.position), axis=1)
    assert np.all(finite[res.status != 'degenerate_geometry'])
    assert not np.any(finite[res.status == 'degenerate_geometry'])
    assert np.all(finite[np.all(np.isfinite(plain.position), axis=1)])
    assert np.all(res.converged == (res.status == 'ok'))


@pytest.mark.parametrize('sigma_z', [0.0, 25.0])
def test_float_bound_along_an_axis_is_the_horizontal_crlb(sigma_z):
    # The robust wmle assessment evaluates the horizontal bound on floats, point by point.
    from bearing_loc_ros.core.horizontal_robust import _bound_sigma_along
    rng = np.random.default_rng(23)
    st = np.column_stack([rng.uniform(-20e3, 20e3, (5, 2)), rng.uniform(0.0, 200.0, 5)])
    has = np.array([True, False, True, False, True])
    sa, se = np.full(5, 0.01), np.where(has, 0.02, np.nan)
    for _ in range(50):
        X = np.array([*rng.uniform(-30e3, 30e3, 2), rng.uniform(500.0, 8e3)])
        v = rng.normal(size=2)
        v /= np.hypot(*v)
        f = np.linalg.norm(st - X, axis=1) / 1000.0
        P = horizontal_crlb(X, st, sa * f, se * f, has, sigma_z)[0, :2, :2]
        np.testing.assert_allclose(_bound_sigma_along(*X, *v, st, sa, se, has, 1000.0, sigma_z),
                                   np.sqrt(v @ P @ v), rtol=1e-12)
    # A station under the point: no finite bound.
    assert _bound_sigma_along(*st[0, :2], 3000.0, 1.0, 0.0, st, sa, se, has, 1000.0,
                              sigma_z) == np.inf
    # Collinear stations and point, azimuths only: the horizontal block is singular.
    line = np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0]])
    assert _bound_sigma_along(5000.0, 0.0, 0.0, 1.0, 0.0, line, np.full(2, 0.01),
                              np.full(2, np.nan), np.zeros(2, dtype=bool), 1000.0,
                              sigma_z) == np.inf


def test_consistency_marks_gross_horizontal_failures():
    # Fifty azimuth-only stations in a 1 km cluster, the target 100 km away, σ 0.05 rad:
    # the pseudo-linear and CTLS fixes end with Mahalanobis errors² of 1e6-1e10 (x-y) and
    # were ok; option consistency (core.horizontal.consistency_status) marks them.
    from bearing_loc_ros.core.horizontal import locate_horizontal
    S = np.c_[np.random.default_rng(3).uniform(-500, 500, (50, 2)), np.zeros(50)]
    bs = simulate_bearings([100e3, 20e3, 2000.0], S, 0.05, has_elevation=False,
                           rng=np.random.default_rng(0))
    for name in ('ls', 'ctls', 'ctls_am'):
        r = locate_horizontal(name, bs, 2000.0, 0.0)
        e = r.position[0, :2] - [100e3, 20e3]
        assert e @ np.linalg.solve(r.covariance[0, :2, :2], e) > 1e5, name
        assert r.status[0] == 'low_confidence', name
        assert locate_horizontal(name, bs, 2000.0, 0.0, consistency=False).status[0] == 'ok'


@pytest.mark.parametrize('has, sz', [((False,) * 4, 0.0), ((False,) * 4, 40.0),
                                     ((True, False, True, False), 40.0)])
def test_consistency_keeps_honest_horizontal_fixes_ok(has, sz):
    # Four stations, σ 2/3 mrad, the true altitude drawn from the stated prior: an honest
    # fix is rejected with probability ≈ 0.1 % + < 0.1 % + a few × 0.01 % (≈ 5 of 2000
    # expected); ≥ 98.9 % ok (22 or more rejections) has Poisson probability below 1e-6.
    from bearing_loc_ros.core.horizontal import locate_horizontal
    rng = np.random.default_rng(12)
    st = np.array([[0.0, 0.0, 0.0], [4000.0, 500.0, 20.0], [-2000.0, 3000.0, 5.0],
                   [1000.0, -2500.0, 0.0]])
    truth = np.tile([1500.0, 2500.0, 600.0], (2000, 1))
    truth[:, 2] += sz * rng.standard_normal(2000)
    bs = simulate_bearings(truth, st, 2e-3, 3e-3, has_elevation=list(has), rng=rng)
    for name in ('ls', 'tls', 'ctls', 'ctls_am'):
        r = locate_horizontal(name, bs, 600.0, sz)
        assert np.mean(r.status == 'ok') >= 0.989, name


def test_consistency_marks_the_horizontal_tail_with_an_uncertain_altitude():
    # One elevation station, σ_z = 300 m, the true altitude drawn from the prior: without
    # the check about 1 % of the tls/ctls_am fixes are confidently wrong (Mahalanobis² above
    # χ²₃ 0.9999 = 21.1); the check (Gauss-Newton iterated to the optimum) marks them, at
    # most 3 % of the fixes, and leaves at most 2 of 2000 such ok fixes.
    from bearing_loc_ros.core.horizontal import locate_horizontal
    st = np.array([[0.0, 0.0, 0.0], [4000.0, 500.0, 20.0], [-2000.0, 3000.0, 5.0],
                   [1000.0, -2500.0, 0.0], [3000.0, 4000.0, 10.0]])
    rng = np.random.default_rng(2)
    truth = np.tile([1500.0, 2500.0, 600.0], (2000, 1))
    truth[:, 2] += 300.0 * rng.standard_normal(2000)
    bs = simulate_bearings(truth, st, 0.6e-3, 0.6e-3,
                           has_elevation=[False, True, False, False, False], rng=rng)
    for name in ('tls', 'ctls_am'):
        wrong = {}
        for check in (False, True):
            r = locate_horizontal(name, bs, 600.0, 300.0, consistency=check)
            ok = r.status == 'ok'
            e = r.position[ok] - truth[ok]
            m2 = np.einsum('mi,mij,mj->m', e, np.linalg.inv(r.covariance[ok]), e)
            wrong[check] = int(np.sum(m2 > 21.1))
            if check:
                assert ok.mean() >= 0.97, name
        assert wrong[False] >= 8 and wrong[True] <= 2, (name, wrong)
