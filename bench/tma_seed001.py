"""Lin et al., section 4.2 Monte Carlo: TMA with a speed prior, ple / ctls / ctls6 / mle / CRLB.

Scenario (config/scenarios/seed001.yaml, Lin et al. sec. 4.2.1): observer from the origin at
(0, 250, 0) m/s, target from (100, 100, 10) km at (−340, 80, −1.21) m/s, azimuth and elevation
every 0.2 s for 100 s (501 bearings), prior relative speed v_c = 380 m/s (the true relative
speed is 380.13 m/s: the paper's prior is 0.035 % off, far below every error here).

Experiments (each ``--runs`` Monte Carlo runs, 200 as in the paper):
  1. σ = 0.1°, 0.15°, 0.2°, 0.25°, 0.3° (azimuth and elevation), start (100, 100, 10) km;
  2. start (100, 100, 5) km × 0.5, 0.75, ..., 2.0 at σ = 0.1° (Lin et al. sec. 4.2.2).

Metrics (Lin et al. sec. 4.1; its formulas are lost, these are the usual ones):
  RDE(t) = sqrt(mean_m (r̂_m(t) − r(t))²) / r(t)  (%), r the target-observer distance;
  APE(t) = sqrt(mean_m |p̂_m(t) − p(t)|²)          (km), p the target position;
at t = 100 s, and averaged over the U = 251 epochs t = 50, 50.2, ..., 100 s, each estimate
using all bearings up to t (the running estimate). CRLB: the constrained CRLB (T15) at the
truth, sqrt(∇rᵀ C ∇r)/r and sqrt(trace C_pos). Runs whose estimate is unusable (status not
ok) are left out of that column and counted in ``fail`` (at 100 s).

The closed forms (ple, ctls, ctls6) of every prefix come from one cumulative sum of the
recursive terms (core.tma.prefix_sums, (T13)); mle runs once per epoch over all runs, warm
started from the previous epoch (from the best closed form at the first one).
A second table repeats ple/ctls in the setting the paper's derivation assumes (sec. 3.1:
the first bearing is exact); the paper's figures look like that setting.

Also prints the wall time of the fusion-node path (TmaAccumulator.add / estimate).

``--confidence`` instead measures the confidence tests (T19)-(T21) of core.tma.confidence
(docs/tma.md, "Confidence of a fix"): with the covariance on, per configuration (the two
experiments at t = 100 s and seed001 cut to 20-80 s) and estimator, the ``ok`` fixes with
the tests off (``max_nonlinearity`` and ``max_ml_distance`` inf; the residual χ² test stays,
0.1 % of correct fixes) and on (the defaults), their mean squared Mahalanobis position error
(NEES, 3 dof), how many exceed χ²₃(0.9999) = 21.1, and their RMSE; then the calibration of
the κ bound: windows 20-100 s × σ 0.1°-0.3° × start 0.5-2 × (100, 100, 10) km,
``--sweep-runs`` runs each, tma_ctls6 and tma_mle, the ``ok`` fixes at each candidate bound.

Run: .venv/bin/python bench/tma_seed001.py [--runs 200] [--seed 1] [--mle-stride 1]
     .venv/bin/python bench/tma_seed001.py --confidence [--runs 200] [--sweep-runs 600]
"""
import argparse
import os
import time

import numpy as np

from bearing_loc_ros.core.simulation import load_scenario, observation_times_ns
from bearing_loc_ros.core.tma import (estimate_from_sums, prefix_sums, simulate_tma,
                                      state_transform, STATUS_OK, tma_crlb, tma_mle)

HERE = os.path.dirname(os.path.abspath(__file__))
SCENARIO = os.path.join(HERE, '..', 'config', 'scenarios', 'seed001.yaml')
SPEED = 380.0
SIGMAS_DEG = (0.1, 0.15, 0.2, 0.25, 0.3)
SCALES = (0.5, 0.75, 1.0, 1.25, 1.5, 1.75, 2.0)
UNIT_START = np.array([100e3, 100e3, 5e3])
CLOSED = ('ple', 'ctls', 'ctls6')


def geometry():
    """Times (K,), observer positions (K, 3), target start (3,), velocity (3,) from the YAML."""
    sc = load_scenario(SCENARIO)
    st = sc.stations[0]
    t = observation_times_ns(st, sc.duration) / 1e9
    tg = sc.targets[0].trajectory
    return t, st.trajectory.position(t), tg.position(0.0), tg.velocity_at(0.0)


def closed_form_tracks(bs, t, k_eval, exact_first=False, truth_first=None):
    """Running ple/ctls/ctls6 estimates at prefixes ``k_eval``: positions and ranges."""
    if exact_first:
        bs.azimuth[:, 0], bs.elevation[:, 0] = truth_first
    sums = prefix_sums(bs, t)
    sub = type(sums)(**{f: getattr(sums, f)[:, k_eval] for f in sums.__dataclass_fields__})
    out = {}
    tau = (t[k_eval] - t[0])[None, :, None]
    v_o = sub.observer_velocity()
    for m in CLOSED:
        p0, v, status, _ = estimate_from_sums(sub, m, SPEED)
        pos = sub.o0 + p0 + (v + v_o) * tau
        rng = np.linalg.norm(p0 + v * tau, axis=-1)
        out[m] = (pos, rng, status == STATUS_OK)
    return out


def mle_track(bs, t, k_eval, stride):
    """Running mle at prefixes k_eval[::stride] (warm started) -> positions, ranges, ok."""
    ks = k_eval[::stride]
    M = bs.M
    pos = np.full((M, len(ks), 3), np.nan)
    rng = np.full((M, len(ks)), np.nan)
    ok = np.zeros((M, len(ks)), bool)
    start = None
    for i, k in enumerate(ks):
        sub = bs.subset(slice(0, k + 1))
        res = tma_mle(sub, t[:k + 1], SPEED, start=start, covariance=False)
        good = res.ok
        pos[:, i], rng[:, i], ok[:, i] = res.position, res.range, good
        if np.all(good):
            start = (res.relative_position0, res.relative_velocity)
        else:
            start = None
    return ks, pos, rng, ok


def metrics(pos, rng, ok, p_true, r_true):
    """RDE (%) and APE (km) per epoch over the usable runs (pos (M, E, 3), rng (M, E))."""
    e2 = np.where(ok, np.sum((pos - p_true) ** 2, -1), np.nan)
    r2 = np.where(ok, (rng - r_true) ** 2, np.nan)
    with np.errstate(invalid='ignore'):
        rde = 100 * np.sqrt(np.nanmean(r2, 0)) / r_true
        ape = np.sqrt(np.nanmean(e2, 0)) / 1e3
    return rde, ape


def experiment(start, velocity, sigma, runs, seed, stride, t, obs):
    """All estimators and the CRLB for one configuration -> dict of rows."""
    k_eval = np.nonzero((t >= 50.0 - 1e-9) & (t <= 100.0 + 1e-9))[0]
    rng_ = np.random.default_rng(seed)
    bs, times = simulate_tma(t, start, velocity, obs, sigma, rng=rng_, M=runs)
    truth_bs, _ = simulate_tma(t, start, velocity, obs, sigma)
    tau = t[k_eval] - t[0]
    p_true = start + velocity * tau[:, None]
    rel0 = start - obs[0]
    v_o = (obs[-1] - obs[0]) / (t[-1] - t[0])
    r_true = np.linalg.norm(p_true - obs[k_eval], axis=-1)
    res = {}
    tracks = closed_form_tracks(bs, t, k_eval)
    for m, (pos, rng, ok) in tracks.items():
        res[m] = metrics(pos, rng, ok, p_true, r_true) + (int(np.sum(~ok[:, -1])),)
    ks, pos, rng, ok = mle_track(bs, t, k_eval, stride)
    sel = np.searchsorted(k_eval, ks)
    res['mle'] = metrics(pos, rng, ok, p_true[sel], r_true[sel]) + (int(np.sum(~ok[:, -1])),)
    first = (truth_bs.azimuth[0, 0], truth_bs.elevation[0, 0])
    paper = closed_form_tracks(bs, t, k_eval, exact_first=True, truth_first=first)
    for m in ('ple', 'ctls'):
        pos, rng, ok = paper[m]
        res[m + '*'] = metrics(pos, rng, ok, p_true, r_true) + (int(np.sum(~ok[:, -1])),)
    # CRLB at the truth for every prefix: prefix sums of the Fisher terms.
    from bearing_loc_ros.core.tma import constrained_crlb, constraint_gradient, fisher_terms
    J = np.cumsum(fisher_terms(rel0[None], (velocity - v_o)[None], (t - t[0])[None],
                               np.zeros((1, len(t), 3)), truth_bs.sigma_az,
                               truth_bs.sigma_el), axis=1)[0, k_eval]
    C = constrained_crlb(J, constraint_gradient(velocity - v_o, v_o))
    T = state_transform(tau)
    Cx = T @ C @ np.swapaxes(T, -1, -2)
    u = (p_true - obs[k_eval]) / r_true[:, None]
    rde_c = 100 * np.sqrt(np.einsum('ei,eij,ej->e', u, Cx[:, :3, :3], u)) / r_true
    ape_c = np.sqrt(np.trace(Cx[:, :3, :3], axis1=1, axis2=2)) / 1e3
    res['CRLB'] = (rde_c, ape_c, 0)
    # Sanity: the single-problem CRLB function agrees with the prefix computation at 100 s.
    C100 = tma_crlb(truth_bs, times[:1], rel0, velocity - v_o)[0]
    assert np.allclose(C100, C[-1], rtol=1e-6, atol=0), 'CRLB mismatch'
    return res


def table(title, label, keys, results, cols, which, eta=None):
    """Markdown table: rows = configurations, columns = estimators (RDE % | APE km).

    ``eta`` = (new, old): add the paper's improvement η = (old − new) / old (%, Lin et al.
    sec. 4.1) of RDE and APE.
    """
    head = ('| ' + label + ' | ' + ' | '.join(f'RDE {c}' for c in cols) + ' | '
            + ' | '.join(f'APE {c}' for c in cols))
    if eta:
        head += f' | η RDE {eta[0]} | η APE {eta[0]}'
    head += ' | fail ' + '/'.join(cols[:-1]) + ' |'
    ncol = 2 * len(cols) + 2 + (2 if eta else 0)
    lines = [f'**{title}**', '', head, '|' + '---:|' * ncol]
    for key, res in zip(keys, results):
        def val(c, i):
            return res[c][i][-1] if which == 'end' else np.mean(res[c][i])
        rde = [val(c, 0) for c in cols]
        ape = [val(c, 1) for c in cols]
        row = f'| {key} | ' + ' | '.join(f'{x:.2f}' for x in rde) + ' | ' \
            + ' | '.join(f'{x:.2f}' for x in ape)
        if eta:
            new, old = eta
            row += ' | ' + ' | '.join(f'{100 * (val(old, i) - val(new, i)) / val(old, i):.1f}'
                                      for i in (0, 1))
        fails = '/'.join(str(res[c][2]) for c in cols[:-1])
        lines.append(row + f' | {fails} |')
    return '\n'.join(lines)


def accumulator_timing(t, obs, start, velocity, window=60.0, repeat=20):
    """Wall time of TmaAccumulator.add (per bearing) and estimate (per call), milliseconds."""
    from bearing_loc_ros.core.tma import TmaAccumulator
    bs, _ = simulate_tma(t, start, velocity, obs, np.deg2rad(0.1),
                         rng=np.random.default_rng(0))
    acc = TmaAccumulator(SPEED, window=window)
    t0 = time.perf_counter()
    for k in range(len(t)):
        acc.add(t[k], obs[k], bs.azimuth[0, k], bs.elevation[0, k], bs.sigma_az[0, k],
                bs.sigma_el[0, k])
    out = {'add': 1e3 * (time.perf_counter() - t0) / len(t)}
    for m in ('ple', 'ctls', 'ctls6', 'mle'):
        t0 = time.perf_counter()
        for _ in range(repeat):
            acc.estimate('tma_' + m)
        out[m] = 1e3 * (time.perf_counter() - t0) / repeat
    return len(acc), out


def _nees(res, truth):
    """Squared Mahalanobis position error (M,) under the reported covariance (NaN if none)."""
    e = res.position - truth
    out = np.full(len(e), np.nan)
    fin = np.all(np.isfinite(e), -1) & np.all(np.isfinite(res.covariance[:, :3, :3]),
                                              axis=(1, 2))
    out[fin] = np.einsum('mi,mi->m', e[fin], np.linalg.solve(res.covariance[fin, :3, :3],
                                                             e[fin][..., None])[..., 0])
    return out


def _cut(t, obs, seconds):
    k = int(np.searchsorted(t, t[0] + seconds + 1e-9))
    return t[:k], obs[:k]


def confidence_tables(t, obs, start0, vel, runs, sweep_runs, seed):
    """``--confidence``: the ok fixes with the confidence tests off and on (module doc)."""
    from bearing_loc_ros.core.tma import tma
    from bearing_loc_ros.core.tma.confidence import range_nonlinearity
    off = {'max_nonlinearity': np.inf, 'max_ml_distance': np.inf}
    configs = ([(100.0, s, 1.0, start0) for s in SIGMAS_DEG]
               + [(100.0, 0.1, k, k * UNIT_START) for k in SCALES]
               + [(w, 0.1, 1.0, start0) for w in (20.0, 40.0, 60.0, 80.0)])
    print('| window s | σ ° | start | estimator | ok off | ok on | mean NEES off | on | '
          '> 21.1 off | on | RMSE km off | on |')
    print('|' + '---:|' * 12)
    for i, (w, sig, k, start) in enumerate(configs):
        tw, ow = _cut(t, obs, w)
        bs, times = simulate_tma(tw, start, vel, ow, np.deg2rad(sig),
                                 rng=np.random.default_rng(seed + 100 + i), M=runs)
        truth = start + vel * (tw[-1] - tw[0])
        label = f'{k:g}×' if np.allclose(start, k * UNIT_START) else '1 (yaml)'
        for m in ('tma_ple', 'tma_ctls', 'tma_ctls6', 'tma_mle'):
            cols = []
            for opts in (off, {}):
                r = tma(m, bs, times, SPEED, **opts)
                ok = r.status == STATUS_OK
                n = _nees(r, truth)[ok]
                e2 = np.sum((r.position[ok] - truth) ** 2, -1)
                cols.append((ok.sum(), np.mean(n) if ok.any() else np.nan,
                             int(np.sum(n > 21.1)),
                             np.sqrt(np.mean(e2)) / 1e3 if ok.any() else np.nan))
            print(f'| {w:g} | {sig:g} | {label} | {m} | {cols[0][0]} | {cols[1][0]} | '
                  f'{cols[0][1]:.3g} | {cols[1][1]:.3g} | {cols[0][2]} | {cols[1][2]} | '
                  f'{cols[0][3]:.3g} | {cols[1][3]:.3g} |')
    # Calibration of max_nonlinearity: κ of every fix that passes (T19)-(T20).
    bounds = (0.1, 0.15, 0.2, 0.25, 0.3, 0.5, np.inf)
    kap, nees, cfg = [], [], []
    ci = 0
    for w in (20.0, 30.0, 40.0, 50.0, 60.0, 80.0, 100.0):
        tw, ow = _cut(t, obs, w)
        for sig in (0.1, 0.2, 0.3):
            for k in (0.5, 1.0, 2.0):
                start = k * np.array([100e3, 100e3, 10e3])
                bs, times = simulate_tma(tw, start, vel, ow, np.deg2rad(sig),
                                         rng=np.random.default_rng(seed + 1000 + ci),
                                         M=sweep_runs)
                truth = start + vel * (tw[-1] - tw[0])
                for m in ('tma_ctls6', 'tma_mle'):
                    r = tma(m, bs, times, SPEED, max_nonlinearity=np.inf)
                    ok = r.status == STATUS_OK
                    T = state_transform(-(times[ok, -1] - times[ok, 0]))
                    C = T @ r.covariance[ok] @ np.swapaxes(T, -1, -2)
                    kap.append(range_nonlinearity(r.relative_position0[ok],
                                                  r.relative_velocity[ok], C,
                                                  r.observer_velocity[ok]))
                    nees.append(_nees(r, truth)[ok])
                    cfg.append(np.full(ok.sum(), ci))
                ci += 1
    kap, nees, cfg = (np.concatenate(x) for x in (kap, nees, cfg))
    print(f'\nCalibration of max_nonlinearity ({ci} configurations × {sweep_runs} runs × '
          'tma_ctls6, tma_mle; fixes that pass the χ² and ML-distance tests)\n')
    print('| κ bound | ok fixes | mean NEES | > 21.1 | share | configurations with ≥ 60 ok: '
          'mean NEES from | to |')
    print('|---:|---:|---:|---:|---:|---:|---:|')
    for b in bounds:
        s = kap <= b
        per = [np.mean(nees[s & (cfg == c)]) for c in range(ci)
               if np.sum(s & (cfg == c)) >= 60]
        print(f'| {b:g} | {s.sum()} | {np.mean(nees[s]):.3g} | {np.sum(nees[s] > 21.1)} | '
              f'{100 * np.mean(nees[s] > 21.1):.3f} % | {min(per):.2f} | {max(per):.2f} |')


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--runs', type=int, default=200, help='Monte Carlo runs per configuration')
    ap.add_argument('--seed', type=int, default=1)
    ap.add_argument('--mle-stride', type=int, default=1,
                    help='evaluate mle every n-th epoch of 50-100 s (1 = all 251)')
    ap.add_argument('--confidence', action='store_true',
                    help='measure the confidence tests (T19)-(T21) instead (module doc)')
    ap.add_argument('--sweep-runs', type=int, default=600,
                    help='--confidence: runs per configuration of the κ calibration')
    args = ap.parse_args(argv)
    t, obs, start0, vel = geometry()
    if args.confidence:
        t0 = time.time()
        print(f'<!-- bench/tma_seed001.py --confidence --runs {args.runs} --seed {args.seed} '
              f'--sweep-runs {args.sweep_runs} -->')
        confidence_tables(t, obs, start0, vel, args.runs, args.sweep_runs, args.seed)
        print(f'\n{time.time() - t0:.1f} s')
        return
    t0 = time.time()
    cols = ('ple', 'ctls', 'ctls6', 'mle', 'CRLB')
    paper_cols = ('ple*', 'ctls*', 'ctls6', 'CRLB')
    res1 = [experiment(start0, vel, np.deg2rad(s), args.runs, args.seed + i, args.mle_stride,
                       t, obs) for i, s in enumerate(SIGMAS_DEG)]
    res2 = [experiment(k * UNIT_START, vel, np.deg2rad(0.1), args.runs, args.seed + 10 + i,
                       args.mle_stride, t, obs) for i, k in enumerate(SCALES)]
    elapsed = time.time() - t0
    k1 = [f'{s:g}°' for s in SIGMAS_DEG]
    k2 = [f'{k:g}×' for k in SCALES]
    print(f'<!-- bench/tma_seed001.py --runs {args.runs} --seed {args.seed} '
          f'--mle-stride {args.mle_stride}: {elapsed:.0f} s -->')
    for name, keys, res, label in (('Experiment 1 (σ sweep)', k1, res1, 'σ'),
                                   ('Experiment 2 (start × (100, 100, 5) km, σ = 0.1°)', k2,
                                    res2, 'start')):
        print()
        print(table(f'{name}, at t = 100 s', label, keys, res, cols, 'end'))
        print()
        print(table(f'{name}, mean over 50-100 s', label, keys, res, cols, 'mean'))
        print()
        print(table(f'{name}, first bearing exact (the paper\'s assumption), at t = 100 s',
                    label, keys, res, paper_cols, 'end', eta=('ctls*', 'ple*')))
        print()
        print(table(f'{name}, first bearing exact, mean over 50-100 s', label, keys, res,
                    paper_cols, 'mean', eta=('ctls*', 'ple*')))
    n, tm = accumulator_timing(t, obs, start0, vel)
    print(f'\nTmaAccumulator, 60 s window ({n} bearings): add {tm["add"]:.3f} ms per bearing; '
          'estimate (with covariance) ' + ', '.join(f'{m} {tm[m]:.2f} ms' for m in
                                                    ('ple', 'ctls', 'ctls6', 'mle')))
    print(f'\n{elapsed:.1f} s for {len(res1) + len(res2)} configurations x {args.runs} runs')


if __name__ == '__main__':
    main()
