"""WGS84 geodetic <-> local ENU conversions (a thin, validated, vectorised wrapper of pymap3d).

DESIGN.md "Frames, units, angles": the world frame is a local ENU Cartesian frame; when a
geodetic origin (lat0, lon0, h0 on WGS84) is configured, stations may be given as latitude,
longitude and ellipsoidal height, and fixes are also published as ``sensor_msgs/NavSatFix``.

The conversions themselves are pymap3d's (``geodetic2ecef``, ``geodetic2enu``,
``enu2geodetic``, ``enu2uvw``/``uvw2enu``), not hand-written formulas; this module only fixes
the conventions:

* Angles are degrees only in names ending ``_deg`` (latitude φ, longitude λ); heights are
  ellipsoidal (above the WGS84 ellipsoid, not the geoid), metres, names ending ``_m``.
* ENU axes at a geodetic point (φ, λ): e = (−sin λ, cos λ, 0),
  n = (−sin φ cos λ, −sin φ sin λ, cos φ), u = (cos φ cos λ, cos φ sin λ, sin φ) in ECEF;
  the ENU coordinates of a point are the projections of (ECEF(point) − ECEF(origin)) on the
  origin's e, n, u (a tangent plane at the origin, not a map projection).
* Latitude must lie in [−90, 90] and longitude in [−180, 180] degrees; heights must be
  finite. Violations raise ``ValueError`` naming the field (pymap3d itself accepts, for
  example, a latitude of 95°).

Everything is vectorised: latitudes, longitudes and heights broadcast against each other;
ENU/ECEF points are arrays of shape (..., 3).
"""

from math import isfinite

import numpy as np
import pymap3d

#: The WGS84 ellipsoid (a = 6378137 m, 1/f = 298.257223563; NGA TR8350.2).
WGS84 = pymap3d.Ellipsoid.from_name('wgs84')


def check_geodetic(lat_deg, lon_deg, alt_m, field='position'):
    """Validate geodetic coordinates; return them as broadcast float arrays.

    Raises ``ValueError`` naming ``field`` and the offending component when a latitude is
    outside [−90, 90]°, a longitude outside [−180, 180]° or any value is not finite.
    """
    lat = np.asarray(lat_deg, dtype=float)
    lon = np.asarray(lon_deg, dtype=float)
    alt = np.asarray(alt_m, dtype=float)
    try:
        lat, lon, alt = np.broadcast_arrays(lat, lon, alt)
    except ValueError:
        raise ValueError(f'{field}: lat_deg, lon_deg and alt_m have incompatible shapes '
                         f'{lat.shape}, {lon.shape}, {alt.shape}') from None
    for name, val in (('lat_deg', lat), ('lon_deg', lon), ('alt_m', alt)):
        if not np.all(np.isfinite(val)):
            raise ValueError(f'{field}: {name} must be finite')
    if np.any(np.abs(lat) > 90.0):
        bad = lat[np.abs(lat) > 90.0].flat[0]
        raise ValueError(f'{field}: lat_deg {bad} is outside [-90, 90]')
    if np.any(np.abs(lon) > 180.0):
        bad = lon[np.abs(lon) > 180.0].flat[0]
        raise ValueError(f'{field}: lon_deg {bad} is outside [-180, 180]')
    return lat, lon, alt


def geodetic_triplet(values, field):
    """Parse a ``[lat_deg, lon_deg, alt_m]`` list (a YAML parameter) into a validated tuple.

    Raises ``ValueError`` naming ``field`` unless exactly three valid numbers are given.
    """
    vals = list(values)
    if len(vals) != 3:
        raise ValueError(f'{field}: expected [lat_deg, lon_deg, alt_m], got {len(vals)} values')
    try:
        # Three plain numbers (the usual case, checked per point by the map exports): on
        # floats; anything else, and every error message, through check_geodetic.
        lat, lon, alt = (float(v) for v in vals)
        if isfinite(lat) and isfinite(lon) and isfinite(alt) and abs(lat) <= 90.0 \
                and abs(lon) <= 180.0:
            return lat, lon, alt
    except (TypeError, ValueError):
        pass
    lat, lon, alt = check_geodetic(vals[0], vals[1], vals[2], field)
    return float(lat), float(lon), float(alt)


def _arrays(*values):
    return tuple(np.asarray(v, dtype=float) for v in values)


def _origin(origin, field='origin'):
    if len(origin) != 3:
        raise ValueError(f'{field}: expected (lat_deg, lon_deg, alt_m)')
    return geodetic_triplet(origin, field)


def geodetic_to_ecef(lat_deg, lon_deg, alt_m):
    """WGS84 geodetic (φ°, λ°, h m) -> ECEF (..., 3) m.

    X = (N + h) cos φ cos λ, Y = (N + h) cos φ sin λ, Z = (N (1 − e²) + h) sin φ with
    N = a / sqrt(1 − e² sin² φ) (pymap3d.geodetic2ecef).
    """
    lat, lon, alt = check_geodetic(lat_deg, lon_deg, alt_m)
    x, y, z = pymap3d.geodetic2ecef(lat, lon, alt, ell=WGS84, deg=True)
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_geodetic(ecef):
    """ECEF (..., 3) m -> WGS84 geodetic (lat_deg, lon_deg, alt_m) (pymap3d.ecef2geodetic)."""
    p = np.asarray(ecef, dtype=float)
    if p.shape[-1:] != (3,) or not np.all(np.isfinite(p)):
        raise ValueError('ecef: expected finite coordinates of shape (..., 3)')
    lat, lon, alt = pymap3d.ecef2geodetic(p[..., 0], p[..., 1], p[..., 2], ell=WGS84, deg=True)
    return _arrays(lat, lon, alt)


def geodetic_to_enu(lat_deg, lon_deg, alt_m, origin, field='position'):
    """WGS84 geodetic point(s) -> ENU (..., 3) m relative to ``origin`` (lat0°, lon0°, h0 m).

    ENU = [e n u]ᵀ (ECEF(φ, λ, h) − ECEF(φ0, λ0, h0)) with the origin's axes (module
    docstring; pymap3d.geodetic2enu). ``field`` names the point in error messages.
    """
    lat0, lon0, alt0 = _origin(origin)
    lat, lon, alt = check_geodetic(lat_deg, lon_deg, alt_m, field)
    e, n, u = pymap3d.geodetic2enu(lat, lon, alt, lat0, lon0, alt0, ell=WGS84, deg=True)
    return np.stack(np.broadcast_arrays(e, n, u), axis=-1)


def enu_to_geodetic(enu, origin):
    """ENU point(s) (..., 3) m relative to ``origin`` -> (lat_deg, lon_deg, alt_m) on WGS84.

    Inverse of :func:`geodetic_to_enu` (pymap3d.enu2geodetic).
    """
    lat0, lon0, alt0 = _origin(origin)
    p = np.asarray(enu, dtype=float)
    if p.shape[-1:] != (3,) or not np.all(np.isfinite(p)):
        raise ValueError('enu: expected finite coordinates of shape (..., 3)')
    lat, lon, alt = pymap3d.enu2geodetic(p[..., 0], p[..., 1], p[..., 2], lat0, lon0, alt0,
                                         ell=WGS84, deg=True)
    return _arrays(lat, lon, alt)


def enu_axes_rotation(origin, lat_deg, lon_deg):
    """Rotation matrices R (..., 3, 3) taking vectors in the origin's ENU axes to the ENU axes
    at the point(s) (lat_deg, lon_deg): v_local = R v_origin.

    R = R_pᵀ R_0, where the columns of R_0 (R_p) are the e, n, u axes of the origin (of the
    point) in ECEF (pymap3d.enu2uvw / uvw2enu applied to the basis vectors). R is the
    identity at the origin; away from it the up axes tilt by about distance / Earth radius
    (1.6 mrad 10 km away) and East/North turn about up by the meridian convergence
    (λ − λ0) sin φ. Used to express a covariance in a NavSatFix, whose
    ``position_covariance`` is in the ENU tangent plane through the reported position.
    """
    lat0, lon0, _ = _origin(origin)
    lat, lon, _ = check_geodetic(lat_deg, lon_deg, 0.0, 'point')
    cols = []
    for basis in np.eye(3):
        ux, uy, uz = pymap3d.enu2uvw(basis[0], basis[1], basis[2], lat0, lon0, deg=True)
        e, n, u = pymap3d.uvw2enu(ux, uy, uz, lat, lon, deg=True)
        cols.append(np.stack(np.broadcast_arrays(e, n, u), axis=-1))
    return np.stack(cols, axis=-1)
