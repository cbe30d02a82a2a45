"""Accuracy maps, the CTLS error model, placement and OccupancyGrid maps (core/planning.py)."""
import numpy as np
import pytest

from bearing_loc_ros.core.bearings import simulate_bearings
from bearing_loc_ros.core.crlb import crlb, gdop
from bearing_loc_ros.core.planning import (AccuracyMap, GridSpec, Stations, accuracy_map,
                                           ctls_error_covariance, error_to_occupancy,
                                           occupancy_error_map, place_station, position_error)

KM = 1000.0
SEED000 = np.array([[30, -10, 0.1], [30, 20, 0.2], [-30, 5, 0.15]]) * KM


def dense_eq30(target, positions, sigma, has_el, unit=1.0):
    """Wang, Zhang & Wu (2006) eq. (30) literally: 2N x 2N block-diagonal F_j, G, H_X.

    1D stations have 1 x 1 blocks.
    """
    tgt = np.asarray(target, float) / unit
    pos = np.asarray(positions, float) / unit
    rows, F = [], [[], [], [], []]
    for (xi, yi, zi), e in zip(pos, has_el):
        d = tgt - (xi, yi, zi)
        th, ps = np.arctan2(d[1], d[0]), np.arctan2(d[2], np.hypot(d[0], d[1]))
        s, c, sp, cp = np.sin(th), np.cos(th), np.sin(ps), np.cos(ps)
        blocks = [[[-c, 0], [s * sp, -c * cp]], [[-s, 0], [-c * sp, -s * cp]],
                  [[0, 0], [0, -sp]],
                  [[-(c * xi + s * yi), 0],
                   [s * sp * xi - c * sp * yi, -(c * cp * xi + s * cp * yi + sp * zi)]]]
        k = 2 if e else 1
        for j in range(4):
            F[j].append(np.array(blocks[j], float)[:k, :k])
        rows += [[s, -c, 0], [c * sp, s * sp, -cp]][:k]
    from scipy.linalg import block_diag
    F = [block_diag(*f) for f in F]
    H = np.array(rows)
    HX = tgt[0] * F[0] + tgt[1] * F[1] + tgt[2] * F[2] - F[3]
    G = sum(f.T @ f for f in F)
    W = np.linalg.inv(HX @ np.linalg.inv(G) @ HX.T)
    Ai = np.linalg.inv(H.T @ W @ H)
    PE = np.diag(np.concatenate([[sa ** 2, se ** 2][:2 if e else 1]
                                 for (sa, se), e in zip(sigma, has_el)]))
    return Ai @ H.T @ W @ HX @ PE @ HX.T @ W @ H @ Ai * unit ** 2


def _random_layout(rng, n=4, one_d=(False, False, True, False)):
    pos = np.column_stack([rng.uniform(-30e3, 30e3, (n, 2)), rng.uniform(0, 300, n)])
    saz = rng.uniform(1e-3, 5e-3, n)
    sel = rng.uniform(1e-3, 5e-3, n)
    has_el = ~np.array(one_d[:n])
    return Stations.from_arrays(pos, saz, sel, has_el)


@pytest.mark.parametrize('unit', [1.0, KM])
def test_ctls_model_matches_dense_eq30(unit):
    rng = np.random.default_rng(30)
    for _ in range(5):
        st = _random_layout(rng)
        tgt = np.array([rng.uniform(-50e3, 50e3), rng.uniform(-50e3, 50e3), 5e3])
        P = ctls_error_covariance(tgt, st, length_unit=unit)[0]
        R = dense_eq30(tgt, st.positions, np.column_stack([st.sigma_az, st.sigma_el]),
                       st.has_elevation, unit)
        np.testing.assert_allclose(P, R, rtol=1e-9, atol=1e-9 * np.abs(R).max())


def test_ctls_model_matches_core_ctls_covariance():
    # The CTLS covariance, Wang, Zhang & Wu eq. (30) (core.constrained_tls, evaluated at the
    # true target), and the planner's block formulas must agree: the planner predicts the
    # estimator's error.
    from bearing_loc_ros.core.constrained_tls import ctls_covariance
    rng = np.random.default_rng(31)
    st = _random_layout(rng)
    tgt = np.column_stack([rng.uniform(-60e3, 60e3, (50, 2)), rng.uniform(1e3, 15e3, 50)])
    bs = simulate_bearings(tgt, st.positions, st.sigma_az, np.nan_to_num(st.sigma_el, nan=1.0),
                           has_elevation=st.has_elevation)
    ref = ctls_covariance(tgt, bs)
    np.testing.assert_allclose(ctls_error_covariance(tgt, st), ref, rtol=1e-8,
                               atol=1e-8 * np.abs(ref).max())


def test_ctls_model_is_never_better_than_the_crlb():
    # Eq. (30) is the first-order covariance of an unbiased estimator: P − CRLB is PSD.
    rng = np.random.default_rng(32)
    st = _random_layout(rng)
    tgt = np.column_stack([rng.uniform(-60e3, 60e3, (200, 2)), rng.uniform(1e3, 15e3, 200)])
    P = ctls_error_covariance(tgt, st)
    C = crlb(tgt, st.positions, st.sigma_az, st.sigma_el, st.has_elevation)
    w = np.linalg.eigvalsh(P - C)
    assert np.all(w[:, 0] >= -1e-9 * np.trace(C, axis1=1, axis2=2))


def test_crlb_map_is_the_core_crlb():
    # The planner and the estimators speak about the same error: core.crlb's GDOP.
    st = Stations.from_arrays(SEED000, 1.5e-3, 3e-3, [True, True, False])
    g = GridSpec.from_extent(-60 * KM, 60 * KM, -40 * KM, 40 * KM, 2 * KM, 5 * KM)
    m = accuracy_map(st, g)
    assert m.error.shape == (40, 60)
    ref = gdop(crlb(g.points(), st.positions, st.sigma_az, st.sigma_el, st.has_elevation))
    np.testing.assert_allclose(m.error.ravel(), ref, rtol=1e-10)


def test_grid_layout_is_occupancy_grid_order():
    g = GridSpec(origin_x=-100.0, origin_y=50.0, resolution=10.0, width=4, height=3,
                 altitude=7.0)
    pts = g.points()
    assert pts.shape == (12, 3)
    # data[r * width + c] is the cell whose centre is origin + ((c + 0.5), (r + 0.5)) * res.
    r, c = 2, 1
    np.testing.assert_allclose(pts[r * 4 + c], [-100 + 15.0, 50 + 25.0, 7.0])
    assert g.extent == (-100.0, -60.0, 50.0, 80.0)
    with pytest.raises(ValueError, match='resolution'):
        GridSpec(0, 0, 0.0, 3, 3, 0)
    with pytest.raises(ValueError, match='width'):
        GridSpec(0, 0, 1.0, 0, 3, 0)


def test_unobservable_and_on_axis_cells():
    # Two 1D stations never fix the height: in 3D every cell is +inf (unobservable); the
    # default (auto) assesses them with the horizontal solve, altitude known.
    st = Stations.from_arrays(SEED000[:2], 1e-3, has_elevation=False)
    g = GridSpec.from_extent(-10 * KM, 10 * KM, -10 * KM, 10 * KM, 5 * KM, 1 * KM)
    assert accuracy_map(st, g).solve == 'horizontal'
    m = accuracy_map(st, g, dimension='3d')
    assert np.all(np.isposinf(m.error))
    assert m.stats()['unobservable_cells'] == 16
    # A cell centre on a station's vertical axis (azimuth undefined) is NaN, not a number.
    st = Stations.from_arrays([[500.0, 500.0, 0.0], [9e3, -3e3, 0.0]], 1e-3)
    g = GridSpec(0.0, 0.0, 1000.0, 2, 2, 2000.0)
    e = accuracy_map(st, g).error
    assert np.isnan(e[0, 0]) and np.all(np.isfinite(e.ravel()[1:]))


# ----------------------------------------------- Wang, Zhang & Wu (2006), section 4 maps


@pytest.fixture(scope='module')
def seed000_maps():
    """The four maps of Wang, Zhang & Wu (2006) fig. 2 (CTLS and CRLB), 300 m cells over ±60 km."""
    out = {}
    for sigma in (1.5e-3, 4.5e-3):
        st = Stations.from_arrays(SEED000, sigma)
        for alt in (5 * KM, 15 * KM):
            g = GridSpec.from_extent(-60 * KM, 60 * KM, -60 * KM, 60 * KM, 300.0, alt)
            for model in ('ctls', 'crlb'):
                out[model, sigma, alt] = accuracy_map(st, g, model)
    return out


def test_seed000_smaller_sigma_is_better(seed000_maps):
    # Both models are linear in σ (P ∝ σ²), so 4.5 mrad is exactly 3x worse everywhere.
    for model in ('ctls', 'crlb'):
        for alt in (5 * KM, 15 * KM):
            a = seed000_maps[model, 1.5e-3, alt].error
            b = seed000_maps[model, 4.5e-3, alt].error
            np.testing.assert_allclose(b, 3.0 * a, rtol=1e-9)


def test_seed000_error_grows_with_range(seed000_maps):
    # "Elsewhere, the farther the target from the stations, the worse": the median error in
    # 10 km rings around the stations' centroid increases ring by ring.
    for key, m in seed000_maps.items():
        pts = m.grid.points()[:, :2]
        dc = np.linalg.norm(pts - SEED000[:, :2].mean(axis=0), axis=1).reshape(m.error.shape)
        edges = np.array([0, 10, 20, 30, 40, 50, 60, 70, 90]) * KM
        med = [np.median(m.error[(dc >= a) & (dc < b)]) for a, b in zip(edges[:-1], edges[1:])]
        assert np.all(np.diff(med) > 0), (key, med)
        assert med[-1] > 2.5 * med[0], (key, med)


def test_seed000_higher_altitude_is_better_on_average(seed000_maps):
    # "Targets at 15 km are located better than at 5 km": true for the area mean, the 90th
    # percentile and the worst cell; not cell by cell (within 2 km of a station the low
    # target is better, which the paper does not mention).
    for model in ('ctls', 'crlb'):
        for sigma in (1.5e-3, 4.5e-3):
            lo = seed000_maps[model, sigma, 5 * KM].error
            hi = seed000_maps[model, sigma, 15 * KM].error
            assert hi.mean() < 0.98 * lo.mean()
            assert np.percentile(hi, 90) < np.percentile(lo, 90)
            assert hi.max() < lo.max()
            pts = seed000_maps[model, sigma, 5 * KM].grid.points()[:, :2]
            dmin = np.min(np.linalg.norm(pts[:, None] - SEED000[None, :, :2], axis=2), axis=1)
            near = (dmin < 2 * KM).reshape(lo.shape)
            assert np.median(hi[near]) > np.median(lo[near])


def _ring(m, centre, radius, angles_deg):
    return np.array([m.at(centre[0] + radius * np.cos(np.radians(a)),
                          centre[1] + radius * np.sin(np.radians(a))) for a in angles_deg])


def test_seed000_narrow_bad_region_near_each_station(seed000_maps):
    # CTLS at 5 km: a narrow ridge of high error runs through each station along the line where
    # the line of sight is perpendicular to the station's position vector (there G's elevation
    # entry collapses and the station's elevation loses its weight). On a 1.5 km ring around each
    # station the ridge direction is >= 1.25x the ring median (values 1.29-1.84 on both sides)
    # and contains the ring maximum (within 15°); the CRLB map has no ridge (<= 1.15x).
    ctls = seed000_maps['ctls', 1.5e-3, 5 * KM]
    crlb_map = seed000_maps['crlb', 1.5e-3, 5 * KM]
    angles = np.arange(0.0, 360.0, 2.0)
    for p in SEED000[:, :2]:
        line = np.degrees(np.arctan2(p[0], -p[1]))  # direction perpendicular to p
        for m, bad in ((ctls, True), (crlb_map, False)):
            ring = _ring(m, p, 1.5 * KM, angles)
            on = _ring(m, p, 1.5 * KM, [line, line + 180.0])
            ratio = on / np.median(ring)
            if bad:
                assert np.all(ratio >= 1.25), ratio
                off = (angles[np.argmax(ring)] - line + 90.0) % 180.0 - 90.0
                assert abs(off) <= 15.0
            else:
                assert np.all(ratio <= 1.15), ratio


# ---------------------------------------------------------------------------------- placement


def test_placement_symmetric_layout_puts_the_station_in_the_middle():
    # Four stations on the axes at ±20 km and an area centred on the origin: the layout and
    # the area are invariant under the 90° rotations and reflections, and the CRLB optimum is
    # unique, so it is the centre. The candidate grid (10 x 10) does not contain the centre,
    # so the local refinement has to find it.
    st = Stations.from_arrays([[20e3, 0, 0], [-20e3, 0, 0], [0, 20e3, 0], [0, -20e3, 0]], 2e-3)
    area = GridSpec.from_extent(-10e3, 10e3, -10e3, 10e3, 2e3, 3e3)
    for objective in ('mean', 'max'):
        r = place_station(st, area, (-30e3, 30e3, -30e3, 30e3), 0.0, objective=objective,
                          candidates=10)
        assert np.hypot(*r.position[:2]) < 50.0, r.position
        assert np.hypot(*r.grid_best[:2]) > 3e3
        assert r.after < r.before
        assert r.improvement == pytest.approx(r.before - r.after)
        new = accuracy_map(st.with_station(r.position, 2e-3), area).error
        val = new.mean() if objective == 'mean' else new.max()
        assert val == pytest.approx(r.after, rel=1e-9)


def test_placement_from_an_unobservable_layout_and_ctls():
    st = Stations.from_arrays([[20e3, 0, 0]], 2e-3)
    area = GridSpec.from_extent(-5e3, 5e3, -5e3, 5e3, 2.5e3, 2e3)
    r = place_station(st, area, (-20e3, 20e3, -20e3, 20e3), candidates=5, refine=False,
                      has_elevation=False)
    d = r.as_dict()
    assert d['before_m'] is None and d['improvement_m'] is None and d['after_m'] > 0
    assert d['before']['unobservable_cells'] == 16 and d['after']['unobservable_cells'] == 0
    r = place_station(Stations.from_arrays(SEED000, 1.5e-3), area, (-40e3, 40e3, -40e3, 40e3),
                      model='ctls', candidates=5)
    assert r.after < r.before


def test_a_new_station_on_a_cell_centre_is_not_rewarded_by_a_dropped_cell():
    # A cell centre on the new station's vertical axis has no azimuth from it (NaN), and the
    # objective skipped NaN cells: the placement was rewarded for removing a cell from the
    # mean or max (2 x 2 cells: 174.8 -> 8.0 m). That cell now keeps the existing stations'
    # error (the new station makes no bearing there, as in the simulator).
    st = Stations.from_arrays([[50e3, 0, 0], [50e3, 10e3, 0]], 2e-3)
    area = GridSpec.from_extent(-2e3, 2e3, -2e3, 2e3, 2e3, 0.0)   # centres at ±1 km
    before = accuracy_map(st, area).error
    for objective, reduce in (('mean', np.mean), ('max', np.max)):
        r = place_station(st, area, (1e3, 1e3, 1e3, 1e3), 0.0, objective=objective,
                          candidates=2, refine=False)       # forced onto the centre (1, 1) km
        after = accuracy_map(st.with_station(r.position, 2e-3), area).error
        assert np.isnan(after[1, 1]) and np.all(np.isfinite(np.delete(after.ravel(), 3)))
        honest = np.where(np.isnan(after), before, after)
        assert r.after == pytest.approx(reduce(honest), rel=1e-9)
    assert r.after >= before[1, 1]                           # max: the cell still counts


@pytest.mark.parametrize('kwargs,field', [({'objective': 'median'}, 'objective'),
                                          ({'model': 'gdop'}, 'model'),
                                          ({'region': (1, 0, 0, 1)}, 'region'),
                                          ({'candidates': 1}, 'candidates')])
def test_placement_bad_input(kwargs, field):
    st = Stations.from_arrays(SEED000, 1e-3)
    area = GridSpec.from_extent(-5e3, 5e3, -5e3, 5e3, 2.5e3, 2e3)
    args = dict(region=(-1e3, 1e3, -1e3, 1e3))
    args.update(kwargs)
    with pytest.raises(ValueError, match=field):
        place_station(st, area, **args)


# ---------------------------------------------------------------------------- OccupancyGrid


def test_error_to_occupancy_mapping():
    e = np.array([np.nan, np.inf, -1.0, 10.0, 55.0, 100.0, 1e9])
    np.testing.assert_array_equal(error_to_occupancy(e, 10.0, 100.0),
                                  [-1, 100, 0, 0, 50, 100, 100])
    v = error_to_occupancy(np.array([1.0, 10.0, 100.0, np.sqrt(10.0)]), 1.0, 100.0, 'log')
    np.testing.assert_array_equal(v, [0, 50, 100, 25])
    assert v.dtype == np.int8
    for args, field in (((0.0, 0.0), 'min_error'), ((0.0, 10.0, 'log'), 'min_error'),
                        ((1.0, 2.0, 'sqrt'), 'scale')):
        with pytest.raises(ValueError, match=field):
            error_to_occupancy(e, *args)


def test_occupancy_error_map_for_the_fusion_node():
    st = Stations.from_arrays(SEED000, 1.5e-3)
    g = GridSpec(origin_x=-60e3, origin_y=-60e3, resolution=1000.0, width=120, height=100,
                 altitude=5e3)
    om = occupancy_error_map(st, g)
    assert om.data.shape == (120 * 100,) and om.data.dtype == np.int8
    assert om.error.shape == (100, 120)
    assert om.data.min() == 0 and om.data.max() == 100
    assert om.min_error == pytest.approx(np.min(om.error))
    np.testing.assert_array_equal(om.data.reshape(100, 120),
                                  error_to_occupancy(om.error, om.min_error, om.max_error))
    fixed = occupancy_error_map(st, g, model='ctls', scale='log', min_error=10.0,
                                max_error=1000.0)
    assert (fixed.min_error, fixed.max_error, fixed.scale) == (10.0, 1000.0, 'log')
    assert isinstance(om.data.tolist()[0], int)


def test_accuracy_map_stats_and_lookup():
    st = Stations.from_arrays(SEED000, 1.5e-3)
    g = GridSpec.from_extent(-60 * KM, 60 * KM, -60 * KM, 60 * KM, 4 * KM, 5 * KM)
    m = accuracy_map(st, g)
    assert isinstance(m, AccuracyMap)
    s = m.stats()
    assert s['cells'] == 900 and s['min_m'] <= s['median_m'] <= s['max_m']
    assert m.at(0.0, 0.0) == pytest.approx(position_error([2e3, 2e3, 5e3], st)[0])
    assert np.isnan(m.at(1e6, 0.0))
