"""``bearing_loc plan``: where to put stations (docs/planning.md).

Sub-commands:

* ``cut-angle``: the optimal cut angle (Wang, Su, Bai & Zhong 2009) of a 2D + 1D sensor
  pair (JSON), or its tables 1-4 for ranges of k1 and k2 (``--table``).
* ``map``: expected 3D position error over a grid at one target altitude (CRLB or the CTLS
  error model of Wang, Zhang & Wu), written as a PNG heat map with labelled contours and as CSV.
* ``place``: the position of one more station that minimises the mean (or worst) expected
  error over an area, with the before/after figures (JSON) and optional maps; "before" is
  assessed with the solve the existing stations need, "after" with the one the layout with
  the new station needs (``solve_before``, ``solve``: docs/planning.md).

Stations come from a simulator scenario (``--scenario``, core.simulation.load_scenario) or
from ``--stations 'x,y,z[,1d];x,y,z;...'`` in ``--stations-unit`` (km by default). A value
that starts with a minus sign may follow its option directly (``--area-km -10,10,-10,10``)
or be attached with '='.
"""

import json
import math
import os
import sys

import numpy as np

from . import InputError, writing
from .deprecation import DeprecatedOption
from .helptext import sub_command
from .plan_args import (color_limits, contour_levels, ctls_unit, finite, grid_spec,
                        image_path, KM, load_stations, num_or_none, output_file,
                        parse_box_km, parse_values)


def add_arguments(parser):
    """Register the ``plan`` sub-commands."""
    sub = parser.add_subparsers(dest='plan_command', metavar='COMMAND')
    sub.required = True

    p = sub_command(sub, 'cut-angle', 'optimal cut angle of a 2D + 1D sensor pair (Wang, Su, '
                    'Bai & Zhong 2009)', 'bearing_loc plan cut-angle --k1 0.8 --k2 0.5 '
                    '--elevation-deg 10')
    p.add_argument('--k1', type=float, default=None,
                   help='sigma_theta1^2 / sigma_theta2^2, azimuth variance ratio (default 1)')
    p.add_argument('--k2', type=float, default=None,
                   help='sigma_eps1^2 / sigma_theta2^2, elevation variance ratio of the 2D '
                        'sensor (default 0: two 1D sensors when --elevation-deg is 0)')
    p.add_argument('--elevation-deg', type=float, default=None,
                   help='target elevation eps1 seen from the 2D sensor, deg (default 0)')
    p.add_argument('--table', action='store_true',
                   help='print the tables of Wang, Su, Bai & Zhong 2009: every --k1-values x '
                        '--k2-values pair')
    p.add_argument('--k1-values', default=None,
                   help='k1 list for --table: comma-separated numbers or start:stop:step '
                        'ranges (default 0.1:1.0:0.1,1.2,1.5,2.0)')
    p.add_argument('--k2-values', default=None,
                   help='k2 list for --table (default 0,0.2,0.5,0.8: tables 1-4)')
    p.add_argument('--json', action='store_true', help='--table as a JSON list')
    p.add_argument('--sigmas-deg', type=float, nargs=2, default=None, metavar=('S1', 'S2'),
                   help='two azimuth-only (1D + 1D) sensors with azimuth sigmas S1, S2 (deg): '
                        'the optimum on a fixed baseline (equal sigmas: 109.47 deg; 90 deg is '
                        'the optimum for fixed target ranges)')

    for name, help_text, example in (
            ('map', 'expected-error map of a station layout',
             'bearing_loc plan map --scenario seed000 --altitude 5000 --png map.png'),
            ('place', 'best position for one more station',
             'bearing_loc plan place --scenario seed000 --altitude 5000 '
             '--area-km -20,40,-20,30')):
        p = sub_command(sub, name, help_text, example)
        src = p.add_mutually_exclusive_group(required=True)
        src.add_argument('--scenario', help='scenario YAML, a path or the name of a shipped '
                                            'scenario (seed000); station positions at t = 0')
        src.add_argument('--stations',
                         help="'x,y,z[,1d];x,y,z;...' station positions (2D unless ',1d'); "
                              'in --stations-unit')
        p.add_argument('--stations-unit', choices=('km', 'm'), default='km',
                       help='unit of --stations coordinates (default km)')
        p.add_argument('--altitude', type=float, required=True,
                       help='target altitude (ENU z), m')
        p.add_argument('--dimension', choices=('auto', '3d', 'horizontal'), default='auto',
                       help='auto (default: the horizontal solve, altitude known, when no '
                            'station measures elevation), 3d or horizontal (error sqrt(Pxx + '
                            'Pyy) of the 2 x 2 CRLB)')
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
                       help='error model: crlb (default) or ctls (Wang, Zhang & Wu eqs. '
                            '(30)-(32))')
        p.add_argument('--ctls-unit', choices=('m', 'km'), default='m',
                       help='length unit inside the CTLS weighting G (Wang, Zhang & Wu: G '
                            'depends on it; default m)')
        p.add_argument('--extent-km', default=None,
                       help='map extent: L (square [-L, L]) or XMIN,XMAX,YMIN,YMAX, km '
                            '(--extent-km=-10,...; map default 60; place default: area and '
                            'region)')
        p.add_argument('--resolution', type=float, default=None,
                       help='map cell size, m (default: extent / 400)')
        p.add_argument('--levels', default=None,
                       help='contour levels, m, comma-separated (default: automatic)')
        p.add_argument('--vmin', type=float, default=None,
                       help='lower end of the colour scale, m, below --vmax (default: the map '
                            'minimum)')
        p.add_argument('--vmax', type=float, default=None,
                       help='upper end of the colour scale, m (default: 99th percentile)')
        if name == 'map':
            p.add_argument('--png', default=None,
                           help='write the heat map to this image file (.png added to a name '
                                'without an extension)')
            p.add_argument('--csv', default=None,
                           help='write the grid here as x_m,y_m,z_m,error_m (default: next '
                                'to --png with .csv)')
            p.add_argument('--title', default=None, help='plot title')
            from .gisargs import add_gis_arguments
            add_gis_arguments(p, fixes=False)
        else:
            p.add_argument('--area-km', required=True,
                           help='area of interest XMIN,XMAX,YMIN,YMAX, km (required; a '
                                'negative XMIN may follow directly: --area-km -10,10,-10,10)')
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


# ---------------------------------------------------------------------------------- cut-angle

#: Largest variance ratio k1/k2 accepted (beyond it the cut-angle maths overflows float64).
MAX_RATIO = 1e6


def _ratio_bound(values, flag):
    if max(values) > MAX_RATIO:
        raise InputError(f'{flag}: variance ratios must be <= {MAX_RATIO:g}, got {max(values)}')


def run_cut_angle(args):
    """Print the optimum (JSON) or the tables of Wang, Su, Bai & Zhong 2009."""
    from ..core.cutangle import cut_angle_table, optimal_cut_angle
    pair = {'--k1': args.k1, '--k2': args.k2, '--elevation-deg': args.elevation_deg,
            '--table': args.table or None, '--k1-values': args.k1_values,
            '--k2-values': args.k2_values}
    given = [flag for flag, v in pair.items() if v is not None]
    if args.sigmas_deg is not None:
        if given:
            raise InputError(f'--sigmas-deg: not with {given[0]} (--sigmas-deg is a 1D + 1D '
                             'pair; the other flags describe a 2D + 1D pair)')
        return run_two_azimuth(args)
    for flag in (('--k1', '--k2') if args.table else ('--k1-values', '--k2-values')):
        if flag in given:
            raise InputError(f'{flag}: only {"without" if args.table else "with"} --table')
    elevation_deg = 0.0 if args.elevation_deg is None else args.elevation_deg
    el = math.radians(finite(elevation_deg, '--elevation-deg'))
    if abs(elevation_deg) >= 89.0:
        raise InputError('--elevation-deg: |elevation| must be < 89')
    if not args.table:
        k1 = 1.0 if args.k1 is None else args.k1
        k2 = 0.0 if args.k2 is None else args.k2
        finite(k1, '--k1', True)
        if not (math.isfinite(k2) and k2 >= 0):
            raise InputError(f'--k2: must be a finite number >= 0, got {k2}')
        _ratio_bound([k1], '--k1')
        _ratio_bound([k2], '--k2')
        # the elevation as given (its degrees -> radians -> degrees would print 29.999...96)
        print(json.dumps(dict(optimal_cut_angle(k1, k2, el).as_dict(),
                              elevation_deg=elevation_deg)))
        return 0
    k1s = parse_values(args.k1_values or '0.1:1.0:0.1,1.2,1.5,2.0', '--k1-values')
    k2s = parse_values(args.k2_values or '0,0.2,0.5,0.8', '--k2-values')
    if min(k1s) <= 0:
        raise InputError('--k1-values: every k1 must be > 0')
    if min(k2s) < 0:
        raise InputError('--k2-values: every k2 must be >= 0')
    _ratio_bound(k1s, '--k1-values')
    _ratio_bound(k2s, '--k2-values')
    rows = [dict(r.as_dict(), elevation_deg=elevation_deg)
            for r in cut_angle_table(k1s, k2s, el)]
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print('# optimal cut angle (Wang, Su, Bai & Zhong 2009), '
          f'elevation {elevation_deg:g} deg '
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


def run_two_azimuth(args):
    """Two azimuth-only sensors (Wang, Su, Bai & Zhong 2009, 1D + 1D): print the optimum."""
    from ..core.horizontal_crlb import optimal_cut_angle_two_azimuth
    s1, s2 = (finite(v, '--sigmas-deg', True) for v in args.sigmas_deg)
    try:
        r = optimal_cut_angle_two_azimuth(math.radians(s1), math.radians(s2))
    except ValueError as exc:
        raise InputError(f'--sigmas-deg: {exc}') from None
    print(json.dumps({'sensors': '1D+1D', 'sigma1_deg': s1, 'sigma2_deg': s2, 'k': r.k,
                      'theta1_deg': math.degrees(r.theta1),
                      'theta2_deg': math.degrees(r.theta2),
                      'cut_angle_deg': math.degrees(r.cut_angle), 'f_min': r.f,
                      'feasible': bool(r.feasible), 'fixed_range_cut_angle_deg': 90.0}))
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

    from ..core.display import log_color_limits
    g = amap.grid
    err = amap.error
    limits = log_color_limits(err, vmin, vmax)
    fig, ax = plt.subplots(figsize=(6.4, 5.2), dpi=100)
    ext = [v / KM for v in g.extent]
    if limits is None:
        # Nothing is observable (e.g. one station before a placement): the layout alone.
        ax.set_facecolor('0.8')
        ax.text(0.5, 0.75, 'no target here can be located\n(unobservable layout)',
                transform=ax.transAxes, ha='center', va='center', fontsize=11)
    else:
        vmin, vmax = limits
        im = ax.imshow(np.where(np.isfinite(err), err, np.nan), origin='lower', extent=ext,
                       norm=LogNorm(vmin, vmax), cmap='viridis', interpolation='nearest')
        kind = 'horizontal' if amap.solve == 'horizontal' else '3D'
        fig.colorbar(im, ax=ax, label=f'expected {kind} position error (m)')
        lv = levels if levels is not None else _nice_levels(err, vmax)
        if lv:
            cs = ax.contour(g.x / KM, g.y / KM, np.where(np.isfinite(err), err, np.nan),
                            levels=lv, colors='white', linewidths=0.6)
            ax.clabel(cs, fmt=lambda v: f'{v:g}', fontsize=7)
    st = amap.stations
    if st is not None:
        two = st.has_elevation
        if np.any(two):
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
    fig.savefig(path)
    plt.close(fig)


def write_csv(amap, path):
    """x_m,y_m,z_m,error_m rows in OccupancyGrid order (row-major, row = y)."""
    pts = amap.grid.points()
    np.savetxt(path, np.column_stack([pts, amap.error.ravel()]), delimiter=',',
               fmt=['%.3f', '%.3f', '%.3f', '%.6g'], header='x_m,y_m,z_m,error_m',
               comments='')


def _stations_json(st):
    return [{'name': n, 'position_m': [float(v) for v in p], 'dims': 2 if e else 1,
             'sigma_az_mrad': float(sa) * 1e3,
             'sigma_el_mrad': num_or_none(se * 1e3) if e else None}
            for n, p, e, sa, se in zip(st.names, st.positions, st.has_elevation,
                                       st.sigma_az, st.sigma_el)]


def _grid_json(g):
    return {'origin_m': [g.origin_x, g.origin_y], 'resolution_m': g.resolution,
            'width': g.width, 'height': g.height, 'altitude_m': g.altitude}


def run_map(args):
    """Compute the map, write PNG/CSV, print a JSON summary."""
    from ..core.planning import accuracy_map
    st = load_stations(args)
    grid = grid_spec(args, parse_box_km('60', '--extent-km'))
    levels = contour_levels(args)
    color_limits(args)
    if args.png:
        args.png = output_file('--png', image_path('--png', args.png))
    if args.csv is None and args.png:
        args.csv = os.path.splitext(args.png)[0] + '.csv'
    if args.csv:
        output_file('--csv', args.csv)
    from .gisargs import check
    check(args)             # --kml and --origin, before the work
    from ..core.planning import horizontal_solve
    if args.model != 'crlb' and horizontal_solve(st, args.dimension):
        # (auto keeps the 3D model for place, whose new station may measure elevation; a map
        # of an azimuth-only layout would be unobservable everywhere)
        raise InputError('--model: the CTLS error model (Wang, Zhang & Wu eq. (30)) is 3D; the '
                         'horizontal solve (an azimuth-only layout, or --dimension horizontal) '
                         'needs --model crlb')
    try:
        amap = accuracy_map(st, grid, args.model, ctls_unit(args), args.dimension)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    out = {'model': args.model, 'solve': amap.solve, 'stations': _stations_json(st),
           'grid': _grid_json(grid), 'stats': amap.stats()}
    csv = args.csv
    if args.png:
        with writing('--png', args.png):
            plot_map(amap, args.png, args.title, levels, args.vmax, vmin=args.vmin)
        out['png'] = args.png
    if csv:
        with writing('--csv', csv):
            write_csv(amap, csv)
        out['csv'] = csv
    from .gisargs import export_plan_map
    out.update(export_plan_map(args, amap))
    print(json.dumps(out))
    return 0


def _solve_of(stations, args, new_has_elevation=False):
    """``horizontal`` or ``3d``: the solve ``plan place`` assesses ``stations`` (plus a new
    station measuring elevation or not) with, as ``plan map`` would that layout."""
    from ..core.planning import horizontal_crlb_applies, horizontal_solve
    try:
        horizontal = horizontal_crlb_applies(
            args.model, horizontal_solve(stations, args.dimension, new_has_elevation),
            args.dimension)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    return 'horizontal' if horizontal else '3d'


def _before_figures(amap, result):
    """The "before" figures of a placement from the existing layout's own map over the area
    (``amap``): before_m, improvement_m, ratio (as core.planning.PlacementResult) and the
    before statistics."""
    from ..core.planning import objective_value
    before = float(objective_value(amap.error.ravel(), result.objective))
    after = float(result.after)
    finite_before = math.isfinite(before)
    return {'before_m': num_or_none(before),
            'improvement_m': num_or_none(before - after if finite_before else math.inf),
            'ratio': num_or_none(after / before if finite_before and before > 0 else math.nan),
            'before': amap.stats()}


def run_place(args):
    """Suggest one more station; print before/after (JSON); optional maps."""
    from ..core.planning import GridSpec, accuracy_map, place_station
    st = load_stations(args)
    area = parse_box_km(args.area_km, '--area-km')
    for key in ('png_before', 'png_after'):
        if getattr(args, key):
            flag = '--' + key.replace('_', '-')
            setattr(args, key, output_file(flag, image_path(flag, getattr(args, key))))
    region = parse_box_km(args.region_km, '--region-km') if args.region_km else area
    color_limits(args)
    if args.area_cells < 2 or args.area_cells > 200:
        raise InputError(f'--area-cells: must be 2..200, got {args.area_cells}')
    if args.candidates < 2 or args.candidates > 101:
        raise InputError(f'--candidates: must be 2..101, got {args.candidates}')
    alt = finite(args.altitude, '--altitude')
    height = float(np.mean(st.positions[:, 2])) if args.height is None \
        else finite(args.height, '--height')
    res = max(area[1] - area[0], area[3] - area[2]) / args.area_cells
    area_grid = GridSpec(area[0], area[2], res, max(1, round((area[1] - area[0]) / res)),
                         max(1, round((area[3] - area[2]) / res)), alt)
    grid = levels = None
    if args.png_before or args.png_after:
        box = (min(area[0], region[0]), max(area[1], region[1]),
               min(area[2], region[2]), max(area[3], region[3]))
        pad = 0.15 * max(box[1] - box[0], box[3] - box[2])
        grid = grid_spec(args, (box[0] - pad, box[1] + pad, box[2] - pad, box[3] + pad))
        levels = contour_levels(args)
    # Each layout is assessed with the solve it needs (docs/planning.md): the existing
    # stations with their own (an azimuth-only layout: horizontal, altitude known), the
    # layout with the new station with its (3D when the new station measures elevation).
    solve_before = _solve_of(st, args)
    solve_after = _solve_of(st, args, not args.new_1d)
    try:
        res_new = place_station(st, area_grid, region, height, has_elevation=not args.new_1d,
                                objective=args.objective, model=args.model,
                                candidates=args.candidates, length_unit=ctls_unit(args),
                                dimension=args.dimension)
        out = res_new.as_dict()
        if solve_before != solve_after:     # the placement's "before" used the after solve
            out.update(_before_figures(accuracy_map(st, area_grid, args.model,
                                                    ctls_unit(args), solve_before), res_new))
    except ValueError as exc:
        raise InputError(str(exc)) from None
    out.update(model=args.model, stations=_stations_json(st), area_m=list(area),
               region_m=list(region), new_station_dims=1 if args.new_1d else 2,
               solve=solve_after, solve_before=solve_before)
    if grid is not None:
        after_st = st.with_station(res_new.position, st.sigma_az[0],
                                   st.sigma_el[0] if st.has_elevation[0] else st.sigma_az[0],
                                   not args.new_1d)
        extra = {'area': area, 'region': region}
        maps = {'before': (args.png_before, st), 'after': (args.png_after, after_st)}
        # One colour scale for both maps so they can be compared.
        before = accuracy_map(st, grid, args.model, ctls_unit(args), solve_before)
        fin = before.error[np.isfinite(before.error)]
        vmax = args.vmax or (float(np.percentile(fin, 99)) if fin.size else None)
        for key, (path, layout) in maps.items():
            if not path:
                continue
            amap = before if key == 'before' else accuracy_map(layout, grid, args.model,
                                                               ctls_unit(args), solve_after)
            ex = dict(extra, new=res_new.position) if key == 'after' else extra
            with writing(f'--png-{key}', path):
                plot_map(amap, path, f'{args.model.upper()} error {key} adding a station, '
                                     f'altitude {alt / KM:g} km', levels, vmax, ex, args.vmin)
            out[f'png_{key}'] = path
    print(json.dumps(out))
    return 0


if __name__ == '__main__':  # pragma: no cover
    from . import main
    sys.exit(main(['plan'] + sys.argv[1:]))
