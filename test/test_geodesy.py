"""bearing_loc_ros.core.geodesy against published reference points (no ROS needed).

References (each value is copied from the cited page; tolerances are the number of digits the
source prints, converted to metres or degrees):

* WGS84 definition (NGA TR8350.2): a = 6378137 m, 1/f = 298.257223563, so the ECEF axes meet
  the ellipsoid at (0°, 0°) -> (a, 0, 0), (0°, 90°) -> (0, a, 0), (90°, 0°) -> (0, 0, b) with
  b = a (1 − f) = 6356752.314245 m.
* GNU Octave mapping package, geodetic2ecef help example "Aalborg GPS Centre"
  (https://octave.sourceforge.io/mapping/function/geodetic2ecef.html): 57.02929569°,
  9.950248114°, 56.95 m -> X 3426949.39675307, Y 601195.852419885, Z 5327723.99358255 m.
* MATLAB Mapping Toolbox geodetic2ecef example (Paris,
  https://www.mathworks.com/help/map/ref/geodetic2ecef.html): 48.8562°, 2.3508°, 0.0674 km
  -> x = 4.2010e+03 km, y = 172.46 km, z = 4.7801e+03 km.
* MATLAB Mapping Toolbox geodetic2enu / enu2geodetic example (the Matterhorn from Zermatt,
  https://www.mathworks.com/help/map/ref/geodetic2enu.html): origin 46.017°, 7.750°, 1673 m,
  point 45.976°, 7.658°, 4531 m -> xEast −7134.8, yNorth −4556.3, zUp 2852.4 m (shortG).
* pymap3d's own test suite (tests/test_geodetic.py): (42°, −82°, 200 m) ->
  (660675.2518247, −4700948.68316, 4245737.66222) m.
* yoronneko/qzsl6tool docs/llh2ecef-en.md (a QZSS/GNSS tool): ECEF (−3551876.829,
  3887786.860, 3586946.387) m <-> 34.4401061° N, 132.4147804° E, 233.362 m.
"""

import numpy as np
import pymap3d
import pytest

from bearing_loc_ros.core import geodesy

A = 6378137.0
B = A * (1.0 - 1.0 / 298.257223563)


def test_wgs84_axes():
    ecef = geodesy.geodetic_to_ecef([0.0, 0.0, 90.0, -90.0], [0.0, 90.0, 0.0, 0.0], 0.0)
    np.testing.assert_allclose(ecef, [[A, 0, 0], [0, A, 0], [0, 0, B], [0, 0, -B]], atol=1e-6)


@pytest.mark.parametrize('lla, xyz, atol', [
    # Octave mapping example, printed to 1e-8 m: 1 mm leaves room for ellipsoid constants.
    ((57.02929569, 9.950248114, 56.95), (3426949.39675307, 601195.852419885, 5327723.99358255),
     1e-3),
    # pymap3d test suite, printed to 1e-5 m or better.
    ((42.0, -82.0, 200.0), (660675.2518247, -4700948.68316, 4245737.66222), 1e-3),
    # qzsl6tool: lat/lon printed to 1e-7 deg (1.1 cm on the ground), heights to 1 mm.
    ((34.4401061, 132.4147804, 233.362), (-3551876.829, 3887786.860, 3586946.387), 0.02),
    # MATLAB Paris example, printed to 5 significant digits in km: x, z to 0.05 km, y to 0.005.
    ((48.8562, 2.3508, 67.4), (4201.0e3, 172.46e3, 4780.1e3), (50.0, 5.0, 50.0)),
])
def test_geodetic_to_ecef_reference_points(lla, xyz, atol):
    got = geodesy.geodetic_to_ecef(*lla)
    assert got.shape == (3,)
    assert np.all(np.abs(got - np.asarray(xyz)) <= np.asarray(atol))


def test_ecef_to_geodetic_reference_point():
    lat, lon, alt = geodesy.ecef_to_geodetic([-3551876.829, 3887786.860, 3586946.387])
    assert lat == pytest.approx(34.4401061, abs=1e-7)
    assert lon == pytest.approx(132.4147804, abs=1e-7)
    assert alt == pytest.approx(233.362, abs=0.01)


def test_matlab_matterhorn_enu_both_ways():
    zermatt = (46.017, 7.750, 1673.0)
    enu = geodesy.geodetic_to_enu(45.976, 7.658, 4531.0, zermatt)
    np.testing.assert_allclose(enu, [-7134.8, -4556.3, 2852.4], atol=0.05)
    lat, lon, alt = geodesy.enu_to_geodetic([-7134.8, -4556.3, 2852.4], zermatt)
    # MATLAB prints 45.976, 7.658, 4531 (shortG); the rounded ENU input moves the point by
    # up to 0.05 m per axis, i.e. < 1e-6 deg and < 0.1 m.
    assert (float(lat), float(lon)) == pytest.approx((45.976, 7.658), abs=1e-6)
    assert float(alt) == pytest.approx(4531.0, abs=0.1)


def test_vectorised_round_trip_and_shapes():
    rng = np.random.default_rng(1)
    origin = (-33.86, 151.21, 40.0)
    enu = rng.uniform(-20e3, 20e3, size=(4, 5, 3))
    lat, lon, alt = geodesy.enu_to_geodetic(enu, origin)
    assert lat.shape == lon.shape == alt.shape == (4, 5)
    back = geodesy.geodetic_to_enu(lat, lon, alt, origin)
    assert back.shape == (4, 5, 3)
    np.testing.assert_allclose(back, enu, atol=1e-6)
    # The origin itself is the ENU origin.
    np.testing.assert_allclose(geodesy.geodetic_to_enu(*origin, origin), 0.0, atol=1e-9)
    # Identical to calling pymap3d directly (this module only wraps it).
    e, n, u = pymap3d.geodetic2enu(lat, lon, alt, *origin)
    np.testing.assert_allclose(back, np.stack([e, n, u], axis=-1), rtol=0, atol=1e-9)


@pytest.mark.parametrize('lla, field_part', [
    ((90.5, 0.0, 0.0), 'lat_deg'),
    ((-91.0, 0.0, 0.0), 'lat_deg'),
    ((0.0, 180.5, 0.0), 'lon_deg'),
    ((0.0, -200.0, 0.0), 'lon_deg'),
    ((float('nan'), 0.0, 0.0), 'lat_deg'),
    ((0.0, 0.0, float('inf')), 'alt_m'),
])
def test_range_checks_name_the_field(lla, field_part):
    with pytest.raises(ValueError, match=f'geodetic_position: {field_part}'):
        geodesy.geodetic_to_enu(*lla, (0.0, 0.0, 0.0), field='geodetic_position')
    with pytest.raises(ValueError, match=f'geodetic_origin: {field_part}'):
        geodesy.geodetic_triplet(lla, 'geodetic_origin')


def test_triplet_length_and_bounds_inclusive():
    with pytest.raises(ValueError, match='geodetic_origin: expected'):
        geodesy.geodetic_triplet([1.0, 2.0], 'geodetic_origin')
    assert geodesy.geodetic_triplet([90, -180, -10], 'x') == (90.0, -180.0, -10.0)


def test_enu_axes_rotation():
    origin = (46.017, 7.750, 1673.0)
    np.testing.assert_allclose(geodesy.enu_axes_rotation(origin, 46.017, 7.750), np.eye(3),
                               atol=1e-12)
    lat, lon = np.array([46.2, 45.5]), np.array([8.1, 7.0])
    R = geodesy.enu_axes_rotation(origin, lat, lon)
    assert R.shape == (2, 3, 3)
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-12)
    # A 1 m step along the local East/North/Up at each point, expressed in the origin's ENU
    # axes (through pymap3d, independently of the function under test), must map back to the
    # local unit steps. Linearisation error of a 1 m step ~ 1 m / 6.4e6 m ~ 2e-7.
    for k, (la, lo) in enumerate(zip(lat, lon)):
        p0 = geodesy.geodetic_to_enu(la, lo, 500.0, origin)
        for axis in range(3):
            step = np.eye(3)[axis]
            la1, lo1, h1 = pymap3d.enu2geodetic(*step, la, lo, 500.0)
            d_origin = geodesy.geodetic_to_enu(la1, lo1, h1, origin) - p0
            np.testing.assert_allclose(R[k] @ d_origin, step, atol=1e-6)
    # The up axes differ by about distance / Earth radius (radii of curvature at 46° N are
    # 6.37e6 to 6.39e6 m: 2 %); East/North also turn by the meridian convergence Δλ sin φ.
    tilt = np.arccos(R[0, 2, 2])
    dist = np.linalg.norm(geodesy.geodetic_to_enu(46.2, 8.1, 1673.0, origin))
    assert tilt == pytest.approx(dist / 6.37e6, rel=0.02)
    twist = np.arctan2(R[0, 0, 1] - R[0, 1, 0], R[0, 0, 0] + R[0, 1, 1])
    assert abs(twist) == pytest.approx(np.radians(8.1 - 7.75) * np.sin(np.radians(46.1)),
                                       rel=0.02)
