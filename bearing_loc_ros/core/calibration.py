"""Receiver calibration against a transmitter at a known position (pure numpy/scipy).

A calibration run records, at each station, the bearings of a transmitter whose position is
known. For reading i of station s, with β_i the measured compass bearing (clockwise from
North, with the station's current geometry) and β*_i the true one (from the station to the
transmitter), the compass residual r_i = wrap(β_i − β*_i) follows

    r_i = δ_s + ε_i,   ε_i ~ N(0, σ_i²),   ln σ_i = a + b · (1 − c̃_i),

where δ_s is the station's heading bias (rad; the array points δ_s further clockwise than
configured), c̃_i = clip(c_i, 0, 1) the reading's confidence and (a, b) the log-linear
confidence -> σ model of :class:`bearing_loc_ros.core.receiver.SigmaModel`
(σ₁ = e^a at full confidence, σ₀ = e^(a+b) at zero confidence). Readings are independent.

The parameters θ = (δ_1 … δ_S, a, b) are fitted by maximum likelihood: with z_i = r_i − δ_s
and w_i = e^(−2 ln σ_i), the negative log-likelihood (constants dropped) is

    L(θ) = Σ_i [ ln σ_i + ½ z_i² w_i ],

minimised by a trust-region Newton method with the analytic gradient and Hessian

    ∂L/∂δ_s = −Σ_{i∈s} z_i w_i,        ∂L/∂a = Σ (1 − z_i² w_i),   ∂L/∂b = Σ x_i (1 − z_i² w_i),
    ∂²L/∂δ_s² = Σ_{i∈s} w_i,           ∂²L/∂δ_s∂a = 2 Σ_{i∈s} z_i w_i,
    ∂²L/∂δ_s∂b = 2 Σ_{i∈s} x_i z_i w_i, ∂²L/∂a² = 2 Σ z_i² w_i,
    ∂²L/∂a∂b = 2 Σ x_i z_i² w_i,       ∂²L/∂b² = 2 Σ x_i² z_i² w_i,

with x_i = 1 − c̃_i. Standard errors are the square roots of the diagonal of the inverse
observed information (the Hessian at the optimum). The residuals are wrapped to (−π, π]; a
reading whose residual exceeds ``max_residual`` (a reflection, another emitter) is left out
and counted. The correction to apply is ``heading_offset_deg`` −= δ_s (in degrees).
"""

from dataclasses import dataclass, field
import math

import numpy as np
from scipy import optimize

from .conventions import enu_to_compass, wrap_angle, wrap_angle_scalar


@dataclass
class CalibrationResult:
    """Maximum-likelihood calibration (module docstring).

    Attributes:
        stations: station ids, in the order of ``bias``.
        bias: (S,) heading biases δ_s, rad (compass sense: positive = clockwise).
        bias_se: (S,) their standard errors, rad.
        a, b: the σ model's log-linear coefficients (ln rad); a_se, b_se their SEs.
        covariance: (S + 2, S + 2) inverse observed information of (δ, a, b).
        n_used, n_outliers: readings per station used and left out (dicts).
        nll: the minimised negative log-likelihood; converged: the optimiser's success, or a
            Newton decrement gᵀH⁻¹g at its end of at most :data:`CONVERGED_DECREMENT` with H
            positive definite (the optimum within rounding, where trust-exact can stop
            with "a bad approximation" because no step improves the cost any more).
    """

    stations: list
    bias: np.ndarray
    bias_se: np.ndarray
    a: float
    b: float
    a_se: float
    b_se: float
    covariance: np.ndarray
    n_used: dict = field(default_factory=dict)
    n_outliers: dict = field(default_factory=dict)
    nll: float = math.nan
    converged: bool = False

    @property
    def sigma_conf1_deg(self):
        """σ at full confidence, degrees (e^a)."""
        return math.degrees(math.exp(self.a))

    @property
    def sigma_conf0_deg(self):
        """σ at zero confidence, degrees (e^(a+b))."""
        return math.degrees(math.exp(self.a + self.b))


def true_compass(station_xy, transmitter_xy):
    """True compass bearing(s) β* (rad, clockwise from North) from stations (..., 2) to the
    transmitter (2,): β* = atan2(Δx, Δy) (x East, y North)."""
    s = np.asarray(station_xy, dtype=float)
    t = np.asarray(transmitter_xy, dtype=float)
    return np.arctan2(t[0] - s[..., 0], t[1] - s[..., 1])


def compass_residuals(azimuth, station_xy, transmitter_xy):
    """Compass residuals r_i = wrap(β_i − β*_i) (rad) of bearings against a known transmitter.

    Maths: β_i = π/2 − θ_i is the measured compass bearing (clockwise from North) of the ENU
    azimuth θ_i (counter-clockwise from East, :func:`conventions.enu_to_compass`); β*_i =
    atan2(Δx, Δy) the true one from the bearing's station to the transmitter
    (:func:`true_compass`); the difference is wrapped to (−π, π] (module docstring).

    Args:
        azimuth: (n,) ENU azimuths θ_i, rad.
        station_xy: (n, 2) or (2,) station East/North positions, m (ENU).
        transmitter_xy: (2,) transmitter East/North position, m (ENU).

    Returns an (n,) array of residuals, rad.
    """
    beta = enu_to_compass(np.asarray(azimuth, dtype=float))
    return np.atleast_1d(wrap_angle(beta - true_compass(station_xy, transmitter_xy)))


def corrected_heading_offset_deg(offset_deg, bias):
    """The heading offset (degrees) that removes a fitted compass bias δ (rad).

    Maths: offset' = wrap(offset − δ), wrapped to (−180°, 180°] (module docstring: "the
    correction to apply is heading_offset_deg −= δ_s"). Units: offset in degrees (the station
    parameter ``kraken.heading_offset_deg``), δ in radians (compass sense, clockwise positive).
    """
    return math.degrees(wrap_angle_scalar(math.radians(float(offset_deg)) - float(bias)))


def _nll_parts(theta, idx, r, x, S):
    d = theta[:S][idx]
    a, b = theta[S], theta[S + 1]
    ln_s = a + b * x
    w = np.exp(-2.0 * ln_s)
    z = r - d
    return z, w, ln_s


def _nll(theta, idx, r, x, S):
    z, w, ln_s = _nll_parts(theta, idx, r, x, S)
    return float(np.sum(ln_s + 0.5 * z * z * w))


def _grad(theta, idx, r, x, S):
    z, w, _ = _nll_parts(theta, idx, r, x, S)
    g = np.empty(S + 2)
    g[:S] = -np.bincount(idx, weights=z * w, minlength=S)
    q = 1.0 - z * z * w
    g[S] = np.sum(q)
    g[S + 1] = np.sum(x * q)
    return g


def _hess(theta, idx, r, x, S):
    z, w, _ = _nll_parts(theta, idx, r, x, S)
    h = np.zeros((S + 2, S + 2))
    h[np.arange(S), np.arange(S)] = np.bincount(idx, weights=w, minlength=S)
    h[:S, S] = h[S, :S] = 2.0 * np.bincount(idx, weights=z * w, minlength=S)
    h[:S, S + 1] = h[S + 1, :S] = 2.0 * np.bincount(idx, weights=x * z * w, minlength=S)
    zzw = z * z * w
    h[S, S] = 2.0 * np.sum(zzw)
    h[S, S + 1] = h[S + 1, S] = 2.0 * np.sum(x * zzw)
    h[S + 1, S + 1] = 2.0 * np.sum(x * x * zzw)
    return h


#: Newton decrement gᵀH⁻¹g (twice the predicted decrease of the negative log-likelihood) at
#: or below which the fit is at its optimum: parameters within about 3e-5 standard errors.
CONVERGED_DECREMENT = 1e-9


def fit_calibration(residuals, confidences, max_residual=math.radians(45.0), min_readings=5):
    """Fit heading biases and the confidence -> σ model (module docstring) by ML.

    Args:
        residuals: {station: (n,) compass residuals r_i = β_i − β*_i, rad} (wrapped here).
        confidences: {station: (n,) receiver confidences c_i} (same keys and lengths).
        max_residual: |r_i − median_s(r)| above this (rad) is an outlier, left out.
        min_readings: fewer usable readings at a station -> ValueError naming it.

    Returns a :class:`CalibrationResult`. Raises ValueError (too few readings, a model that
    cannot be identified: every confidence equal, so b has no information).
    """
    stations = list(residuals)
    if not stations:
        raise ValueError('calibration: no station readings')
    idx, rs, xs = [], [], []
    used, out = {}, {}
    for k, s in enumerate(stations):
        r = np.asarray(wrap_angle(np.asarray(residuals[s], dtype=float)), dtype=float).ravel()
        c = np.asarray(confidences[s], dtype=float).ravel()
        if r.shape != c.shape:
            raise ValueError(f'calibration: station {s}: {r.size} residuals but {c.size} '
                             'confidences')
        ok = np.isfinite(r) & np.isfinite(c)
        med = float(np.median(r[ok])) if ok.any() else 0.0
        keep = ok & (np.abs(wrap_angle(r - med)) <= max_residual)
        used[s], out[s] = int(keep.sum()), int((~keep).sum())
        if used[s] < min_readings:
            raise ValueError(f'calibration: station {s}: {used[s]} usable readings (need '
                             f'{min_readings})')
        # residuals about the station's median, so a bias near ±π does not wrap inside
        idx.append(np.full(used[s], k))
        rs.append(med + wrap_angle(r[keep] - med))
        xs.append(1.0 - np.clip(c[keep], 0.0, 1.0))
    idx, r, x = np.concatenate(idx), np.concatenate(rs), np.concatenate(xs)
    S = len(stations)
    if np.ptp(x) < 1e-6:
        raise ValueError('calibration: every reading has the same confidence; the '
                         'confidence -> sigma slope cannot be fitted')
    theta0 = np.zeros(S + 2)
    theta0[:S] = [np.median(r[idx == k]) for k in range(S)]
    resid0 = r - theta0[:S][idx]
    theta0[S] = math.log(max(float(np.std(resid0)), 1e-6))
    args = (idx, r, x, S)
    sol = optimize.minimize(_nll, theta0, args=args, jac=_grad, hess=_hess,
                            method='trust-exact', options={'gtol': 1e-9, 'maxiter': 200})
    H = _hess(sol.x, *args)
    try:
        cov = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        raise ValueError('calibration: the observed information is singular') from None
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    g = _grad(sol.x, *args)
    decrement = float(g @ cov @ g)
    converged = bool(sol.success) or (0.0 <= decrement <= CONVERGED_DECREMENT
                                      and bool(np.all(np.linalg.eigvalsh(H) > 0.0)))
    bias = np.asarray(wrap_angle(sol.x[:S]), dtype=float).reshape(S)
    return CalibrationResult(stations=stations, bias=bias, bias_se=se[:S],
                             a=float(sol.x[S]), b=float(sol.x[S + 1]), a_se=float(se[S]),
                             b_se=float(se[S + 1]), covariance=cov, n_used=used,
                             n_outliers=out, nll=float(sol.fun), converged=converged)
