"""How the paper's CTLS depends on the coordinate origin and units (Wang, Zhang & Wu, section 4).

The constrained TLS of Wang, Zhang & Wu weights the angle errors through G = Σ F_jᵀF_j, and F_4
holds the station coordinates, so ``ctls`` changes when the same geometry is written in km
instead of m or with another origin. The Abatzoglou-Mendel variant ``ctls_am`` (G⁻¹ → P_E) and
``mle`` do not. Scenario of Wang, Zhang & Wu section 4: stations (30, −10, 0.1), (30, 20, 0.2),
(−30, 5, 0.15) km, equal σ on every angle, targets at 5 and 15 km altitude.

For each coordinate frame the bearings are identical (angles do not depend on the frame);
only the station coordinates handed to the estimator change, and the estimate is mapped back
to metres in the original frame. Columns: Monte Carlo RMSE / CRLB (sqrt(trace)), and for
``ctls`` the eq. (32) prediction ε / CRLB evaluated at the true target in that frame. The
estimators run as published (options ``robust`` and ``consistency`` off).

Run: .venv/bin/python bench/ctls_origin.py [--trials 2000]
"""
import argparse
import time

import numpy as np

from bearing_loc_ros.core.bearings import BearingSet, simulate_bearings
from bearing_loc_ros.core.crlb import crlb_for, gdop
from bearing_loc_ros.core.constrained_tls import ctls_covariance
from bearing_loc_ros.core.estimators import locate
from bearing_loc_ros.core.registry import scoped_options

STATIONS_KM = np.array([[30.0, -10.0, 0.1], [30.0, 20.0, 0.2], [-30.0, 5.0, 0.15]])
HORIZONTAL_KM = [(0.0, 0.0), (20.0, 40.0), (-40.0, -30.0), (60.0, 10.0)]
ALTITUDES_KM = [5.0, 15.0]
SIGMAS = [1.5e-3, 4.5e-3]
# name: (scale: metres per frame unit, origin of the frame in metres)
FRAMES = {
    'm': (1.0, np.zeros(3)),
    'km': (1000.0, np.zeros(3)),
    'm, origin at station 3': (1.0, STATIONS_KM[2] * 1e3),
    'm, origin at (-300, 400, 0) km': (1.0, np.array([-300e3, 400e3, 0.0])),
}


def in_frame(bs, scale, origin):
    """The same bearings with station coordinates written in another frame."""
    return BearingSet((bs.positions - origin) / scale, bs.azimuth, bs.elevation, bs.sigma_az,
                      bs.sigma_el)


def rmse_ratio(method, bs, target, scale, origin, bound):
    # The estimators as published (no consistency status, no robust refit): ``converged``
    # is their own convergence.
    r = locate(method, in_frame(bs, scale, origin),
               **scoped_options(method, {'robust': False, 'consistency': False}))
    est = r.position * scale + origin
    ok = r.converged
    e = est[ok] - target
    return np.sqrt(np.mean(np.sum(e ** 2, axis=1))) / bound, np.mean(ok)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--trials', type=int, default=2000)
    ap.add_argument('--seed', type=int, default=0)
    a = ap.parse_args()
    t0 = time.perf_counter()
    st = STATIONS_KM * 1e3
    print(f'Wang, Zhang & Wu scenario, {a.trials} trials per cell, seed {a.seed}; RMSE / CRLB '
          '(eq. (32) prediction / CRLB in brackets)')
    head = ['σ (mrad)', 'target (km)', 'CRLB (m)', 'mle']
    head += [f'ctls [{f}]' for f in FRAMES] + [f'ctls_am [{f}]' for f in ('m', 'km')]
    print('| ' + ' | '.join(head) + ' |')
    print('|' + '---|' * len(head))
    rng = np.random.default_rng(a.seed)
    for sigma in SIGMAS:
        for alt in ALTITUDES_KM:
            for hx, hy in HORIZONTAL_KM:
                tgt = np.array([hx, hy, alt]) * 1e3
                bs = simulate_bearings(np.tile(tgt, (a.trials, 1)), st, sigma, rng=rng)
                bound = gdop(crlb_for(tgt[None], bs.problem(0)))[0]
                cells = [f'{sigma * 1e3:.1f}', f'({hx:g}, {hy:g}, {alt:g})', f'{bound:.0f}']
                q, _ = rmse_ratio('mle', bs, tgt, 1.0, np.zeros(3), bound)
                cells.append(f'{q:.3f}')
                for scale, origin in FRAMES.values():
                    q, _ = rmse_ratio('ctls', bs, tgt, scale, origin, bound)
                    one = in_frame(bs.problem(0), scale, origin)
                    pred = gdop(ctls_covariance(((tgt - origin) / scale)[None], one))[0]
                    cells.append(f'{q:.3f} ({pred * scale / bound:.3f})')
                for f in ('m', 'km'):
                    scale, origin = FRAMES[f]
                    q, _ = rmse_ratio('ctls_am', bs, tgt, scale, origin, bound)
                    cells.append(f'{q:.3f}')
                print('| ' + ' | '.join(cells) + ' |')
    print(f'({time.perf_counter() - t0:.1f} s)')


if __name__ == '__main__':
    main()
