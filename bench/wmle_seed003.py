"""Zong & Cui 2015, section 3 Monte Carlo: RMSE of ls, mle and wmle against the CRLB.

Scenario (Zong & Cui 2015, section 3.1): six 2D stations on the x axis from −3000 to 3000 m;
one source per trial, uniform in X(−3000, 3000), Y(1000, 7000), Z(−500, 500) m. Azimuth and
elevation errors grow with range (Zong & Cui 2015 eqs. (9)-(10)): σ_k = σ_ref · d_k / d_ref,
d_k the true slant range; the bearings report the nominal σ_ref (a station does not know the
range), so ``mle`` weights all bearings equally and ``wmle`` (option reference_range = d_ref)
re-weights them with the range of its current estimate. The CRLB is the inverse Fisher
information at the true source with the true σ_k; the table gives RMSE = sqrt(mean |e|²) and
CRLB = sqrt(mean trace(CRLB)) over the trials, in metres, and their ratio. The estimators run
as published (options ``robust`` and ``consistency`` off). Trials in which an estimator did
not converge (status other than ok) are dropped from every column and counted in the last
column.

Run: .venv/bin/python bench/wmle_seed003.py [--trials 1000] [--reference-range 1000]
"""
import argparse
import time

import numpy as np

from bearing_loc_ros.core.bearings import BearingSet
from bearing_loc_ros.core.conventions import azimuth_elevation, wrap_angle
from bearing_loc_ros.core.crlb import crlb
from bearing_loc_ros.core.estimators import locate
from bearing_loc_ros.core.registry import scoped_options

STATIONS = np.column_stack([np.linspace(-3000.0, 3000.0, 6), np.zeros(6), np.zeros(6)])
BOX_MIN = np.array([-3000.0, 1000.0, -500.0])
BOX_MAX = np.array([3000.0, 7000.0, 500.0])


def scenario(sigma_ref, trials, d_ref, rng):
    """Sources (K, 3), bearings (BearingSet reporting σ_ref) and the CRLB (K, 3, 3)."""
    src = rng.uniform(BOX_MIN, BOX_MAX, size=(trials, 3))
    d = src[:, None, :] - STATIONS[None]
    az, el = azimuth_elevation(d)
    sig = sigma_ref * np.linalg.norm(d, axis=-1) / d_ref          # Zong & Cui 2015 eqs. (9)-(10)
    az = wrap_angle(az + sig * rng.standard_normal(az.shape))
    el = el + sig * rng.standard_normal(el.shape)
    el = np.clip(el, -1.5, 1.5)
    bs = BearingSet.from_arrays(np.broadcast_to(STATIONS, (trials, 6, 3)), az, el,
                                sigma_ref, sigma_ref)
    bound = crlb(src, STATIONS, sig, sig)
    return src, bs, bound


def run(sigmas_deg, trials, d_ref, seed=3, methods=('ls', 'mle', 'wmle')):
    rows = []
    for s_deg in sigmas_deg:
        rng = np.random.default_rng(seed)
        src, bs, bound = scenario(np.deg2rad(s_deg), trials, d_ref, rng)
        # The estimators as the papers publish them: no robust refit, no consistency
        # status (their own statuses only), so "dropped" counts the papers' failures.
        paper = {'reference_range': d_ref, 'robust': False, 'consistency': False}
        res = {m: locate(m, bs, **scoped_options(m, paper)) for m in methods}
        # Trials where every estimator converged (the others are counted, not averaged).
        keep = np.all([r.converged for r in res.values()], axis=0)
        c = np.sqrt(np.mean(np.trace(bound[keep], axis1=1, axis2=2)))
        row = {'sigma_deg': s_deg, 'crlb': c, 'failed': int(np.sum(~keep))}
        for m, r in res.items():
            e = r.position[keep] - src[keep]
            row[m] = np.sqrt(np.mean(np.sum(e ** 2, axis=1)))
        rows.append(row)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--trials', type=int, default=1000)
    ap.add_argument('--reference-range', type=float, default=1000.0)
    ap.add_argument('--seed', type=int, default=3)
    a = ap.parse_args()
    t0 = time.perf_counter()
    rows = run([0.5, 1.0, 1.5, 2.0, 2.5, 3.0], a.trials, a.reference_range, a.seed)
    print(f'Zong & Cui 2015 scenario, {a.trials} trials per row, d_ref = {a.reference_range:g} m, '
          f'seed {a.seed}')
    print('| σ_ref (deg) | CRLB (m) | ls RMSE (m) | mle RMSE (m) | wmle RMSE (m) '
          '| ls/CRLB | mle/CRLB | wmle/CRLB | trials dropped |')
    print('|---|---|---|---|---|---|---|---|---|')
    for r in rows:
        c = r['crlb']
        print(f'| {r["sigma_deg"]:.1f} | {c:.1f} | {r["ls"]:.1f} | {r["mle"]:.1f} | '
              f'{r["wmle"]:.1f} | {r["ls"] / c:.3f} | {r["mle"] / c:.3f} | '
              f'{r["wmle"] / c:.3f} | {r["failed"]} |')
    print(f'({time.perf_counter() - t0:.1f} s)')


if __name__ == '__main__':
    main()
