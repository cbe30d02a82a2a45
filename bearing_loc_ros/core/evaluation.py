"""Monte Carlo evaluation of bearing-only estimators against the Cramér-Rao lower bound.

Pure numpy (no rclpy). One vectorised estimator call per (noise level, estimator): the M
trials of a noise level are one :class:`~bearing_loc_ros.core.bearings.BearingSet` batch.

Experiment (Zong & Cui (2015), section 3): stations s_i fixed, one target X_m per trial m
(in that paper drawn uniformly from a box), bearings θ_mi = θ_i(X_m) + n_mi,
ψ_mi = ψ_i(X_m) + m_mi with n_mi ~ N(0, σ_θ,mi²), m_mi ~ N(0, σ_ψ,mi²) (Zong & Cui (2015),
sec. 1; Wang, Zhang & Wu (2006) eq. (1)). The σ that generates the noise may grow with range,
σ_mi = σ · clip(d_mi / d_ref, f_min, f_max) (Zong & Cui (2015) eqs. (9)-(10); the stations'
``sigma_growth`` of the scenario, core.simulation), while the bearings *report* σ (the value at
d_ref), as a DF receiver that does not know the range would. The estimators see only the reported
values.

Statistics over the trials m whose estimate converged (error e_m = X̂_m − X_m, m):

* RMSE = sqrt(mean_m |e_m|²)                           (Zong & Cui (2015) figs. 2-4)
* bias = |mean_m e_m| (norm of the mean error vector)
* CRLB = sqrt(mean_m trace(J_m⁻¹)) over every trial with a finite bound, J_m the Fisher
  information of trial m at the true target with the *true* (generating) σ (Zong & Cui (2015)
  eqs. (6)-(8), :func:`~.crlb.crlb`): the root of the smallest mean squared error any
  unbiased estimator can reach over those targets. RMSE/CRLB is the ratio of the RMSE and
  the root mean trace over the same trials, the converged ones with a finite bound, >= 1 up
  to Monte Carlo error and estimator bias when every trial converges; when only some do, they
  are a selection (often the easy targets, and the fixes whose error happened to be small),
  and the ratio can fall below 1.
* mean NEES = mean_m e_mᵀ P_m⁻¹ e_m with P_m the estimator's reported covariance: 3 for a
  consistent estimator in 3D (chi-square with 3 degrees of freedom); > 3 means the
  estimator claims more accuracy than it delivers.
* convergence rate = fraction of trials with ``converged`` True; time per fix = wall time
  of the batched call / M.
* the tail: median and 95th percentile of |e_m| over the same (converged) trials as the
  RMSE; ``rmse_all``, the RMSE over every trial with a finite estimate whatever its
  status (``ok``, ``low_confidence``, ``max_iterations``...), the fraction of each
  estimator status, and among the ``ok`` fixes (a consumer's trusted fixes): their RMSE,
  mean NEES and the fraction whose NEES exceeds the 0.9999 quantile of χ² with the NEES's
  degrees of freedom (21.1 for χ²₃; 18.4 for χ²₂, the horizontal fix of an exactly stated
  altitude), a confidently wrong fix.

Simulated elevations are clipped to |ψ| ≤ π/2 − 1e-9 (core.simulation.MAX_ELEVATION), as in
the simulator: at large σ a Gaussian draw can cross the zenith, and the clipped value is
still a valid bearing (the distribution of ψ is the Gaussian with its tails beyond ±90°
moved onto ±90°). With ``outliers`` (fraction f, magnitudes a..b rad) each bearing is, with
probability f, replaced by an outlier: its azimuth and its elevation each get an extra
error ±U(a, b) with a random sign (elevation clipped as above).
* standard errors for comparing rows: SE(RMSE) = sd_m(|e_m|²) / (2 RMSE sqrt(n)) (delta
  method on the mean of |e|²) and SE(mean NEES) = sd_m(NEES_m) / sqrt(n). They describe the
  Monte Carlo spread of the statistic itself, so tests and plots can say whether two curves
  differ by more than chance.

One module (about 500 lines) on purpose: trials, noise levels, statistics and the sweep are
one pipeline that is read top to bottom, and each part is used only by the next.
"""

from dataclasses import asdict, dataclass, field
import time

import numpy as np

from .crlb import crlb as crlb_matrix
from .crlb import safe_inverse

#: Sweeps of Zong & Cui (2015): ``joint`` σ_θ = σ_ψ = σ (fig. 2); ``azimuth`` σ_θ varies,
#: σ_ψ fixed; ``elevation`` σ_ψ varies, σ_θ fixed (figs. 3-4).
SWEEPS = ('joint', 'azimuth', 'elevation')
#: Expected mean NEES of a consistent 3D estimator (chi-square, 3 degrees of freedom).
NEES_DOF = 3


@dataclass
class NoiseLevel:
    """One noise level: σ_θ, σ_ψ (rad) reported by the bearings, the same in degrees as
    given by the user (exact labels for tables), and ``x_deg``, the swept value."""

    sigma_az: float
    sigma_el: float
    x_deg: float
    sigma_az_deg: float = float('nan')
    sigma_el_deg: float = float('nan')


@dataclass
class Stats:
    """Statistics of one estimator at one noise level (see the module docstring)."""

    estimator: str
    sweep: str
    sigma_az_deg: float
    sigma_el_deg: float
    trials: int
    converged: int
    rmse: float
    bias: float
    crlb: float
    rmse_over_crlb: float
    mean_nees: float
    convergence_rate: float
    time_per_fix_s: float
    median_error: float
    p95_error: float = float('nan')
    rmse_all: float = float('nan')
    ok_fraction: float = float('nan')
    low_confidence_fraction: float = float('nan')
    other_fraction: float = float('nan')
    rmse_ok: float = float('nan')
    nees_ok: float = float('nan')
    confident_wrong_fraction: float = float('nan')
    rmse_se: float = float('nan')
    nees_se: float = float('nan')
    bias_vector: list = field(default_factory=list)

    def row(self):
        """A flat dict (CSV/JSON row)."""
        d = asdict(self)
        bx, by, bz = (d.pop('bias_vector') or [np.nan] * 3)
        d.update(bias_x=bx, bias_y=by, bias_z=bz)
        return d


def noise_levels(sigmas_deg, sweep='joint', fixed_deg=0.5):
    """Noise levels of a sweep from σ values in degrees.

    ``joint``: σ_θ = σ_ψ = σ (Zong & Cui (2015) fig. 2); ``azimuth``: σ_θ = σ,
    σ_ψ = ``fixed_deg``; ``elevation``: σ_ψ = σ, σ_θ = ``fixed_deg`` (Zong & Cui (2015)
    figs. 3-4, fixed value 0.5°).
    Returns a list of :class:`NoiseLevel` in radians. Raises ValueError for σ <= 0.
    """
    if sweep not in SWEEPS:
        raise ValueError(f'sweep: must be one of {SWEEPS}, got {sweep!r}')
    sig = np.atleast_1d(np.asarray(sigmas_deg, dtype=float))
    if sig.size == 0 or not np.all(np.isfinite(sig)) or np.any(sig <= 0):
        raise ValueError('sigma_deg: every value must be finite and > 0')
    if not np.isfinite(fixed_deg) or fixed_deg <= 0:
        raise ValueError('fixed_sigma_deg: must be finite and > 0')
    out = []
    for s in sig:
        az = s if sweep in ('joint', 'azimuth') else fixed_deg
        el = s if sweep in ('joint', 'elevation') else fixed_deg
        out.append(NoiseLevel(float(np.radians(az)), float(np.radians(el)), float(s),
                              float(az), float(el)))
    return out


@dataclass
class Trials:
    """Geometry of M Monte Carlo trials (one target per trial, N stations).

    Attributes:
        stations: (M, N, 3) station positions, m (the same row for static stations).
        targets: (M, 3) target positions, m.
        has_elevation: (N,) bool, True for 2D stations.
        range_ref: (N,) reference range r_ref of σ growth, m (NaN: constant σ).
        min_factor, max_factor: (N,) clip bounds of the growth factor.
        report_actual: (N,) bool, True if the bearing reports σ(r) instead of σ_ref.
        station_ids: N station ids; trial_seed: (M,) simulator seed of each trial.
    """

    stations: np.ndarray
    targets: np.ndarray
    has_elevation: np.ndarray
    range_ref: np.ndarray
    min_factor: np.ndarray
    max_factor: np.ndarray
    report_actual: np.ndarray
    station_ids: list = field(default_factory=list)
    trial_seed: np.ndarray = None

    @property
    def M(self):
        """Number of trials."""
        return self.targets.shape[0]

    def sigma_factor(self):
        """(M, N) growth factor f = clip(r / r_ref, f_min, f_max), 1 without growth.

        Zong & Cui (2015) eqs. (9)-(10), as core.simulation.SigmaGrowth.factor: σ(r) = σ_ref · f.
        """
        r = np.linalg.norm(self.targets[:, None, :] - self.stations, axis=-1)
        grow = np.isfinite(self.range_ref)
        ref = np.where(grow, self.range_ref, 1.0)
        f = np.clip(r / ref, self.min_factor, self.max_factor)
        return np.where(grow[None, :], f, 1.0)

    def reference_range(self):
        """The common r_ref of every station with σ growth, or None (none or different)."""
        refs = set(self.range_ref[np.isfinite(self.range_ref)].tolist())
        return refs.pop() if len(refs) == 1 else None

    def no_azimuth(self):
        """(M, N) bool: the target on station n or straight above it in problem m (horizontal
        range <= core.simulation.MIN_HORIZONTAL_RANGE): its azimuth is undefined, and the
        simulator makes no bearing there, so neither does the evaluation."""
        from .simulation import MIN_HORIZONTAL_RANGE
        d = self.targets[:, None, :2] - self.stations[..., :2]
        return np.hypot(d[..., 0], d[..., 1]) <= MIN_HORIZONTAL_RANGE

    def unobserved(self):
        """{station id: problems whose bearing is not made (:meth:`no_azimuth`)}, the stations
        with any (as core.simulation.Simulation.unobserved)."""
        n = np.count_nonzero(self.no_azimuth(), axis=0)
        ids = self.station_ids or [f'station {i}' for i in range(n.size)]
        return {ids[i]: int(n[i]) for i in np.flatnonzero(n)}

    def take(self, idx, keep):
        """The problems ``idx`` seen by the stations ``keep`` ((N,) bool) only."""
        from dataclasses import replace
        return replace(self, stations=self.stations[idx][:, keep], targets=self.targets[idx],
                       has_elevation=self.has_elevation[keep], range_ref=self.range_ref[keep],
                       min_factor=self.min_factor[keep], max_factor=self.max_factor[keep],
                       report_actual=self.report_actual[keep],
                       station_ids=[s for s, k in zip(self.station_ids, keep) if k]
                       if self.station_ids else self.station_ids,
                       trial_seed=None if self.trial_seed is None else self.trial_seed[idx])


def trials_from_scenario(scenario, trials, seed=0, range_ref=None):
    """Monte Carlo geometry of a scenario (core.simulation): trial m uses simulator seed seed+m.

    Targets come from ``core.simulation.realize_targets(scenario, seed + m)`` (a ``random_static``
    target is drawn anew from its box each trial, Zong & Cui (2015) section 3.1; a Monte Carlo
    run = a simulator seed, so ``bearing_loc bag simulate --seed <seed+m>`` replays trial m's
    target). Moving targets and stations are taken at scenario time t_m = duration · m / trials. A
    scenario with T targets gives T problems per trial (M = trials · T), target-major within a
    trial. σ growth and 1D/2D come from the stations.
    ``range_ref`` (m) overrides every station's growth reference range r_ref (stations
    without growth get σ(r) = σ · r / r_ref, unclipped); 0 turns growth off (constant σ).
    """
    from .simulation import realize_targets, station_position, target_position
    trials = int(trials)
    if trials < 1:
        raise ValueError(f'trials: must be >= 1, got {trials}')
    if int(seed) < 0:
        raise ValueError(f'seed: must be >= 0, got {seed}')
    seeds = int(seed) + np.arange(trials)
    t = scenario.duration * np.arange(trials) / trials
    tg_rows, st_rows, seed_rows = [], [], []
    for m in range(trials):
        st_m = [station_position(s, t[m]) for s in scenario.stations]   # once per trial
        for tg in realize_targets(scenario, int(seeds[m])):
            tg_rows.append(target_position(tg, t[m]))
            st_rows.append(st_m)
            seed_rows.append(seeds[m])
    g = [s.sigma_growth for s in scenario.stations]
    if range_ref is not None:
        from .simulation import SigmaGrowth
        if not (np.isfinite(range_ref) and range_ref >= 0):
            raise ValueError(f'range_ref: must be >= 0 m, got {range_ref}')
        g = [None if range_ref == 0 else
             (SigmaGrowth(float(range_ref), x.min_factor, x.max_factor, x.report) if x
              else SigmaGrowth(float(range_ref))) for x in g]
    return Trials(
        stations=np.asarray(st_rows, dtype=float), targets=np.asarray(tg_rows, dtype=float),
        has_elevation=np.array([s.dims == 2 for s in scenario.stations]),
        range_ref=np.array([x.range_ref if x else np.nan for x in g], dtype=float),
        min_factor=np.array([x.min_factor if x else 1.0 for x in g], dtype=float),
        max_factor=np.array([x.max_factor if x else 1.0 for x in g], dtype=float),
        report_actual=np.array([bool(x and x.report == 'actual') for x in g]),
        station_ids=[s.id for s in scenario.stations], trial_seed=np.asarray(seed_rows))


def _deg(label, rad):
    return float(label) if np.isfinite(label) else float(np.degrees(rad))


def nees_values(e, P):
    """Normalized estimation error squared eᵀP⁻¹e of each fix and its degrees of freedom.

    ``e`` (M, 3) m, ``P`` (M, 3, 3) m². A horizontal fix with an exactly stated altitude
    (core.horizontal, σ_z = 0: P_zz = 0 and no x-y/z covariance) has 2 degrees of freedom,
    the xy block (its z error is the altitude assumption's, not the estimator's); every other
    fix 3. Returns (nees (M,), dof (M,) int), NaN where the block is not invertible.
    """
    e = np.asarray(e, dtype=float).reshape(-1, 3)
    P = np.asarray(P, dtype=float).reshape(-1, 3, 3)
    flat = (P[:, 2, 2] == 0.0) & (P[:, 0, 2] == 0.0) & (P[:, 1, 2] == 0.0)
    out = np.full(e.shape[0], np.nan)
    if np.any(~flat):
        Pi = safe_inverse(P[~flat])
        out[~flat] = np.einsum('mi,mij,mj->m', e[~flat], Pi, e[~flat])
    if np.any(flat):
        from .horizontal_crlb import inverse2
        Pi, ok = inverse2(P[flat][:, :2, :2])
        v = np.einsum('mi,mij,mj->m', e[flat][:, :2], np.where(ok[:, None, None], Pi, 0.0),
                      e[flat][:, :2])
        out[flat] = np.where(ok, v, np.nan)
    return out, np.where(flat, 2, 3)


def error_statistics(estimator, sweep, level, truth, result, crlb_cov, elapsed_s):
    """:class:`Stats` of one batched run (see the module docstring for the definitions).

    ``truth`` (M, 3) m; ``result`` a FixResult; ``crlb_cov`` (M, 3, 3) m² at the true
    targets; ``elapsed_s`` wall time of the estimator call. Trials whose estimate is not
    converged or not finite are excluded from RMSE, bias and NEES (and counted in the
    convergence rate); NEES also skips trials whose covariance is not invertible. A statistic
    with no trial to average is NaN (never a fake number).
    """
    truth = np.asarray(truth, dtype=float)
    M = truth.shape[0]
    est = np.asarray(result.position, dtype=float)
    conv = np.asarray(result.converged, dtype=bool) & np.all(np.isfinite(est), axis=1)
    e = est[conv] - truth[conv]
    sq = np.einsum('mi,mi->m', e, e)
    n = int(conv.sum())
    rmse = float(np.sqrt(sq.mean())) if n else float('nan')
    bias_vec = e.mean(axis=0) if n else np.full(3, np.nan)
    tr_all = np.trace(crlb_cov, axis1=-2, axis2=-1)
    tr = tr_all[np.isfinite(tr_all)]
    bound = float(np.sqrt(tr.mean())) if tr.size else float('nan')
    # The ratio compares like with like: RMSE and bound over the same trials, the converged
    # ones with a finite bound (when few converge, they are the easy targets, and the bound
    # of every trial is larger).
    tr_conv = tr_all[conv]
    fb = np.isfinite(tr_conv)
    ratio = (float(np.sqrt(sq[fb].mean() / tr_conv[fb].mean()))
             if fb.any() and tr_conv[fb].mean() > 0 else float('nan'))
    P = np.asarray(result.position_covariance, dtype=float)[conv]
    nees = nees_values(e, P)[0] if n else np.zeros(0)
    nees = nees[np.isfinite(nees)]
    rmse_se = (float(sq.std(ddof=1) / (2.0 * rmse * np.sqrt(n)))
               if n > 1 and rmse > 0 else float('nan'))
    tail = _tail_statistics(truth, est, result, M)
    nees_se = float(nees.std(ddof=1) / np.sqrt(nees.size)) if nees.size > 1 else float('nan')
    return Stats(
        estimator=estimator, sweep=sweep,
        sigma_az_deg=_deg(level.sigma_az_deg, level.sigma_az),
        sigma_el_deg=_deg(level.sigma_el_deg, level.sigma_el),
        trials=M, converged=n, rmse=rmse, bias=float(np.linalg.norm(bias_vec)),
        crlb=bound,
        rmse_over_crlb=ratio,
        mean_nees=float(nees.mean()) if nees.size else float('nan'),
        convergence_rate=n / M if M else float('nan'),
        time_per_fix_s=float(elapsed_s) / M if M else float('nan'),
        median_error=float(np.sqrt(np.median(sq))) if n else float('nan'),
        p95_error=float(np.sqrt(np.percentile(sq, 95))) if n else float('nan'),
        rmse_se=rmse_se, nees_se=nees_se, **tail,
        bias_vector=[float(v) for v in bias_vec])


#: NEES above which an ``ok`` fix is confidently wrong: the χ²₃ quantile 0.9999 (a NEES
#: with 2 degrees of freedom, :func:`nees_values`, uses its χ²₂ quantile
#: :data:`CONFIDENT_WRONG_NEES_2D`).
CONFIDENT_WRONG_NEES = 21.107513
CONFIDENT_WRONG_NEES_2D = 18.420681


def _tail_statistics(truth, est, result, M):
    """rmse_all, status fractions and the ``ok`` fixes' RMSE, NEES and confident-wrong share."""
    nan = float('nan')
    status = np.asarray(result.status).astype(str)
    finite = np.all(np.isfinite(est), axis=1)
    e_all = est[finite] - truth[finite]
    ok = finite & (status == 'ok')
    e = est[ok] - truth[ok]
    nees, dof = (nees_values(e, np.asarray(result.position_covariance, dtype=float)[ok])
                 if ok.any() else (np.zeros(0), np.zeros(0, dtype=int)))
    finite_nees = np.isfinite(nees)
    nees, dof = nees[finite_nees], dof[finite_nees]
    wrong = nees > np.where(dof == 2, CONFIDENT_WRONG_NEES_2D, CONFIDENT_WRONG_NEES)
    n_ok, n_lc = int(ok.sum()), int(np.count_nonzero(status == 'low_confidence'))
    return dict(
        rmse_all=float(np.sqrt(np.mean(np.sum(e_all ** 2, axis=1)))) if e_all.size else nan,
        ok_fraction=n_ok / M if M else nan,
        low_confidence_fraction=n_lc / M if M else nan,
        other_fraction=(M - n_ok - n_lc) / M if M else nan,
        rmse_ok=float(np.sqrt(np.mean(np.sum(e ** 2, axis=1)))) if n_ok else nan,
        nees_ok=float(nees.mean()) if nees.size else nan,
        confident_wrong_fraction=float(np.count_nonzero(wrong)) / n_ok if n_ok else nan)


def noisy_bearings(trials, sigma_az, sigma_el, rng, outliers=None):
    """Noisy bearings of :class:`Trials` with true σ (M, N) rad: a validated BearingSet.

    θ = θ* + σ_θ n, ψ = clip(ψ* + σ_ψ m, ±(π/2 − 1e-9)) (module docstring), n, m ~ N(0, 1)
    drawn from ``rng`` (azimuth block, then elevation block). ``outliers`` = (f, a, b):
    fraction and magnitude range (rad) of the outlier bearings, drawn after the noise so that
    the Gaussian part does not change with them. σ reported: as drawn (the caller replaces it).
    """
    from .bearings import BearingSet
    from .conventions import azimuth_elevation, wrap_angle
    from .simulation import MAX_ELEVATION
    M, N = trials.stations.shape[:2]
    az, el = azimuth_elevation(trials.targets[:, None, :] - trials.stations)
    az = az + sigma_az * rng.standard_normal((M, N))
    el = el + sigma_el * rng.standard_normal((M, N))
    if outliers is not None and outliers[0] > 0:
        f, a, b = (float(v) for v in outliers)
        hit = rng.random((M, N)) < f
        mag = rng.uniform(a, b, (2, M, N)) * np.where(rng.random((2, M, N)) < 0.5, -1.0, 1.0)
        az = az + hit * mag[0]
        el = el + hit * mag[1]
    el = np.clip(el, -MAX_ELEVATION, MAX_ELEVATION)
    el = np.where(trials.has_elevation[None, :], el, np.nan)
    return BearingSet.from_arrays(trials.stations, wrap_angle(az), el,
                                  np.broadcast_to(sigma_az, (M, N)),
                                  np.broadcast_to(sigma_el, (M, N)),
                                  require_elevation=bool(np.any(trials.has_elevation)))


def run_level(estimators, trials, level, rng, sweep='joint', options=None, locate=None,
              on_run=None, outliers=None, solve_options=None):
    """Evaluate ``estimators`` at one noise level on :class:`Trials`; returns [Stats].

    One noisy bearing batch (M = trials.M problems) is drawn from ``rng`` with the true
    σ_mi = σ · f_mi (:meth:`Trials.sigma_factor`) and shared by every estimator (common
    random numbers: differences between estimators are not blurred by different noise
    draws). The bearings report σ (or σ · f for stations with ``report: actual``). Each
    estimator is one vectorised ``locate(name, bearings, **options[name])`` call, timed with
    ``time.perf_counter``. The CRLB uses the true σ at the true targets. ``outliers``
    (fraction, min, max magnitude in rad) adds outlier bearings (:func:`noisy_bearings`).
    ``solve_options`` (``dimension``, ``target_altitude`` (m, scalar or (M,)),
    ``target_altitude_sigma``, ``use_elevations``; core.horizontal) run every estimator
    through core.registry.solve with them; problems solved horizontally are measured against
    the bound of the horizontal solve (core.horizontal_crlb: the stated altitude as a prior
    N(z₀, σ_z²) at the true target) and their NEES has 2 degrees of freedom when σ_z = 0
    (:func:`nees_values`). ``target_altitude`` :data:`TRUTH` states each problem's altitude
    as a measurement of the true one: z₀_m = z_m + σ_z·u_m, u_m ~ N(0, 1) drawn from ``rng``
    after the bearing noise (so the bearings do not depend on σ_z), which is what the bound
    with the prior N(z₀, σ_z²) and a 3-dof NEES assume; z₀ = z exactly when σ_z = 0.
    A target on a station or straight above it (:meth:`Trials.no_azimuth`) has no azimuth
    from that station: as in the simulator its bearing is not made, and the problem is
    solved, and bounded, with the other stations' bearings (problems grouped by the
    bearings they have; fewer than two: no fix, ``degenerate_geometry``, infinite bound).
    """
    if locate is None:
        if solve_options:
            from .registry import solve as locate
        else:
            from .estimators import locate
    options = options or {}
    solve_options = dict(solve_options or {})
    f = trials.sigma_factor()
    saz, sel = level.sigma_az * f, level.sigma_el * f
    noisy = noisy_bearings(trials, saz, sel, rng, outliers)
    rep = trials.report_actual[None, :]
    noisy.sigma_az = np.where(rep, saz, level.sigma_az)
    noisy.sigma_el = np.where(noisy.has_elevation, np.where(rep, sel, level.sigma_el), np.nan)
    if isinstance(solve_options.get('target_altitude'), str):
        solve_options['target_altitude'] = stated_altitudes(
            trials, solve_options['target_altitude'],
            solve_options.get('target_altitude_sigma', 0.0), rng)
    groups = _observed_groups(trials)
    parts = []                      # (problems, stations kept, bearings, bound, solve options)
    for idx, keep in groups:
        if np.count_nonzero(keep) < 2:      # one bearing or none: no fix, no bound
            parts.append((idx, keep, None, np.full((idx.size, 3, 3), np.inf), None))
            continue
        whole = idx.size == trials.M and bool(np.all(keep))
        tr = trials if whole else trials.take(idx, keep)
        nb = noisy if whole else _take_bearings(noisy, idx, keep)
        so = solve_options if whole else _take_solve_options(solve_options, idx, trials.M)
        s_az, s_el = (saz, sel) if whole else (saz[idx][:, keep], sel[idx][:, keep])
        bound = crlb_matrix(tr.targets, tr.stations, s_az, s_el, tr.has_elevation)
        if so.get('target_altitude') is not None:
            bound = _horizontal_bound(bound, tr, nb, s_az, s_el, so)
        parts.append((idx, keep, nb, bound, so))
    bound = np.empty((trials.M, 3, 3))
    for idx, _, _, b, _ in parts:
        bound[idx] = b
    out = []
    for name in estimators:
        t0 = time.perf_counter()
        results = [(idx, None if nb is None else locate(name, nb, **options.get(name, {}), **so))
                   for idx, _, nb, _, so in parts]
        res = (results[0][1] if len(results) == 1 and results[0][1] is not None
               else _merge_results(name, results, trials.M))
        dt = time.perf_counter() - t0
        out.append(error_statistics(name, sweep, level, trials.targets, res, bound, dt))
        if on_run is not None:
            on_run()
    return out


def _observed_groups(trials):
    """[(problem indices, (N,) bool stations that observe them)]: the problems grouped by
    which bearings exist (:meth:`Trials.no_azimuth` removes a station's bearing). One group
    of every problem and station when every target is off the stations' vertical axes."""
    seen = ~trials.no_azimuth()
    if np.all(seen):
        return [(np.arange(trials.M), np.ones(seen.shape[1], dtype=bool))]
    patterns, inverse = np.unique(seen, axis=0, return_inverse=True)
    inverse = np.asarray(inverse).reshape(-1)
    return [(np.flatnonzero(inverse == k), patterns[k]) for k in range(patterns.shape[0])]


def _take_bearings(bearings, idx, keep):
    """The BearingSet of problems ``idx`` and stations ``keep`` (already validated)."""
    from .bearings import BearingSet
    return BearingSet(bearings.positions[idx][:, keep], bearings.azimuth[idx][:, keep],
                      bearings.elevation[idx][:, keep], bearings.sigma_az[idx][:, keep],
                      bearings.sigma_el[idx][:, keep],
                      None if bearings.stations is None else
                      [s for s, k in zip(bearings.stations, keep) if k])


def _take_solve_options(solve_options, idx, M):
    """``solve_options`` of problems ``idx``: per-problem (M,) arrays cut to them."""
    out = {}
    for k, v in solve_options.items():
        a = np.asarray(v) if not isinstance(v, str) else None
        out[k] = a[idx] if a is not None and a.ndim == 1 and a.shape[0] == M else v
    return out


def _merge_results(method, results, M):
    """One FixResult of M problems from [(problem indices, FixResult or None)]: position,
    covariance, iterations, converged and status (what :func:`error_statistics` reads); a
    group with fewer than two bearings (None) has no fix: NaN, ``degenerate_geometry``."""
    from .fix import FixResult, STATUS_DEGENERATE
    pos = np.full((M, 3), np.nan)
    cov = np.full((M, 3, 3), np.inf)
    its = np.zeros(M, dtype=int)
    conv = np.zeros(M, dtype=bool)
    status = np.full(M, STATUS_DEGENERATE, dtype=object)
    for idx, r in results:
        if r is None:
            continue
        pos[idx] = r.position
        cov[idx] = r.position_covariance
        its[idx] = r.iterations
        conv[idx] = r.converged
        status[idx] = np.asarray(r.status).astype(str)
    return FixResult(pos, cov, its, conv, status.astype(str), method)


#: ``solve_options['target_altitude']`` of :func:`run_level` that states each problem's true
#: altitude, with the error N(0, σ_z²) of ``target_altitude_sigma`` (:func:`stated_altitudes`).
TRUTH = 'truth'


def stated_altitudes(trials, which, sigma_z, rng):
    """The altitudes (M,), m, stated to the horizontal solve when ``which`` is :data:`TRUTH`.

    z₀_m = z_m + σ_z·u_m with z_m the true target altitude of problem m and u_m ~ N(0, 1)
    from ``rng`` (no draw when σ_z = 0: z₀ = z): the stated altitude is a measurement of the
    truth with the σ the solve is told, as the prior N(z₀, σ_z²) of core.horizontal_crlb
    assumes. ``sigma_z`` m, scalar or (M,), finite and >= 0; ValueError naming
    target_altitude / target_altitude_sigma otherwise.
    """
    if which != TRUTH:
        raise ValueError(f'target_altitude: a number (m), an (M,) array or {TRUTH!r}, '
                         f'got {which!r}')
    sz = np.broadcast_to(np.asarray(sigma_z, dtype=float), (trials.M,))
    if not np.all(np.isfinite(sz)) or np.any(sz < 0):
        raise ValueError('target_altitude_sigma: must be finite and >= 0 m')
    z = trials.targets[:, 2].copy()
    if np.any(sz > 0):
        z = z + sz * rng.standard_normal(trials.M)
    return z


def _horizontal_bound(bound, trials, noisy, saz, sel, solve_options):
    """``bound`` with the problems the dimension selection solves horizontally replaced by
    the horizontal CRLB (core.horizontal_crlb) at the true target (its z = the truth's)."""
    from .horizontal import select_dimension, SOLVE_HORIZONTAL
    from .horizontal_crlb import horizontal_crlb
    horiz = select_dimension(noisy, solve_options.get('dimension', 'auto'),
                             solve_options.get('use_elevations', True)) == SOLVE_HORIZONTAL
    if not np.any(horiz):
        return bound
    M = trials.M
    sz = np.broadcast_to(np.asarray(solve_options.get('target_altitude_sigma', 0.0),
                                    dtype=float), (M,))
    has_el = trials.has_elevation[None, :] & bool(solve_options.get('use_elevations', True))
    has_el = np.broadcast_to(has_el, saz.shape)
    idx = np.flatnonzero(horiz)
    out = np.array(bound, dtype=float)
    out[idx] = horizontal_crlb(trials.targets[idx], trials.stations[idx], saz[idx], sel[idx],
                               has_el[idx], sz[idx])
    return out


def level_rng(seed, sweep, index):
    """Independent, reproducible generator for noise level ``index`` of ``sweep``.

    numpy SeedSequence(seed, spawn_key=(sweep number, index)): results do not depend on which
    other sweeps, levels or estimators are run.
    """
    return np.random.default_rng(np.random.SeedSequence(
        int(seed), spawn_key=(SWEEPS.index(sweep) + 1, int(index))))


def targets_rng(seed):
    """Reproducible generator for target sampling (spawn key 0, distinct from the noise)."""
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(0,)))


def evaluate(estimators, trials, sigmas_deg, sweeps=('joint',), seed=0, fixed_sigma_deg=0.5,
             options=None, progress=None, locate=None, outliers=None, solve_options=None):
    """Full Monte Carlo study: every sweep × σ level × estimator; returns a list of Stats.

    ``trials`` (:class:`Trials`) are used for every level. ``progress(done, total)`` is
    called after each estimator run with the number of runs done and to do.
    Deterministic for a given ``seed`` (noise of level k of a sweep from
    :func:`level_rng`). The σ of the sweep replace the scenario's per-station σ_ref.
    ``solve_options``: the dimension selection of every estimator (:func:`run_level`).
    """
    if not estimators:
        raise ValueError('estimators: need at least one')
    for sw in sweeps:
        if sw not in SWEEPS:
            raise ValueError(f'sweep: must be one of {SWEEPS}, got {sw!r}')
    all_levels = [(sw, k, lv) for sw in sweeps
                  for k, lv in enumerate(noise_levels(sigmas_deg, sw, fixed_sigma_deg))]
    total = len(all_levels) * len(estimators)
    rows, done = [], [0]

    def on_run():
        done[0] += 1
        if progress is not None:
            progress(done[0], total)

    for sw, k, lv in all_levels:
        rows.extend(run_level(estimators, trials, lv, level_rng(seed, sw, k), sw, options,
                              locate, on_run, outliers, solve_options))
    return rows


def findings(rows):
    """Summaries used by the report (docs/benchmarks.md "Evaluation") and the tests.

    * ``ranking``: for each sweep and swept σ, estimator names sorted by RMSE (best first).
    * ``azimuth_vs_elevation``: for each σ present in both single-angle sweeps and each
      estimator (and ``CRLB``), RMSE with the azimuth σ varied / RMSE with the elevation σ
      varied (> 1: azimuth error costs more). Zong & Cui (2015), sec. 3.2, conclusion 2)
      compares exactly these two curves (its figs. 3-4).
    """
    def key(r):
        return r.sigma_el_deg if r.sweep == 'elevation' else r.sigma_az_deg

    ranking = {}
    for r in rows:
        ranking.setdefault(f'{r.sweep}@{key(r):g}', []).append((r.rmse, r.estimator))

    def order(t):
        return (np.nan_to_num(t[0], nan=np.inf), t[1])

    ranking = {k: [n for _, n in sorted(v, key=order)] for k, v in ranking.items()}
    by = {(r.sweep, key(r), r.estimator): r for r in rows}
    ratios = []
    for (sw, x, est), r in sorted(by.items(), key=lambda kv: (kv[0][1], kv[0][2])):
        if sw != 'azimuth' or ('elevation', x, est) not in by:
            continue
        e = by[('elevation', x, est)]
        ratios.append({'sigma_deg': x, 'estimator': est, 'rmse_azimuth': r.rmse,
                       'rmse_elevation': e.rmse, 'ratio': r.rmse / e.rmse})
        if est == rows[0].estimator:
            ratios.append({'sigma_deg': x, 'estimator': 'CRLB', 'rmse_azimuth': r.crlb,
                           'rmse_elevation': e.crlb, 'ratio': r.crlb / e.crlb})
    return {'ranking': ranking, 'azimuth_vs_elevation': ratios}


def track_errors(truth, estimate, covariance=None):
    """Error statistics of a sequence of fixes against the truth at the same times.

    ``truth``, ``estimate`` (K, 3) m; ``covariance`` (K, 3, 3) m² or None. Returns a dict:
    n, rmse = sqrt(mean |e|²), mean_error, median_error, p95_error, max_error (|e|, m),
    bias (the mean error vector, m), mean_nees = mean eᵀP⁻¹e and nees_dof, its expectation
    for an honest covariance (3; 2 for horizontal fixes with an exactly stated altitude,
    :func:`nees_values`; NaN without covariances). Non-finite rows are ignored; with no rows
    every value is NaN (n = 0).
    """
    t = np.asarray(truth, dtype=float).reshape(-1, 3)
    x = np.asarray(estimate, dtype=float).reshape(-1, 3)
    ok = np.all(np.isfinite(t), axis=1) & np.all(np.isfinite(x), axis=1)
    e = x[ok] - t[ok]
    n = int(ok.sum())
    nan = float('nan')
    if n == 0:
        return {'n': 0, 'rmse': nan, 'mean_error': nan, 'median_error': nan,
                'p95_error': nan, 'max_error': nan, 'bias': [nan] * 3, 'mean_nees': nan,
                'nees_dof': nan}
    d = np.linalg.norm(e, axis=1)
    nees, dof = nan, nan
    if covariance is not None:
        v, k = nees_values(e, np.asarray(covariance, dtype=float).reshape(-1, 3, 3)[ok])
        good = np.isfinite(v)
        if np.any(good):
            nees, dof = float(v[good].mean()), float(k[good].mean())
    return {'n': n, 'rmse': float(np.sqrt(np.mean(d ** 2))), 'mean_error': float(d.mean()),
            'median_error': float(np.median(d)), 'p95_error': float(np.percentile(d, 95)),
            'max_error': float(d.max()), 'bias': [float(v) for v in e.mean(axis=0)],
            'mean_nees': nees, 'nees_dof': dof}


def track_crlb_statistics(estimates, covariances, truth, station_positions, sigma_az,
                          sigma_el):
    """Per-fix error, predicted σ and Cramér-Rao bound along a true track, and their summary.

    Maths: error_k = |x̂_k − x_k| (m); predicted σ_k = sqrt(tr P_k) (m, the RMS 3D error the
    fix's covariance predicts); crlb_k = sqrt(tr CRLB(x_k)) (m, Zong & Cui (2015) eqs. (6)-(8),
    :func:`~.crlb.crlb`, at the true position with the stations and their σ). Summary:
    RMSE = sqrt(mean error²), CRLB RMS = sqrt(mean tr CRLB), ratio = RMSE / CRLB RMS
    (1 = efficient) and mean_predicted = sqrt(mean predicted σ²).

    Args:
        estimates, truth: (K, 3) ENU positions, m. covariances: (K, 3, 3) fix covariances, m².
        station_positions: (N, 3) ENU, m. sigma_az: (N,) azimuth σ, rad; sigma_el: (N,)
            elevation σ, rad, NaN for an azimuth-only station.

    Returns a dict with arrays 'error', 'predicted', 'crlb' (K,) and floats 'rmse',
    'crlb_rms', 'ratio', 'mean_predicted'.
    """
    x = np.asarray(truth, dtype=float)
    e = np.linalg.norm(np.asarray(estimates, dtype=float) - x, axis=1)
    pred = np.sqrt(np.trace(np.asarray(covariances, dtype=float), axis1=1, axis2=2))
    C = crlb_matrix(x, np.asarray(station_positions, dtype=float), sigma_az, sigma_el)
    tr = np.trace(C, axis1=1, axis2=2)
    rmse = float(np.sqrt(np.mean(e ** 2)))
    crlb_rms = float(np.sqrt(np.mean(tr)))
    return {'error': e, 'predicted': pred, 'crlb': np.sqrt(tr), 'rmse': rmse,
            'crlb_rms': crlb_rms, 'ratio': rmse / crlb_rms,
            'mean_predicted': float(np.sqrt(np.mean(pred ** 2)))}
