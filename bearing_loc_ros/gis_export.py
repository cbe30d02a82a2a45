"""Geographic files of fixes, error ellipses, stations, bearing rays and accuracy maps.

The geometry comes from :mod:`bearing_loc_ros.core.gis` (a RFC 7946 FeatureCollection as a
dict); this module only writes it, with well-kept libraries instead of hand-written
serialisers:

* GeoJSON (RFC 7946: WGS84, ``[longitude, latitude(, height)]``): the ``geojson`` package
  checks the collection (``is_valid``) and writes it.
* KML 2.2 (Google Earth, QGIS): ``simplekml``. One folder per kind (stations, bearings,
  ellipses, fixes); fixes carry a ``TimeStamp`` and every property as ``ExtendedData``.
  Points and lines with a height are placed at it (``altitudeMode`` absolute, the WGS84
  ellipsoidal height read as above mean sea level); polygons (ellipses) and 2D geometry
  lie on the ground; every height is also in the properties.
* CSV: one row per fix with ENU metres and latitude/longitude/height next to them.
* Raster: an error map (m) as a PNG (matplotlib colour map, log scale, transparent where the
  error is not finite) placed with a KML ``GroundOverlay`` whose ``gx:LatLonQuad`` holds the
  exact geodetic corners of the ENU-aligned grid.
"""

import csv
import errno
import json
import math
import os
import re
from xml.sax.saxutils import escape

import numpy as np

from .core import gis

#: Colours (KML aabbggrr) per feature kind.
KML_COLOURS = {'station': 'ff0000ff', 'bearing': 'c000a5ff', 'ellipse': 'ffffff00',
               'fix': 'ff00ff00', 'track': 'ff00ff00'}
#: KML folder names per feature kind.
FOLDERS = {'station': 'stations', 'bearing': 'bearing rays', 'track': 'track',
           'ellipse': 'error ellipses', 'fix': 'fixes'}
UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def geojson_text(fc):
    """Checked RFC 7946 text of a FeatureCollection dict.

    The ``geojson`` package checks the collection (``GeoJSON.to_instance(strict=True)`` and
    ``is_valid``: ValueError naming the first problem); the dict is then written as strict
    JSON (no NaN) with the coordinates as given (core.gis rounds degrees to 1e-9, about
    0.1 mm; the package's own writer would round them to 1e-6 deg, about 0.1 m).
    """
    import geojson
    try:
        obj = geojson.GeoJSON.to_instance(fc, strict=True)
    except (TypeError, ValueError, AttributeError) as exc:
        raise ValueError(f'geojson: invalid collection: {exc}') from None
    if not obj.is_valid:
        raise ValueError(f'geojson: invalid collection: {obj.errors()}')
    return json.dumps(fc, allow_nan=False, separators=(',', ':'))


def _open_out(path):
    """``path`` opened for writing text; OSError naming the path when it cannot be (a
    missing directory, a directory, no permission): the caller names its option."""
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise FileNotFoundError(errno.ENOENT, f'directory {directory} does not exist', path)
    return open(path, 'w', encoding='utf-8', newline='')


def write_geojson(path, fc):
    """Write a FeatureCollection dict as a checked GeoJSON file (OSError when ``path`` cannot
    be written, ValueError for an invalid collection)."""
    text = geojson_text(fc)
    with _open_out(path) as f:
        f.write(text)
        f.write('\n')


#: Characters XML 1.0 does not allow in text (C0 controls but tab, LF and CR; U+FFFE/FFFF;
#: lone surrogates): replaced by U+FFFD in KML text.
_XML_INVALID = re.compile('[\x00-\x08\x0b\x0c\x0e-\x1f\ud800-\udfff\ufffe\uffff]')


def xml_text(text):
    """``text`` with the characters XML 1.0 cannot hold replaced by U+FFFD (a station id
    with a control character made the KML unreadable)."""
    return _XML_INVALID.sub('\ufffd', text)


def _prop_text(value):
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return ' '.join(_prop_text(v) for v in value)
    if isinstance(value, dict):
        return '; '.join(f'{k}={_prop_text(v)}' for k, v in value.items())
    return '' if value is None else str(value)


def _name(props):
    kind = props.get('kind', '')
    if kind == 'station':
        return props.get('name', 'station')
    if kind == 'bearing':
        return f'{props.get("station", "")} {props.get("time") or ""}'.strip()
    if kind == 'fix':
        status = props.get('status')
        tag = f' ({status})' if status and status != 'ok' else ''    # low_confidence shows
        return f'fix{tag} {props.get("time") or ""}'.strip()
    if kind == 'ellipse':
        return f'{100 * props.get("probability", 0):g}% ellipse {props.get("time") or ""}'.strip()
    return kind


def _add_geometry(container, geom, name):
    """simplekml geometry for a GeoJSON geometry dict (Point/LineString/Polygon/Multi*)."""
    import simplekml
    t, c = geom['type'], geom['coordinates']
    if t in ('Point', 'LineString'):
        pts = [c] if t == 'Point' else c
        if t == 'Point':
            out = container.newpoint(name=name, coords=[tuple(c)])
        else:
            out = container.newlinestring(name=name, coords=[tuple(p) for p in c])
        if all(len(p) == 3 for p in pts):
            # at its height (an aircraft's fix is not on the ground); KML reads "absolute"
            # above mean sea level and these are WGS84 ellipsoidal heights, as in the GeoJSON:
            # shown offset by the local geoid height (docs/view.md); 2D stays on the ground
            out.altitudemode = simplekml.AltitudeMode.absolute
        return [out]
    if t == 'Polygon':
        return [container.newpolygon(name=name, outerboundaryis=[tuple(p) for p in c[0]])]
    multi = container.newmultigeometry(name=name)
    if t == 'MultiLineString':
        for part in c:
            line = multi.newlinestring(coords=[tuple(p) for p in part])
            if all(len(p) == 3 for p in part):
                line.altitudemode = simplekml.AltitudeMode.absolute
    elif t == 'MultiPolygon':
        for poly in c:
            multi.newpolygon(outerboundaryis=[tuple(p) for p in poly[0]])
    else:
        raise ValueError(f'kml: unsupported geometry {t}')
    return [multi]


def _styles():
    """One shared simplekml Style per kind (written once in the document)."""
    import simplekml
    out = {}
    for kind, colour in KML_COLOURS.items():
        st = simplekml.Style()
        if kind in ('station', 'fix'):
            st.iconstyle.color = colour
            st.iconstyle.scale = 1.1 if kind == 'station' else 0.7
            st.labelstyle.scale = 0.8 if kind == 'station' else 0.0
        else:
            st.linestyle.color = colour
            st.linestyle.width = 2 if kind == 'ellipse' else 1
            st.polystyle.color = simplekml.Color.changealphaint(60, colour)
            st.polystyle.outline = 1
        out[kind] = st
    return out


def kml_document(fc, name='bearing_loc_ros', overlays=()):
    """simplekml.Kml of a FeatureCollection dict (+ GroundOverlays).

    ``overlays``: (name, png_href, corners (4, 2) lon/lat, description) tuples; corners in
    gx:LatLonQuad order (lower-left, lower-right, upper-right, upper-left). A feature
    without geometry (a fix inside the Earth) has no KML placemark.
    """
    import simplekml
    kml = simplekml.Kml(name=name)
    styles = _styles()
    folders = {}
    for ft in fc['features']:
        props = ft.get('properties') or {}
        if ft.get('geometry') is None:
            continue        # a fix that cannot be placed (core.gis.fix_altitude_problem)
        kind = props.get('kind', 'feature')
        if kind not in folders:
            folders[kind] = kml.newfolder(name=FOLDERS.get(kind, kind))
        for obj in _add_geometry(folders[kind], ft['geometry'], xml_text(_name(props))):
            if props.get('time') and kind == 'fix':
                obj.timestamp.when = props['time']
            for key, value in props.items():
                # simplekml escapes names but writes Data values as they are: '<' or '&' in
                # a station id made the file invalid XML.
                obj.extendeddata.newdata(name=key,
                                         value=escape(xml_text(_prop_text(value))))
            if kind in styles:
                obj.style = styles[kind]
    for oname, href, corners, desc in overlays:
        go = kml.newgroundoverlay(name=oname, description=desc)
        go.icon.href = href
        go.gxlatlonquad.coords = [(float(lo), float(la)) for lo, la in corners]
        go.color = 'b0ffffff'
    return kml


def write_kml(path, fc, name='bearing_loc_ros', overlays=()):
    """Write a FeatureCollection dict (+ GroundOverlays) as a KML file (OSError when ``path``
    cannot be written)."""
    text = kml_document(fc, name, overlays).kml(format=True)
    with _open_out(path) as f:
        f.write(text)


GEO_CSV_COLUMNS = ('stamp_ns', 'time', 'x_m', 'y_m', 'z_m', 'latitude_deg', 'longitude_deg',
                   'altitude_m', 'sigma_east_m', 'sigma_north_m', 'sigma_up_m',
                   'sigma_horizontal_m', 'cov_xx', 'cov_xy', 'cov_xz', 'cov_yy', 'cov_yz',
                   'cov_zz', 'status', 'estimator', 'stations')


def write_geo_csv(path, fixes, origin):
    """CSV of GeoFix rows: ENU (m) and WGS84 latitude/longitude (deg) / height (m) side by side.

    Covariance columns are ENU m² (the origin's axes); σ = sqrt of its diagonal, horizontal
    σ = sqrt(C_xx + C_yy). Latitude/longitude/height are
    :func:`~bearing_loc_ros.core.geodesy.enu_to_geodetic` of the ENU position, the same as
    the ``fix/navsat`` topic.
    """
    origin = gis.check_origin(origin)
    with _open_out(path) as f:
        w = csv.writer(f)
        w.writerow(GEO_CSV_COLUMNS)
        for fx in fixes:
            p = np.asarray(fx.position, dtype=float)
            c = np.asarray(fx.covariance, dtype=float)
            lon, lat, alt = gis.enu_to_lonlat(p, origin)
            d = np.diag(c)
            sig = [math.sqrt(v) if v >= 0 else float('nan') for v in d]
            no_time = fx.stamp_ns is None            # (a locate fix): empty columns
            w.writerow(['' if no_time else int(fx.stamp_ns),
                        '' if no_time else gis.iso_time(fx.stamp_ns), *map(repr, map(float, p)),
                        f'{float(lat):.10f}', f'{float(lon):.10f}', f'{float(alt):.4f}',
                        *map(repr, sig), repr(math.sqrt(max(d[0] + d[1], 0.0))),
                        *(repr(float(c[i, j])) for i, j in UPPER),
                        fx.status, fx.estimator, ' '.join(fx.stations)])


def error_png(error, path, vmin=None, vmax=None, cmap='viridis'):
    """Write an error map (rows south to north, m) as an RGBA PNG, one pixel per cell.

    Log colour scale from vmin to vmax (default: finite min and 99th percentile); cells
    whose error is not finite are transparent. The image's first row is the northern edge
    (image convention), so the PNG drapes directly on a north-up quad. Returns (vmin, vmax);
    OSError when ``path`` cannot be written, ValueError when nothing is finite.
    """
    import matplotlib
    matplotlib.use('Agg')
    from matplotlib import colormaps
    from matplotlib.colors import LogNorm
    import matplotlib.pyplot as plt
    from .core.display import log_color_limits
    err = np.asarray(error, dtype=float)
    limits = log_color_limits(err, vmin, vmax)
    if limits is None:
        raise ValueError('map: no finite error anywhere; nothing to draw')
    vmin, vmax = limits
    rgba = colormaps[cmap](LogNorm(vmin, vmax, clip=True)(np.where(err > 0, err, vmin)))
    rgba[~np.isfinite(err)] = 0.0
    plt.imsave(path, rgba[::-1])
    return vmin, vmax


def accuracy_overlay(grid, error, origin, png_path, title='expected position error',
                     vmin=None, vmax=None):
    """PNG of an accuracy map + its GroundOverlay tuple for :func:`kml_document`.

    ``grid``: a core.planning.GridSpec (ENU-aligned cells of ``resolution`` m from
    (origin_x, origin_y)); the quad corners are the geodetic positions of the grid's outer
    corners at its altitude (:func:`~bearing_loc_ros.core.gis.grid_corners_lonlat`).
    """
    corners = gis.grid_corners_lonlat(grid.origin_x, grid.origin_y,
                                      grid.width * grid.resolution,
                                      grid.height * grid.resolution, grid.altitude, origin)
    lo, hi = error_png(error, png_path, vmin, vmax)
    desc = (f'{title}: sqrt(trace P), log colour scale (viridis) from {lo:.3g} m to '
            f'{hi:.3g} m; {grid.width}x{grid.height} cells of {grid.resolution:g} m at '
            f'altitude {grid.altitude:g} m')
    return (title, os.path.basename(png_path), corners, desc)
