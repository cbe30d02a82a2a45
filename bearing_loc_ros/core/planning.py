"""Station planning: expected-accuracy maps, one-more-station placement, OccupancyGrid maps.

Parts: :mod:`.planning_layout` (the :class:`Stations` layout and the :class:`GridSpec` grid),
:mod:`.planning_error` (the ``crlb`` and ``ctls`` error models with their maths, Wang, Zhang &
Wu eqs. (30)-(32), and the accuracy maps), and here the placement of one more station and the
OccupancyGrid-ready map. Every public name is importable from ``bearing_loc_ros.core.planning``.
"""

from dataclasses import dataclass, field
import warnings

import numpy as np

from .planning_error import (accuracy_map, AccuracyMap, check_model, CHUNK,  # noqa: F401
                             ctls_error_covariance, error_from_terms, error_terms,
                             horizontal_crlb_applies, horizontal_solve, MODELS,
                             position_error)
from .planning_layout import GridSpec, Stations  # noqa: F401

OBJECTIVES = ('mean', 'max')
SCALES = ('linear', 'log')


# ----------------------------------------------------------------------------------------------
# Placement of one more station


@dataclass
class PlacementResult:
    """Best position for one more station and what it brings.

    Attributes:
        position: (3,) suggested station position, m.
        objective: 'mean' or 'max' (of ε over the area, m).
        before, after: objective value without / with the new station, m (inf if some area
            point is unobservable).
        improvement: before − after, m; ratio: after / before (NaN when before is inf).
        before_stats, after_stats: :meth:`AccuracyMap.stats` of the area maps.
        candidates: number of grid candidates evaluated; evaluations: total objective calls.
        grid_best: (3,) best grid candidate before local refinement.
    """

    # Dataclass fields: alike other field lists in shape only, there is no logic to share.
    position: np.ndarray
    objective: str
    before: float
    after: float
    improvement: float
    ratio: float
    before_stats: dict = field(default_factory=dict)
    after_stats: dict = field(default_factory=dict)
    candidates: int = 0
    evaluations: int = 0
    grid_best: np.ndarray = None

    def as_dict(self):
        """JSON-ready dict (inf and NaN become None)."""
        def num(v):
            v = float(v)
            return v if np.isfinite(v) else None
        return {'position_m': [float(v) for v in self.position], 'objective': self.objective,
                'before_m': num(self.before), 'after_m': num(self.after),
                'improvement_m': num(self.improvement), 'ratio': num(self.ratio),
                'before': self.before_stats, 'after': self.after_stats,
                'candidates': self.candidates, 'evaluations': self.evaluations,
                'grid_best_m': [float(v) for v in self.grid_best]}


def objective_value(err, objective):
    """The placement objective ``objective`` ('mean' or 'max') of the errors ε over the area
    points (last axis), m; +inf if any point is unobservable; NaN points (on a station's
    vertical axis, azimuth undefined) are skipped."""
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', RuntimeWarning)  # all-NaN rows give NaN
        if objective == 'max':
            return np.nanmax(err, axis=-1)
        return np.nanmean(err, axis=-1)


def place_station(stations, area, region, height=0.0, sigma_az=None, sigma_el=None,
                  has_elevation=True, objective='mean', model='crlb', candidates=21,
                  refine=True, length_unit=1.0, dimension='auto'):
    """Where to put one more station to minimise the mean (or worst) expected error.

    Objective: J(s) = mean (or max) over the area's cell centres of ε = sqrt(trace P) with
    the existing ``stations`` plus a new station at s = (x, y, ``height``); P from
    ``model`` (see :func:`position_error`). Search: a ``candidates`` × ``candidates`` grid over
    ``region`` = (xmin, xmax, ymin, ymax), m, vectorised (per-station information terms are
    additive, so the existing stations' terms are computed once and each candidate adds its
    own (G, 3, 3) block), then Nelder-Mead refinement (scipy) inside the region from the
    three best grid candidates. A cell centre straight above (or below) the new station gets
    no term from it (its azimuth is undefined; the simulator makes no such bearing), so the
    cell keeps the existing stations' error instead of dropping out of the mean or max.

    Args:
        stations: existing :class:`Stations` (may be unobservable on their own).
        area: :class:`GridSpec` of the area of interest (its altitude is the target height).
        region: (xmin, xmax, ymin, ymax) allowed for the new station, m.
        height: z of the new station, m.
        sigma_az, sigma_el, has_elevation: the new station's σ (rad; default: the first
            existing station's) and type.
        objective: 'mean' or 'max'. model: 'crlb' or 'ctls'.
        dimension: ``auto`` (horizontal when neither the layout nor the new station has
            an elevation), ``3d`` or ``horizontal`` (:func:`position_error`).
    Returns:
        :class:`PlacementResult`. Raises ValueError naming the bad argument, or when no
        candidate makes every area point observable.
    """
    from scipy.optimize import minimize
    check_model(model)
    horizontal = horizontal_crlb_applies(
        model, horizontal_solve(stations, dimension, has_elevation), dimension)
    if objective not in OBJECTIVES:
        raise ValueError(f'objective: choose one of {list(OBJECTIVES)}, got {objective!r}')
    try:
        xmin, xmax, ymin, ymax = (float(v) for v in region)
    except (TypeError, ValueError):
        raise ValueError('region: expected (xmin, xmax, ymin, ymax) in m') from None
    if not (np.isfinite([xmin, xmax, ymin, ymax]).all() and xmax >= xmin and ymax >= ymin):
        raise ValueError('region: need finite xmin <= xmax and ymin <= ymax')
    if not np.isfinite(height):
        raise ValueError('height: must be finite')
    if int(candidates) < 2:
        raise ValueError('candidates: need at least 2 per axis')
    candidates = int(candidates)
    saz = stations.sigma_az[0] if sigma_az is None else sigma_az
    sel = (stations.sigma_el[0] if np.isfinite(stations.sigma_el[0]) else saz) \
        if sigma_el is None else sigma_el
    new = Stations.from_arrays(np.zeros(3), saz, sel, has_elevation)
    n_saz, n_sel = new.sigma_az[0], new.sigma_el[0]

    pts = area.points()
    G = pts.shape[0]
    A0, B0 = error_terms(pts, stations.positions, stations.sigma_az, stations.sigma_el, model,
                         length_unit)
    err_before = error_from_terms(A0, B0, horizontal)

    def errors(cands):
        """(C, G) errors for candidate positions (C, 3)."""
        C = cands.shape[0]
        tgt = np.broadcast_to(pts, (C, G, 3)).reshape(-1, 3)
        pos = np.repeat(cands, G, axis=0)[:, None, :]
        A, B = error_terms(tgt, pos, n_saz, n_sel, model, length_unit)
        # A cell centre on the new station's vertical axis gets no bearing from it (azimuth
        # undefined, as in the simulator): no information there, not a NaN cell that the
        # objective would skip (which rewarded putting the station on a cell centre).
        axis = np.any(np.isnan(A), axis=(-2, -1))
        A = np.where(axis[:, None, None], 0.0, A)
        B = None if B is None else np.where(axis[:, None, None], 0.0, B)
        A = A.reshape(C, G, 3, 3) + A0
        B = None if B is None else B.reshape(C, G, 3, 3) + B0
        return error_from_terms(A, B, horizontal)

    gx = np.linspace(xmin, xmax, candidates)
    gy = np.linspace(ymin, ymax, candidates)
    GX, GY = np.meshgrid(gx, gy)
    cands = np.stack([GX.ravel(), GY.ravel(), np.full(GX.size, float(height))], -1)
    per = max(1, CHUNK // max(G, 1))
    J = np.concatenate([objective_value(errors(cands[s:s + per]), objective)
                        for s in range(0, cands.shape[0], per)])
    evaluations = cands.shape[0]
    order = np.argsort(np.where(np.isnan(J), np.inf, J))
    if not np.isfinite(J[order[0]]):
        raise ValueError('region: no candidate position makes every area point observable '
                         '(add a station, a 2D station or widen the region)')
    best = cands[order[0]].copy()
    grid_best = best.copy()
    best_J = J[order[0]]
    if refine:
        step = max((xmax - xmin), (ymax - ymin)) / (candidates - 1)
        bounds = [(xmin, xmax), (ymin, ymax)]

        def fun(p):
            return float(objective_value(errors(np.array([[p[0], p[1], height]])), objective)[0])

        for k in order[:3]:
            x0 = cands[k, :2]
            simplex = np.array([x0, x0 + [step / 2, 0], x0 + [0, step / 2]])
            simplex = np.clip(simplex, [xmin, ymin], [xmax, ymax])
            if xmax == xmin or ymax == ymin:
                break
            res = minimize(fun, x0, method='Nelder-Mead', bounds=bounds,
                           options={'initial_simplex': simplex, 'xatol': 1e-4 * step,
                                    'fatol': 1e-9 * max(best_J, 1e-12), 'maxfev': 400})
            evaluations += res.nfev
            if np.isfinite(res.fun) and res.fun < best_J:
                best_J = res.fun
                best = np.array([res.x[0], res.x[1], height])
    after_err = errors(best[None])[0]
    before = float(objective_value(err_before, objective))
    after = float(objective_value(after_err, objective))
    improvement = before - after if np.isfinite(before) else float('inf')
    ratio = after / before if np.isfinite(before) and before > 0 else float('nan')
    shape = (area.height, area.width)
    return PlacementResult(
        best, objective, before, after, improvement, ratio,
        AccuracyMap(area, err_before.reshape(shape), model).stats(),
        AccuracyMap(area, after_err.reshape(shape), model).stats(),
        cands.shape[0], evaluations, grid_best)


# ----------------------------------------------------------------------------------------------
# OccupancyGrid-ready map (for the fusion node)


def error_to_occupancy(error, min_error, max_error, scale='linear'):
    """Map errors (m) to nav_msgs/OccupancyGrid cell values (int8).

    linear: v = round(100 (ε − min) / (max − min));  log: v = round(100 ln(ε/min) / ln(max/min));
    v clipped to 0..100 (ε ≤ min → 0, ε ≥ max → 100, so +inf, an unobservable cell, is 100);
    NaN (unknown: a cell on a station's vertical axis) → −1. Returns an int8 array of
    ``error``'s shape. Raises ValueError for min/max that are not finite with min < max
    (and min > 0 for log).
    """
    if scale not in SCALES:
        raise ValueError(f'scale: choose one of {list(SCALES)}, got {scale!r}')
    lo, hi = float(min_error), float(max_error)
    if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
        raise ValueError(f'min_error/max_error: need finite min < max, got {lo}, {hi}')
    if scale == 'log' and lo <= 0:
        raise ValueError(f'min_error: must be > 0 m for the log scale, got {lo}')
    e = np.asarray(error, dtype=float)
    with np.errstate(divide='ignore', invalid='ignore'):
        if scale == 'linear':
            v = 100.0 * (e - lo) / (hi - lo)
        else:
            v = 100.0 * np.log(np.maximum(e, lo) / lo) / np.log(hi / lo)
    v = np.clip(np.where(np.isposinf(e), 100.0, v), 0.0, 100.0)
    return np.where(np.isnan(e), -1, np.rint(np.nan_to_num(v))).astype(np.int8)


@dataclass
class OccupancyErrorMap:
    """An expected-error map ready to fill a nav_msgs/OccupancyGrid.

    Attributes:
        grid: the :class:`GridSpec` (info.resolution, info.width, info.height,
            info.origin.position = (origin_x, origin_y, altitude), identity orientation).
        error: (height, width) ε in m, row-major like ``data`` (inf unobservable, NaN unknown).
        data: (height·width,) int8 cell values 0..100, −1 unknown (``data.tolist()`` for the
            message).
        min_error, max_error: the mapping range, m. scale: 'linear' or 'log'. model: error
            model.
    """

    grid: GridSpec
    error: np.ndarray
    data: np.ndarray
    min_error: float
    max_error: float
    scale: str
    model: str


def occupancy_error_map(stations, grid, model='crlb', scale='linear', min_error=None,
                        max_error=None, length_unit=1.0):
    """Expected-error map of a layout as OccupancyGrid cell values (for the fusion node).

    ε = sqrt(trace P) at every cell centre of ``grid`` (:func:`accuracy_map`), mapped by
    :func:`error_to_occupancy` between ``min_error`` and ``max_error`` (m). Defaults: the
    smallest and largest finite ε of this map (log scale: min clamped to ≥ 1e-6·max), so
    each map uses the full 0..100 range; pass fixed values for maps comparable over time.

    Args:
        stations: :class:`Stations` (positions m, σ rad, 1D where sigma_el is NaN).
        grid: :class:`GridSpec` (origin, resolution, width, height, altitude; m).
        model: 'crlb' (default) or 'ctls'. scale: 'linear' (default) or 'log'.
    Returns:
        :class:`OccupancyErrorMap`. Raises ValueError naming the bad field.
    """
    amap = accuracy_map(stations, grid, model, length_unit)
    fin = amap.error[np.isfinite(amap.error)]
    lo = (float(fin.min()) if fin.size else 0.0) if min_error is None else float(min_error)
    hi = (float(fin.max()) if fin.size else 1.0) if max_error is None else float(max_error)
    if scale == 'log' and min_error is None:
        lo = max(lo, 1e-6 * hi, 1e-9)
    if hi <= lo:
        hi = lo + max(abs(lo), 1.0) * 1e-6 if max_error is None else hi
    data = error_to_occupancy(amap.error, lo, hi, scale).ravel()
    return OccupancyErrorMap(grid, amap.error, data, lo, hi, scale, model)
