"""Station planning: expected-accuracy maps, one-more-station placement, OccupancyGrid maps.

Error models (both give a 3×3 position covariance P, m², per target; the reported expected
error is ε = sqrt(trace P), seed 000 eq. (32)):

* ``crlb``: the Cramér-Rao lower bound J⁻¹ of :mod:`bearing_loc_ros.core.crlb`
  (seed 003 eqs. (6)-(8)), the best any unbiased estimator can do.
* ``ctls``: seed 000's first-order error model of its constrained TLS estimator, eq. (30),
  with P_E = diag(σ_θi², σ_ψi²) (eq. (31) when all σ are equal, P_E = σ² I):

      P = A⁻¹ B A⁻¹,  A = H*ᵀ W H*,  B = H*ᵀ W H_X P_E H_Xᵀ W H*,  W = (H_X G⁻¹ H_Xᵀ)⁻¹,

  with H* the true coefficient matrix of eq. (3), H_X = Σ_j a_j F_j − F_4 and
  G = Σ_j F_jᵀ F_j (theorem 1, eq. (9)), all evaluated at the true target and angles.

Block-diagonal structure: F_j, G, H_X, W and P_E are block diagonal with one 2×2 block per
station (rows: azimuth equation, elevation equation of eq. (2)), so A and B are sums of
per-station 3×3 terms: the 2×2 block entries are computed elementwise on (G, N) arrays and
summed over stations with batched products; no 2N×2N matrix is ever formed. A 1D station
has no elevation row (its row is masked out).

Note on ``ctls``: G mixes the dimensionless F_1..F_3 with F_4, whose entries are station
coordinates, so the model depends on the coordinate origin and the length unit
(``length_unit``; the paper does not say which it used). At the true angles
H_X = diag(−ρ_i, −r_i) (horizontal and slant range), so W_i = H_X⁻ᵀ G_i H_X⁻¹ and the
estimator is efficient (P = CRLB) only if G_i = c P_Ei⁻¹ with one c for all stations.
Where a station's line of sight is perpendicular to its position vector,
p = cos θ x_i + sin θ y_i = 0 and G_i's elevation entry 1 + (cos ψ p + sin ψ z_i)² collapses
(from ~1e7 to ~1e4 in metres for the seed 000 layout at 1.5 km from a station): that
station's elevation equation loses almost all its weight and the error jumps. These are the
"narrow regions" of seed 000 section 4, an artefact of the weighting (the CRLB map has none).
"""

from dataclasses import dataclass, field
import warnings

import numpy as np

from .crlb import fisher_information

MODELS = ('crlb', 'ctls')
OBJECTIVES = ('mean', 'max')
SCALES = ('linear', 'log')
_CHUNK = 65536  # grid points per vectorised block (bounds the memory of (G, N, 2, 3) arrays)


# ----------------------------------------------------------------------------------------------
# Stations and grids


@dataclass
class Stations:
    """A station layout for planning: N stations, each 1D (azimuth) or 2D (azimuth+elevation).

    Attributes:
        positions: (N, 3) ENU positions, m.
        sigma_az: (N,) azimuth σ_θ, rad (> 0).
        sigma_el: (N,) elevation σ_ψ, rad (> 0), NaN for a 1D station.
        names: N station names.
    """

    positions: np.ndarray
    sigma_az: np.ndarray
    sigma_el: np.ndarray
    names: list = None

    @property
    def N(self):
        """Number of stations."""
        return self.positions.shape[0]

    @property
    def has_elevation(self):
        """(N,) bool: True for 2D stations."""
        return np.isfinite(self.sigma_el)

    @classmethod
    def from_arrays(cls, positions, sigma_az, sigma_el=None, has_elevation=True, names=None):
        """Build and validate a layout; raise ValueError naming the bad field.

        ``sigma_az``/``sigma_el`` (rad) are scalars or (N,) arrays; ``sigma_el`` None means
        σ_ψ = σ_θ; ``has_elevation`` a bool or (N,) mask (False = 1D station).
        """
        pos = np.asarray(positions, dtype=float)
        if pos.ndim == 1 and pos.size == 3:
            pos = pos[None]
        if pos.ndim != 2 or pos.shape[1] != 3 or pos.shape[0] == 0:
            raise ValueError(f'stations: expected positions of shape (N, 3), got {pos.shape}')
        if not np.all(np.isfinite(pos)):
            raise ValueError('stations: non-finite station coordinate')
        N = pos.shape[0]
        try:
            saz = np.broadcast_to(np.asarray(sigma_az, dtype=float), (N,)).copy()
            sel = np.broadcast_to(np.asarray(saz if sigma_el is None else sigma_el,
                                             dtype=float), (N,)).copy()
            mask = np.broadcast_to(np.asarray(has_elevation, dtype=bool), (N,))
        except ValueError:
            raise ValueError(f'sigma: expected a scalar or {N} values (one per station)') \
                from None
        if not np.all(np.isfinite(saz)) or np.any(saz <= 0):
            raise ValueError('sigma_az: must be finite and > 0')
        mask = mask & np.isfinite(sel)
        if np.any(sel[mask] <= 0):
            raise ValueError('sigma_el: must be finite and > 0 for 2D stations')
        sel = np.where(mask, sel, np.nan)
        if names is None:
            names = [f'station_{i + 1}' for i in range(N)]
        if len(names) != N:
            raise ValueError(f'names: expected {N} names, got {len(names)}')
        return cls(pos, saz, sel, list(names))

    @classmethod
    def from_scenario(cls, scenario, t=0.0, sigma_az=None, sigma_el=None):
        """Layout of a simulator scenario (core.simulation.Scenario / load_scenario).

        Station positions at scenario time ``t`` (s), 1D where ``dims`` is 1, σ from the
        scenario unless ``sigma_az``/``sigma_el`` (rad) override them for every station.
        """
        from .simulation import station_position
        st = scenario.stations
        pos = np.array([station_position(s, t) for s in st], dtype=float).reshape(-1, 3)
        saz = np.array([s.sigma_az for s in st], dtype=float)
        sel = np.array([s.sigma_el for s in st], dtype=float)
        if sigma_az is not None:
            saz = np.full(len(st), float(sigma_az))
            sel = np.full(len(st), float(sigma_az))
        if sigma_el is not None:
            sel = np.full(len(st), float(sigma_el))
        return cls.from_arrays(pos, saz, sel, [s.dims == 2 for s in st], [s.id for s in st])

    def with_station(self, position, sigma_az, sigma_el=None, has_elevation=True,
                     name='new'):
        """A new layout with one more station appended (see :meth:`from_arrays`)."""
        sel = sigma_az if sigma_el is None else sigma_el
        return Stations.from_arrays(
            np.vstack([self.positions, np.asarray(position, dtype=float)[None]]),
            np.append(self.sigma_az, sigma_az),
            np.append(self.sigma_el, sel if has_elevation else np.nan),
            np.append(self.has_elevation, bool(has_elevation)),
            list(self.names) + [name])


@dataclass
class GridSpec:
    """A horizontal grid of targets at one altitude, laid out like nav_msgs/OccupancyGrid.

    Cell (c, r) (column c along +x, row r along +y) has its centre at
    (origin_x + (c + 0.5)·resolution, origin_y + (r + 0.5)·resolution, altitude); arrays are
    (height, width), row-major, row 0 at the lowest y, exactly the order of
    OccupancyGrid.data (data[r·width + c]). (origin_x, origin_y, altitude) is the
    OccupancyGrid info.origin position. Units: m.
    """

    origin_x: float
    origin_y: float
    resolution: float
    width: int
    height: int
    altitude: float

    def __post_init__(self):
        for name in ('origin_x', 'origin_y', 'resolution', 'altitude'):
            if not np.isfinite(float(getattr(self, name))):
                raise ValueError(f'grid.{name}: must be finite')
        if self.resolution <= 0:
            raise ValueError(f'grid.resolution: must be > 0 m, got {self.resolution}')
        for name in ('width', 'height'):
            v = getattr(self, name)
            if int(v) != v or v < 1:
                raise ValueError(f'grid.{name}: must be a positive integer, got {v}')
            setattr(self, name, int(v))
        if self.width * self.height > 25_000_000:
            raise ValueError('grid: more than 25 million cells')

    @classmethod
    def from_extent(cls, xmin, xmax, ymin, ymax, resolution, altitude):
        """Grid covering [xmin, xmax] × [ymin, ymax] (m) with cells of ``resolution`` m."""
        if not (np.isfinite([xmin, xmax, ymin, ymax]).all() and xmax > xmin and ymax > ymin):
            raise ValueError('extent: need finite xmin < xmax and ymin < ymax')
        if not np.isfinite(resolution) or resolution <= 0:
            raise ValueError(f'resolution: must be > 0 m, got {resolution}')
        width = max(1, int(round((xmax - xmin) / resolution)))
        height = max(1, int(round((ymax - ymin) / resolution)))
        return cls(float(xmin), float(ymin), float(resolution), width, height, float(altitude))

    @property
    def x(self):
        """(width,) cell-centre x, m."""
        return self.origin_x + (np.arange(self.width) + 0.5) * self.resolution

    @property
    def y(self):
        """(height,) cell-centre y, m."""
        return self.origin_y + (np.arange(self.height) + 0.5) * self.resolution

    @property
    def extent(self):
        """(xmin, xmax, ymin, ymax) of the cell edges, m."""
        return (self.origin_x, self.origin_x + self.width * self.resolution,
                self.origin_y, self.origin_y + self.height * self.resolution)

    def points(self):
        """(height·width, 3) cell centres in OccupancyGrid order (row-major, row = y)."""
        X, Y = np.meshgrid(self.x, self.y)
        return np.stack([X.ravel(), Y.ravel(), np.full(X.size, float(self.altitude))], axis=-1)


# ----------------------------------------------------------------------------------------------
# Error models


def _check_model(model):
    if model not in MODELS:
        raise ValueError(f'model: unknown error model {model!r}; choose one of {list(MODELS)}')


def _crlb_terms(targets, positions, sigma_az, sigma_el):
    """Fisher information J (M, 3, 3), 1/m², summed over stations (core.crlb, seed 003)."""
    mask = np.isfinite(sigma_el)
    return fisher_information(targets, positions, sigma_az, np.where(mask, sigma_el, np.nan),
                              mask)


def _ctls_terms(targets, positions, sigma_az, sigma_el, length_unit=1.0):
    """A = Σ_i H_iᵀ W_i H_i and B = Σ_i H_iᵀ W_i H_Xi P_Ei H_Xiᵀ W_i H_i (M, 3, 3).

    Seed 000 eq. (30) per station block i, at the true angles θ_i, ψ_i of each target:

        H_i  = [[sin θ, −cos θ, 0], [cos θ sin ψ, sin θ sin ψ, −cos ψ]]        (eq. (3))
        f_1i = [[−cos θ, 0], [sin θ sin ψ, −cos θ cos ψ]]
        f_2i = [[−sin θ, 0], [−cos θ sin ψ, −sin θ cos ψ]]
        f_3i = [[0, 0], [0, −sin ψ]]
        f_4i = [[−(cos θ x_i + sin θ y_i), 0],
                [sin θ sin ψ x_i − cos θ sin ψ y_i, −(cos θ cos ψ x_i + sin θ cos ψ y_i
                                                     + sin ψ z_i)]]       (eq. (9))
        H_Xi = x f_1i + y f_2i + z f_3i − f_4i,  G_i = Σ_j f_jiᵀ f_ji,
        W_i  = (H_Xi G_i⁻¹ H_Xiᵀ)⁻¹ = H_Xi⁻ᵀ G_i H_Xi⁻¹,  P_Ei = diag(σ_θi², σ_ψi²).

    Coordinates enter G through f_4 in units of ``length_unit`` metres (1 = m, 1000 = km);
    A is returned in those units⁻² scaled back so that A⁻¹ B A⁻¹ is in m². 1D stations: the
    elevation row of H and of every f_j is zero (E has no m_i), so W_i = diag(G_00/H_X00², 0).
    ``positions`` is (N, 3) or (M, N, 3); σ arrays broadcast to (M, N) (σ_el NaN = 1D).
    """
    tgt = np.asarray(targets, dtype=float) / length_unit
    pos = np.asarray(positions, dtype=float) / length_unit
    if pos.ndim == 2:
        pos = pos[None]
    M = tgt.shape[0]
    N = pos.shape[1]
    sel = np.broadcast_to(np.asarray(sigma_el, dtype=float), (M, N))
    saz2 = np.broadcast_to(np.asarray(sigma_az, dtype=float), (M, N)) ** 2
    el = np.isfinite(sel)
    sel2 = np.where(el, sel, 0.0) ** 2
    el = el.astype(float)  # masks the elevation row of 1D stations
    d = tgt[:, None, :] - pos
    rho = np.hypot(d[..., 0], d[..., 1])
    r = np.hypot(rho, d[..., 2])
    with np.errstate(divide='ignore', invalid='ignore'):
        ct, st = d[..., 0] / rho, d[..., 1] / rho  # cos θ, sin θ (true angles)
        cp, sp = rho / r, d[..., 2] / r            # cos ψ, sin ψ
    xi, yi, zi = pos[..., 0], pos[..., 1], pos[..., 2]
    # The f_j blocks written out (their (0, 1) entries are all zero):
    # G = Σ_j f_jᵀ f_j with p = cos θ x_i + sin θ y_i, q = sin θ x_i − cos θ y_i:
    p = ct * xi + st * yi
    q = st * xi - ct * yi
    u = cp * p + sp * zi
    g00 = 1.0 + p * p + el * sp * sp * (1.0 + q * q)
    g01 = -el * sp * q * u
    g11 = el * (1.0 + u * u)
    # H_X = x f_1 + y f_2 + z f_3 − f_4 (lower triangular; diag(−ρ, −r) at the truth):
    x, y, z = tgt[:, None, 0], tgt[:, None, 1], tgt[:, None, 2]
    h00 = p - (ct * x + st * y)
    h10 = el * sp * (st * x - ct * y - q)
    h11 = el * (u - cp * (ct * x + st * y) - sp * z)
    # W = H_X⁻ᵀ G H_X⁻¹; a 1D station's missing h11 is set to 1 (its G row/column is 0).
    with np.errstate(divide='ignore', invalid='ignore'):
        i00 = 1.0 / h00
        i11 = 1.0 / np.where(el > 0, h11, 1.0)
        i10 = -h10 * i00 * i11
    W00 = i00 * i00 * g00 + 2.0 * i00 * i10 * g01 + i10 * i10 * g11
    W01 = i11 * (i00 * g01 + i10 * g11)
    W11 = i11 * i11 * g11
    # Rows of H (eq. (3)); a 1D station's elevation row is zero.
    zero = np.zeros_like(ct)
    r0 = np.stack([st, -ct, zero], -1)
    r1 = np.stack([ct * sp, st * sp, -cp], -1) * el[..., None]
    # K = W H_X and L = Kᵀ H (rows L0, L1); B = Σ_p P_E,pp L_p L_pᵀ.
    K00 = W00 * h00 + W01 * h10
    K10 = W01 * h00 + W11 * h10
    K01 = W01 * h11
    K11 = W11 * h11
    L0 = K00[..., None] * r0 + K10[..., None] * r1
    L1 = K01[..., None] * r0 + K11[..., None] * r1

    def outer_sum(w, a_, b_):
        return np.matmul(np.swapaxes(a_ * w[..., None], -1, -2), b_)

    c01 = outer_sum(W01, r0, r1)
    A = outer_sum(W00, r0, r0) + c01 + np.swapaxes(c01, -1, -2) + outer_sum(W11, r1, r1)
    B = outer_sum(saz2, L0, L0) + outer_sum(sel2, L1, L1)
    return A * length_unit ** -2, B * length_unit ** -2


def ctls_error_covariance(targets, stations, length_unit=1.0):
    """Seed 000 eq. (30) (eq. (31) for equal σ): CTLS position covariance (M, 3, 3), m².

    ``targets`` (M, 3) or (3,) true positions, m; ``stations`` a :class:`Stations`.
    See :func:`_ctls_terms` for the block formulas and the module docstring for the origin and
    unit dependence of G. inf where A is singular.
    """
    tgt = np.atleast_2d(np.asarray(targets, dtype=float))
    A, B = _ctls_terms(tgt, stations.positions, stations.sigma_az, stations.sigma_el,
                       length_unit)
    Ainv, ok = _inv3(A)
    P = np.full(A.shape, np.inf)
    P[ok] = Ainv[ok] @ B[ok] @ Ainv[ok]
    return P


def _inv3(A, rcond=1e-12):
    """Closed-form inverse of symmetric 3×3 matrices (..., 3, 3) via the adjugate.

    Returns (inverse, ok); ok is False (inverse inf) where the matrix is not finite or
    det / (a00 a11 a22) ≤ ``rcond`` (Hadamard ratio, ≤ 1 for a positive definite matrix).
    """
    a = np.asarray(A, dtype=float)
    a00, a01, a02 = a[..., 0, 0], a[..., 0, 1], a[..., 0, 2]
    a11, a12, a22 = a[..., 1, 1], a[..., 1, 2], a[..., 2, 2]
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    with np.errstate(all='ignore'):
        ok = np.isfinite(det) & (det > rcond * np.abs(a00 * a11 * a22)) & (det > 0)
        inv = np.stack([np.stack([c00, c01, c02], -1), np.stack([c01, c11, c12], -1),
                        np.stack([c02, c12, c22], -1)], -2) / det[..., None, None]
    inv[~ok] = np.inf
    return inv, ok


def _error_from_terms(A, B=None, horizontal=False):
    """sqrt(trace(A⁻¹ B A⁻¹)) (or sqrt(trace A⁻¹) when B is None), +inf where A is singular.

    ``horizontal`` (the horizontal solve with the target altitude known, core.horizontal,
    CRLB only): sqrt(trace (A_h)⁻¹), A_h the 2 × 2 (x, y) block of the Fisher information
    (z fixed: the horizontal GDOP of core.horizontal_crlb with σ_z = 0). NaN terms (a
    target on a station's vertical axis, where the azimuth is undefined) give NaN.
    """
    nan = np.any(np.isnan(A), axis=(-2, -1))
    if horizontal:
        from .horizontal_crlb import inverse2
        Ainv, ok = inverse2(np.where(nan[..., None, None], 1.0, A[..., :2, :2]))
        out = np.where(ok, np.sqrt(np.abs(Ainv[..., 0, 0] + Ainv[..., 1, 1])), np.inf)
        out[nan] = np.nan
        return out
    Ainv, ok = _inv3(np.where(nan[..., None, None], 0.0, A))
    if B is None:
        tr = np.trace(Ainv, axis1=-2, axis2=-1)
    else:
        tr = np.einsum('...ij,...jk,...ki->...', Ainv, np.where(ok[..., None, None], B, 0.0),
                       Ainv)
    out = np.where(ok, np.sqrt(np.abs(tr)), np.inf)
    out[nan] = np.nan
    return out


def _terms(targets, positions, sigma_az, sigma_el, model, length_unit):
    if model == 'crlb':
        return _crlb_terms(targets, positions, sigma_az, sigma_el), None
    return _ctls_terms(targets, positions, sigma_az, sigma_el, length_unit)


def horizontal_solve(stations, dimension='auto', new_has_elevation=False):
    """True when a layout is assessed with the horizontal solve (core.horizontal): dimension
    ``horizontal``, or ``auto`` and no 2D station (``new_has_elevation``: a station to be
    added). ValueError naming ``dimension`` for another value."""
    if dimension not in ('auto', '3d', 'horizontal'):
        raise ValueError(f'dimension: must be one of auto, 3d, horizontal, got {dimension!r}')
    if dimension == 'auto':
        return not (np.any(stations.has_elevation) or bool(new_has_elevation))
    return dimension == 'horizontal'


def _check_horizontal(model, horizontal, dimension):
    """Whether the CRLB of the horizontal solve applies: ``auto`` with the CTLS model keeps
    the 3D model (unobservable, +inf, for azimuth-only layouts); a forced ``horizontal``
    with it is a ValueError."""
    if horizontal and model != 'crlb' and dimension == 'auto':
        return False
    if horizontal and model != 'crlb':
        raise ValueError('model: the CTLS error model (Wang, Zhang & Wu eq. (30)) is 3D; '
                         'azimuth-only layouts (the horizontal solve) use model crlb')
    return horizontal


def position_error(targets, stations, model='crlb', length_unit=1.0, dimension='auto'):
    """Expected position error ε, m, at each target (M,) (Wang, Zhang & Wu eq. (32)).

    3D solve: ε = sqrt(trace P), P the CRLB (``model='crlb'``) or Wang, Zhang & Wu's CTLS
    error model eq. (30)/(31) (``model='ctls'``, see :func:`ctls_error_covariance`).
    Horizontal solve (``dimension`` ``horizontal``, or ``auto`` for a layout of 1D
    stations only, :func:`horizontal_solve`): the target altitude is known (the target's
    z), ε = sqrt(P_xx + P_yy) with P the 2 × 2 CRLB of (x, y) (core.horizontal_crlb,
    σ_z = 0; CRLB model only: ``auto`` with the CTLS model stays 3D). ``targets`` (M, 3)
    or (3,), m. +inf where the geometry is unobservable (for example only 1D stations in
    3D, or a target on the line through all 1D stations), NaN on a station's vertical axis
    (azimuth undefined). Vectorised in blocks of 65536 targets.
    """
    _check_model(model)
    horizontal = _check_horizontal(model, horizontal_solve(stations, dimension), dimension)
    tgt = np.atleast_2d(np.asarray(targets, dtype=float))
    if tgt.shape[-1] != 3 or not np.all(np.isfinite(tgt)):
        raise ValueError('targets: expected finite (M, 3) positions')
    out = np.empty(tgt.shape[0])
    for s in range(0, tgt.shape[0], _CHUNK):
        sl = slice(s, s + _CHUNK)
        A, B = _terms(tgt[sl], stations.positions, stations.sigma_az, stations.sigma_el,
                      model, length_unit)
        out[sl] = _error_from_terms(A, B, horizontal)
    return out


@dataclass
class AccuracyMap:
    """Expected position error over a :class:`GridSpec`.

    Attributes:
        grid: the grid.
        error: (height, width) ε = sqrt(trace P), m (inf unobservable, NaN on a station axis).
        model: 'crlb' or 'ctls'.
        stations: the layout used.
        solve: '3d' or 'horizontal' (ε = sqrt(P_xx + P_yy), altitude known).
    """

    grid: GridSpec
    error: np.ndarray
    model: str
    stations: Stations = None
    solve: str = '3d'

    def stats(self, mask=None):
        """Summary of the finite errors (m): min, median, mean, p90, max, and counts."""
        e = self.error if mask is None else self.error[mask]
        fin = e[np.isfinite(e)]
        out = {'cells': int(e.size), 'finite_cells': int(fin.size),
               'unobservable_cells': int(np.sum(np.isposinf(e)))}
        if fin.size:
            out.update(min_m=float(fin.min()), median_m=float(np.median(fin)),
                       mean_m=float(fin.mean()), p90_m=float(np.percentile(fin, 90)),
                       max_m=float(fin.max()))
        return out

    def at(self, x, y):
        """Error (m) of the cell containing (x, y) m (nearest cell centre); NaN outside."""
        g = self.grid
        c = int(np.floor((x - g.origin_x) / g.resolution))
        r = int(np.floor((y - g.origin_y) / g.resolution))
        if 0 <= c < g.width and 0 <= r < g.height:
            return float(self.error[r, c])
        return float('nan')


def accuracy_map(stations, grid, model='crlb', length_unit=1.0, dimension='auto'):
    """Expected-error map (Wang, Zhang & Wu section 4 GDOP maps) of a layout over ``grid``.

    ε(x, y) at each cell centre at ``grid.altitude`` (see :func:`position_error`; for an
    azimuth-only layout the horizontal GDOP with the altitude known). A 400 × 400 grid takes
    well under a second (bench/bench_planning.py). Returns an :class:`AccuracyMap`.
    """
    err = position_error(grid.points(), stations, model, length_unit, dimension)
    solve = ('horizontal' if _check_horizontal(model, horizontal_solve(stations, dimension),
                                               dimension) else '3d')
    return AccuracyMap(grid, err.reshape(grid.height, grid.width), model, stations, solve)


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


def _objective(err, objective):
    """Mean or max of ε over the area points (last axis), m; +inf if any point is
    unobservable; NaN points (on a station's vertical axis, azimuth undefined) are skipped."""
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
    three best grid candidates.

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
    _check_model(model)
    horizontal = _check_horizontal(model, horizontal_solve(stations, dimension, has_elevation),
                                   dimension)
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
    A0, B0 = _terms(pts, stations.positions, stations.sigma_az, stations.sigma_el, model,
                    length_unit)
    err_before = _error_from_terms(A0, B0, horizontal)

    def errors(cands):
        """(C, G) errors for candidate positions (C, 3)."""
        C = cands.shape[0]
        tgt = np.broadcast_to(pts, (C, G, 3)).reshape(-1, 3)
        pos = np.repeat(cands, G, axis=0)[:, None, :]
        A, B = _terms(tgt, pos, n_saz, n_sel, model, length_unit)
        A = A.reshape(C, G, 3, 3) + A0
        B = None if B is None else B.reshape(C, G, 3, 3) + B0
        return _error_from_terms(A, B, horizontal)

    gx = np.linspace(xmin, xmax, candidates)
    gy = np.linspace(ymin, ymax, candidates)
    GX, GY = np.meshgrid(gx, gy)
    cands = np.stack([GX.ravel(), GY.ravel(), np.full(GX.size, float(height))], -1)
    per = max(1, _CHUNK // max(G, 1))
    J = np.concatenate([_objective(errors(cands[s:s + per]), objective)
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
            return float(_objective(errors(np.array([[p[0], p[1], height]])), objective)[0])

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
    before = float(_objective(err_before, objective))
    after = float(_objective(after_err, objective))
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
