"""Timings of the planning core (docs/planning.md): maps, placement, cut angle.

Prints, best of ``--repeat`` runs on one thread:

* accuracy map, 400 × 400 cells, the Wang, Zhang & Wu (2006) stations (3 × 2D), CRLB and CTLS model
  (planning.accuracy_map), and the CTLS map through core.constrained_tls.ctls_covariance (the
  estimator's own eq. (30) implementation, general but with 5-operand einsums) for reference;
* accuracy map with N = 20 stations (mixed 1D/2D);
* placement of a 4th station: 21 × 21 candidates, 30 × 30 area cells, refinement;
* OccupancyGrid map 200 × 200 (what the fusion node would publish);
* Wang, Su, Bai & Zhong (2009): one optimal cut angle, and the four tables (52 solves).

Run: .venv/bin/python bench/bench_planning.py [--repeat 3]
"""
import argparse
import os
import time

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')

import numpy as np  # noqa: E402

from bearing_loc_ros.core.bearings import simulate_bearings  # noqa: E402
from bearing_loc_ros.core.constrained_tls import ctls_covariance  # noqa: E402
from bearing_loc_ros.core.cutangle import cut_angle_table, optimal_cut_angle  # noqa: E402
from bearing_loc_ros.core.planning import (GridSpec, Stations, accuracy_map,  # noqa: E402
                                           occupancy_error_map, place_station)

KM = 1000.0
SEED000 = np.array([[30, -10, 0.1], [30, 20, 0.2], [-30, 5, 0.15]]) * KM


def best_of(fn, repeat):
    times = []
    out = None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return min(times), out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--repeat', type=int, default=3)
    args = ap.parse_args()
    r = args.repeat
    st = Stations.from_arrays(SEED000, 1.5e-3)
    g400 = GridSpec.from_extent(-60 * KM, 60 * KM, -60 * KM, 60 * KM, 300.0, 5 * KM)
    rows = []
    for model in ('crlb', 'ctls'):
        t, m = best_of(lambda: accuracy_map(st, g400, model), r)
        rows.append((f'map 400x400, 3 stations, {model}', t, f'median {np.median(m.error):.1f} m'))
    pts = g400.points()

    def via_core_ctls():
        bs = simulate_bearings(pts, SEED000, 1.5e-3, 1.5e-3)
        return np.sqrt(np.trace(ctls_covariance(pts, bs), axis1=1, axis2=2))
    t, e = best_of(via_core_ctls, 1)
    ref = accuracy_map(st, g400, 'ctls').error.ravel()
    rows.append(('map 400x400 via constrained_tls.ctls_covariance', t,
                 f'max rel diff {np.max(np.abs(e - ref) / ref):.1e}'))
    rng = np.random.default_rng(0)
    pos20 = np.column_stack([rng.uniform(-50e3, 50e3, (20, 2)), rng.uniform(0, 300, 20)])
    st20 = Stations.from_arrays(pos20, 2e-3, has_elevation=np.arange(20) % 3 != 0)
    for model in ('crlb', 'ctls'):
        t, _ = best_of(lambda: accuracy_map(st20, g400, model), r)
        rows.append((f'map 400x400, 20 stations (1/3 1D), {model}', t, ''))
    area = GridSpec.from_extent(-20 * KM, 20 * KM, -20 * KM, 20 * KM, 40 * KM / 30, 5 * KM)
    for model in ('crlb', 'ctls'):
        t, res = best_of(lambda: place_station(st, area, (-60 * KM, 60 * KM, -60 * KM, 60 * KM),
                                               150.0, model=model), r)
        rows.append((f'place 4th station, 21x21 cand., 30x30 area, {model}', t,
                     f'{res.before:.1f} -> {res.after:.1f} m at '
                     f'({res.position[0] / KM:.2f}, {res.position[1] / KM:.2f}) km, '
                     f'{res.evaluations} evaluations'))
    g200 = GridSpec(-60 * KM, -60 * KM, 600.0, 200, 200, 5 * KM)
    t, _ = best_of(lambda: occupancy_error_map(st, g200), r)
    rows.append(('occupancy_error_map 200x200, crlb', t, ''))
    t, c = best_of(lambda: optimal_cut_angle(0.8, 0.2, np.radians(20)), r)
    rows.append(('optimal_cut_angle (one solve)', t, f'phi {np.degrees(c.cut_angle):.3f} deg'))
    k1s = [round(0.1 * i, 1) for i in range(1, 11)] + [1.2, 1.5, 2.0]
    t, tab = best_of(lambda: cut_angle_table(k1s, [0.0, 0.2, 0.5, 0.8]), 1)
    rows.append((f'cut_angle_table ({len(tab)} solves)', t, ''))
    print(f'{"case":58s} {"time":>9s}  note')
    for name, t, note in rows:
        print(f'{name:58s} {t * 1e3:7.1f} ms  {note}')


if __name__ == '__main__':
    main()
