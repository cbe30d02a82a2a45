"""GDOP maps of Wang, Zhang & Wu (2006), section 4 (fig. 2) and a table like its table 1.

Stations (30, −10, 0.1), (30, 20, 0.2), (−30, 5, 0.15) km (config/scenarios/seed000.yaml),
σ = 1.5 and 4.5 mrad on every angle, target altitude 5 and 15 km, the paper's CTLS error model
(eqs. (30)-(32)); plus the CRLB map for 1.5 mrad at 5 km for comparison and a placement
example. Every figure is made by the ``bearing_loc plan`` command printed before it, with one
colour scale and one set of contour levels (m) for all maps. Prints the expected error at
fixed positions in every map (the paper's table 1 lists such values; its numbers are not
reproduced here).

Run: .venv/bin/python bench/seed000_maps.py [--out docs/img] [--csv-out results] [--resolution 300]
"""
import argparse
import contextlib
import io
import json
import math
import os
import shlex

import numpy as np

from bearing_loc_ros.cli import main as cli_main
from bearing_loc_ros.core.planning import Stations, position_error

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENARIO = 'config/scenarios/seed000.yaml'
LEVELS = '50,70,100,150,200,300,500,700,1000,1500'
POINTS_KM = [(0, 0), (20, 20), (-40, -40), (50, 0), (58.5, 27.75), (-50, 40)]


def run(argv):
    print('$ bearing_loc ' + ' '.join(shlex.quote(a) for a in argv))
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = cli_main(argv)
    if rc:
        raise SystemExit(rc)
    return json.loads(buf.getvalue())


def _deg(mrad):
    """The --sigma-deg value of a σ given in mrad (the figures are labelled in mrad)."""
    return repr(math.degrees(float(mrad) * 1e-3))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--out', default='docs/img', help='output directory (default docs/img)')
    ap.add_argument('--resolution', default='300', help='cell size, m (default 300: 400x400)')
    ap.add_argument('--csv-out', default='results',
                    help='directory for the grids as CSV (default results/, gitignored)')
    args = ap.parse_args()
    os.chdir(ROOT)
    common = ['--scenario', SCENARIO, '--extent-km', '60', '--resolution', args.resolution,
              '--levels', LEVELS, '--vmin', '40', '--vmax', '2000']
    summary = []
    for sigma in ('1.5', '4.5'):
        for alt_km in ('5', '15'):
            name = f'seed000_ctls_{sigma.replace(".", "p")}mrad_{alt_km}km'
            png = os.path.join(args.out, name + '.png')
            out = run(['plan', 'map', *common, '--altitude', str(int(alt_km) * 1000),
                       '--sigma-deg', _deg(sigma), '--model', 'ctls', '--png', png,
                       '--csv', os.path.join(args.csv_out, name + '.csv'),
                       '--title', 'CTLS error (Wang, Zhang & Wu 2006, eq. 32), '
                                  f'sigma {sigma} mrad, altitude {alt_km} km'])
            summary.append((name, out['stats']))
    png = os.path.join(args.out, 'seed000_crlb_1p5mrad_5km.png')
    out = run(['plan', 'map', *common, '--altitude', '5000', '--sigma-deg', _deg('1.5'),
               '--model', 'crlb', '--png', png,
               '--csv', os.path.join(args.csv_out, 'seed000_crlb_1p5mrad_5km.csv'),
               '--title', 'CRLB sqrt(trace), sigma 1.5 mrad, altitude 5 km'])
    summary.append(('seed000_crlb_1p5mrad_5km', out['stats']))
    out = run(['plan', 'place', '--scenario', SCENARIO, '--sigma-deg', _deg('1.5'), '--altitude',
               '5000', '--area-km=-20,40,-20,30', '--region-km=-60,60,-60,60', '--height',
               '150', '--levels', LEVELS, '--vmin', '40', '--vmax', '2000',
               '--resolution', str(2 * float(args.resolution)),
               '--png-after', os.path.join(args.out, 'seed000_place_after.png')])
    print(f'\nplacement: ({out["position_m"][0] / 1e3:.2f}, {out["position_m"][1] / 1e3:.2f}) '
          f'km, mean error over the area {out["before_m"]:.1f} -> {out["after_m"]:.1f} m')
    print('\nmap statistics (m):')
    print(f'{"map":30s} {"min":>7s} {"median":>7s} {"mean":>7s} {"p90":>7s} {"max":>7s}')
    for name, s in summary:
        print(f'{name:30s} {s["min_m"]:7.1f} {s["median_m"]:7.1f} {s["mean_m"]:7.1f} '
              f'{s["p90_m"]:7.1f} {s["max_m"]:7.1f}')
    print('\nexpected error (m) at fixed positions (CTLS eq. (32) / CRLB):')
    pos = np.array([[30, -10, 0.1], [30, 20, 0.2], [-30, 5, 0.15]]) * 1e3
    cols = [(s, a) for s in (1.5e-3, 4.5e-3) for a in (5e3, 15e3)]
    print(f'{"position (km)":18s}' + ''.join(f'  s={s * 1e3:.1f} h={a / 1e3:2.0f}km'
                                             for s, a in cols))
    for x, y in POINTS_KM:
        cells = []
        for s, a in cols:
            st = Stations.from_arrays(pos, s)
            p = [[x * 1e3, y * 1e3, a]]
            cells.append(f'{position_error(p, st, "ctls")[0]:7.1f}/'
                         f'{position_error(p, st, "crlb")[0]:<7.1f}')
        print(f'({x:6.2f}, {y:6.2f})  ' + '  '.join(f'{c:>16s}' for c in cells))
    for f in sorted(os.listdir(args.out)):
        if f.startswith('seed000_') and f.endswith('.png'):
            print(f'{f}: {os.path.getsize(os.path.join(args.out, f)) / 1e3:.0f} kB')


if __name__ == '__main__':
    main()
