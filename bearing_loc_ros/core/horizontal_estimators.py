"""Estimators of the horizontal solve: (x, y) from azimuths, the target altitude stated.

Conventions (DESIGN.md): ENU metres, azimuth θ CCW from East, elevation ψ above the horizontal,
radians; an azimuth-only (1D) bearing has elevation NaN. The user states the target altitude
z₀ (m, world frame) and its standard deviation σ_z (m, 0 = exactly known); the model, the
Gaussian prior z ~ N(z₀, σ_z²) and the bound are in :mod:`.horizontal_crlb`.

Estimators (batch-first like the 3D ones: M problems of N bearings, vectorised over M, O(N)
per problem and iteration, no dense 2N × 2N matrix):

* ``ls``: Wang, Zhang & Wu eq. (4) on the plane-reduced pseudo-linear system (below), rows
  whitened by the angle σ (exactly eq. (4) when all σ are equal).
* ``tls``: Wang, Zhang & Wu eq. (5) on the same (whitened) system.
* ``ctls``/``ctls_am``: Wang, Zhang & Wu eqs. (9)-(20) reduced to the plane
  (:mod:`.horizontal_ctls`).
* ``mle``: Zong & Cui 2015 eqs. (3)-(8) with the z prior, Gauss-Newton with
  Levenberg-Marquardt damping (:mod:`.horizontal_ml`).
* ``wmle``: Zong & Cui 2015 eqs. (9)-(11), σ grown with range, same iteration.

Plane-reduced pseudo-linear system. Substituting the stated z = z₀ into the rows of Wang,
Zhang & Wu eq. (2) and moving it to the right-hand side gives, per station i (Δz_i = z₀ − z_i):

    azimuth row:    [sin θ_i, −cos θ_i] · (x, y) = sin θ_i x_i − cos θ_i y_i
    elevation row:  [cos θ_i sin ψ_i, sin θ_i sin ψ_i] · (x, y)
                    = cos θ_i sin ψ_i x_i + sin θ_i sin ψ_i y_i + cos ψ_i Δz_i.

Dividing the elevation row by sin ψ_i gives cos θ_i x + sin θ_i y = cos θ_i x_i + sin θ_i y_i
+ Δz_i / tan ψ_i: the horizontal range ρ_i = Δz_i / tan ψ_i along the line of sight, which is
how a 2D station's elevation carries range information once the altitude is known. The
form above (not divided) stays finite when ψ_i → 0 and has the noise scale of eq. (2): to
first order the azimuth row's error is ρ_i n_i and the elevation row's is r_i m_i − cos ψ_i δz₀
(ρ, r horizontal and slant range, δz₀ the error of the stated altitude). Rows are whitened by
1/σ_θi and 1/σ_ψi. With A = HᵀWH the ``ls`` solution X = A⁻¹HᵀWY is linear in z₀
(∂Y/∂z₀ = (0, cos ψ_i) per station), so its covariance is exact to first order in the noise:

    P_h = A⁻¹ (Hᵀ W Σ W H + σ_z² g gᵀ) A⁻¹,  P_hz = σ_z² A⁻¹ g,  P_zz = σ_z²,
    Σ = diag(ρ_i² σ_θi², r_i² σ_ψi²),  g = Σ_{2D} h_ei w_ei cos ψ_i,

so g = 0 (no x-y/z correlation) without elevations.

σ_z through a fit that is not linear in z₀ (``tls``, ``ctls``, ``ctls_am``;
:func:`altitude_covariance`). Every estimator here fits with z = z₀. The TLS eigenvalue λ
grows with the square of the misfit between the elevation rows and the azimuths, and the
CTLS weights S_i depend on Δz_i and on X, so with an elevation station and a σ_z of tens of
metres the fit moves with z₀ far from its first-order gain, and not linearly (it can even
turn back when z₀ + s nears a station's height). The true altitude is z₀ + s,
s ~ N(0, σ_z²); the fit at the true altitude, X̂(z₀ + s), errs only by the bearing noise
(covariance P₀, the σ_z = 0 sandwich), so the reported (X̂(z₀), z₀) errs by
v(s) = (X̂(z₀) − X̂(z₀ + s), −s) plus that noise, and

    P = P₀ + E_s[v vᵀ] ≈ P₀ + Σ_j w_j v(σ_z x_j) v(σ_z x_j)ᵀ,

the five-point Gauss-Hermite rule of N(0, 1) (nodes x_j = 0, ±1.3556, ±2.8570, weights 8/15,
0.2221, 0.0113; v(0) = 0): exact when X̂ is a polynomial of degree ≤ 4 in z₀ over the prior
(for ``ls``, X̂ linear, it is the formula above). Cost: four refits of the problems with
σ_z > 0 and a used elevation, started from the fit (the others do not depend on z₀).
Measured (test/test_horizontal_covariance.py, 5 stations, one or two with an elevation,
σ = 0.6 mrad, σ_z = 100-300 m), mean NEES of the 3 × 3 covariance: first-order gain 4-4600;
local derivative ∂X̂/∂z₀ 3-1100 (misses the curvature); CRLB with the prior 30-50000 (these
fits keep z = z₀ and do not reach the bound); three-point rule 3.0-3.2 but 178 where the
fit turns back; five-point rule 2.8-3.7. The error is then not Gaussian in s: the mean NEES
is right, but up to ~2 % of the fixes exceed the χ²₃ 0.9999 quantile when the altitude term
dominates the bearing noise (``mle``, which estimates z, has no such term).

Options (keyword arguments; an unknown one raises ``ValueError('options.<name>: ...')``):
``max_iterations`` (default 50), ``tolerance`` (1e-9, relative to the rms station range),
``initial`` ((2,), (3,), (M, 2) or (M, 3) m; only x, y are used unless σ_z > 0),
``reference_range`` (``wmle``, m, default 1000), ``step_decay`` (``ctls``/``ctls_am``).
Statuses as in core/estimators.py: ``ok``, ``max_iterations``, ``diverged``,
``degenerate_geometry`` (horizontal information singular at the estimate, e.g. all stations
and the target on one line with no usable elevation, or a covariance that is not finite;
position NaN, covariance inf). Covariances are symmetrised, (P + Pᵀ)/2.
"""

import numbers

import numpy as np

from .bearings import BearingSet, MAX_ABS_ANGLE, MAX_ABS_POSITION, SIGMA_MAX, SIGMA_MIN
from .estimator_spec import (BEARING_SIGMA, EstimatorSpec, MAX_ABS_ALTITUDE, MAX_ALTITUDE_SIGMA,
                             MAX_ITERATIONS, MULTISTATION, Option, RANGE_GROWN_SIGMA,
                             REFERENCE_RANGE, STEP_DECAY, TOLERANCE)
from .estimators import FixResult, STATUS_DEGENERATE, STATUS_OK
from .horizontal_crlb import _as_problem_vector, inverse2

HALF_PI = np.pi / 2.0
#: Starting point of the iterative horizontal estimators (checked by
#: :func:`parse_horizontal_options`).
INITIAL = Option('initial', None, 'object',
                 'starting point (2,), (3,), (M, 2) or (M, 3), m (default: ls)')
_COMMON = (MAX_ITERATIONS, TOLERANCE)
_ITERATIVE = _COMMON + (INITIAL,)
#: Option declarations of the horizontal estimators (same names and meaning as the 3D ones).
SPECS = {name: EstimatorSpec(name, MULTISTATION, options, noise, FixResult)
         for name, options, noise in (
             ('ls', _COMMON, BEARING_SIGMA),
             ('tls', _COMMON, BEARING_SIGMA),
             ('ctls', _ITERATIVE + (STEP_DECAY,), BEARING_SIGMA),
             ('ctls_am', _ITERATIVE + (STEP_DECAY,), BEARING_SIGMA),
             ('mle', _ITERATIVE, BEARING_SIGMA),
             ('wmle', _ITERATIVE + (REFERENCE_RANGE,), RANGE_GROWN_SIGMA))}
#: Accepted options and defaults per horizontal estimator.
OPTION_DEFAULTS = {name: spec.defaults() for name, spec in SPECS.items()}
#: Tail probability of the χ² test of :func:`on_station_line` (bearings consistent with a
#: target on the stations' line at this level are declared degenerate; small, so that a
#: target truly on the line is practically never given a fix).
LINE_CHI2_TAIL = 1e-6
#: Nonzero nodes (ascending, symmetric) and weights of the five-point Gauss-Hermite rule of
#: N(0, 1): ±1.3556, ±2.8570 with weights 0.2221, 0.0113 (the node 0 has weight 8/15);
#: E[f(s)] exact for polynomials f of degree ≤ 9 (:func:`altitude_covariance`).
_GH_X, _GH_W = np.polynomial.hermite_e.hermegauss(5)
GH_NODES = _GH_X[_GH_X != 0.0]
GH_WEIGHTS = (_GH_W / _GH_W.sum())[_GH_X != 0.0]


class HorizontalProblem:
    """Validated arrays of a horizontal solve, (M, N) per bearing and (M,) per problem.

    Attributes: px, py, pz station coordinates (m); az θ and el ψ (rad; el 0 where unused);
    saz, sel σ (rad; sel NaN where unused); use_el (bool, elevation used); z0, sz the stated
    altitude and its σ (m).
    """

    _FIELDS = ('px', 'py', 'pz', 'az', 'el', 'saz', 'sel', 'use_el', 'z0', 'sz')

    # Size properties: alike BearingSet's in shape only (a different container).
    @property
    def M(self):
        """Number of problems."""
        return self.az.shape[0]

    @property
    def N(self):
        """Number of bearings per problem."""
        return self.az.shape[1]

    def take(self, idx):
        """The problems ``idx`` only."""
        out = object.__new__(HorizontalProblem)
        for name in self._FIELDS:
            setattr(out, name, getattr(self, name)[idx])
        return out


def prepare(bearings, target_altitude, target_altitude_sigma=0.0, use_elevations=True):
    """Validate a horizontal solve's input; return a :class:`HorizontalProblem`.

    Raises ``ValueError`` naming the field: ``bearings`` (not a BearingSet, fewer than two
    azimuths), ``position``/``azimuth``/``elevation``/``sigma_azimuth``/``sigma_elevation``
    (the rules of BearingSet.validate without its demand for an elevation),
    ``target_altitude`` (missing, not a number, NaN, infinite or |z₀| above
    :data:`MAX_ABS_ALTITUDE` m), ``target_altitude_sigma`` (negative, NaN, infinite or above
    :data:`MAX_ALTITUDE_SIGMA` m), ``use_elevations`` (not a bool).
    """
    if not isinstance(bearings, BearingSet):
        raise ValueError(f'bearings: expected a BearingSet, got {type(bearings).__name__}')
    if bearings.M == 1:
        p = _prepare_one(bearings, target_altitude, target_altitude_sigma, use_elevations)
        if p is not None:
            return p
    pos, az, el = bearings.positions, bearings.azimuth, bearings.elevation
    saz, sel = bearings.sigma_az, bearings.sigma_el
    if bearings.N >= 2:
        bearings.validate(require_elevation=False)
    has_el = np.isfinite(el)
    if bearings.N < 2:
        raise ValueError(f'bearings: {bearings.N} azimuth(s); a horizontal fix needs at least '
                         'two stations')
    if target_altitude is None:
        raise ValueError('target_altitude: required for a horizontal solve (m, world frame); '
                         'the bearings do not fix the height')
    if isinstance(target_altitude, bool):
        raise ValueError('target_altitude: expected a number (m), got a bool')
    z0 = _as_problem_vector(target_altitude, bearings.M, 'target_altitude')
    if not np.all(np.isfinite(z0)):
        raise ValueError('target_altitude: must be finite (m, world frame), got NaN or inf')
    if np.any(np.abs(z0) > MAX_ABS_ALTITUDE):
        raise ValueError(f'target_altitude: |z0| above {MAX_ABS_ALTITUDE:g} m (the bound of '
                         'every coordinate)')
    if isinstance(target_altitude_sigma, bool):
        raise ValueError('target_altitude_sigma: expected a number (m), got a bool')
    sz = _as_problem_vector(target_altitude_sigma, bearings.M, 'target_altitude_sigma')
    if not np.all(np.isfinite(sz) & (sz >= 0)):
        raise ValueError('target_altitude_sigma: must be finite and >= 0 (m; 0 = altitude '
                         'exactly known)')
    if np.any(sz > MAX_ALTITUDE_SIGMA):
        raise ValueError(f'target_altitude_sigma: above {MAX_ALTITUDE_SIGMA:g} m (the range '
                         'of the node parameter; 0 = altitude exactly known)')
    use_elevations = check_bool(use_elevations, 'use_elevations')
    p = object.__new__(HorizontalProblem)
    p.px, p.py, p.pz = pos[..., 0], pos[..., 1], pos[..., 2]
    p.use_el = has_el & use_elevations
    p.az = az
    p.el = np.where(p.use_el, el, 0.0)
    p.saz = saz
    p.sel = np.where(p.use_el, sel, np.nan)
    p.z0, p.sz = z0, sz
    return p


def _prepare_one(bearings, target_altitude, target_altitude_sigma, use_elevations):
    """:func:`prepare` of one problem whose input is certainly valid, else None.

    The same checks on Python floats (:func:`fields_valid`; z₀, σ_z plain finite
    numbers, |z₀| ≤ :data:`MAX_ABS_ALTITUDE`, 0 ≤ σ_z ≤ :data:`MAX_ALTITUDE_SIGMA`;
    ``use_elevations`` a bool) and the same arrays; anything else (None) takes the full
    check, which names the bad field.
    """
    z0, sz = _one_number(target_altitude), _one_number(target_altitude_sigma)
    if z0 is None or sz is None or not isinstance(use_elevations, (bool, np.bool_)):
        return None
    if not (abs(z0) <= MAX_ABS_ALTITUDE and 0.0 <= sz <= MAX_ALTITUDE_SIGMA) \
            or not fields_valid(bearings):
        return None
    pos, el = bearings.positions, bearings.elevation
    p = object.__new__(HorizontalProblem)
    p.px, p.py, p.pz = pos[..., 0], pos[..., 1], pos[..., 2]
    p.use_el = np.isfinite(el) & bool(use_elevations)
    p.az = bearings.azimuth
    p.el = np.where(p.use_el, el, 0.0)
    p.saz = bearings.sigma_az
    p.sel = np.where(p.use_el, bearings.sigma_el, np.nan)
    p.z0, p.sz = np.array([z0]), np.array([sz])
    return p


def fields_valid(bearings):
    """True when a one-problem BearingSet of float64 arrays certainly passes the field rules.

    The rules of ``BearingSet.validate(require_elevation=False)`` (core/bearings.py) on
    Python floats: |coordinate| ≤ MAX_ABS_POSITION m, |θ| ≤ MAX_ABS_ANGLE rad, ψ NaN (1D)
    or |ψ| < π/2, σ_θ (and σ_ψ where ψ is given) in [SIGMA_MIN, SIGMA_MAX] rad, N ≥ 2.
    Anything else returns False and goes through the full check, which names the bad field.
    """
    arrays = (bearings.positions, bearings.azimuth, bearings.elevation, bearings.sigma_az,
              bearings.sigma_el)
    if not all(type(a) is np.ndarray and a.dtype == np.float64 for a in arrays):
        return False
    N = bearings.azimuth.shape[-1]
    if (bearings.positions.shape != (1, N, 3) or N < 2
            or any(a.shape != (1, N) for a in arrays[1:])):
        return False
    if not (all(abs(v) <= MAX_ABS_POSITION for v in bearings.positions.ravel().tolist())
            and all(abs(v) <= MAX_ABS_ANGLE for v in bearings.azimuth[0].tolist())):
        return False
    for el, saz, sel in zip(bearings.elevation[0].tolist(), bearings.sigma_az[0].tolist(),
                            bearings.sigma_el[0].tolist()):
        if not SIGMA_MIN <= saz <= SIGMA_MAX:
            return False
        if el == el and not (abs(el) < HALF_PI and SIGMA_MIN <= sel <= SIGMA_MAX):
            return False
    return True


def _one_number(value):
    """``value`` as a float when it is a plain number or a (1,)/() float or int array."""
    if isinstance(value, np.ndarray):
        if value.shape not in ((), (1,)) or value.dtype.kind not in 'fiu':
            return None
        value = value.reshape(-1)[0]
    if isinstance(value, (bool, np.bool_)) \
            or not isinstance(value, (float, int, np.floating, np.integer)):
        return None
    try:
        return float(value)
    except OverflowError:
        return None


def parse_horizontal_options(method, options, M):
    """Validate ``options`` for horizontal estimator ``method``; returns (options, initial).

    ``initial`` ((2,), (3,), (M, 2) or (M, 3), m, finite) comes back as (M, 3) (z NaN when
    only x, y were given) or None. The other options are checked by their declarations
    (core/estimator_spec.py); ValueError('options.<name>: ...').
    """
    opts = SPECS[method].parse(options, M)
    x0 = opts.get('initial')
    if x0 is None:
        return opts, None
    a = np.asarray(x0, dtype=float)
    a = a[None] if a.ndim == 1 else a
    if a.ndim != 2 or a.shape[1] not in (2, 3) or a.shape[0] not in (1, M):
        raise ValueError(f'options.initial: expected shape (2,), (3,), ({M}, 2) or ({M}, 3), '
                         f'got {np.shape(x0)}')
    if not np.all(np.isfinite(a)):
        raise ValueError('options.initial: non-finite coordinate')
    out = np.full((M, 3), np.nan)
    out[:, :a.shape[1]] = a
    return opts, out


# ----------------------------------------------------------------------------------------------
# Pseudo-linear estimators (Wang, Zhang & Wu eqs. (2)-(5) reduced to the plane)


def plane_system(p):
    """Rows of the plane-reduced system (module docstring): H (M, N, 2, 2), Y (M, N, 2).

    Row 0 of each station is the azimuth row, row 1 the elevation row (zero where the
    elevation is not used). Also returns the whitening weights w = (1/σ_θ², 1/σ_ψ²) (M, N, 2),
    0 for unused elevation rows.
    """
    st, ct = np.sin(p.az), np.cos(p.az)
    sp, cp = np.sin(p.el), np.cos(p.el)
    m = p.use_el.astype(float)
    H = np.empty(p.az.shape + (2, 2))
    H[..., 0, 0], H[..., 0, 1] = st, -ct
    H[..., 1, 0], H[..., 1, 1] = m * ct * sp, m * st * sp
    Y = np.empty(p.az.shape + (2,))
    Y[..., 0] = st * p.px - ct * p.py
    Y[..., 1] = m * (ct * sp * p.px + st * sp * p.py + cp * (p.z0[:, None] - p.pz))
    w = np.stack([1.0 / p.saz ** 2, np.where(p.use_el, 1.0 / np.where(p.use_el, p.sel, 1.0) ** 2,
                                             0.0)], axis=-1)
    return H, Y, w


def solve2(A, b):
    """x = A⁻¹ b for (M, 2, 2) systems; (x, ok), x NaN where A is singular (horizontal RCOND)."""
    Ainv, ok = inverse2(A)
    x = np.full(b.shape, np.nan)
    if np.any(ok):
        x[ok] = np.einsum('mij,mj->mi', Ainv[ok], b[ok])
    return x, Ainv, ok


def linear_covariance(p, xy, ok, H, w, Ainv):
    """σ_z = 0 covariance and altitude gain of X = A⁻¹HᵀWY (module docstring).

    Returns (P₀, k): P₀ (M, 3, 3), m², the first-order sandwich A⁻¹HᵀWΣWHA⁻¹ in the x-y block
    and zeros in the z row and column (+inf where not ``ok``); k = A⁻¹g (M, 2), the exact
    ∂X/∂z₀ of the linear fit (dimensionless; 0 without a used elevation).
    """
    dx = np.where(ok[:, None], xy[:, 0:1], 0.0) - p.px
    dy = np.where(ok[:, None], xy[:, 1:2], 0.0) - p.py
    rho2 = dx * dx + dy * dy
    r2 = rho2 + (p.z0[:, None] - p.pz) ** 2
    var = np.stack([rho2 * p.saz ** 2, np.where(p.use_el, r2 * np.nan_to_num(p.sel) ** 2, 0.0)],
                   axis=-1)
    B = np.einsum('mnki,mnk,mnkj->mij', H, w * w * var, H)
    g = np.einsum('mni,mn->mi', H[..., 1, :], w[..., 1] * np.cos(p.el))
    return sandwich(Ainv, B, g, ok)


def sandwich(Ainv, B, g, ok):
    """(P₀, k) of :func:`linear_covariance` from A⁻¹, B (M, 2, 2) and g (M, 2); P₀ = A⁻¹BA⁻¹
    symmetrised, k = A⁻¹g; P₀ = +inf and k = 0 where not ``ok``."""
    M = Ainv.shape[0]
    P = np.full((M, 3, 3), np.inf)
    k = np.zeros((M, 2))
    if np.any(ok):
        Ai = Ainv[ok]
        Ph = Ai @ B[ok] @ Ai
        P[ok, :2, :2] = 0.5 * (Ph + np.swapaxes(Ph, 1, 2))
        P[ok, :2, 2] = P[ok, 2, :] = 0.0
        k[ok] = np.einsum('mij,mj->mi', Ai, g[ok])
    return P, k


def _outer(v):
    return v[:, :, None] * v[:, None, :]


def linear_altitude_covariance(p, P0, k):
    """P₀ + σ_z² u uᵀ, u = (k, 1): the covariance of a fit X̂(z₀) linear in z₀ with gain k.

    ``P0`` (M, 3, 3) and ``k`` (M, 2) from :func:`linear_covariance`; exact for ``ls`` (module
    docstring). Non-finite P₀ stays as it is.
    """
    u = np.concatenate([k, np.ones((p.M, 1))], axis=1) * p.sz[:, None]
    with np.errstate(invalid='ignore'):
        return P0 + _outer(u)


def with_altitude(p, idx, dz):
    """The problems ``idx`` of ``p`` with the stated altitude z₀ + ``dz`` (m) and σ_z = 0."""
    q = p.take(idx)
    q.z0 = q.z0 + dz
    q.sz = np.zeros_like(q.sz)
    return q


def altitude_covariance(p, xy, P0, k, refit):
    """Covariance (M, 3, 3), m², of a fit X̂(z₀) that holds z = z₀: σ_z through the fit itself.

    P = P₀ + Σ_j w_j v_j v_jᵀ, v_j = (X̂(z₀) − X̂(z₀ + s_j), −s_j), s_j = σ_z x_j over the
    nonzero nodes x_j of the five-point Gauss-Hermite rule (module docstring), symmetrised.
    ``xy`` (M, 2) the fit, ``P0`` its σ_z = 0 covariance (zero z row and column), ``k``
    (M, 2) its first-order gain ∂X̂/∂z₀. ``refit(q, idx)`` returns the fit (len(idx), 2), NaN
    where none, of ``q`` = :func:`with_altitude` (the problems ``idx`` at shifted altitudes,
    σ_z = 0; ``idx`` repeats each problem once per node, so one batch call does every node).
    Refits run only where σ_z > 0, an elevation is used and P₀ is finite; elsewhere X̂ does
    not depend on z₀ (or the fix is degenerate) and P = P₀ + σ_z² (k, 1)(k, 1)ᵀ. A node
    without a finite refit takes the mirror of its opposite node (−v), or else the linear
    v = −s_j (k, 1).
    """
    P = linear_altitude_covariance(p, P0, k)
    finite = np.all(np.isfinite(P0), axis=(1, 2)) & np.all(np.isfinite(xy), axis=1)
    idx = np.flatnonzero(finite & (p.sz > 0) & np.any(p.use_el, axis=1))
    if idx.size:
        n = GH_NODES.size
        rep = np.tile(idx, n)
        s = (GH_NODES[:, None] * p.sz[idx]).ravel()
        X = refit(with_altitude(p, rep, s), rep)
        v = np.concatenate([xy[rep] - X, -s[:, None]], axis=1).reshape(n, idx.size, 3)
        ok = np.all(np.isfinite(v), axis=2)
        lin = -(GH_NODES[:, None] * p.sz[idx])[:, :, None] * np.concatenate(
            [k[idx], np.ones((idx.size, 1))], axis=1)
        mirror = -v[::-1]                        # GH_NODES is symmetric: node j ↔ n − 1 − j
        v = np.where(ok[:, :, None], v, np.where(ok[::-1, :, None], mirror, lin))
        P[idx] = P0[idx] + np.einsum('j,jmi,jmk->mik', GH_WEIGHTS, v, v)
    return 0.5 * (P + np.swapaxes(P, 1, 2))


def on_station_line(p):
    """(M,) bool: azimuth-only problems whose data place the target on the stations' line.

    When every station lies on one horizontal line and the target is on it too, azimuths
    say nothing about the along-line position (the information is singular there). With
    noise the lines cross somewhere far along it, and a first-order covariance at that
    crossing is meaningless. Test: the stations are collinear (the 2 × 2 scatter of their
    horizontal positions has λ_min ≤ 1e-6 λ_max, i.e. a perpendicular spread below 1e-3 of
    the along-line spread) and χ² = Σ δ_i²/σ_θi² ≤ :data:`LINE_CHI2_TAIL`'s χ²_N quantile,
    δ_i the angle between azimuth θ_i and the line (mod π): the bearings are consistent with
    a target on the line. Problems with a usable elevation are never flagged (with the
    altitude known an elevation measures the range).
    """
    from . import chisq as chi2
    d = np.stack([p.px - p.px.mean(axis=1, keepdims=True),
                  p.py - p.py.mean(axis=1, keepdims=True)], axis=-1)
    C = np.einsum('mni,mnj->mij', d, d)
    w, v = np.linalg.eigh(C)
    collinear = (w[:, 1] > 0) & (w[:, 0] <= 1e-6 * w[:, 1])
    phi = np.arctan2(v[:, 1, 1], v[:, 0, 1])
    delta = np.mod(p.az - phi[:, None] + HALF_PI, np.pi) - HALF_PI
    stat = np.sum((delta / p.saz) ** 2, axis=1)
    return collinear & ~np.any(p.use_el, axis=1) & (stat <= chi2.isf(LINE_CHI2_TAIL, p.N))


def fix_result(p, xy, cov, iterations, converged, status, method, z=None):
    """FixResult with position (M, 3) = (x, y, z) (z = z₀ unless given); NaN where degenerate.

    Problems flagged by :func:`on_station_line` are degenerate_geometry too, and so is an
    ``ok`` fix whose covariance or (x, y) is not finite (never an ``ok`` fix without an
    honest, finite covariance).
    """
    cov = np.array(cov, dtype=float)
    finite = np.all(np.isfinite(cov), axis=(1, 2)) & np.all(np.isfinite(xy), axis=1)
    status = np.where(on_station_line(p) | ((status == STATUS_OK) & ~finite), STATUS_DEGENERATE,
                      status)
    bad = status == STATUS_DEGENERATE
    pos = np.empty((p.M, 3))
    pos[:, :2] = np.where(bad[:, None], np.nan, xy)
    pos[:, 2] = np.where(bad, np.nan, p.z0 if z is None else z)
    cov[bad] = np.inf
    return FixResult(pos, cov, np.asarray(iterations, dtype=int), converged & ~bad,
                     status.astype(str), method)


def _closed_form(p, xy, ok, H, w, Ainv, method, refit=None):
    """Result of a pseudo-linear solution; degenerate where singular or on a station.

    Covariance: :func:`linear_altitude_covariance` (``ls``), or :func:`altitude_covariance`
    with ``refit`` (``tls``).

    A solution within 1e-9 × (1 m + largest |station coordinate| + largest station range) of
    a station (horizontally) is the answer of co-located stations, where the bearing model is
    undefined (see estimators._closed_form_result): degenerate_geometry.
    """
    with np.errstate(invalid='ignore'):
        dist = np.hypot(xy[:, 0:1] - p.px, xy[:, 1:2] - p.py)
        scale = 1.0 + np.max(np.abs(np.stack([p.px, p.py])), axis=(0, 2)) + np.max(dist, axis=1)
        ok = ok & np.all(np.isfinite(xy), axis=1) & ~np.any(dist <= 1e-9 * scale[:, None],
                                                            axis=1)
    P0, k = linear_covariance(p, xy, ok, H, w, Ainv)
    cov = linear_altitude_covariance(p, P0, k) if refit is None \
        else altitude_covariance(p, xy, P0, k, refit)
    status = np.where(ok, STATUS_OK, STATUS_DEGENERATE)
    return fix_result(p, xy, cov, np.zeros(p.M, dtype=int), ok.copy(), status, method)


def solve_ls(p):
    """Whitened pseudo-linear LS (x, y) (M, 2), with (ok, H, w, A⁻¹); NaN where singular."""
    H, Y, w = plane_system(p)
    A = np.einsum('mnki,mnk,mnkj->mij', H, w, H)
    b = np.einsum('mnki,mnk,mnk->mi', H, w, Y)
    xy, Ainv, ok = solve2(A, b)
    return xy, ok, H, w, Ainv


def ls(p, **options):
    """Pseudo-linear least squares, Wang, Zhang & Wu eq. (4) reduced to the plane.

    X = (HᵀWH)⁻¹HᵀWY with the plane-reduced rows (module docstring) and W = diag(1/σ_θi²,
    1/σ_ψi²) (eq. (4) itself when every σ is equal); sums over stations, O(N). z = z₀.
    Covariance: the first-order sandwich with σ_z of the module docstring, m². Status
    degenerate_geometry where HᵀWH is singular (e.g. parallel bearings). ``p`` is a
    :class:`HorizontalProblem` (see :func:`prepare`).
    """
    parse_horizontal_options('ls', options, p.M)
    xy, ok, H, w, Ainv = solve_ls(p)
    return _closed_form(p, xy, ok, H, w, Ainv, 'ls')


def tls(p, **options):
    """Total least squares, Wang, Zhang & Wu eq. (5) on the whitened plane-reduced system.

    X = (HᵀWH − λI)⁻¹HᵀWY with λ the smallest eigenvalue of the 3 × 3 normal matrix of
    W^½[−Y H] (the squared smallest singular value σ₃² of eq. (5)), refined by three
    Rayleigh-quotient steps λ ← ‖W^½(HX − Y)‖² / (1 + ‖X‖²) as the 3D ``tls`` does. Origin-
    and unit-dependent, like eq. (5). Covariance, m²: the LS sandwich for the bearing noise
    (the TLS correction is second order in it) and σ_z carried through the TLS solution
    itself (:func:`altitude_covariance`: λ grows with the square of the altitude misfit, so
    X̂ is not linear in z₀ when an elevation is used).
    """
    parse_horizontal_options('tls', options, p.M)
    xy, ok, H, w, Ainv = _tls_solve(p)
    return _closed_form(p, xy, ok, H, w, Ainv, 'tls',
                        refit=lambda q, idx: _finite(*_tls_solve(q)[:2]))


def _finite(xy, ok):
    """``xy`` with NaN rows where not ``ok``."""
    return np.where(ok[:, None], xy, np.nan)


def _tls_solve(p):
    """The TLS fit of :func:`tls`: (xy (M, 2), ok, H, w, A⁻¹) with A = HᵀWH."""
    H, Y, w = plane_system(p)
    A = np.einsum('mnki,mnk,mnkj->mij', H, w, H)
    b = np.einsum('mnki,mnk,mnk->mi', H, w, Y)
    yy = np.einsum('mnk,mnk,mnk->m', Y, w, Y)
    C3 = np.empty((p.M, 3, 3))
    C3[:, 0, 0] = yy
    C3[:, 0, 1:] = C3[:, 1:, 0] = -b
    C3[:, 1:, 1:] = A
    C3[~np.all(np.isfinite(C3), axis=(1, 2))] = 0.0
    lam = np.linalg.eigvalsh(C3)[:, 0]
    eye = np.eye(2)
    for _ in range(3):
        xy, _, _ = solve2(A - lam[:, None, None] * eye, b)
        r = np.einsum('mnki,mi->mnk', H, xy) - Y
        lam_new = np.einsum('mnk,mnk,mnk->m', r, w, r) / (1.0 + np.einsum('mi,mi->m', xy, xy))
        lam = np.where(np.isfinite(lam_new), lam_new, lam)
    xy, _, ok = solve2(A - lam[:, None, None] * eye, b)
    Ainv, ok_ls = inverse2(A)
    return xy, ok & ok_ls, H, w, Ainv


def start(p, initial):
    """Initial (M, 3): ``initial`` (x, y; z when given and σ_z > 0) or else ``ls`` at z₀."""
    if initial is None:
        xy, ok, _, _, _ = solve_ls(p)
        x0 = np.concatenate([xy, p.z0[:, None]], axis=1)
        x0[~ok] = np.nan
        return x0
    x0 = initial.copy()
    x0[:, 2] = np.where(np.isfinite(x0[:, 2]) & (p.sz > 0), x0[:, 2], p.z0)
    return x0


def check_bool(value, name):
    """``value`` as a bool; ValueError naming ``name`` for anything but a bool."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, numbers.Number):
        raise ValueError(f'{name}: expected true or false, got {value!r}')
    raise ValueError(f'{name}: expected true or false')
