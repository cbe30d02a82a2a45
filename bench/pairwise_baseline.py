"""Horizontal solve against the pairwise-intersection baseline (the df-aggregator method).

Scenario: the three stations of Wang, Zhang & Wu section 4 (config/scenarios/seed000.yaml),
all azimuth only, the target at its position at scenario time 0 with its altitude known
(σ_z = 0). For each angle σ, ``--trials`` independent bearing sets (fixed seed) are solved by

* ``pairwise``: intersect the azimuth lines of every station pair in the horizontal plane
  (s_i + t_i u_i = s_j + t_j u_j, u = (cos θ, sin θ)) and average all the intersections;
  pairs whose lines are parallel (|sin(θ_j − θ_i)| < 1e-12) are skipped;
* the project's horizontal estimators (core/horizontal.py; ``mle`` is the default).

The table prints RMSE = sqrt(mean |e_xy|²) in metres and RMSE/CRLB, the CRLB being the
horizontal GDOP sqrt(trace of the 2 × 2 bound) at the true target (core/horizontal_crlb.py),
then the median horizontal error (m, and divided by the same bound) and the time per fix
(whole batch / trials; the first estimator run includes warm-up).

Run: .venv/bin/python bench/pairwise_baseline.py [--trials 20000] [--seed 11]
"""
import argparse
import os
import time

import numpy as np

from bearing_loc_ros.core.horizontal import DEFAULT_ESTIMATOR, locate_horizontal, \
    simulate_bearings
from bearing_loc_ros.core.horizontal_crlb import horizontal_crlb_for, horizontal_gdop
from bearing_loc_ros.core.simulation import load_scenario, station_position, target_position

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def pairwise_intersections(bearings):
    """Mean of every pairwise azimuth-line intersection, (M, 2) m; NaN if no pair crosses."""
    p = bearings.positions[..., :2]
    th = bearings.azimuth
    total = np.zeros((bearings.M, 2))
    count = np.zeros(bearings.M)
    for i in range(bearings.N):
        for j in range(i + 1, bearings.N):
            s = np.sin(th[:, j] - th[:, i])
            ok = np.abs(s) >= 1e-12
            d = p[:, j] - p[:, i]
            # t_i from the cross product of the two line equations.
            t = (d[:, 0] * np.sin(th[:, j]) - d[:, 1] * np.cos(th[:, j])) / np.where(ok, s, 1.0)
            x = p[:, i] + t[:, None] * np.stack([np.cos(th[:, i]), np.sin(th[:, i])], axis=1)
            total += np.where(ok[:, None], x, 0.0)
            count += ok
    with np.errstate(invalid='ignore', divide='ignore'):
        return total / count[:, None]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--trials', type=int, default=20000)
    ap.add_argument('--seed', type=int, default=11)
    ap.add_argument('--sigma-mrad', type=float, nargs='+', default=[1.5, 4.5])
    args = ap.parse_args()
    sc = load_scenario(os.path.join(REPO, 'config', 'scenarios', 'seed000.yaml'))
    st = np.array([station_position(s, 0.0) for s in sc.stations])
    tgt = np.asarray(target_position(sc.targets[0], 0.0), dtype=float)
    print(f'stations {st.tolist()} m; target {tgt.tolist()} m (altitude known); '
          f'{args.trials} trials, seed {args.seed}')
    methods = ['pairwise', 'ls', 'ctls', 'ctls_am', DEFAULT_ESTIMATOR]
    head = ' '.join(f'{m + " RMSE":>14} {"/CRLB":>6}' for m in methods)
    print(f'{"sigma mrad":>10} {"CRLB m":>9} {head}')
    for sig in args.sigma_mrad:
        rng = np.random.default_rng(args.seed)
        bs = simulate_bearings(np.tile(tgt, (args.trials, 1)), st, sig * 1e-3, rng=rng)
        bound = horizontal_gdop(horizontal_crlb_for(tgt[None], bs.problem(0))[0])
        row = f'{sig:10.2f} {bound:9.2f} '
        times, medians = [], []
        for m in methods:
            t0 = time.perf_counter()
            if m == 'pairwise':
                xy = pairwise_intersections(bs)
            else:
                xy = locate_horizontal(m, bs, tgt[2]).position[:, :2]
            times.append(time.perf_counter() - t0)
            err = np.hypot(*(xy - tgt[:2]).T)
            rmse = np.sqrt(np.nanmean(err ** 2))
            medians.append(np.nanmedian(err))
            row += f'{rmse:14.2f} {rmse / bound:6.3f} '
        print(row)
        print(f'{"median |e| m":>20} ' + ' '.join(f'{m:14.2f} {m / bound:6.3f}' for m in medians))
        per_fix = ' '.join(f'{1e6 * t / args.trials:11.2f} us/fix' for t in times)
        print(f'{"time per fix":>20} {per_fix}')


if __name__ == '__main__':
    main()
