"""Error against sigma at low SNR: RMSE, median, 95th percentile, CRLB, statuses, ok-fix NEES.

Two parts, both on core.evaluation (the numbers of ``bearing_loc evaluate``):

* the plot (default): the six stations with constant sigma
  (config/scenarios/six_station_const.yaml: ls, mle as the paper gives it and mle with
  option robust, its default) and with sigma growing with range (Zong & Cui 2015,
  config/scenarios/seed003.yaml: ls, mle and wmle as the papers give them and wmle with
  option robust, core.robust); one line per (estimator, sigma) with RMSE over every finite
  fix, median, p95, status fractions, the ok fixes' mean NEES and their confident-wrong
  share; draws docs/img/low_snr.png;
* ``--acceptance``: the acceptance table of the robust fixes: the Zong & Cui (2015) scenario
  (sigma grows with range; wmle with option robust against ls) in the joint, azimuth and
  elevation sweeps, the constant-sigma scenario (mle, the default estimator), 10 %
  outliers of +-(20-90) deg and the Wang, Zhang & Wu (2006) scenario (seed000.yaml) at 1.5
  and 4.5 mrad. For each row: ok share, mean NEES of the ok fixes with its chi2_3 99 % band
  3 +- 2.576 sqrt(6 / n_ok), and the share of ok fixes whose NEES exceeds the chi2_3 0.9999
  quantile (confidently wrong). After each scenario: the confidently wrong fixes pooled over
  its sweep points, k of n ok fixes, with the exact one-sided 95 % Poisson upper bound of
  their rate, chi2_{2(k+1)}(0.95) / (2 n): one sweep point of 2000 trials cannot show a rate
  below 1e-3 (with k = 0 the bound is 1.5e-3), the pooled count can. ``--seed`` draws other
  targets and noise (independent repetitions of the whole table).

    python bench/low_snr.py [--trials N] [--out docs/img/low_snr.png]
    python bench/low_snr.py --acceptance [--trials 2000] [--seed 0]
    python bench/low_snr.py --seeds 0,1,2,3,4 [--trials 2000]     # pooled over seeds
    python bench/low_snr.py --near-stations     # robust wmle fixes that end near a station
    python bench/low_snr.py --sigma-points --seeds 0,1,2,3,4    # a covariance not kept
    python bench/low_snr.py --line-posterior --seeds 0,1,2,3,4  # an estimate not kept
    python bench/low_snr.py --line-mse --seeds 0,1,2,3,4        # a covariance not kept
    python bench/low_snr.py --range-inflation 1.5 --seeds 0,1,2,3,4   # a covariance not kept

``--sigma-points``: the constant-sigma scenario's ok fixes of the default mle, their mean NEES
and confidently wrong count per sweep point, pooled over ``--seeds``, with the reported
covariance P (the CRLB at the fix) and with P averaged over the fix's own region along its
major axis v (three Gauss-Hermite points: 2/3 P + (P(x + sqrt(3) s v) + P(x - sqrt(3) s v))/6,
s^2 the major eigenvalue; the sigma-point spread of Julier & Uhlmann (1997) with n + kappa = 3).
``--line-posterior``: the same fixes moved to the mean of the likelihood along the line
x + t s v (a flat prior on t, v oriented away from the stations' centroid, t from -8 to 16 in
steps of 0.1), with that likelihood's variance along v in place of s^2 (the Bayesian
posterior moments of the range coordinate alone); the last column is the RMSE of the moved
fixes over that of the fixes as reported. ``--line-mse``: the fixes as reported, with the
second moment of that likelihood about them (its variance plus its mean offset squared) in
place of s^2. ``--range-inflation C``: the fixes as reported, s^2 multiplied by 1 + C s / r,
r the distance from the stations' centroid (s / r the fix's relative range uncertainty).
"""

import argparse
import math
import os

import numpy as np

from bearing_loc_ros.core import chisq
from bearing_loc_ros.core import evaluation as ev
from bearing_loc_ros.core.bearings import BearingSet
from bearing_loc_ros.core.estimators import locate
from bearing_loc_ros.core.simulation import load_scenario
from bearing_loc_ros.scenarios import resolve_scenario

CONST = 'config/scenarios/six_station_const.yaml'
RANGE_GROWN = 'config/scenarios/seed003.yaml'
#: Plot rows: (scenario, sigma values, [(label, estimator, options)]): each scenario with
#: the estimators whose noise model fits it.
PLOT = ((CONST, (0.5, 1, 2, 3, 4, 5),
         (('ls', 'ls', {}), ('mle (paper)', 'mle', {'robust': False}),
          ('mle (default, robust)', 'mle', {'robust': True}))),
        (RANGE_GROWN, (0.5, 1, 1.5, 2, 2.5, 3, 4, 5),
         (('ls', 'ls', {}), ('mle (paper)', 'mle', {'robust': False}),
          ('wmle (paper)', 'wmle', {'robust': False}),
          ('wmle robust', 'wmle', {'robust': True}))))
SEED000 = 'config/scenarios/seed000.yaml'


SEED = 0


def trials_of(path, n):
    sc = load_scenario(resolve_scenario(path))
    return sc, ev.trials_from_scenario(sc, n, SEED)


def run(name, opts, tr, sigmas, sweep='joint', outliers=None):
    """Stats of estimator ``name`` per sigma (deg) of ``sweep``: {sigma: Stats}."""
    ref = tr.reference_range()
    if name == 'wmle':
        opts = dict(opts, reference_range=ref or 1000.0)
    out = {}
    for k, lv in enumerate(ev.noise_levels(sigmas, sweep)):
        out[lv.x_deg] = ev.run_level([name], tr, lv, ev.level_rng(SEED, sweep, k), sweep,
                                     {name: opts}, locate, outliers=outliers)[0]
    return out


def wrong_count(r):
    """(confidently wrong ok fixes, ok fixes) of one Stats row."""
    n = round(r.ok_fraction * r.trials)
    return (round(r.confident_wrong_fraction * n) if n else 0), n


def pooled_tail(label, rows):
    """Print the confidently wrong ok fixes pooled over ``rows`` with a 95 % upper bound."""
    k = sum(wrong_count(r)[0] for r in rows)
    n = sum(wrong_count(r)[1] for r in rows)
    upper = float(chisq.ppf(0.95, 2 * (k + 1))) / (2.0 * n) if n else float('nan')
    print(f'{label}: confidently wrong {k} of {n} ok fixes = {1e2 * k / max(n, 1):.3f} %, '
          f'95 % upper bound {1e2 * upper:.3f} %')


def band(r):
    n = round(r.ok_fraction * r.trials)
    return 2.576 * math.sqrt(6.0 / n) if n else float('nan')


def verdict(r):
    if not r.ok_fraction:
        return ' (no ok fix)'
    ok_nees = abs(r.nees_ok - 3.0) <= band(r)
    ok_tail = r.confident_wrong_fraction < 1e-3
    return ('' if ok_nees else ' NEES') + ('' if ok_tail else ' TAIL')


def print_rows(sweep, sig, res, ls):
    """One table row per sigma: the estimator's results ``res`` against ``ls``."""
    for s in sig:
        r, q = res[s], ls[s]
        print(f'{sweep:10s} {s:4.1f}  {q.rmse_all:7.0f}  {r.rmse_all:9.0f}  '
              f'{r.rmse_all / r.crlb:5.2f}  {100 * r.ok_fraction:5.1f}   '
              f'{r.nees_ok:5.2f} (±{band(r):4.2f})   {100 * r.confident_wrong_fraction:6.3f}'
              f'  {"RMSE>ls" if r.rmse_all > q.rmse_all else ""}{verdict(r)}')


def acceptance(n):
    sig = [0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0]
    _, tr = trials_of(RANGE_GROWN, n)
    print(f'## {RANGE_GROWN}: wmle robust vs ls, {n} trials per sigma_ref')
    print('sweep      sigma  ls RMSE  wmle RMSE  /CRLB   ok %   NEES ok (band)      wrong %  fail')
    rows = []
    for sweep in ('joint', 'azimuth', 'elevation'):
        ls = run('ls', {}, tr, sig, sweep)
        wm = run('wmle', {'robust': True}, tr, sig, sweep)
        print_rows(sweep, sig, wm, ls)
        rows += list(wm.values())
    pooled_tail('pooled', rows)
    _, tr = trials_of(CONST, n)
    print(f'\n## {CONST}: mle (default, robust), {n} trials per sigma')
    print('sweep      sigma  ls RMSE   mle RMSE  /CRLB   ok %   NEES ok (band)      wrong %  fail')
    sig = [1.0, 2.0, 3.0, 4.0, 5.0]
    rows = []
    for sweep in ('joint', 'azimuth', 'elevation'):
        ls = run('ls', {}, tr, sig, sweep)
        ml = run('mle', {}, tr, sig, sweep)
        print_rows(sweep, sig, ml, ls)
        rows += list(ml.values())
    pooled_tail('pooled', rows)
    print(f'\n## {CONST}: 10 % outliers of ±(20-90) deg, mle (default, robust)')
    sig = [1.0, 2.5]
    clean = run('mle', {}, tr, sig)
    dirty = run('mle', {}, tr, sig, outliers=(0.1, math.radians(20), math.radians(90)))
    ls = run('ls', {}, tr, sig, outliers=(0.1, math.radians(20), math.radians(90)))
    for s in sig:
        r = dirty[s]
        c = clean[s].rmse_all
        print(f'sigma {s:3.1f}: ok RMSE {r.rmse_ok:6.1f} m vs outlier-free {c:6.1f} m '
              f'({r.rmse_ok / c:4.2f}x), ok {100 * r.ok_fraction:5.1f} %, '
              f'wrong {100 * r.confident_wrong_fraction:5.3f} %, ls RMSE {ls[s].rmse_all:6.0f}')
    _, tr = trials_of(SEED000, n)
    print(f'\n## {SEED000}: mle (default, robust) vs mle (paper)')
    sig = [math.degrees(1.5e-3), math.degrees(4.5e-3)]
    for label, opts in (('paper', {'robust': False}), ('default', {})):
        for s, r in run('mle', opts, tr, sig).items():
            print(f'{label:8s} {math.radians(s) * 1e3:3.1f} mrad: RMSE/CRLB '
                  f'{r.rmse_all / r.crlb:5.3f}, ok {100 * r.ok_fraction:5.1f} %, NEES ok '
                  f'{r.nees_ok:5.3f} (±{band(r):4.2f}), wrong '
                  f'{100 * r.confident_wrong_fraction:5.3f} %{verdict(r)}')


def pooled_acceptance(n, seeds):
    """The range-grown and constant-sigma tables pooled over independent ``seeds``.

    Per sweep point: RMSE over all fixes sqrt(mean over seeds of RMSE^2) (equal trial
    counts), the ok fixes' mean NEES weighted by their count with the band of the pooled
    count, and the confidently wrong ok fixes k of n with the exact 95 % Poisson upper bound
    of their rate (a per-point criterion of 0.1 % needs thousands of ok fixes to show).
    """
    global SEED
    cases = ((RANGE_GROWN, 'wmle', {'robust': True}, [0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0]),
             (CONST, 'mle', {}, [1.0, 2.0, 3.0, 4.0, 5.0]))
    for path, name, opts, sig in cases:
        rows = {}
        for seed in seeds:
            SEED = seed
            _, tr = trials_of(path, n)
            for sweep in ('joint', 'azimuth', 'elevation'):
                ls, est = run('ls', {}, tr, sig, sweep), run(name, opts, tr, sig, sweep)
                for s in sig:
                    rows.setdefault((sweep, s), []).append((ls[s], est[s]))
        print(f'\n## {path}: {name} {opts or ""} vs ls, seeds {",".join(map(str, seeds))}, '
              f'{n} trials each')
        print('sweep      sigma  ls RMSE  RMSE  ratio   ok fixes  NEES ok (band)   wrong k/n  '
              '95 % bound')
        for (sweep, s), pairs in rows.items():
            q = math.sqrt(np.mean([a.rmse_all ** 2 for a, _ in pairs]))
            r = math.sqrt(np.mean([b.rmse_all ** 2 for _, b in pairs]))
            kn = [wrong_count(b) for _, b in pairs]
            k, m = sum(x for x, _ in kn), sum(y for _, y in kn)
            nees = (sum(y * b.nees_ok for (_, y), (_, b) in zip(kn, pairs) if y) / m
                    if m else float('nan'))
            bd = 2.576 * math.sqrt(6.0 / m) if m else float('nan')
            up = float(chisq.ppf(0.95, 2 * (k + 1))) / (2.0 * m) if m else float('nan')
            flag = ('' if not m or abs(nees - 3.0) <= bd else ' NEES') + \
                ('' if not m or up < 1e-3 else ' TAIL?') + (' RMSE>ls' if r > q else '')
            print(f'{sweep:10s} {s:4.1f}  {q:7.0f}  {r:5.0f}  {r / q:5.3f}  {m:8d}  '
                  f'{nees:5.2f} (±{bd:4.2f})  {k:3d}/{m:<6d} {1e2 * up:6.3f} %{flag}')


def near_stations(n):
    """Robust ``wmle`` fixes on the Zong & Cui (2015) scenario that end within 1 % of the rms
    station range of a station (the range-grown likelihood has no lower bound there), with
    and without 10 % outliers of +-(20-90) deg, per sigma_ref, and their statuses."""
    from collections import Counter
    _, tr = trials_of(RANGE_GROWN, n)
    f = tr.sigma_factor()
    ref = tr.reference_range() or 1000.0
    print(f'## {RANGE_GROWN}: wmle robust, {n} trials, fixes within 1 % of the range of a '
          'station')
    for k, sd in enumerate((0.5, 1.0, 2.0, 3.0, 5.0, 10.0)):
        for out in (None, (0.1, math.radians(20), math.radians(90))):
            s = math.radians(sd)
            b = ev.noisy_bearings(tr, s * f, s * f, ev.level_rng(SEED, 'joint', k), out)
            b.sigma_az = np.full_like(b.sigma_az, s)
            b.sigma_el = np.where(b.has_elevation, s, np.nan)
            r = locate('wmle', b, robust=True, reference_range=ref)
            d = np.linalg.norm(r.position[:, None] - b.positions, axis=2)
            near = np.min(d, axis=1) < 0.01 * np.sqrt(np.mean(d * d, axis=1))
            print(f'sigma_ref {sd:4.1f} deg, {"10 % outliers" if out else "clean":13s}: '
                  f'{int(near.sum()):3d} {dict(Counter(map(str, r.status[near])))}')


def plot(a):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(len(PLOT), 3, figsize=(13, 4.0 * len(PLOT)), dpi=100)
    for row, (path, sig, runs) in zip(axes, PLOT):
        sc, tr = trials_of(path, a.trials)
        table = {}
        for label, name, opts in runs:
            for s, r in run(name, opts, tr, list(sig)).items():
                table[(label, s)] = r
                print(f'{sc.name:14s} {label:22s} {s:4.1f} deg  RMSE {r.rmse_all:8.1f}  '
                      f'CRLB {r.crlb:8.1f}  median {r.median_error:7.1f}  '
                      f'p95 {r.p95_error:8.1f}  ok {r.ok_fraction:.3f}  '
                      f'low {r.low_confidence_fraction:.3f}  NEESok {r.nees_ok:6.2f}  '
                      f'wrong {100 * r.confident_wrong_fraction:.3f} %')
        for ax, key, title in zip(row, ('rmse_all', 'median_error', 'p95_error'),
                                  ('RMSE (every fix)', 'median error (ok fixes)',
                                   '95th percentile (ok fixes)')):
            for label, _, _ in runs:
                ax.plot(sig, [getattr(table[(label, s)], key) for s in sig], marker='o',
                        label=label)
            ax.plot(sig, [table[('ls', s)].crlb for s in sig], 'k--', label='CRLB')
            ax.set_yscale('log')
            ax.set_xlabel('σ (deg)' if path == CONST else 'σ_ref at 1 km (deg)')
            ax.set_title(f'{sc.name}: {title}', fontsize=9)
            ax.grid(True, which='both', alpha=0.3)
        row[0].set_ylabel('error (m)')
        row[0].legend(fontsize=7)
    fig.suptitle(f'{a.trials} trials per σ; ok = passed the consistency checks', fontsize=9)
    fig.tight_layout()
    os.makedirs(os.path.dirname(a.out) or '.', exist_ok=True)
    fig.savefig(a.out)
    print(f'wrote {a.out}')


def ok_fixes_const(n, seeds):
    """Yield (sweep, sigma deg, bearings, X, P, targets) of the default mle's ok fixes in the
    constant-sigma scenario, every sweep point of every seed (the --acceptance trials)."""
    for seed in seeds:
        _, tr = trials_of_seed(CONST, n, seed)
        for sweep in ('joint', 'azimuth', 'elevation'):
            for k, lv in enumerate(ev.noise_levels([1.0, 2.0, 3.0, 4.0, 5.0], sweep)):
                got = []
                ev.run_level(['mle'], tr, lv, ev.level_rng(seed, sweep, k), sweep, {'mle': {}},
                             lambda name, b, **o: got.append((b, locate(name, b, **o)))
                             or got[-1][1])
                b, r = got[0]
                ok = r.status == 'ok'
                sub = BearingSet(b.positions[ok], b.azimuth[ok], b.elevation[ok],
                                 b.sigma_az[ok], b.sigma_el[ok])
                yield sweep, lv.x_deg, sub, r.position[ok], r.covariance[ok], tr.targets[ok]


def major_axes(X, P, positions):
    """(unit major axes v (M, 3) pointing away from the stations' centroid, s (M,) m)."""
    w, V = np.linalg.eigh(P)
    v = V[:, :, 2]
    v = np.where(((v * (X - positions.mean(axis=1))).sum(axis=1) < 0)[:, None], -v, v)
    return v, np.sqrt(w[:, 2])


def line_posterior(b, X, P):
    """(X', P') of the line-posterior variant (module docstring): the moments of the
    likelihood along the major axis, t on a grid of -8 s ... 16 s in steps of 0.1 s."""
    from bearing_loc_ros.core.conventions import wrap_angle
    v, s = major_axes(X, P, b.positions)
    t = np.linspace(-8.0, 16.0, 241)
    pts = X[:, None, :] + (t[None, :, None] * s[:, None, None]) * v[:, None, :]
    d = pts[:, :, None, :] - b.positions[:, None, :, :]
    ea = wrap_angle(b.azimuth[:, None, :] - np.arctan2(d[..., 1], d[..., 0]))
    ee = b.elevation[:, None, :] - np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1]))
    has = b.has_elevation[:, None, :]
    se = np.where(b.has_elevation, b.sigma_el, 1.0)[:, None, :]
    cost = ((ea / b.sigma_az[:, None, :]) ** 2 + np.where(has, (ee / se) ** 2, 0.0)).sum(-1)
    L = np.exp(-0.5 * (cost - cost.min(axis=1, keepdims=True)))
    L /= L.sum(axis=1, keepdims=True)
    mu = (L * t).sum(axis=1)
    var = (L * (t - mu[:, None]) ** 2).sum(axis=1)
    return (X + (mu * s)[:, None] * v,
            P + ((var - 1.0) * s * s)[:, None, None] * v[:, :, None] * v[:, None, :])


def covariance_variants(n, seeds, variant, c=None):
    """Print the ``--sigma-points``, ``--line-posterior``, ``--line-mse`` or
    ``--range-inflation`` (factor ``c``) table (module docstring)."""
    from bearing_loc_ros.core.crlb import crlb
    q = float(chisq.ppf(0.9999, 3))
    acc = {}
    for sweep, sig, b, X, P, tgt in ok_fixes_const(n, seeds):
        if variant == 'sigma points':
            v, s = major_axes(X, P, b.positions)
            step = math.sqrt(3.0) * v * s[:, None]
            sel = np.where(b.has_elevation, b.sigma_el, np.nan)
            at = [crlb(X + d, b.positions, b.sigma_az, sel, b.has_elevation)
                  for d in (step, -step)]
            X2, P2 = X, 2.0 / 3.0 * P + (at[0] + at[1]) / 6
        elif variant == 'range inflation':
            v, s = major_axes(X, P, b.positions)
            kappa = s / np.linalg.norm(X - b.positions.mean(axis=1), axis=1)
            X2, P2 = X, P + (c * kappa * s * s)[:, None, None] * v[:, :, None] * v[:, None, :]
        else:
            X2, P2 = line_posterior(b, X, P)
            if variant == 'line MSE':
                # The same likelihood's second moment about the fix itself: var + mean².
                v, s = major_axes(X, P, b.positions)
                mu = ((X2 - X) * v).sum(axis=1) / s
                X2, P2 = X, P2 + ((mu * s) ** 2)[:, None, None] * v[:, :, None] * v[:, None, :]
        for name, Xv, C in (('P', X, P), (variant, X2, P2)):
            e = Xv - tgt
            nees = np.einsum('mi,mij,mj->m', e, np.linalg.inv(C), e)
            a = acc.setdefault((sweep, sig, name), [0, 0.0, 0, 0.0])
            a[0] += nees.size
            a[1] += float(nees.sum())
            a[2] += int((nees > q).sum())
            a[3] += float((e * e).sum())
    print(f'## {CONST}: mle (default) ok fixes, seeds {",".join(map(str, seeds))}, {n} trials')
    print(f'sweep      sigma  ok fixes  NEES P (band)         wrong P   NEES {variant:13s} '
          'wrong  RMSE ratio')
    for (sweep, s, name), (m, total, k, se) in acc.items():
        if name != 'P':
            continue
        _, t2, k2, se2 = acc[(sweep, s, variant)]
        band = 2.576 * math.sqrt(6.0 / m)
        print(f'{sweep:10s} {s:4.1f}  {m:8d}  {total / m:5.3f} (±{band:4.2f})  {k:6d}   '
              f'{t2 / m:5.3f}              {k2:6d}  {math.sqrt(se2 / se):6.3f}')
    for name in ('P', variant):
        k = sum(v[2] for key, v in acc.items() if key[2] == name)
        m = sum(v[0] for key, v in acc.items() if key[2] == name)
        print(f'pooled, {name}: confidently wrong {k} of {m} ({1e2 * k / m:.4f} %)')


def trials_of_seed(path, n, seed):
    """(scenario, trials) of ``path`` with ``n`` trials drawn with ``seed``."""
    sc = load_scenario(resolve_scenario(path))
    return sc, ev.trials_from_scenario(sc, n, seed)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--trials', type=int, default=2000)
    ap.add_argument('--out', default='docs/img/low_snr.png')
    ap.add_argument('--acceptance', action='store_true',
                    help='print the acceptance table instead of drawing the plot')
    ap.add_argument('--seed', type=int, default=0,
                    help='seed of the targets and the noise (independent repetitions)')
    ap.add_argument('--seeds', default=None,
                    help='comma-separated seeds: the acceptance tables pooled over them')
    ap.add_argument('--near-stations', action='store_true',
                    help='count the robust wmle fixes that end near a station')
    ap.add_argument('--sigma-points', action='store_true',
                    help='constant sigma: the ok fixes\' NEES with the sigma-point covariance')
    ap.add_argument('--line-posterior', action='store_true',
                    help='constant sigma: the ok fixes\' NEES and RMSE with the moments of '
                         'the likelihood along the major axis')
    ap.add_argument('--line-mse', action='store_true',
                    help='constant sigma: the ok fixes kept, their major variance replaced by '
                         'the second moment of that likelihood about them')
    ap.add_argument('--range-inflation', type=float, default=None, metavar='C',
                    help='constant sigma: the ok fixes kept, their major variance s^2 '
                         'multiplied by 1 + C s / r (r the range from the stations\' centroid)')
    a = ap.parse_args()
    global SEED
    SEED = a.seed
    if a.sigma_points or a.line_posterior or a.line_mse or a.range_inflation is not None:
        covariance_variants(a.trials, [int(v) for v in (a.seeds or '0,1,2,3,4').split(',')],
                            'sigma points' if a.sigma_points else
                            'line posterior' if a.line_posterior else
                            'line MSE' if a.line_mse else 'range inflation',
                            a.range_inflation)
    elif a.near_stations:
        near_stations(a.trials)
    elif a.seeds:
        pooled_acceptance(a.trials, [int(v) for v in a.seeds.split(',')])
    elif a.acceptance:
        acceptance(a.trials)
    else:
        plot(a)
    return 0


if __name__ == '__main__':
    np.seterr(all='ignore')
    raise SystemExit(main())
