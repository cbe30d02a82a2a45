"""Display geometry for RViz / Foxglove: error ellipsoids, bearing rays, marker sizes, and
the expected-accuracy map of the live stations (no ROS; ros_conversions builds the messages).

Conventions: world ENU frame (x East, y North, z Up; REP-103), metres, radians; azimuth
counter-clockwise from East, elevation above the horizontal (Wang, Zhang & Wu eq. (1));
quaternions (x, y, z, w).
"""

from dataclasses import dataclass
import time

import numpy as np

from .conventions import los_vector
from .planning import GridSpec, MODELS, occupancy_error_map, SCALES, Stations

#: Bearing rays without a configured length reach this × the station-to-fix distance.
RAY_OVERSHOOT = 1.2
#: Line width and fix sphere size as fractions of the scene size (metres, >= 1 m).
RAY_WIDTH_FRACTION = 0.002
FIX_SIZE_FRACTION = 0.01
#: Accuracy map: automatic side = AUTO_SIZE_FACTOR × the largest horizontal station
#: distance from the centre, at least AUTO_MIN_SIZE m; automatic cell = side / AUTO_CELLS.
AUTO_SIZE_FACTOR = 3.0
AUTO_MIN_SIZE = 100.0
AUTO_CELLS = 100
MAX_MAP_CELLS = 2000
#: A recomputation for moved stations of the same set waits at least this long after the
#: last map, s, and at least MOVE_COST_FACTOR × that map's compute time: the node computes
#: the map on its executor, so moving stations (or a station whose position jumps) may take
#: at most about 1 / MOVE_COST_FACTOR of its time (a 2000 × 2000 map takes seconds).
MIN_MOVE_INTERVAL_S = 1.0
MOVE_COST_FACTOR = 20.0


def log_color_limits(error, vmin=None, vmax=None):
    """(vmin, vmax), m, of the log colour scale of an error map (plots and overlays).

    Defaults: the smallest finite positive error and the 99th percentile of those errors;
    vmax is raised to at least 1.01 vmin. None when no error is finite and positive.
    """
    err = np.asarray(error, dtype=float)
    fin = err[np.isfinite(err) & (err > 0)]
    if not fin.size:
        return None
    vmin = float(fin.min()) if vmin is None else float(vmin)
    vmax = float(np.percentile(fin, 99)) if vmax is None else float(vmax)
    return vmin, max(vmax, vmin * 1.01)


def quaternion_from_matrix(R):
    """Unit quaternion(s) (x, y, z, w), w >= 0, of rotation matrices R (..., 3, 3).

    Shepperd's method: of 4w², 4x², 4y², 4z² (1 + tr R, 1 + R00 − R11 − R22, ...) the largest
    is square-rooted and the other components follow from the off-diagonal sums/differences,
    which is accurate for every rotation including half turns. Same convention as
    conventions.quaternion_from_azel (R maps body axes onto world axes).
    """
    R = np.asarray(R, dtype=float)
    m = [[R[..., i, j] for j in range(3)] for i in range(3)]
    diag = np.stack([1.0 + m[0][0] + m[1][1] + m[2][2], 1.0 + m[0][0] - m[1][1] - m[2][2],
                     1.0 - m[0][0] + m[1][1] - m[2][2], 1.0 - m[0][0] - m[1][1] + m[2][2]],
                    axis=-1)
    k = np.argmax(diag, axis=-1)
    s = 0.5 * np.sqrt(np.maximum(np.take_along_axis(diag, k[..., None], -1)[..., 0], 1e-300))
    f = 0.25 / s
    cand = np.stack([
        np.stack([(m[2][1] - m[1][2]) * f, (m[0][2] - m[2][0]) * f, (m[1][0] - m[0][1]) * f,
                  s], -1),
        np.stack([s, (m[0][1] + m[1][0]) * f, (m[0][2] + m[2][0]) * f,
                  (m[2][1] - m[1][2]) * f], -1),
        np.stack([(m[0][1] + m[1][0]) * f, s, (m[1][2] + m[2][1]) * f,
                  (m[0][2] - m[2][0]) * f], -1),
        np.stack([(m[0][2] + m[2][0]) * f, (m[1][2] + m[2][1]) * f, s,
                  (m[1][0] - m[0][1]) * f], -1)], axis=-2)
    q = np.take_along_axis(cand, k[..., None, None], -2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0.0, -q, q)


def error_ellipsoid(covariance, n_sigma=1.0):
    """Axes and orientation of the n-σ error ellipsoid of position covariance(s) (..., 3, 3).

    With the eigen-decomposition P = V diag(λ) Vᵀ (V made a proper rotation, det V = +1), the
    ellipsoid {x : xᵀ P⁻¹ x <= n²} has semi-axes n √λ_k along the columns of V. Returns
    (diameters (..., 3) = 2 n √λ, m, ready for an RViz SPHERE marker's scale, and the
    quaternion (..., 4) (x, y, z, w) rotating the marker's x, y, z axes onto V's columns).
    Negative eigenvalues from round-off are clipped to 0. Raises ``ValueError`` for a
    non-finite covariance.
    """
    P = np.asarray(covariance, dtype=float)
    if not np.all(np.isfinite(P)):
        raise ValueError('covariance: non-finite entries')
    lam, V = np.linalg.eigh(0.5 * (P + np.swapaxes(P, -1, -2)))
    det = np.linalg.det(V)
    V = V.copy()
    V[..., :, 2] *= np.where(det < 0.0, -1.0, 1.0)[..., None]
    return 2.0 * float(n_sigma) * np.sqrt(np.clip(lam, 0.0, None)), quaternion_from_matrix(V)


def ray_endpoints(positions, azimuth, elevation, length):
    """Line segments (N, 2, 3) from each station along its bearing, for LINE_LIST markers.

    End = p_i + L_i u(θ_i, ψ_i), u the line-of-sight unit vector
    (cos ψ cos θ, cos ψ sin θ, sin ψ); an azimuth-only bearing (ψ NaN) is drawn horizontal.
    ``length`` L (m) is a scalar or (N,) array.
    """
    p = np.asarray(positions, dtype=float).reshape(-1, 3)
    u = los_vector(np.asarray(azimuth, dtype=float).reshape(-1),
                   np.asarray(elevation, dtype=float).reshape(-1))
    L = np.broadcast_to(np.asarray(length, dtype=float), (p.shape[0],))
    return np.stack([p, p + L[:, None] * u], axis=1)


def scene_size(station_positions, fix_position):
    """Largest extent (m, >= 1) along x, y or z of the stations (N, 3) and the fix (3,)."""
    pos = np.vstack([np.asarray(station_positions, dtype=float).reshape(-1, 3),
                     np.asarray(fix_position, dtype=float).reshape(1, 3)])
    return float(max(1.0, np.max(np.ptp(pos, axis=0))))


@dataclass
class FixMarkers:
    """Geometry of the markers of one fix (m, world frame).

    used_rays, rejected_rays: (N, 2, 3) segments of the bearings in the fix and of those the
    outlier gate dropped; ray_width: line width; fix_size: diameter of the fix sphere;
    ellipsoid_diameters (3,) and ellipsoid_quaternion (4,) (x, y, z, w): the n-σ error
    ellipsoid (:func:`error_ellipsoid`).
    """

    used_rays: np.ndarray
    rejected_rays: np.ndarray
    ray_width: float
    fix_size: float
    ellipsoid_diameters: np.ndarray
    ellipsoid_quaternion: np.ndarray


def fix_markers(epoch, ray_length=0.0, n_sigma=3.0):
    """:class:`FixMarkers` of a fix Epoch (``position``, ``covariance``, ``bearings``,
    ``rejected``).

    Rays are ``ray_length`` m long, or RAY_OVERSHOOT × the station-to-fix distance when
    ``ray_length`` <= 0; line width RAY_WIDTH_FRACTION and fix size FIX_SIZE_FRACTION of
    :func:`scene_size` (stations in the fix plus the fix). ValueError for a non-finite
    covariance.
    """
    fix = np.asarray(epoch.position, dtype=float)
    scene = scene_size([b.position for b in epoch.bearings], fix)

    def rays(group):
        if not group:
            return np.zeros((0, 2, 3))
        pos = np.array([b.position for b in group], dtype=float)
        length = (ray_length if ray_length > 0.0
                  else RAY_OVERSHOOT * np.linalg.norm(pos - fix, axis=1))
        return ray_endpoints(pos, [b.azimuth for b in group], [b.elevation for b in group],
                             length)
    diam, q = error_ellipsoid(epoch.covariance, n_sigma)
    return FixMarkers(rays(epoch.bearings), rays(epoch.rejected),
                      RAY_WIDTH_FRACTION * max(1.0, scene), FIX_SIZE_FRACTION * scene, diam, q)


@dataclass(frozen=True)
class AccuracyMapConfig:
    """Settings of the expected-accuracy map (the node's ``accuracy_map.*`` parameters).

    center: () or (x, y) m (empty: centroid of the live stations); size: side of the square
    map, m (0: automatic); resolution: cell, m (0: size / AUTO_CELLS); altitude: target z,
    m; model: core.planning.MODELS; scale: core.planning.SCALES; min_error, max_error: ε
    mapped to cell values 0 and 100, m; move_threshold: a station moving more than this
    (m; 0: one cell) triggers a recomputation.
    """

    center: tuple = ()
    size: float = 0.0
    resolution: float = 0.0
    altitude: float = 0.0
    model: str = 'crlb'
    scale: str = 'linear'
    min_error: float = 0.0
    max_error: float = 100.0
    move_threshold: float = 0.0

    @classmethod
    def from_parameters(cls, values, prefix='accuracy_map.'):
        """The settings of node parameter values (name -> value): each ``<prefix><field>``
        but ``<prefix>enabled``, lists as tuples (not validated here)."""
        return cls(**{k[len(prefix):]: (tuple(v) if isinstance(v, list) else v)
                      for k, v in values.items()
                      if k.startswith(prefix) and k != prefix + 'enabled'})

    def validate(self):
        """Raise ``ValueError('accuracy_map.<field>: ...')`` for the first invalid field."""
        def bad(name, text):
            return ValueError(f'accuracy_map.{name}: {text}')
        if self.model not in MODELS:
            raise bad('model', f'{self.model!r} is not one of {list(MODELS)}')
        if self.scale not in SCALES:
            raise bad('scale', f'{self.scale!r} is not one of {list(SCALES)}')
        if not self.max_error > self.min_error:
            raise bad('max_error', 'must exceed accuracy_map.min_error')
        if self.scale == 'log' and self.min_error <= 0.0:
            raise bad('min_error', 'must be > 0 m for the log scale')
        if self.center and len(self.center) != 2:
            raise bad('center', 'expected [] or [x, y]')
        if self.size > 0.0 and self.resolution > 0.0 and \
                self.size / self.resolution > MAX_MAP_CELLS:
            raise bad('resolution', f'size / resolution exceeds {MAX_MAP_CELLS} cells per side')
        return self

    def grid(self, positions):
        """GridSpec of the map for live station positions (N, 3), m.

        Centre: ``center`` or the stations' horizontal centroid; side ``size`` or
        AUTO_SIZE_FACTOR × the largest horizontal distance of a station from the centre
        (>= AUTO_MIN_SIZE); cells of ``resolution`` (or side / AUTO_CELLS), at most
        MAX_MAP_CELLS per side, at ``altitude``.
        """
        pos = np.asarray(positions, dtype=float).reshape(-1, 3)
        c = np.asarray(self.center, dtype=float) if self.center else pos[:, :2].mean(axis=0)
        size = self.size
        if size <= 0.0:
            reach = float(np.max(np.hypot(*(pos[:, :2] - c).T))) if len(pos) else 0.0
            size = max(AUTO_MIN_SIZE, AUTO_SIZE_FACTOR * reach)
        res = self.resolution if self.resolution > 0.0 else size / AUTO_CELLS
        n = max(1, min(MAX_MAP_CELLS, int(round(size / res))))
        half = 0.5 * n * res
        return GridSpec(float(c[0] - half), float(c[1] - half), float(res), n, n,
                        float(self.altitude))


class AccuracyMap:
    """The expected-accuracy grid of the live stations, recomputed only when it changes.

    :meth:`update` takes the pipeline's geometry (station -> (position (3,) m, σ_θ rad, σ_ψ
    rad or NaN), FusionCore.geometry()) and returns (GridSpec, int8 cell values) when the set
    of live stations changed or, with two or more, one moved more than ``move_threshold``,
    else None. Given the steady time ``now_s`` of the call, a recomputation for moved stations
    waits until max(:data:`MIN_MOVE_INTERVAL_S`, :data:`MOVE_COST_FACTOR` × the last map's
    compute time) after the last map (``pending`` is then True, and a later call computes
    it); a new station set is computed at once. Cell value
    = error_to_occupancy(ε) of ε = sqrt(trace P) per cell (core.planning.occupancy_error_map,
    the CRLB or the CTLS first-order error of Wang, Zhang & Wu eqs. (30)-(32)). No live
    station: every cell −1 (unknown) on the last grid. ValueError from the planning core
    (degenerate station sets) propagates; the map is then left unchanged.
    """

    def __init__(self, config):
        self.config = config.validate()
        self.grid = None          # GridSpec of the last map
        self.last = None          # OccupancyErrorMap of the last map (None: all unknown)
        self.stations = []        # live station names of the last map
        self._key = None          # (station names, positions) of the last map
        self._next_move_s = -np.inf  # steady time from which moved stations recompute it
        #: True while stations have moved but their recomputation is not due yet: call
        #: :meth:`update` again (from a later tick) even if the geometry does not change.
        self.pending = False

    def _changed(self, names, positions, now_s):
        if self._key is None:
            return True
        old_names, old_pos = self._key
        if names != old_names:
            return True
        if len(names) < 2:
            # No station, or one: every cell is unobservable whatever its position, so a
            # single moving station (a DF car) does not recompute the map as it drives.
            return False
        thr = self.config.move_threshold
        if thr <= 0.0 and self.grid is not None:
            thr = self.grid.resolution
        moved = bool(np.max(np.linalg.norm(positions - old_pos, axis=1)) > thr)
        self.pending = moved and now_s < self._next_move_s
        return moved and not self.pending

    def update(self, geometry, now_s=None):
        """(grid, data) of a new map, or None when nothing changed or a recomputation for
        moved stations is not due (class docstring). ``now_s``: steady time, s (None: the
        process's monotonic clock)."""
        start = time.monotonic()
        now_s = start if now_s is None else float(now_s)
        names = sorted(geometry)
        positions = np.array([geometry[s][0] for s in names]).reshape(-1, 3)
        if not self._changed(names, positions, now_s):
            return None
        m = self.config
        if names:
            sel = np.array([geometry[s][2] for s in names], dtype=float)
            stations = Stations.from_arrays(positions, [geometry[s][1] for s in names], sel,
                                            has_elevation=np.isfinite(sel), names=names)
            grid = m.grid(positions)
            om = occupancy_error_map(stations, grid, m.model, m.scale, m.min_error,
                                     m.max_error)
            data = om.data
        elif self.grid is not None:
            grid, om = self.grid, None
            data = np.full(grid.width * grid.height, -1, dtype=np.int8)
        else:
            return None
        self._key = (names, positions)
        self.grid, self.last, self.stations = grid, om, names
        self.pending = False
        cost = time.monotonic() - start
        self._next_move_s = now_s + cost + max(MIN_MOVE_INTERVAL_S, MOVE_COST_FACTOR * cost)
        return grid, data
