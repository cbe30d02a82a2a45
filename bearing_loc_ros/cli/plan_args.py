"""Argument parsing of ``bearing_loc plan``: numbers, lists, boxes, stations and their σ.

Every function raises InputError naming the flag.
"""

import math
import os

import numpy as np

from . import InputError

KM = 1000.0
#: Most values a --k1-values/--k2-values/--levels list may expand to (start:stop:step).
MAX_VALUES = 10000

# ----------------------------------------------------------------------------------- parsing

#: Largest magnitude of any number given on the command line (m, mrad, ratios): beyond it
#: squares overflow float64 in the error models.
MAX_ABS = 1e12


def finite(value, flag, positive=False):
    """``value`` if finite with |value| <= MAX_ABS (and > 0 if ``positive``), else InputError."""
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
        rad = finite(value, flag, True) * scale
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


def grid_spec(args, default_box):
    """GridSpec of --extent-km (else ``default_box`` (xmin, xmax, ymin, ymax), m), --resolution.

    Cell size in m (default: the longer side / 400; at least 1 mm, at most 4000 cells per
    side and at most the shorter side) at target altitude --altitude (m, world z).
    """
    from ..core.planning import GridSpec
    box = parse_box_km(args.extent_km, '--extent-km') if args.extent_km else default_box
    res = args.resolution
    if res is None:
        res = max(box[1] - box[0], box[3] - box[2]) / 400.0
    finite(res, '--resolution', True)
    if res < 1e-3:
        raise InputError(f'--resolution: cell size {res:g} m is below 1 mm (widen --extent-km '
                         'or give a larger --resolution)')
    if max(box[1] - box[0], box[3] - box[2]) / res > 4000:
        raise InputError('--resolution: more than 4000 cells per side; use a larger cell')
    if res > min(box[1] - box[0], box[3] - box[2]):
        raise InputError(f'--resolution: cell size {res:g} m exceeds the map extent '
                         f'({box[1] - box[0]:g} m x {box[3] - box[2]:g} m)')
    return GridSpec.from_extent(*box, res, finite(args.altitude, '--altitude'))


def ctls_unit(args):
    """Length unit (m) inside the CTLS weighting G (Wang, Zhang & Wu): 1000 for km, else 1."""
    return KM if args.ctls_unit == 'km' else 1.0


def contour_levels(args):
    """Sorted contour levels of --levels (m, all > 0), or None for automatic levels."""
    if args.levels is None:
        return None
    lv = sorted(v for v in parse_values(args.levels, '--levels'))
    if lv[0] <= 0:
        raise InputError('--levels: contour levels must be > 0 m')
    return lv


def color_limits(args):
    """Check --vmin and --vmax (m): each finite and > 0, and --vmin below --vmax."""
    for flag, v in (('--vmin', args.vmin), ('--vmax', args.vmax)):
        if v is not None:
            finite(v, flag, True)
    if args.vmin is not None and args.vmax is not None and args.vmin >= args.vmax:
        raise InputError(f'--vmin: must be below --vmax (got --vmin {args.vmin:g}, --vmax '
                         f'{args.vmax:g})')


def image_path(flag, path):
    """The file an image for ``path`` is written to: ``path`` + ``.png`` without an
    extension (as matplotlib writes it); InputError naming ``flag`` for a directory (an
    existing one, or a path ending in '/') or an extension matplotlib cannot write."""
    if path.endswith(('/', os.sep)) or os.path.isdir(path):
        raise InputError(f'{flag}: {path!r} is a directory; give an image file name '
                         f'(e.g. {os.path.join(path, "map.png")!r})')
    ext = os.path.splitext(path)[1].lower().lstrip('.')
    if not ext:
        return path + '.png'
    from matplotlib.backend_bases import FigureCanvasBase
    known = FigureCanvasBase.get_supported_filetypes()
    if ext not in known:
        raise InputError(f'{flag}: cannot write .{ext} images; use one of '
                         f'{", ".join("." + k for k in sorted(known))}')
    return path


def output_file(flag, path):
    """``path`` when it names a file in an existing directory (nothing is created); else an
    InputError naming ``flag``, before the work (docs/cli.md: as ``locate``'s outputs)."""
    if path.endswith(('/', os.sep)) or os.path.isdir(path):
        raise InputError(f'{flag}: cannot write {path!r} (is a directory; give a file name)')
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise InputError(f'{flag}: cannot write {path!r} (directory {directory!r} does not '
                         'exist)')
    return path


def num_or_none(v):
    """``float(v)``, or None when it is NaN or infinite (JSON has no such numbers)."""
    v = float(v)
    return v if math.isfinite(v) else None
