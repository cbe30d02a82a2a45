"""Expected position error of a station layout: the crlb and ctls error models, accuracy maps.

Error models (both give a 3×3 position covariance P, m², per target; the reported expected
error is ε = sqrt(trace P), Wang, Zhang & Wu (2006) eq. (32)):

* ``crlb``: the Cramér-Rao lower bound J⁻¹ of :mod:`bearing_loc_ros.core.crlb`
  (Zong & Cui (2015) eqs. (6)-(8)), the best any unbiased estimator can do.
* ``ctls``: the first-order error model of the constrained TLS estimator of Wang, Zhang & Wu
  (2006), eq. (30), with P_E = diag(σ_θi², σ_ψi²) (eq. (31) when all σ are equal,
  P_E = σ² I):

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
(from ~1e7 to ~1e4 in metres for the Wang, Zhang & Wu (2006) layout at 1.5 km from a
station): that station's elevation equation loses almost all its weight and the error jumps.
These are the "narrow regions" of that paper's section 4, an artefact of the weighting (the
CRLB map has none).
"""

from dataclasses import dataclass

import numpy as np

from .crlb import fisher_information
from .planning_layout import GridSpec, Stations

MODELS = ('crlb', 'ctls')
CHUNK = 65536  # grid points per vectorised block (bounds the memory of (G, N, 2, 3) arrays)


def check_model(model):
    """ValueError unless ``model`` is one of :data:`MODELS` ('crlb', 'ctls')."""
    if model not in MODELS:
        raise ValueError(f'model: unknown error model {model!r}; choose one of {list(MODELS)}')


def _crlb_terms(targets, positions, sigma_az, sigma_el):
    """Fisher information J (M, 3, 3), 1/m², summed over stations (crlb, Zong & Cui (2015))."""
    mask = np.isfinite(sigma_el)
    return fisher_information(targets, positions, sigma_az, np.where(mask, sigma_el, np.nan),
                              mask)


def _ctls_terms(targets, positions, sigma_az, sigma_el, length_unit=1.0):
    """A = Σ_i H_iᵀ W_i H_i and B = Σ_i H_iᵀ W_i H_Xi P_Ei H_Xiᵀ W_i H_i (M, 3, 3).

    Wang, Zhang & Wu (2006) eq. (30) per station block i, at the true angles θ_i, ψ_i of each
    target:

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
    """CTLS position covariance (M, 3, 3), m², of Wang, Zhang & Wu (2006) eq. (30) ((31) equal σ).

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


def error_from_terms(A, B=None, horizontal=False):
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


def error_terms(targets, positions, sigma_az, sigma_el, model, length_unit):
    """Additive per-target terms (M, 3, 3) of ``model``: (J, None) with J the Fisher
    information, 1/m² (crlb), or (A, B) of Wang, Zhang & Wu eq. (30) (ctls, :func:`_ctls_terms`).
    """
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


def horizontal_crlb_applies(model, horizontal, dimension):
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
    check_model(model)
    horizontal = horizontal_crlb_applies(model, horizontal_solve(stations, dimension), dimension)
    tgt = np.atleast_2d(np.asarray(targets, dtype=float))
    if tgt.shape[-1] != 3 or not np.all(np.isfinite(tgt)):
        raise ValueError('targets: expected finite (M, 3) positions')
    out = np.empty(tgt.shape[0])
    for s in range(0, tgt.shape[0], CHUNK):
        sl = slice(s, s + CHUNK)
        A, B = error_terms(tgt[sl], stations.positions, stations.sigma_az, stations.sigma_el,
                           model, length_unit)
        out[sl] = error_from_terms(A, B, horizontal)
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
    horizontal = horizontal_crlb_applies(model, horizontal_solve(stations, dimension), dimension)
    solve = 'horizontal' if horizontal else '3d'
    return AccuracyMap(grid, err.reshape(grid.height, grid.width), model, stations, solve)
