"""GeoJSON, KML and CSV written by ``bag process``, ``locate`` and ``plan map``, checked with
independent readers (jsonschema, the geojson package, xml.etree) against the fix topic and
fix/navsat conversion; the demo's ellipses hold their stated probability (Monte Carlo)."""
import csv
import json
import math
import os
import subprocess
import sys
import xml.etree.ElementTree as ET

import geojson
import jsonschema
from matplotlib.path import Path
import numpy as np
import pytest
from rclpy.serialization import deserialize_message

from bearing_loc_ros import bagio
from bearing_loc_ros.ros_conversions import fix_from_msg, fix_to_navsat
from ros_helpers import REPO
from test_gis import coverage_bound

ORIGIN = (48.137, 11.575, 520.0)
KML = '{http://www.opengis.net/kml/2.2}'
GX = '{http://www.google.com/kml/ext/2.2}'
CLI = [sys.executable, '-c', 'import sys; from bearing_loc_ros.cli import main; sys.exit(main())']

POSITION = {'type': 'array', 'minItems': 2, 'maxItems': 3,
            'prefixItems': [{'type': 'number', 'minimum': -180, 'maximum': 180},
                            {'type': 'number', 'minimum': -90, 'maximum': 90},
                            {'type': 'number'}]}
LINE = {'type': 'array', 'minItems': 2, 'items': POSITION}
RING = {'type': 'array', 'minItems': 4, 'items': POSITION}
#: RFC 7946 sections 3.1-3.3 for the geometry types used (written from the RFC).
RFC7946 = {
    '$schema': 'https://json-schema.org/draft/2020-12/schema',
    'type': 'object', 'required': ['type', 'features'],
    'properties': {'type': {'const': 'FeatureCollection'}, 'features': {'type': 'array', 'items': {
        'type': 'object', 'required': ['type', 'geometry', 'properties'],
        'properties': {'type': {'const': 'Feature'}, 'properties': {'type': 'object'},
                       'geometry': {'oneOf': [
                           {'properties': {'type': {'const': 'Point'}, 'coordinates': POSITION},
                            'required': ['type', 'coordinates']},
                           {'properties': {'type': {'const': 'LineString'}, 'coordinates': LINE},
                            'required': ['type', 'coordinates']},
                           {'properties': {'type': {'const': 'MultiLineString'},
                                           'coordinates': {'type': 'array', 'items': LINE}},
                            'required': ['type', 'coordinates']},
                           {'properties': {'type': {'const': 'Polygon'},
                                           'coordinates': {'type': 'array', 'items': RING}},
                            'required': ['type', 'coordinates']},
                           {'properties': {'type': {'const': 'MultiPolygon'}, 'coordinates': {
                               'type': 'array', 'items': {'type': 'array', 'items': RING}}},
                            'required': ['type', 'coordinates']}]}}}}}}


def run_cli(*args, check=True):
    env = dict(os.environ, MPLBACKEND='Agg')
    proc = subprocess.run(CLI + [str(a) for a in args], capture_output=True, text=True,
                          cwd=REPO, env=env, timeout=120)
    if check:
        assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc


@pytest.fixture(scope='module')
def demo(tmp_path_factory):
    """The seed000 (Wang, Zhang & Wu (2006), section 4) demo bag processed with the GIS exports."""
    d = tmp_path_factory.mktemp('gisdemo')
    run_cli('bag', 'simulate', '--scenario', 'config/scenarios/seed000.yaml', '--out', d / 'sim')
    out = run_cli('bag', 'process', d / 'sim', '--out', d / 'fixes', '--estimator', 'mle',
                  '--geojson', d / 'demo.geojson', '--kml', d / 'demo.kml',
                  '--geo-csv', d / 'demo_geo.csv', '--origin', *ORIGIN)
    assert 'demo.geojson' in out.stdout
    with open(d / 'demo.geojson', encoding='utf-8') as f:
        fc = json.load(f)
    fixes = {}
    with bagio.BagReader(d / 'fixes') as r:
        for m in r.messages(['/fix']):
            from geometry_msgs.msg import PoseWithCovarianceStamped
            stamp, pos, cov = fix_from_msg(deserialize_message(m.raw, PoseWithCovarianceStamped))
            fixes[stamp] = (pos, cov, fix_to_navsat(pos, cov, stamp, ORIGIN, 'map'))
    return {'dir': d, 'fc': fc, 'fixes': fixes}


def kinds(fc):
    out = {}
    for f in fc['features']:
        out.setdefault(f['properties']['kind'], []).append(f)
    return out


def test_demo_geojson_is_valid_rfc7946(demo):
    fc = demo['fc']
    jsonschema.validate(fc, RFC7946)
    assert geojson.loads(json.dumps(fc)).is_valid
    for f in fc['features']:
        g = f['geometry']
        rings = ([g['coordinates']] if g['type'] == 'Polygon'
                 else g['coordinates'] if g['type'] == 'MultiPolygon' else [])
        for poly in rings:
            assert poly[0][0] == poly[0][-1]
    k = kinds(fc)
    assert len(k['fix']) == len(demo['fixes']) == 50
    assert len(k['ellipse']) == 50 and len(k['station']) == 3 and len(k['bearing']) == 150


def test_demo_fix_coordinates_match_fix_navsat(demo):
    for f in kinds(demo['fc'])['fix']:
        p = f['properties']
        pos, cov, nav = demo['fixes'][p['stamp_ns']]
        lon, lat, alt = f['geometry']['coordinates']
        assert lon == pytest.approx(nav.longitude, abs=2e-9)
        assert lat == pytest.approx(nav.latitude, abs=2e-9)
        assert alt == pytest.approx(nav.altitude, abs=1e-3)
        assert p['position_enu_m'] == pytest.approx(pos.tolist(), abs=1e-9)
        assert p['covariance_enu_m2'] == pytest.approx(cov.ravel().tolist(), rel=1e-12)
        assert p['sigma_horizontal_m'] == pytest.approx(math.sqrt(cov[0, 0] + cov[1, 1]))
        assert p['status'] == 'ok' and p['estimator'] == 'mle'
        assert p['time'].startswith('1970-01-01T00:') and p['time'].endswith('Z')


def test_demo_ellipses_hold_the_stated_probability(demo):
    """Monte Carlo over every demo fix (fixed seed): samples of N(x̂, C) in lon/lat inside
    the exported polygon, pooled, within the binomial bound of 0.95."""
    rng = np.random.default_rng(2024)
    from bearing_loc_ros.core.gis import enu_to_lonlat
    k = kinds(demo['fc'])
    fix_by_id = {f['properties']['id']: f['properties'] for f in k['fix']}
    hits = n = 0
    for e in k['ellipse']:
        fp = fix_by_id[e['properties']['fix_id']]
        assert e['properties']['probability'] == 0.95
        cov = np.array(fp['covariance_enu_m2']).reshape(3, 3)
        s = rng.multivariate_normal(fp['position_enu_m'], cov, size=1000)
        lon, lat, _ = enu_to_lonlat(s, ORIGIN)
        ring = np.array(e['geometry']['coordinates'][0])
        hits += Path(ring).contains_points(np.column_stack([lon, lat])).sum()
        n += len(s)
    assert abs(hits / n - 0.95) < coverage_bound(0.95, n), hits / n


def test_demo_kml_parses_and_matches(demo):
    root = ET.parse(demo['dir'] / 'demo.kml').getroot()
    folders = {f.findtext(f'{KML}name'): f for f in root.iter(f'{KML}Folder')}
    assert {'stations', 'bearing rays', 'error ellipses', 'fixes'} <= set(folders)
    marks = folders['fixes'].findall(f'{KML}Placemark')
    assert len(marks) == 50
    for pm in marks:
        data = {d.get('name'): d.findtext(f'{KML}value')
                for d in pm.iter(f'{KML}Data')}
        stamp = int(data['stamp_ns'])
        nav = demo['fixes'][stamp][2]
        lon, lat, alt = map(float, pm.findtext(f'.//{KML}coordinates').split(','))
        assert lon == pytest.approx(nav.longitude, abs=2e-9)
        assert lat == pytest.approx(nav.latitude, abs=2e-9)
        # at the fix's height, not clamped to the ground (they were written at 0)
        assert alt == pytest.approx(nav.altitude, abs=1e-3)
        assert pm.findtext(f'.//{KML}altitudeMode') == 'absolute'
        assert pm.findtext(f'.//{KML}when') == data['time']
        assert data['status'] == 'ok' and data['estimator'] == 'mle'
        assert len(data['covariance_enu_m2'].split()) == 9
    assert len(folders['error ellipses'].findall(f'.//{KML}Polygon')) == 50
    assert len(folders['bearing rays'].findall(f'.//{KML}LineString')) == 150
    overlay = root.find(f'.//{KML}GroundOverlay')
    href = overlay.findtext(f'.//{KML}href')
    assert os.path.isfile(demo['dir'] / href)
    quad = overlay.findtext(f'.//{GX}LatLonQuad/{KML}coordinates').split()
    assert len(quad) == 4


def test_demo_geo_csv_has_latitude_longitude_next_to_enu(demo):
    with open(demo['dir'] / 'demo_geo.csv', newline='', encoding='utf-8') as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 50
    for r in rows:
        pos, _, nav = demo['fixes'][int(r['stamp_ns'])]
        assert [float(r[c]) for c in ('x_m', 'y_m', 'z_m')] == pytest.approx(pos.tolist())
        assert float(r['latitude_deg']) == pytest.approx(nav.latitude, abs=1e-9)
        assert float(r['longitude_deg']) == pytest.approx(nav.longitude, abs=1e-9)


def test_plan_map_kml_ground_overlay_is_georeferenced(tmp_path):
    out = run_cli('plan', 'map', '--scenario', 'config/scenarios/seed000.yaml', '--altitude',
                  5000, '--extent-km=-40,80,-30,50', '--resolution', 1000, '--kml',
                  tmp_path / 'map.kml', '--origin', *ORIGIN)
    summary = json.loads(out.stdout)
    assert summary['kml'] == str(tmp_path / 'map.kml')
    root = ET.parse(tmp_path / 'map.kml').getroot()
    quad = [tuple(map(float, c.split(',')[:2])) for c in root.findtext(
        f'.//{GX}LatLonQuad/{KML}coordinates').split()]
    from bearing_loc_ros.core import geodesy
    corners = [(-40e3, -30e3), (80e3, -30e3), (80e3, 50e3), (-40e3, 50e3)]
    for (lon, lat), (x, y) in zip(quad, corners):
        la, lo, _ = geodesy.enu_to_geodetic([x, y, 5000.0], ORIGIN)
        assert (lon, lat) == pytest.approx((float(lo), float(la)), abs=1e-9)
    import matplotlib.image as mpimg
    img = mpimg.imread(summary['kml_overlay_png'])
    assert img.shape[:2] == (80, 120)         # rows = north-south cells, columns = east-west
    assert len(root.findall(f'.//{KML}Placemark')) == 3


def test_locate_geojson(tmp_path):
    target = np.array([1000.0, 2000.0, 300.0])
    stations = [[0.0, 0.0, 0.0], [3000.0, 0.0, 0.0], [0.0, 4000.0, 0.0]]
    bearings = [{'station': f's{i}', 'position': s,
                 'azimuth': math.atan2(target[1] - s[1], target[0] - s[0]),
                 'elevation': math.atan2(target[2] - s[2], math.dist(target[:2], s[:2])),
                 'sigma_azimuth': 0.01, 'sigma_elevation': 0.01}
                for i, s in enumerate(stations)]
    (tmp_path / 'in.json').write_text(json.dumps({'bearings': bearings}))
    out = run_cli('locate', tmp_path / 'in.json', '--geojson', tmp_path / 'l.geojson',
                  '--geo-csv', tmp_path / 'l.csv', '--kml', tmp_path / 'l.kml',
                  '--origin', *ORIGIN)
    res = json.loads(out.stdout)
    fc = json.loads((tmp_path / 'l.geojson').read_text())
    jsonschema.validate(fc, RFC7946)
    k = kinds(fc)
    assert len(k['fix']) == 1 and len(k['bearing']) == 3 and len(k['station']) == 3
    assert k['fix'][0]['properties']['position_enu_m'] == pytest.approx(res['position'])
    assert k['fix'][0]['properties']['position_enu_m'] == pytest.approx(target.tolist(),
                                                                        abs=1e-6)
    # A locate request carries no time: no 1970-01-01 stamps in any of the three files.
    assert all(f['properties'].get('time') is None for f in fc['features'])
    with open(tmp_path / 'l.csv', newline='') as f:
        row = next(csv.DictReader(f))
    assert row['stamp_ns'] == '' and row['time'] == ''
    assert '1970' not in (tmp_path / 'l.kml').read_text()


@pytest.mark.parametrize('extra, message', [
    ((), 'origin'), (('--origin', 89.9, 0, 0), 'polar'), (('--origin', 95, 0, 0), 'lat_deg')])
def test_export_without_a_usable_origin_fails_with_one_line(tmp_path, extra, message):
    (tmp_path / 'in.json').write_text(json.dumps({'bearings': [
        {'position': [0, 0, 0], 'azimuth': 0.5, 'elevation': 0.1, 'sigma_azimuth': 0.01,
         'sigma_elevation': 0.01},
        {'position': [1000, 0, 0], 'azimuth': 2.0, 'sigma_azimuth': 0.01}]}))
    proc = run_cli('locate', tmp_path / 'in.json', '--geojson', tmp_path / 'x.geojson', *extra,
                   check=False)
    assert proc.returncode == 2 and proc.stdout == ''
    assert len(proc.stderr.strip().splitlines()) == 1 and message in proc.stderr
    assert not (tmp_path / 'x.geojson').exists()


def test_kml_holds_any_station_id_as_valid_xml(tmp_path):
    # '<' or '&' in an id made the file invalid XML (simplekml writes Data values as they
    # are), a control character too; they read back as given (controls as U+FFFD).
    from bearing_loc_ros.gis_export import write_kml
    ids = ['a<b', 'x&lt;y', 'c&d"\'>', 'ctl\x01\x1f', 'Łódź-站点-🛰']
    fc = {'type': 'FeatureCollection', 'features': [
        {'type': 'Feature', 'geometry': {'type': 'Point', 'coordinates': [11.0 + k, 48.0]},
         'properties': {'kind': 'station', 'name': s, 'station': s}}
        for k, s in enumerate(ids)]}
    write_kml(tmp_path / 'ids.kml', fc)
    root = ET.parse(tmp_path / 'ids.kml').getroot()
    marks = list(root.iter(f'{KML}Placemark'))
    expect = [s.replace('\x01', '\ufffd').replace('\x1f', '\ufffd') for s in ids]
    assert [pm.findtext(f'{KML}name') for pm in marks] == expect
    assert [{d.get('name'): d.findtext(f'{KML}value') for d in pm.iter(f'{KML}Data')}[
        'station'] for pm in marks] == expect


def two_station_bag(path, elevation_bias=0.0):
    """A bag of ten epochs of two stations' bearings on a target at (10, 8, 3) km; station
    s2's elevation off by ``elevation_bias`` rad (0.05: every fix fails its consistency
    checks and is low_confidence)."""
    from bearing_loc_ros.core.bearings import Bearing
    stations = {'s1': (0.0, 0.0, 0.0), 's2': (20000.0, 0.0, 0.0)}
    target = np.array([10000.0, 8000.0, 3000.0])
    t0 = 1_700_000_000 * 10**9
    with bagio.BagWriter(path) as bag:
        for s in stations:
            bag.add_topic(f'/{s}/bearing', bagio.POSE_COV_STAMPED, bagio.qos_profile(10))
        for k in range(10):
            t = t0 + k * 10**9
            for s, q in stations.items():
                d = target - np.array(q)
                el = math.atan2(d[2], math.hypot(d[0], d[1])) + (elevation_bias if s == 's2'
                                                                 else 0.0)
                bag.write(f'/{s}/bearing', t, bagio.bearing_message(Bearing(
                    s, t, np.array(q), math.atan2(d[1], d[0]), el, 0.001, 0.001)))
    return path


def test_bag_process_refuses_a_geo_csv_over_its_own_fix_csv(tmp_path):
    """``--out o2 --geo-csv o2.csv`` silently replaced the fixes CSV that --out promises
    never to overwrite; the map image of --kml over another output likewise. Both are
    refused before any processing."""
    bag = two_station_bag(tmp_path / 'in')
    for extra, flag in (((('--out', tmp_path / 'o2', '--geo-csv', tmp_path / 'o2.csv')),
                         '--geo-csv'),
                        ((('--out', tmp_path / 'o2/', '--geojson', tmp_path / 'o2')),
                         '--geojson'),
                        ((('--kml', tmp_path / 'm.kml', '--geo-csv',
                           tmp_path / 'm_accuracy.png')), '--kml')):
        proc = run_cli('bag', 'process', bag, *extra, '--origin', *ORIGIN, check=False)
        assert proc.returncode == 2 and proc.stdout == '', proc
        assert proc.stderr.count('\n') == 1 and flag in proc.stderr
        assert 'is also the file of' in proc.stderr
        assert not any(p.name.startswith(('o2', 'm')) for p in tmp_path.iterdir())


def test_bag_process_kml_near_the_antimeridian_is_written_without_its_overlay(tmp_path):
    """Near ±180° the accuracy raster cannot be one GroundOverlay: ``bag process --kml``
    stopped (exit 2, no KML at all). The KML is now written without the optional overlay,
    with a warning."""
    bag = two_station_bag(tmp_path / 'in')
    proc = run_cli('bag', 'process', bag, '--kml', tmp_path / 'a.kml', '--geojson',
                   tmp_path / 'a.geojson', '--origin', 0.0, 179.9, 0.0)
    assert 'accuracy map left out' in proc.stderr and 'antimeridian' in proc.stderr
    root = ET.parse(tmp_path / 'a.kml').getroot()
    assert len([pm for pm in root.iter(f'{KML}Placemark')
                if pm.findtext(f'{KML}name').startswith('fix')]) == 10
    assert not list(root.iter(f'{KML}GroundOverlay'))
    assert not (tmp_path / 'a_accuracy.png').exists() and (tmp_path / 'a.geojson').exists()


def test_bag_process_draws_low_confidence_fixes_as_its_csv_lists_them(tmp_path):
    """A bag whose fixes all fail their consistency checks gave an empty GeoJSON (no
    stations, no rays) with exit 0 while the CSV of ``-p publish_low_confidence=true`` listed
    them. The map files now follow that parameter as the CSV does: the low-confidence fixes
    drawn with status low_confidence, their rays and stations; without it the stations are
    drawn and a line says why no fix is."""
    bag = two_station_bag(tmp_path / 'in', elevation_bias=0.05)
    proc = run_cli('bag', 'process', bag, '--out', tmp_path / 'o', '--geojson',
                   tmp_path / 'a.geojson', '--kml', tmp_path / 'a.kml', '--geo-csv',
                   tmp_path / 'a_geo.csv', '--origin', *ORIGIN,
                   '-p', 'publish_low_confidence=true')
    assert '(10 fixes, 10 of them low_confidence' in proc.stdout
    with open(tmp_path / 'o.csv', encoding='utf-8') as f:
        csv_rows = list(csv.DictReader(f))
    fc = json.loads((tmp_path / 'a.geojson').read_text())
    k = kinds(fc)
    assert len(k['station']) == 2 and len(k['bearing']) == 20 and len(k['ellipse']) == 10
    assert [f['properties']['stamp_ns'] for f in k['fix']] == \
        [int(r['stamp_ns']) for r in csv_rows]
    assert {f['properties']['status'] for f in k['fix'] + k['ellipse']} == {'low_confidence'}
    with open(tmp_path / 'a_geo.csv', encoding='utf-8') as f:
        assert {r['status'] for r in csv.DictReader(f)} == {'low_confidence'}
    names = [pm.findtext(f'{KML}name') for pm in
             ET.parse(tmp_path / 'a.kml').getroot().iter(f'{KML}Placemark')]
    assert sum(n.startswith('fix (low_confidence) ') for n in names) == 10
    proc = run_cli('bag', 'process', bag, '--geojson', tmp_path / 'b.geojson', '--origin',
                   *ORIGIN)
    assert '10 low_confidence fixes' in proc.stdout and 'publish_low_confidence' in proc.stdout
    k = kinds(json.loads((tmp_path / 'b.geojson').read_text()))
    assert len(k['station']) == 2 and 'fix' not in k


def test_ellipse_probability_is_checked_without_a_geographic_output(tmp_path):
    """``--ellipse-probability 5`` was accepted silently when no GIS file was asked for."""
    (tmp_path / 'in.json').write_text(json.dumps({'bearings': [
        {'position': [0, 0, 0], 'azimuth': 0.5, 'sigma_azimuth': 0.01},
        {'position': [1000, 0, 0], 'azimuth': 2.0, 'sigma_azimuth': 0.01}]}))
    proc = run_cli('locate', tmp_path / 'in.json', '--ellipse-probability', 5, check=False)
    assert proc.returncode == 2 and proc.stdout == ''
    assert '--ellipse-probability' in proc.stderr
