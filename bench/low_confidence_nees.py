"""How far the covariance of a ``low_confidence`` fix is from bounding its error.

Three azimuth-only stations 2-2.5 km apart, σ 0.01 rad, one azimuth 15° off, a stated
target altitude (horizontal solve, default ``mle``), 400 epochs through the fusion's
:func:`~bearing_loc_ros.core.fusion.gating.solve_epoch`. Printed: how many epochs end
``low_confidence`` and the median and mean of their NEES in the plane (2 dof: 2 expected
if the covariance held).

    .venv/bin/python bench/low_confidence_nees.py [--seed 1]
"""
import argparse
import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from bearing_loc_ros.core.bearings import Bearing  # noqa: E402
from bearing_loc_ros.core.fusion.gating import solve_epoch  # noqa: E402

TARGET = np.array([800.0, 1500.0, 0.0])
STATIONS = np.array([[0, 0, 0], [2000, 0, 0], [1000, 2500, 0]], dtype=float)
SIGMA = 0.01


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--seed', type=int, default=1)
    rng = np.random.default_rng(ap.parse_args().seed)
    nees = []
    for _ in range(400):
        bs = []
        for i, p in enumerate(STATIONS):
            d = TARGET - p
            az = math.atan2(d[1], d[0]) + rng.normal() * SIGMA + (math.radians(15.0)
                                                                  if i == 2 else 0.0)
            bs.append(Bearing(f's{i}', 1, p, az, float('nan'), SIGMA, float('nan')))
        ep = solve_epoch(bs, 'mle', {'target_altitude': 0.0}, 2, 0.999)
        if ep.reason == 'low_confidence':
            e = (ep.position - TARGET)[:2]
            nees.append(e @ np.linalg.solve(ep.covariance[:2, :2], e))
    print(f'low_confidence epochs: {len(nees)} of 400; NEES (2 dof): median '
          f'{np.median(nees):.0f}, mean {np.mean(nees):.0f}')


if __name__ == '__main__':
    main()
