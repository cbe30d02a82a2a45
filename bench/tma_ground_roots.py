"""TMA with a ground-speed prior from an observer faster than the target: the two ranges.

An aircraft flies east at 100 m/s, 3 km up, and turns by an angle after 150 s; a vehicle
starts at (10, 20, 0) km at 18 m/s, heading (15, −10, 0) m/s (the true range is the smaller
root of (T8)) or (−15, 10, 0) m/s (the larger); a bearing (azimuth and elevation) a second
for 300 s at σ = 0.2°, ``--runs`` Monte Carlo runs. ``tma_mle`` runs with
``speed_reference: ground`` and the vehicle's true speed. Both roots of (T8) are positive
(docs/tma.md (T23)); for a straight observer (turn 0°) both fit the bearings exactly. Printed
per turn angle and heading: statuses, the mean NEES of the ``ok`` fixes (3 expected), how
many exceed χ²₃ 0.9999 (21.1) and how many ``ok`` fixes lie more than 1 km from the truth
(the wrong range is 7-9 km off).

    .venv/bin/python bench/tma_ground_roots.py [--runs 200]
"""
import argparse
import os
import sys
from collections import Counter

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from bearing_loc_ros.core.evaluation import CONFIDENT_WRONG_NEES  # noqa: E402
from bearing_loc_ros.core.tma import simulate_tma, tma  # noqa: E402

TIMES = np.arange(300.0)
P0 = np.array([10e3, 20e3, 0.0])


def observer(turn_deg, at=150.0, speed=100.0):
    """Positions (K, 3) m: east at ``speed``, then ``turn_deg`` to the left at ``at`` s."""
    a, b = np.minimum(TIMES, at), np.maximum(TIMES - at, 0.0)
    th = np.deg2rad(turn_deg)
    return (np.array([0.0, 0.0, 3000.0]) + np.outer(a, [speed, 0.0, 0.0])
            + np.outer(b, [speed * np.cos(th), speed * np.sin(th), 0.0]))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--runs', type=int, default=200)
    ap.add_argument('--seed', type=int, default=0)
    args = ap.parse_args()
    print('| turn | vehicle velocity m/s | statuses | mean NEES of ok | NEES > 21.1 | '
          'ok > 1 km off |')
    print('|---:|---|---|---:|---:|---:|')
    for turn in (0, 1, 3, 10, 30, 90):
        obs = observer(turn)
        for vt in ((15.0, -10.0, 0.0), (-15.0, 10.0, 0.0)):
            vt = np.array(vt)
            bs, t = simulate_tma(TIMES, P0, vt, obs, np.deg2rad(0.2),
                                 rng=np.random.default_rng(args.seed), M=args.runs)
            r = tma('tma_mle', bs, t, float(np.linalg.norm(vt)), speed_reference='ground')
            ok = np.nonzero(r.status == 'ok')[0]
            e = r.position[ok] - (P0 + vt * TIMES[-1])
            nees = np.array([x @ np.linalg.solve(c[:3, :3], x)
                             for x, c in zip(e, r.covariance[ok])])
            st = ', '.join(f'{k} {n}' for k, n in sorted(Counter(r.status.tolist()).items()))
            mean = f'{nees.mean():.3g}' if len(nees) else '–'
            print(f'| {turn}° | ({vt[0]:g}, {vt[1]:g}) | {st} | {mean} | '
                  f'{int(np.sum(nees > CONFIDENT_WRONG_NEES))} | '
                  f'{int(np.sum(np.linalg.norm(e, axis=1) > 1000.0))} |')


if __name__ == '__main__':
    main()
