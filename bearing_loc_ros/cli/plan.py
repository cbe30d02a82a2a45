"""``bearing_loc plan``: where to put stations (README "Planning").

Sub-commands:

* ``cut-angle``: seed 004's optimal cut angle of a 2D + 1D sensor pair (JSON), or its
  tables 1-4 for ranges of k1 and k2 (``--table``).
* ``map``: expected 3D position error over a grid at one target altitude (CRLB or seed 000's
  CTLS error model), written as a PNG heat map with labelled contours and as CSV.
* ``place``: the position of one more station that minimises the mean (or worst) expected
  error over an area, with the before/after figures (JSON) and optional maps.

Stations come from a simulator scenario (``--scenario``, core.simulation.load_scenario) or
from ``--stations 'x,y,z[,1d];x,y,z;...'`` in ``--stations-unit`` (km by default). A value
that starts with a minus sign must be attached with '=' (``--area-km=-10,10,-10,10``),
otherwise argparse takes it for an option.
"""

import contextlib
import json
import math
import os
import sys

import numpy as np

from . import InputError
from .deprecation import DeprecatedOption

KM = 1000.0
#: Most values a --k1-values/--k2-values/--levels list may expand to (start:stop:step).
MAX_VALUES = 10000


def add_arguments(parser):
    """Register the ``plan`` sub-commands."""
    sub = parser.add_subparsers(dest='plan_command', metavar='COMMAND')
    sub.required = True

    p = sub.add_parser('cut-angle', help='optimal cut angle of a 2D + 1D pair (seed 004)')
    p.add_argument('--k1', type=float, default=1.0,
                   help='sigma_theta1^2 / sigma_theta2^2, azimuth variance ratio (default 1)')
    p.add_argument('--k2', type=float, default=0.0,
                   help='sigma_eps1^2 / sigma_theta2^2, elevation variance ratio of the 2D '
                        'sensor (default 0: two 1D sensors when --elevation-deg is 0)')
    p.add_argument('--elevation-deg', type=float, default=0.0,
                   help='target elevation eps1 seen from the 2D sensor, deg (default 0)')
    p.add_argument('--table', action='store_true',
                   help="print seed 004's tables: every --k1-values x --k2-values pair")
    p.add_argument('--k1-values', default='0.1:1.0:0.1,1.2,1.5,2.0',
                   help='k1 list for --table: comma-separated numbers or start:stop:step '
                        'ranges (default 0.1:1.0:0.1,1.2,1.5,2.0)')
    p.add_argument('--k2-values', default='0,0.2,0.5,0.8',
                   help='k2 list for --table (default 0,0.2,0.5,0.8: tables 1-4)')
    p.add_argument('--json', action='store_true', help='--table as a JSON list')

    for name, help_text in (('map', 'expected-error map of a station layout'),
                            ('place', 'best position for one more station')):
        p = sub.add_parser(name, help=help_text)
        src = p.add_mutually_exclusive_group(required=True)
        src.add_argument('--scenario', help='scenario YAML (README "Simulator"); '
                                            'station positions at t = 0')
        src.add_argument('--stations',
                         help="'x,y,z[,1d];x,y,z;...' station positions (2D unless ',1d'); "
                              "write --stations=-1,... if it starts with a minus sign")
        p.add_argument('--stations-unit', choices=('km', 'm'), default='km',
                       help='unit of --stations coordinates (default km)')
        p.add_argument('--altitude', type=float, required=True,
                       help='target altitude (ENU z), m')
        p.add_argument('--sigma-deg', type=float, default=None,
                       help="azimuth and elevation sigma of every station, degrees (default: "
                            "the scenario's; with --stations this or --sigma-azimuth-deg is "
                            'required)')
        p.add_argument('--sigma-azimuth-deg', type=float, default=None,
                       help='azimuth sigma of every station, degrees (default: --sigma-deg)')
        p.add_argument('--sigma-elevation-deg', type=float, default=None,
                       help='elevation sigma of every station, degrees (default: '
                            '--sigma-deg, else the azimuth sigma with --stations)')
        p.add_argument('--sigma-mrad', type=float, action=DeprecatedOption,
                       replacement='--sigma-deg')
        p.add_argument('--sigma-el-mrad', type=float, action=DeprecatedOption,
                       replacement='--sigma-elevation-deg')
        p.add_argument('--model', choices=('crlb', 'ctls'), default='crlb',
                       help='error model: crlb (default) or ctls (seed 000 eq. (30)-(32))')
        p.add_argument('--ctls-unit', choices=('m', 'km'), default='m',
                       help="length unit inside the CTLS weighting G (seed 000's G depends "
                            'on it; default m)')
        p.add_argument('--extent-km', default=None,
                       help='map extent: L (square [-L, L]) or XMIN,XMAX,YMIN,YMAX, km '
                            '(--extent-km=-10,...; map default 60; place default: area and '
                            'region)')
        p.add_argument('--resolution', type=float, default=None,
                       help='map cell size, m (default: extent / 400)')
        p.add_argument('--levels', default=None,
                       help='contour levels, m, comma-separated (default: automatic)')
        p.add_argument('--vmin', type=float, default=None,
                       help='lower end of the colour scale, m (default: the map minimum)')
        p.add_argument('--vmax', type=float, default=None,
                       help='upper end of the colour scale, m (default: 99th percentile)')
        if name == 'map':
            p.add_argument('--png', default=None, help='write the heat map here')
            p.add_argument('--csv', default=None,
                           help='write the grid here as x_m,y_m,z_m,error_m (default: next '
                                'to --png with .csv)')
            p.add_argument('--title', default=None, help='plot title')
        else:
            p.add_argument('--area-km', required=True,
                           help='area of interest XMIN,XMAX,YMIN,YMAX, km (write '
                                '--area-km=-10,10,-10,10 for a negative XMIN)')
            p.add_argument('--region-km', default=None,
                           help='where the new station may go, XMIN,XMAX,YMIN,YMAX, km '
                                '(--region-km=-30,...; default: the area)')
            p.add_argument('--height', type=float, default=None,
                           help='new station z, m (default: mean z of the stations)')
            p.add_argument('--new-1d', action='store_true',
                           help='the new station measures azimuth only')
            p.add_argument('--objective', choices=('mean', 'max'), default='mean',
                           help='minimise the mean (default) or worst error over the area')
            p.add_argument('--area-cells', type=int, default=30,
                           help='area grid cells per side (default 30)')
            p.add_argument('--candidates', type=int, default=21,
                           help='candidate grid points per side of the region (default 21)')
            p.add_argument('--png-before', default=None, help='map without the new station')
            p.add_argument('--png-after', default=None, help='map with the new station')


def run(args):
    """Dispatch to the sub-command."""
    return {'cut-angle': run_cut_angle, 'map': run_map,
            'place': run_place}[args.plan_command](args)


# ----------------------------------------------------------------------------------- parsing

#: Largest magnitude of any number given on the command line (m, mrad, ratios): beyond it
#: squares overflow float64 in the error models.
MAX_ABS = 1e12


def _finite(value, flag, positive=False):
    if value is None or not math.isfinite(value) or (positive and value <= 0) \
            or abs(value) > MAX_ABS:
        raise InputError(f'{flag}: must be a finite number{" > 0" if positive else ""} of '
                         f'magnitude <= {MAX_ABS:g}, got {value}')
    return value


def parse_values(text, flag):
    """'0.1:1.0:0.1,1.5' -> [0.1, 0.2, ..., 1.0, 1.5] (ranges inclusive of stop)."""
    out = []
    for part in str(text).split(','):
        part = part.strip()
        if not part:
            continue
        try:
            if ':' in part:
                a, b, s = (float(v) for v in part.split(':'))
                if not (s > 0 and b >= a and math.isfinite(a) and math.isfinite(b)):
                    raise ValueError
                n = (b - a) / s + 1e-9
                if not n + 1 + len(out) <= MAX_VALUES:
                    n = None
                else:
                    n = int(math.floor(n)) + 1
                    out.extend(round(a + i * s, 12) for i in range(n))
            else:
                out.append(float(part))
        except ValueError:
            raise InputError(f'{flag}: cannot parse {part!r} (numbers or start:stop:step)') \
                from None
        if ':' in part and n is None:
            raise InputError(f'{flag}: {part!r} gives more than {MAX_VALUES} values')
    if not out or not all(math.isfinite(v) for v in out):
        raise InputError(f'{flag}: need at least one finite value')
    return out


def parse_box_km(text, flag):
    """'L' -> (-L, L, -L, L) m; 'a,b,c,d' -> (a, b, c, d) m (km given)."""
    try:
        vals = [float(v) for v in str(text).split(',')]
    except ValueError:
        raise InputError(f'{flag}: expected L or XMIN,XMAX,YMIN,YMAX in km, got {text!r}') \
            from None
    if len(vals) == 1:
        vals = [-vals[0], vals[0], -vals[0], vals[0]]
    if len(vals) != 4 or not all(math.isfinite(v) and abs(v) * KM <= MAX_ABS for v in vals) \
            or vals[1] <= vals[0] or vals[3] <= vals[2]:
        raise InputError(f'{flag}: expected L > 0 or XMIN<XMAX,YMIN<YMAX in km, got {text!r}')
    return tuple(v * KM for v in vals)


def parse_stations(text, unit='km'):
    """'x,y,z[,1d|2d];...' -> (positions (N, 3) m, has_elevation (N,) bool)."""
    scale = KM if unit == 'km' else 1.0
    pos, dims = [], []
    for k, item in enumerate(s for s in str(text).split(';') if s.strip()):
        fields = [f.strip() for f in item.split(',')]
        kind = '2d'
        if len(fields) == 4:
            kind = fields.pop().lower()
        if len(fields) != 3 or kind not in ('1d', '2d'):
            raise InputError(f'--stations: station {k + 1}: expected x,y,z[,1d] '
                             f'({unit}), got {item!r}')
        try:
            xyz = [float(f) * scale for f in fields]
        except ValueError:
            raise InputError(f'--stations: station {k + 1}: non-numeric coordinate in '
                             f'{item!r}') from None
        if not all(math.isfinite(v) and abs(v) <= MAX_ABS for v in xyz):
            raise InputError(f'--stations: station {k + 1}: non-finite coordinate or one '
                             f'beyond {MAX_ABS:g} m')
        pos.append(xyz)
        dims.append(kind == '2d')
    if not pos:
        raise InputError('--stations: no station given')
    return np.array(pos), np.array(dims)


#: The σ flags: (flag, argparse dest, radians per unit, unit name); the mrad ones are the
#: deprecated former spellings of --sigma-deg and --sigma-elevation-deg.
SIGMA_FLAGS = (('--sigma-deg', 'sigma_deg', math.pi / 180.0, 'deg'),
               ('--sigma-azimuth-deg', 'sigma_azimuth_deg', math.pi / 180.0, 'deg'),
               ('--sigma-elevation-deg', 'sigma_elevation_deg', math.pi / 180.0, 'deg'),
               ('--sigma-mrad', 'sigma_mrad', 1e-3, 'mrad'),
               ('--sigma-el-mrad', 'sigma_el_mrad', 1e-3, 'mrad'))


def sigma_overrides(args):
    """(σ_θ, σ_ψ) in rad from the σ flags, each None when not given.

    σ_θ: --sigma-azimuth-deg, else --sigma-deg (or --sigma-mrad); σ_ψ: --sigma-elevation-deg
    (or --sigma-el-mrad), else --sigma-deg (or --sigma-mrad). InputError names the flag.
    """
    from ..core.bearings import SIGMA_MAX, SIGMA_MIN
    v = {}
    for flag, dest, scale, unit in SIGMA_FLAGS:
        value = getattr(args, dest, None)
        if value is None:
            continue
        rad = _finite(value, flag, True) * scale
        if not SIGMA_MIN <= rad <= SIGMA_MAX:
            raise InputError(f'{flag}: must be in [{SIGMA_MIN / scale:g}, '
                             f'{SIGMA_MAX / scale:g}] {unit}, got {value:g}')
        v[dest] = rad
    both = v.get('sigma_deg', v.get('sigma_mrad'))
    return (v.get('sigma_azimuth_deg', both),
            v.get('sigma_elevation_deg', v.get('sigma_el_mrad', both)))


def load_stations(args):
    """The :class:`~bearing_loc_ros.core.planning.Stations` of --scenario or --stations."""
    from ..core.planning import Stations
    saz, sel = sigma_overrides(args)
    if args.scenario:
        from ..core.simulation import load_scenario
        from ..scenarios import resolve_scenario
        st = Stations.from_scenario(load_scenario(resolve_scenario(args.scenario)), 0.0)
        if saz is None and sel is None:
            return st
        return Stations.from_arrays(st.positions, st.sigma_az if saz is None else saz,
                                    st.sigma_el if sel is None else sel, st.has_elevation,
                                    st.names)
    if saz is None:
        raise InputError('--sigma-deg: required with --stations (or --sigma-azimuth-deg)')
    pos, has_el = parse_stations(args.stations, args.stations_unit)
    return Stations.from_arrays(pos, saz, saz if sel is None else sel, has_el)


def _grid(args, default_box):
    from ..core.planning import GridSpec
    box = parse_box_km(args.extent_km, '--extent-km') if args.extent_km else default_box
    res = args.resolution
    if res is None:
        res = max(box[1] - box[0], box[3] - box[2]) / 400.0
    _finite(res, '--resolution', True)
    if res < 1e-3:
        raise InputError(f'--resolution: cell size {res:g} m is below 1 mm (widen --extent-km '
                         'or give a larger --resolution)')
    if max(box[1] - box[0], box[3] - box[2]) / res > 4000:
        raise InputError('--resolution: more than 4000 cells per side; use a larger cell')
    return GridSpec.from_extent(*box, res, _finite(args.altitude, '--altitude'))


def _ctls_unit(args):
    return KM if args.ctls_unit == 'km' else 1.0


def _levels(args):
    if args.levels is None:
        return None
    lv = sorted(v for v in parse_values(args.levels, '--levels'))
    if lv[0] <= 0:
        raise InputError('--levels: contour levels must be > 0 m')
    return lv


@contextlib.contextmanager
def _writing(flag, path):
    """Turn an OSError while writing ``path`` into an InputError naming ``flag``."""
    try:
        yield
    except OSError as exc:
        raise InputError(f'{flag}: cannot write {path!r} ({exc.strerror or exc})') from None


def _num(v):
    v = float(v)
    return v if math.isfinite(v) else None


# ---------------------------------------------------------------------------------- cut-angle

#: Largest variance ratio k1/k2 accepted (beyond it the cut-angle maths overflows float64).
MAX_RATIO = 1e6


def _ratio_bound(values, flag):
    if max(values) > MAX_RATIO:
        raise InputError(f'{flag}: variance ratios must be <= {MAX_RATIO:g}, got {max(values)}')


def run_cut_angle(args):
    """Print the optimum (JSON) or seed 004's tables."""
    from ..core.cutangle import cut_angle_table, optimal_cut_angle
    el = math.radians(_finite(args.elevation_deg, '--elevation-deg'))
    if abs(args.elevation_deg) >= 89.0:
        raise InputError('--elevation-deg: |elevation| must be < 89')
    if not args.table:
        _finite(args.k1, '--k1', True)
        if not (math.isfinite(args.k2) and args.k2 >= 0):
            raise InputError(f'--k2: must be a finite number >= 0, got {args.k2}')
        _ratio_bound([args.k1], '--k1')
        _ratio_bound([args.k2], '--k2')
        print(json.dumps(optimal_cut_angle(args.k1, args.k2, el).as_dict()))
        return 0
    k1s = parse_values(args.k1_values, '--k1-values')
    k2s = parse_values(args.k2_values, '--k2-values')
    if min(k1s) <= 0:
        raise InputError('--k1-values: every k1 must be > 0')
    if min(k2s) < 0:
        raise InputError('--k2-values: every k2 must be >= 0')
    _ratio_bound(k1s, '--k1-values')
    _ratio_bound(k2s, '--k2-values')
    rows = [r.as_dict() for r in cut_angle_table(k1s, k2s, el)]
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print(f'# seed 004 optimal cut angle, elevation {args.elevation_deg:g} deg '
          '(f: E_r^2 = D^2 sigma_theta2^2 f; infeasible rows show the limit point)')
    head = f'{"k1":>6} {"k2":>6} {"eps1":>6} {"theta1":>9} {"theta2":>9} {"phi":>9} ' \
           f'{"f_min":>9}  feasible'
    last_k2 = None
    for r in rows:
        if r['k2'] != last_k2:
            print(f'\n{head}')
            last_k2 = r['k2']
        print(f'{r["k1"]:6.3g} {r["k2"]:6.3g} {r["elevation_deg"]:6.3g} '
              f'{r["theta1_deg"]:9.3f} {r["theta2_deg"]:9.3f} {r["cut_angle_deg"]:9.3f} '
              f'{r["f_min"]:9.5f}  {"yes" if r["feasible"] else "no"}')
    return 0


# -------------------------------------------------------------------------------- maps, plots

def _nice_levels(err, vmax):
    fin = err[np.isfinite(err)]
    if not fin.size:
        return []
    lo, hi = float(fin.min()), float(min(vmax, fin.max()))
    out = []
    for e in range(int(math.floor(math.log10(max(lo, 1e-9)))) - 1,
                   int(math.ceil(math.log10(max(hi, 1e-9)))) + 1):
        for m in (1, 1.5, 2, 3, 5, 7):
            v = m * 10 ** e
            if lo < v < hi:
                out.append(v)
    while len(out) > 12:
        out = out[::2]
    return out


def plot_map(amap, path, title=None, levels=None, vmax=None, extra=None, vmin=None):
    """Heat map (log colour scale) with labelled contours in metres and the stations.

    ``extra``: optional dict with 'area'/'region' boxes (m) and 'new' station (3,) to draw.
    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    g = amap.grid
    err = amap.error
    fin = err[np.isfinite(err) & (err > 0)]
    if not fin.size:
        raise InputError('map: no finite error anywhere (unobservable layout); nothing to plot')
    vmin = float(fin.min()) if vmin is None else float(vmin)
    vmax = float(np.percentile(fin, 99)) if vmax is None else float(vmax)
    vmax = max(vmax, vmin * 1.01)
    fig, ax = plt.subplots(figsize=(6.4, 5.2), dpi=100)
    ext = [v / KM for v in g.extent]
    im = ax.imshow(np.where(np.isfinite(err), err, np.nan), origin='lower', extent=ext,
                   norm=LogNorm(vmin, vmax), cmap='viridis', interpolation='nearest')
    fig.colorbar(im, ax=ax, label='expected 3D position error (m)')
    lv = levels if levels is not None else _nice_levels(err, vmax)
    if lv:
        cs = ax.contour(g.x / KM, g.y / KM, np.where(np.isfinite(err), err, np.nan),
                        levels=lv, colors='white', linewidths=0.6)
        ax.clabel(cs, fmt=lambda v: f'{v:g}', fontsize=7)
    st = amap.stations
    if st is not None:
        two = st.has_elevation
        ax.plot(st.positions[two, 0] / KM, st.positions[two, 1] / KM, '^', color='red',
                mec='black', ms=8, label='2D station')
        if np.any(~two):
            ax.plot(st.positions[~two, 0] / KM, st.positions[~two, 1] / KM, 'v',
                    color='orange', mec='black', ms=8, label='1D station')
    extra = extra or {}
    for key, style in (('area', 'w--'), ('region', 'r:')):
        if key in extra:
            x0, x1, y0, y1 = (v / KM for v in extra[key])
            ax.plot([x0, x1, x1, x0, x0], [y0, y0, y1, y1, y0], style, lw=1, label=key)
    if 'new' in extra:
        ax.plot(extra['new'][0] / KM, extra['new'][1] / KM, '*', color='magenta', mec='black',
                ms=14, label='new station')
    ax.set_xlabel('x East (km)')
    ax.set_ylabel('y North (km)')
    ax.set_xlim(ext[0], ext[1])
    ax.set_ylim(ext[2], ext[3])
    ax.legend(loc='upper right', fontsize=7, framealpha=0.7)
    ax.set_title(title or f'{amap.model.upper()} expected error, altitude '
                          f'{g.altitude / KM:g} km', fontsize=10)
    fig.tight_layout()
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def write_csv(amap, path):
    """x_m,y_m,z_m,error_m rows in OccupancyGrid order (row-major, row = y)."""
    pts = amap.grid.points()
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    np.savetxt(path, np.column_stack([pts, amap.error.ravel()]), delimiter=',',
               fmt=['%.3f', '%.3f', '%.3f', '%.6g'], header='x_m,y_m,z_m,error_m',
               comments='')


def _stations_json(st):
    return [{'name': n, 'position_m': [float(v) for v in p], 'dims': 2 if e else 1,
             'sigma_az_mrad': float(sa) * 1e3,
             'sigma_el_mrad': _num(se * 1e3) if e else None}
            for n, p, e, sa, se in zip(st.names, st.positions, st.has_elevation,
                                       st.sigma_az, st.sigma_el)]


def _grid_json(g):
    return {'origin_m': [g.origin_x, g.origin_y], 'resolution_m': g.resolution,
            'width': g.width, 'height': g.height, 'altitude_m': g.altitude}


def run_map(args):
    """Compute the map, write PNG/CSV, print a JSON summary."""
    from ..core.planning import accuracy_map
    st = load_stations(args)
    grid = _grid(args, parse_box_km('60', '--extent-km'))
    levels = _levels(args)
    for flag, v in (('--vmin', args.vmin), ('--vmax', args.vmax)):
        if v is not None:
            _finite(v, flag, True)
    amap = accuracy_map(st, grid, args.model, _ctls_unit(args))
    out = {'model': args.model, 'stations': _stations_json(st), 'grid': _grid_json(grid),
           'stats': amap.stats()}
    csv = args.csv
    if csv is None and args.png:
        csv = os.path.splitext(args.png)[0] + '.csv'
    if args.png:
        with _writing('--png', args.png):
            plot_map(amap, args.png, args.title, levels, args.vmax, vmin=args.vmin)
        out['png'] = args.png
    if csv:
        with _writing('--csv', csv):
            write_csv(amap, csv)
        out['csv'] = csv
    print(json.dumps(out))
    return 0


def run_place(args):
    """Suggest one more station; print before/after (JSON); optional maps."""
    from ..core.planning import GridSpec, accuracy_map, place_station
    st = load_stations(args)
    area = parse_box_km(args.area_km, '--area-km')
    region = parse_box_km(args.region_km, '--region-km') if args.region_km else area
    if args.area_cells < 2 or args.area_cells > 200:
        raise InputError(f'--area-cells: must be 2..200, got {args.area_cells}')
    if args.candidates < 2 or args.candidates > 101:
        raise InputError(f'--candidates: must be 2..101, got {args.candidates}')
    alt = _finite(args.altitude, '--altitude')
    height = float(np.mean(st.positions[:, 2])) if args.height is None \
        else _finite(args.height, '--height')
    res = max(area[1] - area[0], area[3] - area[2]) / args.area_cells
    area_grid = GridSpec(area[0], area[2], res, max(1, round((area[1] - area[0]) / res)),
                         max(1, round((area[3] - area[2]) / res)), alt)
    res_new = place_station(st, area_grid, region, height, has_elevation=not args.new_1d,
                            objective=args.objective, model=args.model,
                            candidates=args.candidates, length_unit=_ctls_unit(args))
    out = res_new.as_dict()
    out.update(model=args.model, stations=_stations_json(st), area_m=list(area),
               region_m=list(region), new_station_dims=1 if args.new_1d else 2)
    if args.png_before or args.png_after:
        box = (min(area[0], region[0]), max(area[1], region[1]),
               min(area[2], region[2]), max(area[3], region[3]))
        pad = 0.15 * max(box[1] - box[0], box[3] - box[2])
        box = (box[0] - pad, box[1] + pad, box[2] - pad, box[3] + pad)
        grid = _grid(args, box)
        levels = _levels(args)
        after_st = st.with_station(res_new.position, st.sigma_az[0],
                                   st.sigma_el[0] if st.has_elevation[0] else st.sigma_az[0],
                                   not args.new_1d)
        extra = {'area': area, 'region': region}
        maps = {'before': (args.png_before, st), 'after': (args.png_after, after_st)}
        # One colour scale for both maps so they can be compared.
        before = accuracy_map(st, grid, args.model, _ctls_unit(args))
        fin = before.error[np.isfinite(before.error)]
        vmax = args.vmax or (float(np.percentile(fin, 99)) if fin.size else None)
        for key, (path, layout) in maps.items():
            if not path:
                continue
            amap = before if key == 'before' else accuracy_map(layout, grid, args.model,
                                                               _ctls_unit(args))
            ex = dict(extra, new=res_new.position) if key == 'after' else extra
            with _writing(f'--png-{key}', path):
                plot_map(amap, path, f'{args.model.upper()} error {key} adding a station, '
                                     f'altitude {alt / KM:g} km', levels, vmax, ex, args.vmin)
            out[f'png_{key}'] = path
    print(json.dumps(out))
    return 0


if __name__ == '__main__':  # pragma: no cover
    from . import main
    sys.exit(main(['plan'] + sys.argv[1:]))
