"""Fix covariance with stated station position covariances: mean NEES and tail, fusion core.

Four stations 1-2 km from an emitter at (500, 800, 100) m, σ 3 mrad on azimuth and
elevation, 400 epochs (10 Hz). Each bearing comes from a station whose reported position is
off by N(0, s² I) and states that covariance (s = 0, 5 m (a KrakenSDR's GPS default) and
20 m). Printed per s: the ``ok`` fixes, their mean NEES (χ²₃: 3, 99 % band for 400 fixes
± 0.32) and the share beyond the χ²₃ 0.999 quantile (0.1 % expected). With
``--stated-sigma-only`` the epoch is solved as before the station position covariance was
counted (``solve_epoch(..., station_positions=False)``: the gate alone counts it).

    .venv/bin/python bench/station_position_nees.py [--seed 0] [--stated-sigma-only]
"""
import argparse
import os
import sys

import numpy as np
from scipy.stats import chi2

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from bearing_loc_ros.core.bearings import Bearing  # noqa: E402
from bearing_loc_ros.core.conventions import azimuth_elevation  # noqa: E402
from bearing_loc_ros.core.fusion import FusionConfig, gating, make_core  # noqa: E402

TARGET = np.array([500.0, 800.0, 100.0])
STATIONS = {'s1': (0, 0, 0), 's2': (2000, 0, 10), 's3': (0, 2000, 5), 's4': (2000, 2000, 0)}
SIGMA = 0.003
NS = 10 ** 9


def run(sigma_pos, rng):
    """(epochs, ok fixes, their NEES array) of 400 epochs."""
    core = make_core(FusionConfig(), list(STATIONS))
    cov = np.eye(3) * sigma_pos ** 2
    nees, n = [], 0
    for k in range(1, 401):
        now = 1000 * NS + k * NS // 10
        for s, p in STATIONS.items():
            true = np.array(p, dtype=float)
            az, el = azimuth_elevation(TARGET - true)
            b = Bearing(s, now, true + rng.normal(size=3) * sigma_pos,
                        float(az) + rng.normal() * SIGMA, float(el) + rng.normal() * SIGMA,
                        SIGMA, SIGMA, position_covariance=cov)
            for ep in core.add_bearing(b, now + 1):
                n += 1
                if ep.ok:
                    e = ep.position - TARGET
                    nees.append(e @ np.linalg.solve(ep.covariance, e))
    return n, np.array(nees)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--stated-sigma-only', action='store_true',
                    help='solve as before: only the gate counts the position covariance')
    a = ap.parse_args()
    if a.stated_sigma_only:
        plain = gating.solve_epoch

        def solve_epoch(*args, **kw):
            return plain(*args, **dict(kw, station_positions=False))
        gating.solve_epoch = solve_epoch
        import bearing_loc_ros.core.fusion.multistation as ms
        ms.solve_epoch = solve_epoch
    rng = np.random.default_rng(a.seed)
    q = chi2.ppf(0.999, 3)
    print('| station position σ (m) | epochs | ok fixes | mean NEES | beyond χ²₃ 0.999 |')
    print('|---:|---:|---:|---:|---:|')
    for s in (0.0, 5.0, 20.0):
        n, nees = run(s, rng)
        print(f'| {s:g} | {n} | {nees.size} | {nees.mean():.2f} | '
              f'{100 * np.mean(nees > q):.2f} % |')


if __name__ == '__main__':
    main()
