"""Geographic export flags shared by ``bag process``, ``locate`` and ``plan map``.

``--geojson FILE`` (RFC 7946), ``--kml FILE`` (with the accuracy map as a GroundOverlay PNG
next to it where there is one), ``--geo-csv FILE`` (fixes, ENU and latitude/longitude), all
about the geodetic origin ``--origin LAT LON ALT`` (degrees, degrees, m on WGS84; ``bag
process`` also takes the fusion parameter ``geodetic_origin``). Error ellipses are drawn at
``--ellipse-probability`` (default 0.95: the 2-dof chi-square quantile of the horizontal
marginal, core.gis.ellipse_scale).
"""

import math
import os

import numpy as np

from . import InputError, writing

#: Side of the bag-process accuracy overlay: this factor x the largest horizontal distance of
#: a station from the stations' centroid (as the fusion node's automatic accuracy_map).
OVERLAY_SIZE_FACTOR = 3.0
OVERLAY_MIN_SIZE = 100.0
OVERLAY_CELLS = 200


def add_gis_arguments(parser, fixes=True):
    """Add the export flags; ``fixes`` False (plan map) offers only --kml and --origin."""
    g = parser.add_argument_group('geographic export (needs a geodetic origin)')
    if fixes:
        g.add_argument('--geojson', default=None, metavar='FILE',
                       help='write fixes, error ellipses, stations and bearing rays as '
                            'GeoJSON (RFC 7946, WGS84 lon/lat)')
    g.add_argument('--kml', default=None, metavar='FILE',
                   help='write a KML file' + (' (fixes, ellipses, stations, bearing rays' if
                                              fixes else ' (stations') +
                        ', accuracy map as a GroundOverlay PNG next to it)')
    if fixes:
        g.add_argument('--geo-csv', default=None, metavar='FILE',
                       help='write the fixes as CSV with latitude/longitude next to ENU')
        g.add_argument('--ellipse-probability', type=float, default=0.95, metavar='P',
                       help='probability of the drawn error ellipses (default 0.95)')
    g.add_argument('--origin', type=float, nargs=3, default=None,
                   metavar=('LAT_DEG', 'LON_DEG', 'ALT_M'),
                   help='geodetic origin of the ENU frame (WGS84)')


def wanted(args):
    """True when any geographic output was asked for."""
    return any(getattr(args, k, None) for k in ('geojson', 'kml', 'geo_csv'))


def origin_of(args, params=None):
    """The geodetic origin: --origin, else the ``geodetic_origin`` parameter; InputError."""
    from ..core import gis
    origin = args.origin
    if origin is None and params and params.get('geodetic_origin'):
        origin = list(params['geodetic_origin'])
    if origin is None:
        # Only the verbs that read node parameters (bag process) take -p.
        hint = ' (or -p geodetic_origin=[lat,lon,alt])' if params is not None else ''
        raise InputError('origin: --geojson/--kml/--geo-csv need a geodetic origin: '
                         f'--origin LAT_DEG LON_DEG ALT_M{hint}')
    try:
        return gis.check_origin(origin)
    except ValueError as exc:
        raise InputError(str(exc)) from None


def _same_file(a, b):
    """Whether paths ``a`` and ``b`` name one file (an existing one, or the same path)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def _check_paths(args, reserved=()):
    """Every output path names a file in an existing directory, not the input, not another
    output's file (nor one of ``reserved``: (flag, path) pairs the verb writes itself, as
    ``bag process --out``'s OUT.csv), nor the accuracy image of --kml;
    --ellipse-probability in (0, 1). InputError naming the flag."""
    given = list(reserved)
    source = getattr(args, 'input', None)
    for flag in ('geojson', 'kml', 'geo_csv'):
        path = getattr(args, flag, None)
        if not path:
            continue
        name = '--' + flag.replace('_', '-')
        if path.endswith(('/', os.sep)) or os.path.isdir(path):
            raise InputError(f'{name}: cannot write {path!r} (is a directory; give a file '
                             'name)')
        if not os.path.isdir(os.path.dirname(os.path.abspath(path))):
            raise InputError(f'{name}: directory of {path} does not exist')
        if isinstance(source, str) and source != '-' and _same_file(path, source):
            raise InputError(f'{name}: {path!r} is the input file; writing it would '
                             'overwrite the input')
        for other, other_path in given:
            if _same_file(path, other_path):
                raise InputError(f'{name}: {path!r} is also the file of {other}')
        given.append((name, path))
    kml = getattr(args, 'kml', None)
    if kml:
        overlay = overlay_png_path(kml)
        for other, other_path in given:
            if other != '--kml' and _same_file(overlay, other_path):
                raise InputError(f'--kml: its map image {overlay!r} is also the file of '
                                 f'{other}')
    if kml and getattr(args, 'verb', None) == 'plan':
        # plan map --kml writes its map image next to the KML: not over the heat map.
        overlay = overlay_png_path(kml)
        for flag in ('png', 'csv'):
            other = getattr(args, flag, None)
            if isinstance(other, str) and _same_file(overlay, other):
                raise InputError(f'--kml: its map image {overlay!r} is also the file of '
                                 f'--{flag}')
    _check_probability(args)


def _check_probability(args):
    p = getattr(args, 'ellipse_probability', 0.5)
    if not (math.isfinite(p) and 0.0 < p < 1.0):
        raise InputError(f'--ellipse-probability: must be in (0, 1), got {p:g}')


def check(args, params=None, reserved=()):
    """Validate the flags before the work starts; return the origin (or None if unused).
    ``reserved``: (flag, path) of the files the verb writes besides these (never shared).
    --ellipse-probability is checked even without a geographic output."""
    _check_probability(args)
    if not wanted(args):
        return None
    _check_paths(args, reserved)
    return origin_of(args, params)


def overlay_png_path(kml_path, suffix='accuracy'):
    """PNG written next to a KML file: ``<kml stem>_<suffix>.png``."""
    return os.path.splitext(kml_path)[0] + f'_{suffix}.png'


def _station_layout(epochs):
    """core.planning.Stations of the last position/σ of every station seen in fixes."""
    from ..core.planning import Stations
    last = {}
    for e in epochs:
        for b in e.bearings:
            last[b.station] = b
    if len(last) < 2:
        return None
    bs = list(last.values())
    pos = np.array([np.asarray(b.position, float) for b in bs])
    saz = np.array([b.sigma_azimuth for b in bs])
    sel = np.array([b.sigma_elevation if b.has_elevation else b.sigma_azimuth for b in bs])
    has = np.array([b.has_elevation for b in bs])
    return Stations.from_arrays(pos, saz, sel, has, names=list(last))


def _auto_grid(st, altitude):
    from ..core.planning import GridSpec
    c = st.positions[:, :2].mean(axis=0)
    r = float(np.max(np.hypot(*(st.positions[:, :2] - c).T)))
    side = max(OVERLAY_SIZE_FACTOR * r, OVERLAY_MIN_SIZE)
    res = side / OVERLAY_CELLS
    return GridSpec(c[0] - side / 2, c[1] - side / 2, res, OVERLAY_CELLS, OVERLAY_CELLS,
                    altitude)


def export_epochs(args, params, epochs, printer=print):
    """``bag process`` exports of the fusion epochs (fixes only); prints what was written.

    The accuracy overlay of --kml is optional: when it cannot be placed (a raster across the
    antimeridian, nothing finite to draw) the KML is written without it and a warning on
    stderr says why."""
    import sys
    from ..core import gis
    from .. import gis_export as gx
    if not wanted(args):
        return []
    origin = origin_of(args, params)
    # As the CSV of --out: the low-confidence fixes too with publish_low_confidence.
    low = bool(params and params.get('publish_low_confidence'))
    fixes = gis.drawn_epochs(epochs, low)
    n_low = sum(1 for e in fixes if not e.ok)
    left_out = 0 if low else len(gis.drawn_epochs(epochs, True)) - len(fixes)
    fc = gis.features_from_epochs(epochs, origin, args.ellipse_probability,
                                  low_confidence=low)
    written = []
    if args.geojson:
        with writing('--geojson', args.geojson):
            gx.write_geojson(args.geojson, fc)
        written.append(args.geojson)
    if args.kml:
        overlays = []
        st = _station_layout(fixes)
        if st is not None:
            from ..core.planning import accuracy_map
            alt = float(np.median([e.position[2] for e in fixes]))
            amap = accuracy_map(st, _auto_grid(st, alt), 'crlb')
            png = overlay_png_path(args.kml)
            try:
                with writing('--kml', png):
                    overlays.append(gx.accuracy_overlay(amap.grid, amap.error, origin, png,
                                                        'CRLB expected position error'))
                written.append(png)
            except ValueError as exc:
                print(f'warning: --kml: accuracy map left out of {args.kml} ({exc})',
                      file=sys.stderr)
        with writing('--kml', args.kml):
            gx.write_kml(args.kml, fc, 'bearing_loc bag process', overlays)
        written.append(args.kml)
    if args.geo_csv:
        with writing('--geo-csv', args.geo_csv):
            gx.write_geo_csv(args.geo_csv, gis.geofixes_of(fixes), origin)
        written.append(args.geo_csv)
    low_text = f', {n_low} of them low_confidence' if n_low else ''
    printer('wrote ' + ', '.join(written) + f' ({len(fixes)} fixes{low_text}, '
            f'{100 * args.ellipse_probability:g}% ellipses)')
    if left_out:
        printer(f'{left_out} low_confidence fixes (failed their consistency checks) not drawn; '
                '-p publish_low_confidence=true draws them, with status low_confidence')
    return written


def export_locate(args, results, sets):
    """``locate`` exports: one fix per problem, its bearings drawn a bit beyond it.

    ``results``: the output dicts of cli.locate.solve; ``sets``: the one-problem BearingSets.
    Problems without a finite position are skipped (and counted on stderr).
    """
    if not wanted(args):
        return []
    import sys
    from ..core import gis
    from ..core.bearings import Bearing
    from .. import gis_export as gx
    origin = origin_of(args)
    fixes, rays, stations, skipped = [], [], {}, 0
    for k, (res, bs) in enumerate(zip(results, sets)):
        pos = res['position']
        if pos is None or any(v is None for v in pos):
            skipped += 1
            continue
        cov = np.array([[np.nan if v is None else v for v in row] for row in res['covariance']])
        p = np.asarray(pos, dtype=float)
        fixes.append(gis.GeoFix(None, p, cov, res['status'],       # locate: no time
                                res.get('estimator') or res.get('method', ''),
                                list(bs.stations)))
        for i, name in enumerate(bs.stations):
            b = Bearing(name, None, bs.positions[0, i], float(bs.azimuth[0, i]),
                        float(bs.elevation[0, i]), float(bs.sigma_az[0, i]))
            rays.append((b, p))
            stations[name] = bs.positions[0, i]
    # The map features (rays, ellipses) only for the map formats: the CSV needs the fixes.
    fc = (gis.feature_collection(origin, fixes, rays, stations, args.ellipse_probability)
          if args.geojson or args.kml else None)
    written = []
    if args.geojson:
        with writing('--geojson', args.geojson):
            gx.write_geojson(args.geojson, fc)
        written.append(args.geojson)
    if args.kml:
        with writing('--kml', args.kml):
            gx.write_kml(args.kml, fc, 'bearing_loc locate')
        written.append(args.kml)
    if args.geo_csv:
        with writing('--geo-csv', args.geo_csv):
            gx.write_geo_csv(args.geo_csv, fixes, origin)
        written.append(args.geo_csv)
    if skipped:
        print(f'bearing_loc locate: {skipped} problem(s) without a finite fix left out of '
              f'{", ".join(written)}', file=sys.stderr)
    return written


def export_plan_map(args, amap):
    """``plan map --kml``: stations + the map as a GroundOverlay PNG; returns {kml, png}."""
    from ..core import gis
    from .. import gis_export as gx
    if not args.kml:
        return {}
    _check_paths(args)
    origin = origin_of(args)
    st = amap.stations
    stations = {n: p for n, p in zip(st.names or [f'station_{i + 1}' for i in range(st.N)],
                                     st.positions)}
    fc = gis.feature_collection(origin, stations=stations)
    png = overlay_png_path(args.kml)
    try:
        with writing('--kml', png):
            ov = gx.accuracy_overlay(amap.grid, amap.error, origin, png,
                                     f'{amap.model.upper()} expected position error',
                                     args.vmin, args.vmax)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    with writing('--kml', args.kml):
        gx.write_kml(args.kml, fc, 'bearing_loc plan map', [ov])
    return {'kml': args.kml, 'kml_overlay_png': png}
