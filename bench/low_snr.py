"""Error against sigma for each estimator at low SNR: RMSE, median, 95th percentile, CRLB.

Runs core.evaluation on a scenario (default: the six stations with constant sigma) for
ls, mle, wmle (paper) and mle/wmle with option robust (core.robust), prints one line per
(estimator, sigma) with RMSE over every finite fix, median, p95, status fractions, the ok
fixes' mean NEES and their confident-wrong share, and draws docs/img/low_snr.png.

    python bench/low_snr.py [--scenario S] [--trials N] [--sigma-deg 0.5,1,2,3,4,5]
"""

import argparse
import os

import numpy as np

from bearing_loc_ros.core import evaluation as ev
from bearing_loc_ros.core.simulation import load_scenario
from bearing_loc_ros.scenarios import resolve_scenario

RUNS = (('ls', 'ls', {}), ('mle', 'mle', {}), ('mle robust', 'mle', {'robust': True}),
        ('wmle', 'wmle', {}), ('wmle robust', 'wmle', {'robust': True}))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--scenario', default='config/scenarios/six_station_const.yaml')
    ap.add_argument('--trials', type=int, default=2000)
    ap.add_argument('--sigma-deg', default='0.5,1,2,3,4,5')
    ap.add_argument('--out', default='docs/img/low_snr.png')
    a = ap.parse_args()
    sc = load_scenario(resolve_scenario(a.scenario))
    tr = ev.trials_from_scenario(sc, a.trials, 0)
    ref = tr.reference_range()
    sig = [float(x) for x in a.sigma_deg.split(',')]
    from bearing_loc_ros.core.estimators import locate
    table = {}
    for label, name, opts in RUNS:
        if name == 'wmle':
            opts = dict(opts, reference_range=ref or 1000.0)
        for k, lv in enumerate(ev.noise_levels(sig, 'joint')):
            r = ev.run_level([name], tr, lv, ev.level_rng(0, 'joint', k), 'joint',
                             {name: opts}, locate)[0]
            table[(label, lv.x_deg)] = r
            print(f'{label:12s} {lv.x_deg:4.1f} deg  RMSE {r.rmse_all:8.1f}  CRLB {r.crlb:8.1f}  '
                  f'median {r.median_error:7.1f}  p95 {r.p95_error:8.1f}  ok {r.ok_fraction:.3f}'
                  f'  low {r.low_confidence_fraction:.3f}  NEESok {r.nees_ok:6.2f}  '
                  f'wrong {100 * r.confident_wrong_fraction:.3f} %  '
                  f'{1e6 * r.time_per_fix_s:.1f} us/fix')
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2), dpi=100, sharey=True)
    for ax, key, title in zip(axes, ('rmse_all', 'median_error', 'p95_error'),
                              ('RMSE (every fix)', 'median error (converged)',
                               '95th percentile (converged)')):
        for label, _, _ in RUNS:
            ax.plot(sig, [getattr(table[(label, s)], key) for s in sig], marker='o',
                    label=label)
        ax.plot(sig, [table[('ls', s)].crlb for s in sig], 'k--', label='CRLB')
        ax.set_yscale('log')
        ax.set_xlabel('σ (deg)')
        ax.set_title(title, fontsize=9)
        ax.grid(True, which='both', alpha=0.3)
    axes[0].set_ylabel('error (m)')
    axes[0].legend(fontsize=7)
    fig.suptitle(f'{sc.name}: {a.trials} trials per σ', fontsize=9)
    fig.tight_layout()
    os.makedirs(os.path.dirname(a.out) or '.', exist_ok=True)
    fig.savefig(a.out)
    print(f'wrote {a.out}')
    return 0


if __name__ == '__main__':
    np.seterr(all='ignore')
    raise SystemExit(main())
