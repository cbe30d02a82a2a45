"""Mobile direction finding: the window mode on config/scenarios/mobile_foxhunt.yaml.

Monte Carlo over simulator seeds of the fusion pipeline exactly as ``bearing_loc bag
process`` runs it (core.fusion.make_core + replay, mode ``window``, timer trigger every
``--period`` s, ``target_altitude`` = the transmitter's), once with the scenario's
reflections (10 % of the bearings 20-90° off) and once without. Prints, per epoch time,
the RMSE of the horizontal fix over the seeds against the CRLB of the accumulated bearings
(the horizontal bound, core.horizontal_crlb, of every bearing in the window at the true
position, Zong & Cui 2015 eq. (7) with the altitude stated), the mean NEES (2 dof), and
the ratio of the two runs' RMSE. Also times one window fix of N bearings (N = 100 ... 400,
10 % reflections, robust ``mle``) and, with ``--plot``, draws docs/img/mobile_foxhunt.png.

Usage: .venv/bin/python bench/mobile_foxhunt.py [--seeds 40] [--plot docs/img/mobile_foxhunt.png]
"""

import argparse
import dataclasses
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from bearing_loc_ros.core.bearings import Bearing  # noqa: E402
from bearing_loc_ros.core.evaluation import nees_values  # noqa: E402
from bearing_loc_ros.core.fusion import (FusionConfig, make_core, MODE_WINDOW,  # noqa: E402
                                         replay)
from bearing_loc_ros.core.horizontal_crlb import horizontal_crlb  # noqa: E402
from bearing_loc_ros.core.simulation import load_scenario, simulate  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENARIO = os.path.join(REPO, 'config', 'scenarios', 'mobile_foxhunt.yaml')
NS = 1_000_000_000


def params(z0, period):
    return {'target_altitude': [float(z0)], 'trigger': 'timer', 'rate': 1.0 / period,
            'window': 600.0, 'buffer_age': 30.0, 'window_max_bearings': 400}


def run(sc, seed, period):
    """Epochs (stamp -> (error (3,), covariance, window positions)) of one seed."""
    truth = sc.targets[0].trajectory.position(0.0)
    cfg = FusionConfig.from_parameters(params(truth[2], period))
    core = make_core(cfg, stations=[s.id for s in sc.stations], mode=MODE_WINDOW)
    sim = simulate(sc, seed=seed)
    out = {}
    for ep in replay(core, [(ev.publish_ns, ev.bearing) for ev in sim.bearings]):
        if ep.ok:
            out[ep.stamp_ns] = (ep.position - truth, ep.covariance)
    return out, sim, core


def window_crlb(sc, sim, stamp, sigma):
    """Horizontal CRLB (2, 2) at the truth of the bearings in the window ending at stamp."""
    truth = sc.targets[0].trajectory.position(0.0)
    pos = np.array([e.bearing.position for e in sim.bearings if e.bearing.stamp_ns <= stamp
                    and e.bearing.stamp_ns >= stamp - 600 * NS])[-400:]
    return horizontal_crlb(truth, pos, sigma)[0, :2, :2]


def monte_carlo(sc, seeds, period):
    sigma = sc.stations[0].sigma_az
    per = {}
    rejected = []
    for seed in range(seeds):
        eps, sim, core = run(sc, seed, period)
        rejected.append(core.station_stats('car').outliers)
        for stamp, (e, P) in eps.items():
            per.setdefault(stamp, []).append((e, P, sim))
    rows = []
    for stamp in sorted(per):
        items = per[stamp]
        e = np.array([x[0] for x in items])
        P = np.array([x[1] for x in items])
        crlb = window_crlb(sc, items[0][2], stamp, sigma)
        nees, _ = nees_values(e, P)
        rows.append((stamp, len(items), float(np.sqrt(np.mean(np.sum(e[:, :2] ** 2, 1)))),
                     float(np.sqrt(np.trace(crlb))), float(np.nanmean(nees))))
    return rows, rejected


def time_fix(n, repeats=20):
    """Median wall time (ms) of one window fix with n bearings (10 % reflections)."""
    rng = np.random.default_rng(0)
    cfg = FusionConfig.from_parameters({'target_altitude': [0.0], 'trigger': 'timer',
                                        'window': 1e5, 'window_max_bearings': n,
                                        'buffer_age': 1e5})
    core = make_core(cfg, stations=['car'], mode=MODE_WINDOW)
    target = np.array([1500.0, 3000.0, 0.0])
    for k in range(n):
        p = np.array([10.0 * k, 300.0 * np.sin(k / 40.0), 0.0])
        az = np.arctan2(target[1] - p[1], target[0] - p[0]) + 0.07 * rng.standard_normal()
        if rng.random() < 0.1:
            az += np.radians(rng.uniform(20, 90)) * rng.choice([-1, 1])
        core.add_bearing(Bearing('car', k * NS, p, float(az), sigma_azimuth=0.07), k * NS)
    times = []
    for _ in range(repeats):
        core.strategy._pending = True
        t0 = time.perf_counter()
        ep = core.tick(n * NS)[0]
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times)), ep.reason


def plot(sc, path, period, rows_r, rows_c):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse
    eps, sim, _ = run(sc, 0, period)
    truth = sc.targets[0].trajectory.position(0.0)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(13, 5.6))
    road = sc.stations[0].trajectory.points
    ax.plot(road[:, 0], road[:, 1], '-', color='0.6', lw=6, alpha=0.4, label='road')
    for ev in sim.bearings[::6]:
        p, th = ev.bearing.position, ev.bearing.azimuth
        c = 'tab:red' if ev.outlier else 'tab:blue'
        ax.plot([p[0], p[0] + 7000 * np.cos(th)], [p[1], p[1] + 7000 * np.sin(th)], '-',
                color=c, lw=0.5, alpha=0.6 if ev.outlier else 0.3)
    stamps = sorted(eps)
    fx = np.array([eps[s][0] + truth for s in stamps])
    ax.plot(fx[:, 0], fx[:, 1], '.-', color='tab:green', ms=4, label='window fixes')
    e, P = eps[stamps[-1]]
    w, V = np.linalg.eigh(P[:2, :2])
    k = np.sqrt(-2 * np.log(0.05))
    ax.add_patch(Ellipse(truth[:2] + e[:2], 2 * k * np.sqrt(w[1]), 2 * k * np.sqrt(w[0]),
                         angle=np.degrees(np.arctan2(V[1, 1], V[0, 1])), fill=False,
                         color='k', lw=1.5, label='last fix, 95 % ellipse'))
    ax.plot(*truth[:2], 'k*', ms=14, label='transmitter')
    ax.plot([], [], '-', color='tab:blue', label='bearings (every 6th)')
    ax.plot([], [], '-', color='tab:red', label='reflections')
    ax.set_xlim(-3500, 5000)
    ax.set_ylim(-3000, 3500)
    ax.set_aspect('equal')
    ax.set_xlabel('East (m)')
    ax.set_ylabel('North (m)')
    ax.set_title('mobile_foxhunt: one car, azimuth only, 4°, 10 % reflections')
    ax.legend(loc='upper left', fontsize=8)
    for rows, lab, c in ((rows_c, 'RMSE, no reflections', 'tab:blue'),
                         (rows_r, 'RMSE, 10 % reflections', 'tab:red')):
        t = [(r[0] - sc.epoch_ns) / NS for r in rows]
        bx.semilogy(t, [r[2] for r in rows], '-', color=c, label=lab)
    t = [(r[0] - sc.epoch_ns) / NS for r in rows_c]
    bx.semilogy(t, [r[3] for r in rows_c], 'k--', label='CRLB of the accumulated bearings')
    bx.set_xlabel('drive time (s)')
    bx.set_ylabel('horizontal error (m)')
    bx.set_title('window mode (mle, robust): convergence')
    bx.grid(True, which='both', alpha=0.3)
    bx.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f'wrote {path}')


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--seeds', type=int, default=40)
    ap.add_argument('--period', type=float, default=30.0, help='epoch period, s')
    ap.add_argument('--plot', default=None)
    args = ap.parse_args()
    sc = load_scenario(SCENARIO)
    clean = dataclasses.replace(sc, stations=[dataclasses.replace(s, outlier=0.0)
                                              for s in sc.stations])
    t0 = time.perf_counter()
    rows_r, rej = monte_carlo(sc, args.seeds, args.period)
    rows_c, _ = monte_carlo(clean, args.seeds, args.period)
    print(f'{args.seeds} seeds, epochs every {args.period:g} s, '
          f'{time.perf_counter() - t0:.1f} s wall; reflections rejected per run: '
          f'mean {np.mean(rej):.1f} of ~60')
    clean_by = {r[0]: r for r in rows_c}
    print(f'{"t s":>5} {"n":>3} {"CRLB m":>8} | {"clean RMSE":>10} {"/CRLB":>6} {"NEES":>5} | '
          f'{"refl RMSE":>9} {"/CRLB":>6} {"NEES":>5} | {"refl/clean":>10}')
    ratios = []
    for r in rows_r:
        c = clean_by.get(r[0])
        if c is None:
            continue
        ratios.append(r[2] / c[2])
        print(f'{(r[0] - sc.epoch_ns) / NS:5.0f} {r[1]:3d} {c[3]:8.1f} | {c[2]:10.1f} '
              f'{c[2] / c[3]:6.2f} {c[4]:5.2f} | {r[2]:9.1f} {r[2] / r[3]:6.2f} {r[4]:5.2f} | '
              f'{r[2] / c[2]:10.2f}')
    print(f'RMSE ratio reflections/clean: max {max(ratios):.2f}, over the last half '
          f'{np.mean(ratios[len(ratios) // 2:]):.2f}')
    for n in (100, 200, 300, 400):
        ms, reason = time_fix(n)
        print(f'one window fix, N = {n:3d} bearings (10 % reflections): {ms:6.1f} ms '
              f'({reason})')
    if args.plot:
        plot(sc, args.plot, args.period, rows_r, rows_c)


if __name__ == '__main__':
    main()
