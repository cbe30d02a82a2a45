"""The demo's GeoJSON drawn by a real map library (Leaflet, from npm) in headless Chromium.

The test writes a static page that loads Leaflet and the exported GeoJSON (and the accuracy
overlay PNG), counts the layers Leaflet made and the SVG paths it drew, writes the counts
into the DOM (read back with --dump-dom) and takes a screenshot. Skipped, with the reason,
when chromium or Leaflet (npm) is not available. Set BEARING_LOC_MAP_SCREENSHOT=PATH to keep
the screenshot.
"""
import json
import os
import re
import shutil
import subprocess
import tarfile
import xml.etree.ElementTree as ET

import pytest

from ros_helpers import REPO
from test_gis_export import demo, GX, KML, kinds  # noqa: F401 (demo is a fixture)

LEAFLET = 'leaflet@1.9.4'
NPM_CACHE = os.path.join(REPO, 'build', 'npm')
CHROMIUM_FLAGS = ['--headless', '--no-sandbox', '--disable-gpu',
                  '--disable-background-networking', '--disable-component-update',
                  '--no-first-run', '--hide-scrollbars', '--virtual-time-budget=5000']

PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>bearing_loc_ros map</title>
<link rel="stylesheet" href="leaflet.css">
<style>html, body, #map {{ margin: 0; height: 100%; background: #f4f1ea; }}
#legend {{ position: absolute; z-index: 1000; left: 10px; top: 10px; background: white;
  padding: 6px 10px; font: 13px sans-serif; border: 1px solid #888; }}</style>
<script src="leaflet.js"></script><script src="data.js"></script></head>
<body><div id="map"></div><div id="legend"></div><pre id="result"></pre>
<script>
var colours = {{station: '#d62728', bearing: '#ff9f1c', ellipse: '#1f77b4',
                fix: '#2ca02c', track: '#2ca02c'}};
var map = L.map('map', {{zoomControl: false, attributionControl: false, zoomSnap: 0.1}});
L.control.scale({{imperial: false}}).addTo(map);
if (OVERLAY) L.imageOverlay('overlay.png', OVERLAY, {{opacity: 0.6}}).addTo(map);
var counts = {{}};
var layer = L.geoJSON(DATA, {{
  style: function (f) {{ var k = f.properties.kind;
    return {{color: colours[k], weight: k === 'ellipse' ? 2 : 1,
             fillOpacity: k === 'ellipse' ? 0.15 : 0}}; }},
  pointToLayer: function (f, ll) {{ var k = f.properties.kind;
    return L.circleMarker(ll, {{radius: k === 'station' ? 7 : 3, color: colours[k],
                                fillOpacity: 0.9}}); }},
  onEachFeature: function (f, l) {{ var k = f.properties.kind;
    counts[k] = (counts[k] || 0) + 1;
    if (k === 'station') l.bindTooltip(f.properties.name, {{permanent: true, direction: 'top',
                                                          offset: [0, -8]}}); }}
}}).addTo(map);
var bounds = layer.getBounds();
if (OVERLAY) bounds.extend(OVERLAY);
map.fitBounds(bounds, {{padding: [10, 10]}});
var n = 0; layer.eachLayer(function () {{ n += 1; }});
document.getElementById('legend').innerHTML = '<b>{title}</b><br>' +
  Object.keys(counts).map(function (k) {{
    return '<span style="color:' + colours[k] + '">&#9632;</span> ' + k + ': ' + counts[k];
  }}).join('<br>');
document.getElementById('result').textContent = JSON.stringify({{
  layers: n, counts: counts,
  paths: document.querySelectorAll('.leaflet-overlay-pane path').length}});
</script></body></html>
"""


def leaflet_dist(tmp):
    """leaflet.js and leaflet.css from the npm package (cached under build/npm)."""
    tgz = os.path.join(NPM_CACHE, 'leaflet-1.9.4.tgz')
    if not os.path.isfile(tgz):
        if not shutil.which('npm'):
            pytest.skip('npm is not installed: cannot obtain Leaflet')
        os.makedirs(NPM_CACHE, exist_ok=True)
        proc = subprocess.run(['npm', 'pack', LEAFLET, '--pack-destination', NPM_CACHE,
                               '--silent'], capture_output=True, text=True, timeout=180)
        if proc.returncode != 0 or not os.path.isfile(tgz):
            pytest.skip(f'npm pack {LEAFLET} failed: {proc.stderr.strip()[:200]}')
    with tarfile.open(tgz) as tar:
        for name in ('leaflet.js', 'leaflet.css'):
            member = tar.getmember(f'package/dist/{name}')
            with tar.extractfile(member) as src, open(os.path.join(tmp, name), 'wb') as dst:
                dst.write(src.read())


def chromium():
    exe = shutil.which('chromium') or shutil.which('chromium-browser')
    if not exe:
        pytest.skip('chromium is not installed (Debian: apt-get install chromium)')
    return exe


def write_page(tmp, fc, kml_path, title):
    """The static page, data.js and the overlay (quad bounds from the KML)."""
    overlay = 'null'
    root = ET.parse(kml_path).getroot()
    quad = root.findtext(f'.//{GX}LatLonQuad/{KML}coordinates')
    href = root.findtext(f'.//{KML}GroundOverlay//{KML}href')
    if quad and href:
        pts = [tuple(map(float, c.split(',')[:2])) for c in quad.split()]
        lons, lats = [p[0] for p in pts], [p[1] for p in pts]
        overlay = json.dumps([[min(lats), min(lons)], [max(lats), max(lons)]])
        shutil.copy(os.path.join(os.path.dirname(kml_path), href), tmp / 'overlay.png')
    (tmp / 'data.js').write_text(f'var DATA = {json.dumps(fc)};\nvar OVERLAY = {overlay};\n')
    page = tmp / 'map.html'
    page.write_text(PAGE.format(title=title))
    return page


def run_chromium(exe, tmp, *args):
    profile = tmp / 'profile'
    proc = subprocess.run([exe, *CHROMIUM_FLAGS, f'--user-data-dir={profile}', *args],
                          capture_output=True, text=True, timeout=120)
    return proc


def test_leaflet_draws_every_demo_feature(demo, tmp_path):  # noqa: F811
    exe = chromium()
    leaflet_dist(tmp_path)
    fc = demo['fc']
    page = write_page(tmp_path, fc, demo['dir'] / 'demo.kml',
                      'seed000 demo: 50 MLE fixes, 95% ellipses')
    proc = run_chromium(exe, tmp_path, '--dump-dom', page.as_uri())
    m = re.search(r'<pre id="result">(.*?)</pre>', proc.stdout, re.S)
    assert m and m.group(1), proc.stdout[-2000:] + proc.stderr[-2000:]
    result = json.loads(m.group(1))
    expected = {k: len(v) for k, v in kinds(fc).items()}
    assert result['counts'] == expected
    assert result['layers'] == len(fc['features'])
    assert result['paths'] == len(fc['features'])   # every feature became an SVG path
    shot = tmp_path / 'map.png'
    run_chromium(exe, tmp_path, f'--screenshot={shot}', '--window-size=1100,800',
                 page.as_uri())
    assert shot.is_file()
    import matplotlib.image as mpimg
    import numpy as np
    img = mpimg.imread(shot)
    assert img.shape[:2] == (800, 1100)
    colours = np.unique((img[..., :3] * 255).astype(np.uint8).reshape(-1, 3), axis=0)
    assert len(colours) > 50          # drawn features and overlay, not a blank page
    keep = os.environ.get('BEARING_LOC_MAP_SCREENSHOT')
    if keep:
        shutil.copy(shot, keep)
