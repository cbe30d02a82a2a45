"""Window mode: bearings added per second at a window of N bearings (N = 10³, 10⁴, 10⁵).

One moving station (a car at 10 m/s past an emitter, σ 4°) feeds the fusion core in window
mode with the timer trigger and no tick, so that only adding a bearing is measured (no
fix): ``window`` 10⁶ s and ``window_max_bearings`` N. Printed per N: adds/s while the
window fills from empty to N, and adds/s for ``--adds`` more bearings at the full window
(each one makes the oldest leave). Wall-clock figures of this machine, best of ``--repeat``.

    .venv/bin/python bench/window_adds.py [--adds 2000] [--repeat 3]
"""
import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from bearing_loc_ros.core.bearings import Bearing  # noqa: E402
from bearing_loc_ros.core.fusion import FusionConfig, make_core  # noqa: E402
from bearing_loc_ros.core.fusion.config import MODE_WINDOW  # noqa: E402

TARGET = np.array([1500.0, 3000.0, 0.0])
SIGMA = np.radians(4.0)


def bearings(n, rng):
    """n bearings of the car, one every 10 ms."""
    out = []
    for k in range(n):
        t = 1.0 + 0.01 * k
        pos = np.array([10.0 * t - 1000.0, 200.0 * np.sin(t / 50.0), 0.0])
        az = np.arctan2(TARGET[1] - pos[1], TARGET[0] - pos[0]) + SIGMA * rng.standard_normal()
        out.append(Bearing('car', int(round(t * 1e9)), pos, float(az), sigma_azimuth=SIGMA))
    return out


def run(n, adds, rng):
    cfg = FusionConfig(estimator='mle', trigger='timer', window=1e6, buffer_age=30.0,
                       station_timeout=30.0, estimator_options={'target_altitude': 0.0},
                       window_max_bearings=n)
    core = make_core(cfg, ['car'], MODE_WINDOW)
    bs = bearings(n + adds, rng)
    t0 = time.perf_counter()
    for b in bs[:n]:
        core.add_bearing(b, b.stamp_ns)
    t1 = time.perf_counter()
    for b in bs[n:]:
        core.add_bearing(b, b.stamp_ns)
    t2 = time.perf_counter()
    return n / (t1 - t0), adds / (t2 - t1)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--adds', type=int, default=2000)
    ap.add_argument('--repeat', type=int, default=3)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    print('| N | adds/s filling to N | adds/s at a full window |')
    print('|---:|---:|---:|')
    for n in (1000, 10000, 100000):
        runs = [run(n, args.adds, rng) for _ in range(args.repeat)]
        fill = max(r[0] for r in runs)
        full = max(r[1] for r in runs)
        print(f'| {n} | {fill:,.0f} | {full:,.0f} |')


if __name__ == '__main__':
    main()
