"""core.gis without files: ellipse probability, geodesic rays, antimeridian and polar origins."""
import json
import math

from matplotlib.path import Path
import numpy as np
import pytest
from scipy.stats import chi2

from bearing_loc_ros.core import geodesy, gis
from bearing_loc_ros.core.bearings import Bearing
from bearing_loc_ros.gis_export import geojson_text

MUNICH = (48.137, 11.575, 520.0)


def inside(geometry, lon, lat):
    """Points (lon, lat) inside a GeoJSON Polygon/MultiPolygon (exterior rings)."""
    polys = ([geometry['coordinates']] if geometry['type'] == 'Polygon'
             else geometry['coordinates'])
    hit = np.zeros(len(lon), dtype=bool)
    for poly in polys:
        hit |= Path(np.array(poly[0])).contains_points(np.column_stack([lon, lat]))
    return hit


def coverage_bound(p, n, points=gis.ELLIPSE_POINTS):
    """Accepted |fraction − p| for n Monte Carlo samples: 4.5 binomial σ plus the probability
    the inscribed n-gon loses (area ratio (n/2π) sin(2π/n) → radius factor r; the lost mass
    is exp(−k² r²/2) − exp(−k²/2))."""
    k2 = chi2.ppf(p, 2)
    r2 = points / (2 * math.pi) * math.sin(2 * math.pi / points)
    return 4.5 * math.sqrt(p * (1 - p) / n) + math.exp(-k2 * r2 / 2) - math.exp(-k2 / 2)


@pytest.mark.parametrize('p', [0.5, 0.9, 0.95, 0.99])
def test_ellipse_scale_is_the_two_dof_chi_square_quantile(p):
    assert gis.ellipse_scale(p) ** 2 == pytest.approx(chi2.ppf(p, 2), rel=1e-12)


@pytest.mark.parametrize('bad', [0.0, 1.0, -0.1, float('nan'), 2.0])
def test_ellipse_scale_refuses_impossible_probabilities(bad):
    with pytest.raises(ValueError, match='probability'):
        gis.ellipse_scale(bad)


def test_horizontal_ellipse_axes_and_orientation():
    rot = np.array([[math.cos(0.4), -math.sin(0.4)], [math.sin(0.4), math.cos(0.4)]])
    c = np.zeros((3, 3))
    c[:2, :2] = rot @ np.diag([900.0, 100.0]) @ rot.T
    c[2, 2] = 50.0
    a, b, ang = gis.horizontal_ellipse(c, 0.95)
    k = math.sqrt(chi2.ppf(0.95, 2))
    assert a == pytest.approx(30 * k) and b == pytest.approx(10 * k)
    assert ang == pytest.approx(0.4)


@pytest.mark.parametrize('cov', [np.full((3, 3), np.inf), np.diag([-4.0, 1.0, 1.0]),
                                 np.array([[1.0, 5.0, 0], [0.0, 1.0, 0], [0, 0, 1.0]])])
def test_bad_covariance_gives_no_ellipse_but_keeps_the_fix(cov):
    with pytest.raises(ValueError, match='covariance'):
        gis.horizontal_ellipse(cov)
    feats = gis.fix_features(gis.GeoFix(0, np.array([10.0, 20.0, 0.0]), cov), MUNICH)
    assert len(feats) == 1 and 'covariance' in feats[0]['properties']['ellipse_error']


@pytest.mark.parametrize('p', [0.5, 0.95])
def test_lonlat_ellipse_polygon_encloses_the_stated_probability(p):
    """Monte Carlo (fixed seed): Gaussian fixes around x̂ with covariance C, converted to
    lon/lat, fall inside the exported lon/lat polygon with probability p."""
    rng = np.random.default_rng(11)
    c = np.array([[4.0e4, 1.5e4, 2.0e3], [1.5e4, 1.6e4, 1.0e3], [2.0e3, 1.0e3, 9.0e3]])
    x = np.array([35_000.0, -12_000.0, 3_000.0])
    feats = gis.fix_features(gis.GeoFix(0, x, c), MUNICH, p)
    assert feats[1]['properties']['kind'] == 'ellipse'
    n = 20_000
    samples = rng.multivariate_normal(x, c, size=n)
    lon, lat, _ = gis.enu_to_lonlat(samples, MUNICH)
    frac = inside(feats[1]['geometry'], lon, lat).mean()
    assert abs(frac - p) < coverage_bound(p, n), frac


def test_compass_azimuth_at_the_origin_and_meridian_convergence():
    assert gis.compass_at(0.0, [0.0, 0.0, 0.0], MUNICH) == pytest.approx(90.0)
    assert gis.compass_at(math.pi / 2, [0.0, 0.0, 0.0], MUNICH) == pytest.approx(0.0, abs=1e-9)
    # 50 km east of the origin (northern hemisphere) true north leans west towards the pole,
    # so grid north (the origin's) is (λ − λ0) sin φ east of it.
    east = np.array([50_000.0, 0.0, 0.0])
    lat, lon, _ = geodesy.enu_to_geodetic(east, MUNICH)
    conv = (float(lon) - MUNICH[1]) * math.sin(math.radians(float(lat)))
    assert gis.compass_at(math.pi / 2, east, MUNICH) == pytest.approx(conv, abs=2e-3)
    assert conv > 0.4


def test_geodesic_ray_passes_through_the_target_it_points_at():
    station = np.array([-20_000.0, 5_000.0, 100.0])
    target = np.array([25_000.0, 30_000.0, 100.0])
    az = math.atan2(target[1] - station[1], target[0] - station[0])
    length = gis.ray_length_for(station, target)
    assert length == pytest.approx(gis.RAY_OVERSHOOT * math.dist(station[:2], target[:2]))
    lon, lat = gis.ray_lonlat(station, az, length, MUNICH, points=2001)
    tlat, tlon, _ = geodesy.enu_to_geodetic(target, MUNICH)
    # Closest ray vertex to the target, in metres on the ground (vertices every ~32 m).
    d = [geodesy.geodetic_to_enu(la, lo, target[2], MUNICH) for la, lo in zip(lat, lon)]
    miss = min(math.dist(p[:2], target[:2]) for p in d)
    assert miss < 20.0
    from pymap3d.vincenty import vdist
    dist, _ = vdist(lat[0], lon[0], lat[-1], lon[-1])
    assert float(dist) == pytest.approx(length, rel=1e-9)


def _ring_ok(ring):
    assert ring[0] == ring[-1] and len(ring) >= 4
    assert all(-180.0 <= x <= 180.0 and -90.0 <= y <= 90.0 for x, y in ring)


def test_antimeridian_lines_and_ellipses_are_split_per_rfc7946():
    origin = (-16.5, 179.98, 0.0)       # Fiji: the antimeridian is 2 km east
    fix = gis.GeoFix(10**18, np.array([2_000.0, 0.0, 0.0]), np.diag([4.0e6, 1.0e6, 1.0]))
    ray = Bearing('s1', 10**18, np.array([-8_000.0, 0.0, 0.0]), 0.0, sigma_azimuth=0.01)
    fc = gis.feature_collection(origin, [fix], [(ray, fix.position)])
    json_text = geojson_text(fc)       # the geojson package accepts it
    assert json_text
    by = {f['properties']['kind']: f['geometry'] for f in fc['features']}
    line = by['bearing']
    assert line['type'] == 'MultiLineString' and len(line['coordinates']) == 2
    a, b = line['coordinates']
    assert a[-1][0] == 180.0 and b[0][0] == -180.0 and a[-1][1] == b[0][1]
    for part in (a, b):
        assert all(abs(q[0] - p[0]) < 180.0 for p, q in zip(part, part[1:]))
    ell = by['ellipse']
    assert ell['type'] == 'MultiPolygon' and len(ell['coordinates']) == 2
    for poly in ell['coordinates']:
        _ring_ok(poly[0])
    # The split polygon still holds 95 % of the mass (samples wrapped to [-180, 180)).
    rng = np.random.default_rng(5)
    s = rng.multivariate_normal(fix.position, fix.covariance, size=20_000)
    lon, lat, _ = gis.enu_to_lonlat(s, origin)
    lon = (lon + 180.0) % 360.0 - 180.0
    assert np.any(lon < 0) and np.any(lon > 0)
    frac = inside(ell, lon, lat).mean()
    assert abs(frac - 0.95) < coverage_bound(0.95, 20_000), frac


@pytest.mark.parametrize('origin', [(89.5, 0.0, 0.0), (-86.0, 120.0, 10.0)])
def test_polar_origins_are_refused_with_one_line(origin):
    with pytest.raises(ValueError) as exc:
        gis.feature_collection(origin, [gis.GeoFix(0, np.zeros(3), np.eye(3))])
    assert 'polar' in str(exc.value) and '\n' not in str(exc.value)


def test_huge_ellipse_is_reported_not_drawn_wrong():
    f = gis.GeoFix(0, np.zeros(3), np.diag([1e14, 1e14, 1.0]))
    feats = gis.fix_features(f, MUNICH)
    assert len(feats) == 1
    assert 'too large' in feats[0]['properties']['ellipse_error']


def test_live_picture_keeps_the_newest_and_draws_rays_past_the_fix():
    pic = gis.LivePicture(MUNICH, trail=3)
    for k in range(5):
        pic.update_fix(gis.GeoFix(k, np.array([100.0 * k, 0.0, 0.0]), np.eye(3)))
    pic.update_fix(gis.GeoFix(1, np.array([9e3, 0.0, 0.0]), np.eye(3)))   # older: ignored
    pic.update_bearing(Bearing('a', 5, np.array([0.0, -3000.0, 0.0]), math.atan2(3000, 400)))
    pic.update_bearing(Bearing('a', 2, np.array([0.0, -1.0, 0.0]), 0.0))  # older: ignored
    assert pic.changed
    fc = pic.collection()
    assert not pic.changed
    kinds = [f['properties']['kind'] for f in fc['features']]
    assert kinds == ['station', 'bearing', 'track', 'ellipse', 'fix']
    fix = fc['features'][-1]['properties']
    assert fix['stamp_ns'] == 4 and fix['position_enu_m'] == [400.0, 0.0, 0.0]
    assert fc['features'][2]['properties']['fixes'] == 3
    ray = fc['features'][1]['properties']
    assert ray['length_m'] == pytest.approx(gis.RAY_OVERSHOOT * math.hypot(400.0, 3000.0))


def test_sigma_probability_inverts_ellipse_scale():
    for n in (0.5, 1.0, 2.0, 3.0):
        p = gis.sigma_probability(n)
        assert p == pytest.approx(chi2.cdf(n * n, 2), rel=1e-12)
        assert gis.ellipse_scale(p) == pytest.approx(n, rel=1e-12)
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match='n_sigma'):
            gis.sigma_probability(bad)
    # the 1σ ring: every point at Mahalanobis distance 1 from the centre
    C = np.array([[400.0, 120.0, 0.0], [120.0, 100.0, 0.0], [0.0, 0.0, 9.0]])
    ring = gis.ellipse_ring_enu([5.0, -3.0, 0.0], C, gis.sigma_probability(1.0), points=63)
    d = ring[:, :2] - [5.0, -3.0]
    m = np.einsum('ki,ij,kj->k', d, np.linalg.inv(C[:2, :2]), d)
    np.testing.assert_allclose(m, 1.0, rtol=1e-9)
    assert ring.shape == (64, 3)


def test_a_fix_inside_the_earth_is_exported_without_geometry_and_left_out_of_kml(tmp_path):
    # z = -1e7 m below a Munich origin lies inside the Earth: its point used to be drawn near
    # the antipode (-168.4, -48.8) with a clockwise ellipse ring.
    from bearing_loc_ros.gis_export import kml_document
    fixes = [gis.GeoFix(1, np.array([0.0, 0.0, -1e7]), np.eye(3), 'ok', 'mle', ['a', 'b']),
             gis.GeoFix(2, np.array([10.0, 0.0, 0.0]), np.eye(3), 'ok', 'mle', ['a', 'b'])]
    fc = gis.feature_collection(MUNICH, fixes)
    points = [f for f in fc['features'] if f['properties']['kind'] == 'fix']
    assert points[0]['geometry'] is None
    assert 'below the Earth' in points[0]['properties']['position_error']
    assert points[1]['geometry']['type'] == 'Point'
    assert [f['properties']['kind'] for f in fc['features']].count('ellipse') == 1
    json.loads(geojson_text(fc))
    kml = kml_document(fc).kml()
    assert kml.count('<Point') == 1


def _fc_text(pic):
    """The picture as GeoJSON text (what the live view sends); raises if it cannot be drawn."""
    return geojson_text(pic.collection())


@pytest.mark.parametrize('pos, cov', [
    ([math.nan, 0.0, 0.0], np.eye(3)), ([0.0, math.inf, 0.0], np.eye(3)),
    ([1e13, 0.0, 0.0], np.eye(3)), ([0.0, 0.0, 0.0], np.diag([math.inf, 1.0, 1.0])),
    ([0.0, 0.0, 0.0], np.full((3, 3), math.nan)), ([0.0, 0.0, 0.0], np.eye(2)),
    ([0.0, 0.0, -1e7], np.eye(3)), ([1e11, 0.0, 0.0], np.eye(3))])
def test_live_picture_refuses_an_undrawable_fix_and_goes_on(pos, cov):
    """A NaN/inf fix never enters the picture (it used to sit in the trail, and every later
    picture failed with 'enu: expected finite coordinates')."""
    pic = gis.LivePicture(MUNICH)
    assert pic.update_fix(gis.GeoFix(1, np.array([10.0, 0.0, 0.0]), np.eye(3))) == gis.ACCEPTED
    with pytest.raises(ValueError, match='fix (position|covariance)') as exc:
        pic.update_fix(gis.GeoFix(2, np.array(pos), np.asarray(cov)))
    assert '\n' not in str(exc.value)
    assert pic.fix.stamp_ns == 1 and len(pic.track) == 1
    assert pic.update_fix(gis.GeoFix(3, np.array([20.0, 0.0, 0.0]), np.eye(3))) == gis.ACCEPTED
    fc = json.loads(_fc_text(pic))
    by = {f['properties']['kind']: f for f in fc['features']}
    assert by['fix']['properties']['stamp_ns'] == 3 and by['track']['properties']['fixes'] == 2


@pytest.mark.parametrize('field, value', [('position', np.array([math.nan, 0.0, 0.0])),
                                          ('azimuth', math.inf), ('sigma_azimuth', math.nan),
                                          ('stamp_ns', -1)])
def test_live_picture_refuses_an_undrawable_bearing(field, value):
    pic = gis.LivePicture(MUNICH)
    good = Bearing('a', 1, np.array([0.0, -3000.0, 0.0]), 0.5)
    pic.update_bearing(good)
    bad = Bearing('a', 2, np.array([0.0, -3000.0, 0.0]), 0.5)
    setattr(bad, field, value)
    with pytest.raises(ValueError, match='bearing'):
        pic.update_bearing(bad)
    assert pic.bearings['a'] is good
    assert json.loads(_fc_text(pic))['features']


def test_live_picture_clock_restart_starts_afresh_and_late_inputs_are_dropped():
    """A stamp in the future no longer freezes the picture: the next normal stamp goes back by
    more than CLOCK_JUMP_NS and restarts it; a stamp back by less is out of order."""
    s = gis.NS_PER_S
    pic = gis.LivePicture(MUNICH)

    def fix(t, x=0.0):
        return gis.GeoFix(t, np.array([x, 0.0, 0.0]), np.eye(3))

    def bearing(station, t):
        return Bearing(station, t, np.array([0.0, -3000.0, 0.0]), 0.5)
    assert pic.update_fix(fix(1 * s, 1.0)) == gis.ACCEPTED
    assert pic.update_bearing(bearing('a', 1 * s)) == gis.ACCEPTED
    assert pic.update_fix(fix((2**31 - 1) * s, 2.0)) == gis.ACCEPTED
    assert pic.update_fix(fix(3 * s, 3.0)) == gis.RESTARTED
    assert pic.fix.stamp_ns == 3 * s and not pic.bearings
    assert [t for t, _ in pic.track] == [3 * s]
    for k in range(4, 10):
        assert pic.update_fix(fix(k * s, float(k))) == gis.ACCEPTED
    assert pic.fix.stamp_ns == 9 * s and len(pic.track) == 7
    assert pic.update_fix(fix(9 * s - gis.CLOCK_JUMP_NS, -1.0)) == gis.OUT_OF_ORDER
    assert pic.fix.stamp_ns == 9 * s and len(pic.track) == 7
    assert pic.update_bearing(bearing('a', 8 * s)) == gis.ACCEPTED
    assert pic.update_bearing(bearing('a', 8 * s - 1)) == gis.OUT_OF_ORDER
    assert pic.bearings['a'].stamp_ns == 8 * s
    # A bag replayed again: its first bearing restarts the picture, which then follows it.
    assert pic.update_bearing(bearing('a', 1 * s)) == gis.RESTARTED
    assert pic.fix is None and not pic.track and list(pic.bearings) == ['a']
    assert pic.update_bearing(bearing('b', 1 * s)) == gis.ACCEPTED
    assert pic.update_fix(fix(1 * s, 1.0)) == gis.ACCEPTED
    fc = json.loads(_fc_text(pic))
    kinds = [f['properties']['kind'] for f in fc['features']]
    assert kinds.count('bearing') == 2 and kinds[-1] == 'fix'
    assert fc['features'][-1]['properties']['stamp_ns'] == 1 * s


def test_fix_rate_memory_is_bounded_and_follows_a_clock_restart():
    """The rate's stamps used to grow without bound for equal stamps or after one future
    stamp (300,000 after 300,000 fixes)."""
    rate = gis.FixRate()
    for _ in range(3 * gis.RATE_MAX_STAMPS):
        hz, order = rate.add(0)
    assert hz is None and order == gis.ACCEPTED and len(rate.stamps) == gis.RATE_MAX_STAMPS
    rate = gis.FixRate()
    rate.add((2**31 - 1) * gis.NS_PER_S)
    orders = []
    for k in range(1, 1001):                 # 10 Hz for 100 s
        hz, order = rate.add(k * gis.NS_PER_S // 10)
        orders.append(order)
    assert orders[0] == gis.RESTARTED and set(orders[1:]) == {gis.ACCEPTED}
    assert len(rate.stamps) == 101 and hz == pytest.approx(10.0)
    hz2, order = rate.add(50 * gis.NS_PER_S)             # 50 s back: a restart
    assert order == gis.RESTARTED and hz2 is None and len(rate.stamps) == 1
    rate.add(50 * gis.NS_PER_S + 10**8)
    assert rate.add(50 * gis.NS_PER_S)[1] == gis.OUT_OF_ORDER and len(rate.stamps) == 2


def test_a_ray_over_the_pole_is_split_at_the_pole_not_at_the_antimeridian():
    """Reproducer: origin 85 N 10 E, a station 100 km south of it bearing due north, ray
    750 km long: it passes over the North Pole (its longitude jumps from 10 to -170). It was
    split as an antimeridian crossing, drawn 180 deg along the map's top edge."""
    origin = (85.0, 10.0, 0.0)
    station = np.array([0.0, -100_000.0, 0.0])
    lon, lat = gis.ray_lonlat(station, math.pi / 2, 750_000.0, origin)
    geom = gis.line_geometry(lon, lat)
    assert geom['type'] == 'MultiLineString' and len(geom['coordinates']) == 2
    a, b = geom['coordinates']
    assert a[-1] == [10.0, 90.0] and b[0] == [-170.0, 90.0]
    for part in (a, b):
        assert all(abs(q[0] - p[0]) < 1e-6 for p, q in zip(part, part[1:]))   # meridians
    # The South Pole, directly, and a near miss (drawn as it goes, no split).
    parts = gis.split_line([-30.0, -30.0, 150.0, 150.0], [-89.0, -89.9, -89.9, -89.0])
    assert len(parts) == 2 and parts[0][-1].tolist() == [-30.0, -90.0]
    assert parts[1][0].tolist() == [150.0, -90.0]
    near = gis.split_line([0.0, 60.0, 120.0], [89.0, 89.5, 89.0])
    assert len(near) == 1
    # An antimeridian crossing is still split there.
    am = gis.split_line([179.0, -179.0], [10.0, 12.0])
    assert [p.tolist() for p in am] == [[[179.0, 10.0], [180.0, 11.0]],
                                        [[-180.0, 11.0], [-179.0, 12.0]]]


def test_origin_altitude_is_bounded():
    assert gis.check_origin((48.0, 11.0, -1e6)) == (48.0, 11.0, -1e6)
    for alt in (1e12, -2e6):
        with pytest.raises(ValueError, match='origin: altitude'):
            gis.check_origin((48.0, 11.0, alt))


def test_a_fix_without_provenance_draws_no_status_estimator_or_stations():
    """Live fixes (the fix message carries none of them) draw no status, estimator or
    stations rather than 'ok', '' and []."""
    live, = gis.fix_features(gis.GeoFix(1, np.zeros(3), np.eye(3), None, None, None),
                             MUNICH)[:1]
    assert not {'status', 'estimator', 'stations'} & set(live['properties'])
    full = gis.fix_features(gis.GeoFix(1, np.zeros(3), np.eye(3), 'ok', 'mle', ['a']), MUNICH)
    assert full[0]['properties']['status'] == 'ok' and full[1]['properties']['estimator'] == 'mle'


@pytest.mark.parametrize('north_km', [50.0, 500.0, 1000.0])
def test_ellipse_far_from_the_origin_is_the_local_covariance_as_navsat_has_it(north_km):
    """The ellipse was C[:2, :2] in the origin's tangent plane: a fix with local σ 100 m
    East/North and 3 km up, 1000 km north of a 40° N origin, was drawn 1150 m (not 245 m)
    long northwards, while fix/navsat rotated the covariance. Now the ring is the k-σ set
    of the covariance in the fix's own ENU axes, as fix/navsat gives it."""
    import pymap3d
    from bearing_loc_ros.ros_conversions import fix_to_navsat
    origin = (40.0, 0.0, 0.0)
    p = np.array([0.0, north_km * 1e3, 5000.0])
    lat, lon, h = (float(v) for v in geodesy.enu_to_geodetic(p, origin))
    c_local = np.diag([100.0**2, 100.0**2, 3000.0**2])
    rot = geodesy.enu_axes_rotation(origin, lat, lon)
    c = rot.T @ c_local @ rot
    feats = gis.fix_features(gis.GeoFix(1, p, c), origin)
    ring = np.array(feats[1]['geometry']['coordinates'][0])
    e, n, _ = pymap3d.geodetic2enu(ring[:, 1], ring[:, 0], h, lat, lon, h)
    navsat = np.array(fix_to_navsat(p, c, 1, origin, 'map').position_covariance).reshape(3, 3)
    d = np.stack([e, n], 1)
    m = np.einsum('ij,jk,ik->i', d, np.linalg.inv(navsat[:2, :2]), d)
    k2 = gis.ellipse_scale(0.95) ** 2
    assert np.max(np.abs(m / k2 - 1.0)) < 1e-3
    ell = feats[1]['properties']
    assert ell['semi_major_m'] == pytest.approx(math.sqrt(k2) * 100.0, rel=1e-6)


def test_a_ray_passing_near_a_pole_is_split_there_whatever_its_vertex_spacing():
    """Two nearly parallel north bearings from Munich (locate par.json) meet 5000 km away:
    their 6250 km rays pass 0.2° from the North Pole, and the vertices either side of it
    differ by 178.6° of longitude, missing the old fixed 1° tolerance: the step was taken as
    an antimeridian crossing and drawn along the map's top edge. A step is now a pole pass
    when its great circle comes within POLE_PASS_DEG of the pole between its vertices."""
    origin = (48.137, 11.575, 520.0)
    for station, az in (((0.0, 0.0, 0.0), 1.5707), ((1000.0, 0.0, 0.0), 1.5709)):
        b = Bearing('a', None, np.array(station), az, sigma_azimuth=0.01)
        geom = gis.bearing_feature(b, origin, 6_250_000.0)['geometry']
        assert geom['type'] == 'MultiLineString' and len(geom['coordinates']) == 2
        first, second = geom['coordinates']
        assert first[-1][1] == 90.0 and second[0][1] == 90.0
        for part in (first, second):
            assert all(abs(q[0] - p[0]) < 5.0 for p, q in zip(part, part[1:]))
    assert gis.passes_pole(11.7, 88.42, -169.66, 89.83) == 90.0
    assert gis.passes_pole(0.0, 10.0, 100.0, 10.0) is None       # a long step, far away
    assert gis.passes_pole(179.0, 10.0, -179.0, 12.0) is None


@pytest.mark.parametrize('origin, cov, reason', [
    ((48.0, 11.0, 0.0), np.diag([100.0, 0.0, 1.0]), 'degenerate'),
    ((48.0, 11.0, 0.0), np.diag([100.0, -1e-8, 1.0]), 'degenerate'),
    ((0.0, 11.0, 0.0), np.diag([1.0, 1e14, 1.0]), 'too large'),
    ((48.0, 11.0, 0.0), np.diag([1e13, 1e13, 1.0]), 'too large'),
    ((0.0, 11.0, 0.0), np.diag([1.0, 2e11, 1.0]), 'too large')])
def test_degenerate_and_huge_ellipses_are_refused_with_a_reason(origin, cov, reason):
    """A zero (or slightly negative) variance drew a Polygon of no area; the size test only
    looked at the longitude span, so diag(1, 1e14) at the equator (a 24,000 km north axis)
    was drawn a third of its size while diag(1e13, 1e13) was refused. Both limits are now
    on the axes themselves; the fix is drawn without an ellipse and says why."""
    feats = gis.fix_features(gis.GeoFix(0, np.zeros(3), cov), origin)
    assert len(feats) == 1 and reason in feats[0]['properties']['ellipse_error']
    ok = gis.fix_features(gis.GeoFix(0, np.zeros(3), np.diag([1.0, 1.6e11, 1.0])), origin)
    assert ok[1]['properties']['semi_major_m'] < gis.MAX_ELLIPSE_AXIS_M
