"""Fixes, error ellipses, stations and bearing rays as geographic features (RFC 7946).

Everything here is geometry in plain Python/numpy; the file formats (GeoJSON, KML, CSV) are
written by :mod:`bearing_loc_ros.gis_export` and the live map by the Foxglove view node.

Conventions (DESIGN.md "Frames, units, angles"):

* Input is in the local ENU frame (m) of a geodetic ``origin`` (lat0_deg, lon0_deg, h0_m on
  WGS84); conversions are :mod:`bearing_loc_ros.core.geodesy` (pymap3d).
* Output positions follow RFC 7946 section 3.1.1: ``[longitude, latitude]`` in decimal
  degrees on WGS84, with the ellipsoidal height (m) as a third element for points.
* An azimuth θ is ENU yaw (counter-clockwise from East) in the *origin's* axes. A bearing ray
  is drawn as the geodesic (Vincenty's direct solution, ``pymap3d.vincenty.vreckon``) that
  leaves the station with the same direction expressed in the station's own ENU axes
  (meridian convergence applied with :func:`~bearing_loc_ros.core.geodesy.enu_axes_rotation`),
  i.e. the ground track of the horizontal component of the line of sight.
* Error ellipse: the horizontal marginal of the fix covariance in the local ENU axes at the
  fix, C' = R C Rᵀ (R from :func:`~bearing_loc_ros.core.geodesy.enu_axes_rotation`, the
  rotation ``fix/navsat`` applies to its covariance) and C₂ = C'[:2, :2] (m²), drawn at
  probability p as the set {d : dᵀ C₂⁻¹ d = k²} of East/North offsets d in the tangent
  plane at the fix (converted with :func:`~bearing_loc_ros.core.geodesy.enu_to_geodetic`
  about the fix), with k² = χ²₂(p) = −2 ln(1 − p) (the 2-degree-of-freedom chi-square
  quantile), so a Gaussian error of covariance C₂ falls inside with probability p (default
  95 %, k = 2.4477). Near the origin R is the identity; 1000 km away C[:2, :2] itself (the
  origin's axes, tilted by 9° there) would draw the ellipse several times too long.
* Antimeridian: lines and polygons that cross ±180° of longitude are split into
  ``MultiLineString`` / ``MultiPolygon`` parts that meet at ±180° (RFC 7946 section 3.1.9).
  A line passing over a pole (:func:`passes_pole`) is split at the pole instead: the parts
  meet at ±90° latitude.
  Polar origins (|lat0| > :data:`MAX_ORIGIN_LAT_DEG`) are refused with a one-line
  ``ValueError``: a local tangent-plane picture there does not map onto longitude/latitude.

One module (about 700 lines) on purpose: the ellipse, antimeridian splitting and feature
builders share the origin checks and the ring/line builders and are read together.
"""

from collections import deque
from dataclasses import dataclass, field
from datetime import datetime, timezone
from functools import lru_cache
import math
import typing

import numpy as np
from pymap3d import vincenty

from . import geodesy
from .bearings import MAX_ABS_POSITION

#: Default probability of the drawn error ellipses.
DEFAULT_PROBABILITY = 0.95
#: Vertices of an ellipse ring (plus the closing vertex) and of a bearing ray.
ELLIPSE_POINTS = 72
RAY_POINTS = 33
#: A bearing ray reaches this factor times the station-to-fix horizontal distance.
RAY_OVERSHOOT = 1.25
#: Ray length (m) when there is no fix to aim at and no length is given.
DEFAULT_RAY_LENGTH = 10_000.0
#: Largest |latitude| of a geodetic origin, degrees (polar origins are refused).
MAX_ORIGIN_LAT_DEG = 85.0
#: Largest |altitude| of a geodetic origin, m.
MAX_ORIGIN_ALT_M = 1e6
#: Largest |ENU coordinate| of a live fix or station, m: the bearing contract's bound.
MAX_ABS_ENU_M = MAX_ABS_POSITION
#: A line step of more than 90° of longitude whose great circle comes within this of a pole
#: between its two vertices passes over that pole (:func:`passes_pole`).
POLE_PASS_DEG = 1.0
#: Closest approach of a drawn ellipse to a pole, degrees of latitude.
POLE_MARGIN_DEG = 0.5
#: Drawn ellipses: semi-minor axis at least this (m; thinner is a singular horizontal
#: covariance, a polygon of no area), semi-major axis at most this (m; beyond it the ring
#: laid in the tangent plane at the fix is more than 0.8 % off on the ground).
MIN_ELLIPSE_AXIS_M = 1e-3
MAX_ELLIPSE_AXIS_M = 1e6
#: Drawn fixes: ellipsoidal height at least this (m; 100 km below the ellipsoid, deeper than
#: any place an emitter can be: a fix below it lies inside the Earth, and its point would
#: be drawn near the antipode) and at most this (m; 100,000 km, beyond geostationary orbit).
MIN_FIX_ALTITUDE_M = -1e5
MAX_FIX_ALTITUDE_M = 1e8
#: Decimal places of output degrees (1e-9 deg is about 0.1 mm).
DEG_DECIMALS = 9
NS_PER_S = 1_000_000_000


def check_origin(origin):
    """Validate a geodetic origin (lat0_deg, lon0_deg, h0_m); return it as a float tuple.

    ValueError (one line) for a malformed origin, a polar one (|lat0| above
    :data:`MAX_ORIGIN_LAT_DEG`) or one beyond :data:`MAX_ORIGIN_ALT_M` in altitude.
    """
    if origin is None:
        raise ValueError('origin: a geodetic origin [lat_deg, lon_deg, alt_m] is required for '
                         'geographic output')
    lat, lon, alt = geodesy.geodetic_triplet(origin, 'origin')
    if abs(lat) > MAX_ORIGIN_LAT_DEG:
        raise ValueError(f'origin: latitude {lat:g} deg is polar (beyond +-{MAX_ORIGIN_LAT_DEG:g}'
                         ' deg); a local ENU picture cannot be drawn in longitude/latitude there')
    if abs(alt) > MAX_ORIGIN_ALT_M:
        raise ValueError(f'origin: altitude {alt:g} m is outside +-{MAX_ORIGIN_ALT_M:g} m')
    return lat, lon, alt


def ellipse_scale(probability=DEFAULT_PROBABILITY):
    """k with P(χ²₂ ≤ k²) = p: k = sqrt(−2 ln(1 − p)) (2-dof chi-square quantile, exact).

    The Mahalanobis radius of the p-probability region of a 2D Gaussian. ValueError unless
    0 < p < 1.
    """
    p = float(probability)
    if not 0.0 < p < 1.0:
        raise ValueError(f'probability: must be in (0, 1), got {probability!r}')
    return math.sqrt(-2.0 * math.log1p(-p))


def sigma_probability(n_sigma):
    """p with k = n_sigma in :func:`ellipse_scale`: p = 1 − exp(−n²/2) (2-dof chi-square).

    The probability inside the n-σ ellipse of a 2D Gaussian (n = 1: 39.3 %), to draw a
    "1σ ellipse" with :func:`ellipse_ring_enu`. ValueError unless n > 0 is finite.
    """
    n = float(n_sigma)
    if not (math.isfinite(n) and n > 0.0):
        raise ValueError(f'n_sigma: must be a finite number > 0, got {n_sigma!r}')
    return -math.expm1(-0.5 * n * n)


def horizontal_ellipse(covariance, probability=DEFAULT_PROBABILITY):
    """Semi-axes and orientation of the horizontal error ellipse of a (3, 3) covariance, m².

    C₂ = C[:2, :2] = V diag(λ₁, λ₂) Vᵀ (λ₁ ≥ λ₂); semi-major a = k sqrt(λ₁), semi-minor
    b = k sqrt(λ₂) with k = :func:`ellipse_scale` (p); orientation = angle of the major axis,
    rad, ENU (CCW from East), in (−π/2, π/2]. Returns (a, b, orientation) in m, m, rad.
    ValueError for a non-finite, asymmetric or not positive semi-definite C₂.
    """
    c = np.asarray(covariance, dtype=float)
    if c.shape != (3, 3):
        raise ValueError(f'covariance: expected shape (3, 3), got {c.shape}')
    c2 = c[:2, :2]
    if not np.all(np.isfinite(c2)):
        raise ValueError('covariance: horizontal block is not finite (unobservable fix)')
    if abs(c2[0, 1] - c2[1, 0]) > 1e-9 * max(1.0, abs(c2[0, 0]) + abs(c2[1, 1])):
        raise ValueError('covariance: not symmetric')
    lam, vec = np.linalg.eigh(0.5 * (c2 + c2.T))
    if lam[0] < -1e-9 * max(1.0, lam[1]):
        raise ValueError('covariance: not positive semi-definite')
    k = ellipse_scale(probability)
    a, b = k * math.sqrt(max(lam[1], 0.0)), k * math.sqrt(max(lam[0], 0.0))
    ang = math.atan2(vec[1, 1], vec[0, 1])
    if ang <= -math.pi / 2:
        ang += math.pi
    elif ang > math.pi / 2:
        ang -= math.pi
    return a, b, ang


def ellipse_ring_enu(position, covariance, probability=DEFAULT_PROBABILITY,
                     points=ELLIPSE_POINTS):
    """Closed ring (points + 1, 3) of the horizontal error ellipse at the fix altitude, m.

    x(t) = x̂ + k L (cos t, sin t) for t = 0, 2π/n, ..., 2π, where L Lᵀ = C₂ (L = V
    diag(sqrt λ)) and k = :func:`ellipse_scale` (p); counter-clockwise (RFC 7946 exterior
    ring orientation). ValueError as :func:`horizontal_ellipse`.
    """
    a, b, ang = horizontal_ellipse(covariance, probability)
    p = np.asarray(position, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError('position: expected 3 finite ENU coordinates, m')
    t = np.linspace(0.0, 2.0 * np.pi, int(points) + 1)
    ca, sa = math.cos(ang), math.sin(ang)
    u, v = a * np.cos(t), b * np.sin(t)
    ring = np.empty((t.size, 3))
    ring[:, 0] = p[0] + ca * u - sa * v
    ring[:, 1] = p[1] + sa * u + ca * v
    ring[:, 2] = p[2]
    ring[-1] = ring[0]
    return ring


def enu_to_lonlat(enu, origin):
    """ENU points (..., 3) m -> (lon_deg, lat_deg, alt_m) arrays (geodesy.enu_to_geodetic)."""
    lat, lon, alt = geodesy.enu_to_geodetic(enu, check_origin(origin))
    return lon, lat, alt


def _wrap_lon(lon):
    """Longitude(s) wrapped to [−180, 180), degrees."""
    return (np.asarray(lon, dtype=float) + 180.0) % 360.0 - 180.0


def _cross_lat(lon_a, lat_a, lon_b, lat_b, edge):
    """Latitude where the segment a-b (unwrapped longitudes) meets longitude ``edge``."""
    f = (edge - lon_a) / (lon_b - lon_a)
    return lat_a + f * (lat_b - lat_a)


def passes_pole(lon_a, lat_a, lon_b, lat_b):
    """The pole (+90.0 or −90.0) a line step from a to b (degrees) passes over, else None.

    On the unit sphere (geodetic latitudes as spherical ones: this only decides how to draw
    a step) with a, b the unit vectors of the vertices and n = a × b / |a × b|, the point of
    the great circle nearest the pole P (of the hemisphere of φ_a + φ_b, north when 0) is
    q = (P − (P·n) n) / |P − (P·n) n|. The step passes over P when its wrapped longitude
    change exceeds 90°, q lies on the arc between a and b ((a × q)·n >= 0 and
    (q × b)·n >= 0) and q is within :data:`POLE_PASS_DEG` of P. Antipodal vertices (no
    unique arc) with a 180° longitude step count as a pass.
    """
    if abs(float(_wrap_lon(lon_b - lon_a))) <= 90.0:
        return None
    pole = -90.0 if lat_a + lat_b < 0.0 else 90.0

    def unit(lon, lat):
        lo, la = math.radians(lon), math.radians(lat)
        return np.array([math.cos(la) * math.cos(lo), math.cos(la) * math.sin(lo),
                         math.sin(la)])
    a, b = unit(lon_a, lat_a), unit(lon_b, lat_b)
    p = np.array([0.0, 0.0, 1.0 if pole > 0 else -1.0])
    n = np.cross(a, b)
    norm = np.linalg.norm(n)
    if norm < 1e-12:
        return pole
    n /= norm
    q = p - np.dot(p, n) * n
    qn = np.linalg.norm(q)
    if qn < 1e-12:                      # the great circle is the equator
        return None
    q /= qn
    if np.dot(np.cross(a, q), n) < 0.0 or np.dot(np.cross(q, b), n) < 0.0:
        return None
    closest = math.degrees(math.acos(min(1.0, float(np.dot(q, p)))))
    return pole if closest <= POLE_PASS_DEG else None


def split_line(lon, lat):
    """Split a polyline at the antimeridian and at the poles: list of (k, 2) [lon, lat] parts.

    Between consecutive vertices a and b, with the longitude step Δ = λ_b − λ_a wrapped to
    [−180, 180):

    * a pass over a pole (:func:`passes_pole`: |Δ| > 90° and the step's great circle
      comes within :data:`POLE_PASS_DEG` of the pole between the vertices): the line ends
      at (λ_a, ±90°) and the next part starts at (λ_b, ±90°), so nothing is drawn along the
      map's top or bottom edge;
    * otherwise a raw step of more than 180° is an antimeridian crossing: the crossing
      latitude is interpolated linearly in (unwrapped) longitude and both parts end on the
      meridian, at +180 on one side and −180 on the other.
    """
    lon = _wrap_lon(lon)
    lat = np.asarray(lat, dtype=float)
    parts, cur = [], [[lon[0], lat[0]]]
    for i in range(1, lon.size):
        a, b = lon[i - 1], lon[i]
        pole = passes_pole(a, lat[i - 1], b, lat[i])
        if pole is not None:
            cur.append([a, pole])
            parts.append(np.array(cur))
            cur = [[b, pole]]
        elif abs(b - a) > 180.0:
            b_un = b - 360.0 if b > a else b + 360.0
            edge = 180.0 if b_un > a else -180.0
            y = _cross_lat(a, lat[i - 1], b_un, lat[i], edge)
            cur.append([edge, y])
            parts.append(np.array(cur))
            cur = [[-edge, y]]
        cur.append([b, lat[i]])
    parts.append(np.array(cur))
    return [p for p in parts if len(p) >= 2]


def _clip(ring, keep_below, edge):
    """Sutherland-Hodgman clip of a closed ring (n, 2) by the half-plane lon <= edge (or >=)."""
    def inside(pt):
        return pt[0] <= edge if keep_below else pt[0] >= edge
    out = []
    pts = ring[:-1]
    for i in range(len(pts)):
        cur, prev = pts[i], pts[i - 1]
        if inside(cur):
            if not inside(prev):
                out.append([edge, _cross_lat(prev[0], prev[1], cur[0], cur[1], edge)])
            out.append(list(cur))
        elif inside(prev):
            out.append([edge, _cross_lat(prev[0], prev[1], cur[0], cur[1], edge)])
    if len(out) < 3:
        return None
    out.append(out[0])
    return np.array(out)


def split_ring(lon, lat):
    """Split a closed ring at the antimeridian: list of closed (k, 2) [lon, lat] rings.

    Longitudes are unwrapped along the ring; the part beyond +180 (below −180) is clipped off
    with the meridian as its edge and shifted by −360° (+360°). ValueError when the ring
    spans more than 180° of longitude or comes within :data:`POLE_MARGIN_DEG` of a pole (it
    could enclose the pole, which a lon/lat polygon cannot express).
    """
    lat = np.asarray(lat, dtype=float)
    if np.max(np.abs(lat)) > 90.0 - POLE_MARGIN_DEG:
        raise ValueError('ellipse: reaches a pole; too large to draw in longitude/latitude')
    un = np.degrees(np.unwrap(np.radians(_wrap_lon(lon))))
    if un.max() - un.min() > 180.0:
        raise ValueError('ellipse: spans more than 180 deg of longitude; too large to draw')
    ring = np.column_stack([un, lat])
    if un.max() <= 180.0 and un.min() >= -180.0:
        return [ring]
    edge = 180.0 if un.max() > 180.0 else -180.0
    a = _clip(ring, edge > 0, edge)
    b = _clip(ring, edge < 0, edge)
    out = [r for r in (a,) if r is not None]
    if b is not None:
        b = b.copy()
        b[:, 0] -= 360.0 if edge > 0 else -360.0
        out.append(b)
    return out


def _positions(parts, decimals=DEG_DECIMALS):
    return [[[round(float(x), decimals), round(float(y), decimals)] for x, y in p]
            for p in parts]


def line_geometry(lon, lat):
    """GeoJSON LineString (or MultiLineString when split at the antimeridian or a pole)."""
    parts = _positions(split_line(lon, lat))
    if len(parts) == 1:
        return {'type': 'LineString', 'coordinates': parts[0]}
    return {'type': 'MultiLineString', 'coordinates': parts}


def polygon_geometry(lon, lat):
    """GeoJSON Polygon (or MultiPolygon when split at the antimeridian) of a closed ring."""
    parts = _positions(split_ring(lon, lat))
    if len(parts) == 1:
        return {'type': 'Polygon', 'coordinates': [parts[0]]}
    return {'type': 'MultiPolygon', 'coordinates': [[p] for p in parts]}


def point_geometry(lon, lat, alt):
    """GeoJSON Point [lon, lat, alt] (degrees wrapped to [−180, 180), m)."""
    return {'type': 'Point', 'coordinates': [round(float(_wrap_lon(lon)), DEG_DECIMALS),
                                             round(float(lat), DEG_DECIMALS),
                                             round(float(alt), 4)]}


@lru_cache(maxsize=4096)
def _station_frame(x, y, z, origin):
    """(lon_deg, lat_deg, R) of the station at ENU (x, y, z) m: its geodetic position and the
    rotation R from the origin's ENU axes to its own. Cached: a map export draws many rays
    from few stations."""
    lon, lat, _ = enu_to_lonlat(np.array([x, y, z], dtype=float), origin)
    rot = geodesy.enu_axes_rotation(origin, float(lat), float(lon))
    rot.setflags(write=False)
    return float(lon), float(lat), rot


def _frame_of(station_enu, origin):
    x, y, z = np.asarray(station_enu, dtype=float).reshape(3).tolist()
    return _station_frame(x, y, z, check_origin(origin))


def compass_at(azimuth, station_enu, origin):
    """Initial geodesic azimuth (deg, clockwise from North) at a station of an ENU azimuth θ.

    d = (cos θ, sin θ, 0) in the origin's ENU axes is rotated into the station's ENU axes,
    d' = R d (:func:`~bearing_loc_ros.core.geodesy.enu_axes_rotation`), and the compass
    azimuth is atan2(d'_E, d'_N) (the horizontal part; the meridian convergence is
    (λ − λ0) sin φ).
    """
    rot = _frame_of(station_enu, origin)[2]
    d = rot @ np.array([math.cos(azimuth), math.sin(azimuth), 0.0])
    return math.degrees(math.atan2(d[0], d[1])) % 360.0


def ray_lonlat(station_enu, azimuth, length, origin, points=RAY_POINTS):
    """Geodesic bearing ray from a station: (lon_deg, lat_deg) arrays of ``points`` vertices.

    Vincenty's direct problem (pymap3d.vincenty.vreckon) from the station's geodetic
    position with the initial azimuth of :func:`compass_at`, at ground distances
    0 .. ``length`` m (> 0).
    """
    length = float(length)
    if not (math.isfinite(length) and length > 0.0):
        raise ValueError(f'length: ray length must be finite and > 0 m, got {length!r}')
    lon0, lat0, _ = _frame_of(station_enu, origin)
    az = compass_at(azimuth, station_enu, origin)
    dist = np.linspace(0.0, length, int(points))
    lat, lon = vincenty.vreckon(float(lat0), float(lon0), dist, az, ell=geodesy.WGS84)
    lat = np.array(lat, dtype=float).reshape(dist.shape)
    lon = np.array(lon, dtype=float).reshape(dist.shape)
    lat[0], lon[0] = float(lat0), float(lon0)
    return _wrap_lon(lon), lat


def iso_time(stamp_ns):
    """Integer ns since the Unix epoch -> ISO 8601 UTC string with 'Z' (µs resolution);
    None (no time, e.g. a ``bearing_loc locate`` fix) -> None."""
    if stamp_ns is None:
        return None
    t = datetime.fromtimestamp(int(stamp_ns) // 1000 / 1e6, tz=timezone.utc)
    return t.isoformat().replace('+00:00', 'Z')


@dataclass
class GeoFix:
    """One fix to draw: ENU position (3,) m, covariance (3, 3) m², stamp ns (None: no
    time), and provenance (status, estimator, stations; each None when unknown, as for a
    live ``fix`` message, and then left out of the drawn properties)."""

    stamp_ns: typing.Optional[int]
    position: np.ndarray
    covariance: np.ndarray
    status: str = 'ok'
    estimator: str = ''
    stations: list = field(default_factory=list)

    @classmethod
    def from_epoch(cls, ep):
        """From a fusion Epoch with a fix (core.fusion.Epoch); ``stations`` distinct, in
        order (a window-mode fix holds many bearings of one station)."""
        return cls(int(ep.stamp_ns), np.asarray(ep.position, float),
                   np.asarray(ep.covariance, float), ep.status or ep.reason,
                   ep.estimator, list(dict.fromkeys(ep.stations)))


def _stamp(stamp_ns):
    """int ns, or None for no time."""
    return None if stamp_ns is None else int(stamp_ns)


def _feature(geometry, props):
    return {'type': 'Feature', 'geometry': geometry, 'properties': props}


def local_covariance(covariance, origin, lat_deg, lon_deg):
    """A covariance (3, 3) in the origin's ENU axes, m², expressed in the ENU axes at the
    point (lat_deg, lon_deg): C' = R C Rᵀ with R of
    :func:`~bearing_loc_ros.core.geodesy.enu_axes_rotation` (as ``fix/navsat``). A
    non-finite vertical part (an unobserved height) is left out of the rotation (taken as 0)
    rather than spread into the horizontal; ValueError when C[:2, :2] is not finite."""
    c = np.array(covariance, dtype=float)
    if c.shape != (3, 3):
        raise ValueError(f'covariance: expected shape (3, 3), got {c.shape}')
    if not np.all(np.isfinite(c[:2, :2])):
        raise ValueError('covariance: horizontal block is not finite (unobservable fix)')
    if not np.all(np.isfinite(c)):
        c[2, :] = c[:, 2] = 0.0
    rot = geodesy.enu_axes_rotation(check_origin(origin), float(lat_deg), float(lon_deg))
    return rot @ c @ rot.T


def fix_features(fix, origin, probability=DEFAULT_PROBABILITY, fix_id=None):
    """Point feature of a fix and, when drawable, its error-ellipse polygon feature.

    Point properties: kind 'fix', time (ISO 8601 UTC), stamp_ns, status, estimator,
    stations (each left out when None), position_enu_m, covariance_enu_m2 (row-major 3x3),
    sigma_east_m, sigma_north_m, sigma_up_m, sigma_horizontal_m = sqrt(C_xx + C_yy), sigma_3d_m =
    sqrt(trace C) (C and σ in the origin's ENU axes), and ellipse (probability, semi-axes m,
    orientation rad counter-clockwise from East, all in the local ENU axes at the fix: module
    docstring) or ellipse_error (why none is drawn: a non-finite or indefinite covariance, a
    semi-major axis beyond :data:`MAX_ELLIPSE_AXIS_M` (too large), a semi-minor one below
    :data:`MIN_ELLIPSE_AXIS_M` (degenerate), one reaching a pole or spanning 180° of
    longitude). A fix at a height :func:`fix_altitude_problem` refuses (inside the Earth,
    beyond geostationary orbit) is one feature without geometry (``null``, RFC 7946 sec.
    3.2) and with ``position_error`` saying why.
    """
    p = np.asarray(fix.position, dtype=float)
    c = np.asarray(fix.covariance, dtype=float)
    lon, lat, alt = enu_to_lonlat(p, origin)
    d = np.diag(c) if c.shape == (3, 3) else np.full(3, np.nan)

    def num(v):
        v = float(v)
        return v if math.isfinite(v) else None

    props = {'kind': 'fix', 'time': iso_time(fix.stamp_ns), 'stamp_ns': _stamp(fix.stamp_ns)}
    for key, value in (('status', fix.status), ('estimator', fix.estimator)):
        if value is not None:
            props[key] = str(value)
    if fix.stations is not None:
        props['stations'] = list(fix.stations)
    props.update(position_enu_m=[num(v) for v in p],
                 covariance_enu_m2=[num(v) for v in c.ravel()],
                 sigma_east_m=num(math.sqrt(d[0])) if d[0] >= 0 else None,
                 sigma_north_m=num(math.sqrt(d[1])) if d[1] >= 0 else None,
                 sigma_up_m=num(math.sqrt(d[2])) if d[2] >= 0 else None,
                 sigma_horizontal_m=num(math.sqrt(max(d[0] + d[1], 0.0))),
                 sigma_3d_m=num(math.sqrt(max(np.sum(d), 0.0))))
    if fix_id is not None:
        props['id'] = fix_id
    problem = fix_altitude_problem(float(alt))
    if problem is not None:
        props['position_error'] = problem
        return [_feature(None, props)]
    out = [_feature(point_geometry(lon, lat, alt), props)]
    try:
        local = local_covariance(c, origin, lat, lon)
        a, b, ang = horizontal_ellipse(local, probability)
        if a > MAX_ELLIPSE_AXIS_M:
            raise ValueError(f'ellipse: too large to draw: semi-major axis {a / 1e3:.4g} km, '
                             f'beyond {MAX_ELLIPSE_AXIS_M / 1e3:g} km')
        if b < MIN_ELLIPSE_AXIS_M:
            raise ValueError(f'ellipse: degenerate: semi-minor axis {b:.3g} m, below '
                             f'{MIN_ELLIPSE_AXIS_M * 1e3:g} mm (singular horizontal '
                             'covariance)')
        ring = ellipse_ring_enu(np.zeros(3), local, probability)
        rlat, rlon, _ = geodesy.enu_to_geodetic(ring, (float(lat), float(lon), float(alt)))
        geom = polygon_geometry(rlon, rlat)
    except ValueError as exc:
        props['ellipse_error'] = str(exc)
        return out
    ell = {'probability': float(probability), 'semi_major_m': a, 'semi_minor_m': b,
           'orientation_rad': ang}
    props['ellipse'] = ell
    eprops = {'kind': 'ellipse', 'time': props['time'], 'stamp_ns': props['stamp_ns']}
    for key in ('status', 'estimator'):
        if key in props:
            eprops[key] = props[key]
    eprops.update(ell)
    if fix_id is not None:
        eprops['fix_id'] = fix_id
    out.append(_feature(geom, eprops))
    return out


def station_feature(name, position_enu, origin, dims=None):
    """Point feature of a station: kind 'station', name, position_enu_m, dims (1/2)."""
    p = np.asarray(position_enu, dtype=float)
    lon, lat, alt = enu_to_lonlat(p, origin)
    props = {'kind': 'station', 'name': str(name), 'position_enu_m': [float(v) for v in p]}
    if dims is not None:
        props['dims'] = int(dims)
    return _feature(point_geometry(lon, lat, alt), props)


def ray_length_for(station_enu, target_enu=None, default=DEFAULT_RAY_LENGTH):
    """Ray length (m): RAY_OVERSHOOT x horizontal station-to-target distance, else default."""
    if target_enu is not None and np.all(np.isfinite(target_enu)):
        d = math.hypot(target_enu[0] - station_enu[0], target_enu[1] - station_enu[1])
        if d > 0.0:
            return RAY_OVERSHOOT * d
    return float(default)


def bearing_feature(bearing, origin, length):
    """LineString feature of a core Bearing's ray (geodesic, :func:`ray_lonlat`).

    Properties: kind 'bearing', station, time, stamp_ns, azimuth_rad (ENU), compass_deg
    (clockwise from North at the station), elevation_rad (or None), sigma_azimuth_rad,
    length_m.
    """
    pos = np.asarray(bearing.position, dtype=float)
    lon, lat = ray_lonlat(pos, bearing.azimuth, length, origin)
    el = float(bearing.elevation)
    props = {'kind': 'bearing', 'station': str(bearing.station),
             'time': iso_time(bearing.stamp_ns), 'stamp_ns': _stamp(bearing.stamp_ns),
             'azimuth_rad': float(bearing.azimuth),
             'compass_deg': compass_at(bearing.azimuth, pos, origin),
             'elevation_rad': el if math.isfinite(el) else None,
             'sigma_azimuth_rad': float(bearing.sigma_azimuth), 'length_m': float(length)}
    return _feature(line_geometry(lon, lat), props)


def feature_collection(origin, fixes=(), bearings=(), stations=None,
                       probability=DEFAULT_PROBABILITY, ray_length=None):
    """RFC 7946 FeatureCollection (a dict) of fixes, ellipses, stations and bearing rays.

    ``fixes``: GeoFix objects; ``bearings``: (bearing, fix position or None) pairs, each
    ray drawn to :data:`RAY_OVERSHOOT` x the distance to its fix (``ray_length`` m when
    given, else :data:`DEFAULT_RAY_LENGTH` without a fix); ``stations``: name -> ENU
    position (default: the positions of the bearings, last one per station). Feature order:
    stations, bearings, ellipses and fixes (fixes drawn last, on top).
    """
    origin = check_origin(origin)
    bearings = list(bearings)
    if stations is None:
        stations = {}
        for b, _ in bearings:
            stations[b.station] = np.asarray(b.position, dtype=float)
    feats = [station_feature(n, p, origin) for n, p in stations.items()]
    for b, target in bearings:
        length = ray_length if ray_length else ray_length_for(b.position, target)
        feats.append(bearing_feature(b, origin, length))
    pts = []
    for k, f in enumerate(fixes):
        fx = fix_features(f, origin, probability, fix_id=k)
        pts.append(fx[0])
        feats.extend(fx[1:])
    feats.extend(pts)
    return {'type': 'FeatureCollection', 'features': feats}


#: The fusion's reason (and status) of a fix that failed its consistency checks.
LOW_CONFIDENCE = 'low_confidence'


def drawn_epochs(epochs, low_confidence=False):
    """The fusion epochs (core.fusion.Epoch) that are drawn as fixes: those with a fix
    (``ok``) and, with ``low_confidence``, those whose fix failed its consistency checks
    (reason :data:`LOW_CONFIDENCE`, position kept), as the fusion node's
    ``publish_low_confidence`` publishes them."""
    return [e for e in epochs if e.ok or low_confidence and e.reason == LOW_CONFIDENCE
            and e.position is not None and e.covariance is not None]


def geofixes_of(epochs):
    """:class:`GeoFix` of each epoch with a position (:meth:`GeoFix.from_epoch`); status
    ``low_confidence`` for a fix that failed its consistency checks (reason
    :data:`LOW_CONFIDENCE`)."""
    out = [GeoFix.from_epoch(e) for e in epochs]
    for f, e in zip(out, epochs):
        if e.reason == LOW_CONFIDENCE:
            f.status = LOW_CONFIDENCE
    return out


def features_from_epochs(epochs, origin, probability=DEFAULT_PROBABILITY, last_bearings=False,
                         low_confidence=False):
    """FeatureCollection of fusion epochs (core.fusion.Epoch objects).

    Every fix of :func:`drawn_epochs` (``low_confidence``: also the fixes that failed their
    consistency checks, with status ``low_confidence``) with its ellipse; the bearings of
    every drawn fix (or of the last one only with ``last_bearings``), each ray drawn a bit
    beyond its fix; every station seen in any epoch at its last reported position.
    """
    eps = drawn_epochs(epochs, low_confidence)
    fixes = geofixes_of(eps)
    chosen = eps[-1:] if last_bearings else eps
    rays = [(b, np.asarray(e.position, float)) for e in chosen for b in e.bearings]
    stations = {}
    for e in epochs:
        for b in e.bearings:
            stations[b.station] = np.asarray(b.position, dtype=float)
    return feature_collection(origin, fixes, rays, stations, probability)


def grid_corners_lonlat(origin_x, origin_y, width_m, height_m, altitude, origin):
    """Corners of an ENU-aligned raster, counter-clockwise from lower-left, as (4, 2) lon/lat.

    Order (lower-left, lower-right, upper-right, upper-left) is KML's gx:LatLonQuad order.
    ValueError when the raster crosses the antimeridian (a quad there is ambiguous).
    """
    xs = [origin_x, origin_x + width_m, origin_x + width_m, origin_x]
    ys = [origin_y, origin_y, origin_y + height_m, origin_y + height_m]
    enu = np.column_stack([xs, ys, np.full(4, float(altitude))])
    lon, lat, _ = enu_to_lonlat(enu, origin)
    un = np.degrees(np.unwrap(np.radians(lon)))
    if np.any(np.abs(un) > 180.0) or un.max() - un.min() > 180.0:
        raise ValueError('raster: crosses the antimeridian; cannot be georeferenced as one '
                         'overlay')
    return np.column_stack([lon, lat])


#: A live input stamped more than this before what the picture holds (ns) is a clock restart.
CLOCK_JUMP_NS = 5 * NS_PER_S
#: Window (ns of fix stamps) and largest sample of :class:`FixRate`.
RATE_WINDOW_NS = 10 * NS_PER_S
RATE_MAX_STAMPS = 4096
#: Results of :meth:`LivePicture.update_fix` / :meth:`LivePicture.update_bearing`.
ACCEPTED, RESTARTED, OUT_OF_ORDER = 'accepted', 'restarted', 'out_of_order'


def _finite_enu(p, what):
    p = np.asarray(p, dtype=float)
    # Scalar comparisons (NaN fails them): once per live message, ~1 µs.
    if p.shape != (3,) or not all(abs(v) <= MAX_ABS_ENU_M for v in p.tolist()):
        raise ValueError(f'{what}: expected 3 finite ENU coordinates within '
                         f'+-{MAX_ABS_ENU_M:g} m')


def _check_stamp(stamp_ns, what):
    if stamp_ns is not None and (isinstance(stamp_ns, bool) or int(stamp_ns) != stamp_ns
                                 or stamp_ns < 0):
        raise ValueError(f'{what}: stamp must be an integer >= 0 ns, got {stamp_ns!r}')


def fix_altitude_problem(alt):
    """Why a fix at ellipsoidal height ``alt`` (m) is not drawn, or None: below
    :data:`MIN_FIX_ALTITUDE_M` (inside the Earth) or above :data:`MAX_FIX_ALTITUDE_M`."""
    if not alt >= MIN_FIX_ALTITUDE_M:
        return (f'fix position: {-alt / 1e3:.4g} km below the Earth\'s surface (inside the '
                'Earth), not drawn')
    if alt > MAX_FIX_ALTITUDE_M:
        return f'fix position: {alt / 1e3:.4g} km above the Earth, not drawn'
    return None


def check_live_fix(fix, origin=None):
    """ValueError (one line, naming the field) unless a :class:`GeoFix` can be drawn live:
    position 3 finite ENU coordinates within :data:`MAX_ABS_ENU_M` (with ``origin``, also
    at a height :func:`fix_altitude_problem` accepts), covariance a finite (3, 3) array,
    stamp an integer >= 0 ns (or None)."""
    _finite_enu(fix.position, 'fix position')
    c = np.asarray(fix.covariance, dtype=float)
    if c.shape != (3, 3) or not np.isfinite(c).all():
        raise ValueError('fix covariance: expected a finite (3, 3) array, m^2')
    _check_stamp(fix.stamp_ns, 'fix')
    if origin is not None:
        problem = fix_altitude_problem(float(enu_to_lonlat(
            np.asarray(fix.position, dtype=float), origin)[2]))
        if problem is not None:
            raise ValueError(problem)


def check_live_bearing(bearing):
    """ValueError (one line, naming the field) unless a core Bearing can be drawn live:
    station position as :func:`check_live_fix`'s, finite azimuth, finite σ_θ > 0, stamp an
    integer >= 0 ns."""
    _finite_enu(bearing.position, 'bearing position')
    if not math.isfinite(float(bearing.azimuth)):
        raise ValueError('bearing azimuth: must be finite')
    sa = float(bearing.sigma_azimuth)
    if not (math.isfinite(sa) and sa > 0.0):
        raise ValueError('bearing sigma_azimuth: must be finite and > 0')
    _check_stamp(bearing.stamp_ns, 'bearing')


def stamp_order(stamp_ns, held_ns):
    """How a live input stamped ``stamp_ns`` relates to the stamp held for it (``held_ns``).

    :data:`ACCEPTED` when either is None or the stamp does not go backwards;
    :data:`RESTARTED` when it goes back by more than :data:`CLOCK_JUMP_NS` (the clock
    restarted: a bag replayed again, a simulation restarted, or the held stamp was in the
    future); :data:`OUT_OF_ORDER` when it goes back by at most that (a late message).
    """
    if stamp_ns is None or held_ns is None or stamp_ns >= held_ns:
        return ACCEPTED
    return RESTARTED if held_ns - stamp_ns > CLOCK_JUMP_NS else OUT_OF_ORDER


class FixRate:
    """Fix rate (Hz) over the last :data:`RATE_WINDOW_NS` of fix stamps, in bounded memory.

    :meth:`add` keeps at most ``max_stamps`` stamps (the rate of a faster stream is taken
    over the last ``max_stamps`` fixes). Time order follows :func:`stamp_order`: a clock
    restart starts the window afresh; an out-of-order stamp is not added.
    """

    def __init__(self, window_ns=RATE_WINDOW_NS, max_stamps=RATE_MAX_STAMPS):
        self.window_ns = int(window_ns)
        self.stamps = deque(maxlen=max(int(max_stamps), 2))

    def add(self, stamp_ns):
        """Add a fix stamp (int ns); return (rate Hz or None, :func:`stamp_order` result).

        The rate is (n − 1) / span over the n stamps in the window; None with fewer than two
        stamps or a zero span."""
        stamps = self.stamps
        order = stamp_order(stamp_ns, stamps[-1] if stamps else None)
        if order == RESTARTED:
            stamps.clear()
        if order != OUT_OF_ORDER:
            stamps.append(int(stamp_ns))
            while stamps[0] < stamps[-1] - self.window_ns:
                stamps.popleft()
        span = (stamps[-1] - stamps[0]) / 1e9 if stamps else 0.0
        return ((len(stamps) - 1) / span if span > 0 else None), order


class LivePicture:
    """The current picture of a live system: last bearing per station, last fixes.

    :meth:`update_bearing` keeps the newest bearing of each station (by stamp);
    :meth:`update_fix` the newest fix and a trail of the last ``trail`` fix positions.
    :meth:`collection` draws stations, each station's last ray (to a bit beyond the last
    fix, or ``ray_length`` m without one), the trail as a LineString (kind 'track'), and
    the last fix with its error ellipse. ``changed`` is set by every update and cleared by
    :meth:`collection`.

    Input rules: an input that cannot be drawn (:func:`check_live_fix`,
    :func:`check_live_bearing`) raises ValueError and leaves the picture as it was. Time
    (:func:`stamp_order`, against the current fix or the station's last bearing): an input
    older by at most :data:`CLOCK_JUMP_NS` is dropped (returns :data:`OUT_OF_ORDER`); one
    older by more is a clock restart (a bag replayed again, a simulation restarted, or what
    the picture holds was stamped in the future): the picture starts afresh (:meth:`reset`)
    with that input (returns :data:`RESTARTED`); anything else is taken (:data:`ACCEPTED`).
    """

    def __init__(self, origin, probability=DEFAULT_PROBABILITY, ray_length=DEFAULT_RAY_LENGTH,
                 trail=100):
        self.origin = check_origin(origin)
        ellipse_scale(probability)
        self.probability = float(probability)
        self.ray_length = float(ray_length)
        self.trail = max(int(trail), 0)
        self.bearings = {}
        self.fix = None
        self.track = deque(maxlen=self.trail)    # (stamp_ns, ENU position (3,))
        self.changed = False

    def reset(self):
        """Forget everything (bearings, fix, trail); the next picture is empty."""
        self.bearings.clear()
        self.fix = None
        self.track.clear()
        self.changed = True

    def _order(self, stamp_ns, held_ns):
        order = stamp_order(stamp_ns, held_ns)
        if order == RESTARTED:
            self.reset()
        return order

    def update_bearing(self, bearing):
        """Take ``bearing`` (a core Bearing) as its station's last one (class docstring rules);
        return :data:`ACCEPTED`, :data:`RESTARTED` or :data:`OUT_OF_ORDER`."""
        check_live_bearing(bearing)
        old = self.bearings.get(bearing.station)
        order = self._order(bearing.stamp_ns, None if old is None else old.stamp_ns)
        if order != OUT_OF_ORDER:
            self.bearings[bearing.station] = bearing
            self.changed = True
        return order

    def update_fix(self, fix):
        """Take ``fix`` (a :class:`GeoFix`) as the current one and extend the trail (class
        docstring rules); return :data:`ACCEPTED`, :data:`RESTARTED` or
        :data:`OUT_OF_ORDER`."""
        check_live_fix(fix, self.origin)
        order = self._order(fix.stamp_ns, None if self.fix is None else self.fix.stamp_ns)
        if order == OUT_OF_ORDER:
            return order
        self.fix = fix
        if self.trail:
            self.track.append((fix.stamp_ns, np.array(fix.position, dtype=float)))
        self.changed = True
        return order

    def collection(self):
        """The FeatureCollection dict of the current picture (see class docstring)."""
        self.changed = False
        target = None if self.fix is None else np.asarray(self.fix.position, dtype=float)
        rays = [(b, target) for b in self.bearings.values()]
        fc = feature_collection(self.origin, [self.fix] if self.fix is not None else [], rays,
                                ray_length=None if target is not None else self.ray_length,
                                probability=self.probability)
        if len(self.track) >= 2:
            lon, lat, _ = enu_to_lonlat(np.array([p for _, p in self.track]), self.origin)
            fc['features'].insert(2 * len(self.bearings), _feature(
                line_geometry(lon, lat), {'kind': 'track', 'fixes': len(self.track)}))
        return fc
