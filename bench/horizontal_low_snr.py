"""Robust horizontal fixes at low SNR: ok share, mean NEES and confidently wrong ok fixes.

Two azimuth-only cases, the horizontal solve with each trial's true altitude stated exactly
(core.horizontal; NEES of the x-y block, 2 degrees of freedom; confidently wrong = NEES above
the χ²₂ 0.9999 quantile, 18.42):

* the stations of Wang, Zhang & Wu (2006) (config/scenarios/seed000_azimuth_only.yaml),
  constant σ, ``mle`` (robust by default) against the paper's ``mle``;
* the six stations of Zong & Cui (2015) (config/scenarios/seed003.yaml, σ grows with range,
  d_ref 1000 m), elevations dropped, robust ``wmle`` against the paper's ``wmle``.

Targets from the scenario (seeds 0, 1, ... of core.evaluation.trials_from_scenario), noise
from numpy Generators seeded 100 + seed; ``--seeds`` independent repetitions are pooled.

Run: .venv/bin/python bench/horizontal_low_snr.py [--trials 2000] [--seeds 3]
"""

import argparse
import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from bearing_loc_ros.core import evaluation as ev  # noqa: E402
from bearing_loc_ros.core import registry  # noqa: E402
from bearing_loc_ros.core.bearings import BearingSet  # noqa: E402
from bearing_loc_ros.core.simulation import load_scenario  # noqa: E402
from bearing_loc_ros.scenarios import resolve_scenario  # noqa: E402

CASES = (('seed000_azimuth_only', 'mle', None, (0.5, 1, 2, 3, 4, 5)),
         ('seed003', 'wmle', 1000.0, (0.5, 1, 2, 3, 5)))


def run(scenario, name, d_ref, sigma_deg, trials, seed, robust):
    """(ok fixes, their NEES sum, confidently wrong among them, trials) of one repetition."""
    tr = ev.trials_from_scenario(load_scenario(resolve_scenario(scenario)), trials, seed)
    s = math.radians(sigma_deg)
    f = tr.sigma_factor()
    b = ev.noisy_bearings(tr, s * f, s * f, np.random.default_rng(100 + seed))
    nan = np.full_like(b.elevation, np.nan)
    b = BearingSet(b.positions, b.azimuth, nan, np.full_like(b.sigma_az, s), nan)
    opts = {'robust': robust}
    if d_ref is not None:
        opts['reference_range'] = d_ref
    r = registry.solve(name, b, target_altitude=tr.targets[:, 2], **opts)
    ok = r.status == 'ok'
    e = (r.position - tr.targets)[ok][:, :2]
    nees = np.einsum('mi,mij,mj->m', e, np.linalg.inv(r.covariance[ok][:, :2, :2]), e)
    return int(ok.sum()), float(nees.sum()), int(np.count_nonzero(nees > 18.420681)), len(ok)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--trials', type=int, default=2000)
    ap.add_argument('--seeds', type=int, default=3)
    a = ap.parse_args()
    print(f'{a.trials} trials x {a.seeds} seeds per row; paper estimator in brackets')
    print('| scenario | estimator | σ | ok share | mean NEES of ok (99 % band) | '
          'confidently wrong ok fixes |')
    print('|---|---|---|---|---|---|')
    for scenario, name, d_ref, sigmas in CASES:
        for sd in sigmas:
            cells = []
            for robust in (True, False):
                k = ns = w = n = 0
                for seed in range(a.seeds):
                    dk, dns, dw, dn = run(scenario, name, d_ref, sd, a.trials, seed, robust)
                    k, ns, w, n = k + dk, ns + dns, w + dw, n + dn
                cells.append((k, ns / k if k else float('nan'),
                              2.576 * math.sqrt(4.0 / k) if k else float('nan'), w, n))
            (k, m, bd, w, n), (k0, m0, _, w0, n0) = cells
            print(f'| {scenario} | {name} robust | {sd:g}° | {100 * k / n:.1f} % '
                  f'({100 * k0 / n0:.1f}) | {m:.2f} ± {bd:.2f} ({m0:.2f}) | '
                  f'{w}/{k} ({w0}/{k0}) |', flush=True)


if __name__ == '__main__':
    main()
