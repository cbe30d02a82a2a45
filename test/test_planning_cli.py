"""``bearing_loc plan`` (cli/plan.py): cut-angle, map, place; bad input exits 2."""
import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from bearing_loc_ros.cli import main

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENARIO = os.path.join(ROOT, 'config', 'scenarios', 'seed000.yaml')
STATIONS = '30,-10,0.1;30,20,0.2;-30,5,0.15'


def _run(capsys, *argv):
    rc = main(['plan', *argv])
    out, err = capsys.readouterr()
    return rc, out, err


def _json(capsys, *argv):
    """The JSON printed by a successful ``bearing_loc plan`` run."""
    rc, out, err = _run(capsys, *argv)
    assert rc == 0, err
    return json.loads(out)


def test_cut_angle_json(capsys):
    rc, out, _ = _run(capsys, 'cut-angle', '--k1', '1', '--k2', '0', '--elevation-deg', '0')
    assert rc == 0
    d = json.loads(out)
    assert d['feasible'] is True
    assert d['cut_angle_deg'] == pytest.approx(np.degrees(np.arccos(-1 / 3)), abs=1e-6)
    assert d['theta2_deg'] - d['theta1_deg'] == pytest.approx(d['cut_angle_deg'])
    assert d['f_min'] == pytest.approx(27 / 32)
    rc, out, _ = _run(capsys, 'cut-angle', '--k1', '0.4')
    assert rc == 0 and json.loads(out)['feasible'] is False


def test_cut_angle_echoes_the_elevation_as_given(capsys):
    # degrees -> radians -> degrees printed 29.999999999999996
    rc, out, _ = _run(capsys, 'cut-angle', '--elevation-deg', '30')
    assert rc == 0 and json.loads(out)['elevation_deg'] == 30.0
    rc, out, _ = _run(capsys, 'cut-angle', '--table', '--elevation-deg', '-30', '--json')
    assert rc == 0 and {r['elevation_deg'] for r in json.loads(out)} == {-30.0}


def test_cut_angle_table(capsys):
    rc, out, _ = _run(capsys, 'cut-angle', '--table', '--k1-values', '0.3:0.9:0.3',
                      '--k2-values', '0,0.5', '--json')
    assert rc == 0
    rows = json.loads(out)
    assert [(r['k2'], r['k1']) for r in rows] == [(0.0, 0.3), (0.0, 0.6), (0.0, 0.9),
                                                  (0.5, 0.3), (0.5, 0.6), (0.5, 0.9)]
    assert [r['feasible'] for r in rows] == [False, True, True, True, True, True]
    rc, out, _ = _run(capsys, 'cut-angle', '--table', '--k1-values', '0.5,1', '--k2-values',
                      '0')
    assert rc == 0 and 'feasible' in out and '109.471' in out


@pytest.mark.parametrize('argv,flag', [
    (['cut-angle', '--k1', '0'], '--k1'),
    (['cut-angle', '--k1', '1', '--k2', '-1'], '--k2'),
    (['cut-angle', '--elevation-deg', '95'], '--elevation-deg'),
    (['cut-angle', '--table', '--k1-values', '1:x:2'], '--k1-values'),
    (['map', '--stations', '1,2;3,4,5', '--altitude', '5000', '--sigma-deg', '0.06'],
     '--stations'),
    (['map', '--stations', STATIONS, '--altitude', '5000'], '--sigma-deg'),
    (['map', '--stations', STATIONS, '--altitude', '5000', '--sigma-deg', '-1'],
     '--sigma-deg'),
    (['map', '--stations', STATIONS, '--altitude', '5000', '--sigma-deg', '0.06',
      '--extent-km', '10,5,0,1'], '--extent-km'),
    (['map', '--stations', STATIONS, '--altitude', '5000', '--sigma-deg', '0.06',
      '--resolution', '0'], '--resolution'),
    (['map', '--stations', STATIONS, '--altitude', '5000', '--sigma-deg', '0.06',
      '--extent-km', '-10,10,-1,1', '--resolution', '2500'], '--resolution'),
    (['place', '--stations', STATIONS, '--altitude', '5000', '--sigma-deg', '0.06',
      '--area-km', '0,1'], '--area-km'),
    (['place', '--stations', STATIONS, '--altitude', '5000', '--sigma-deg', '0.06',
      '--area-km=-5,5,-5,5', '--candidates', '1'], '--candidates'),
    (['map', '--stations', STATIONS, '--altitude', '5000', '--sigma-deg', '0.06',
      '--png', 'x.jpg2'], '--png'),
    (['cut-angle', '--sigmas-deg', '1', '2', '--k1', '5'], '--sigmas-deg'),
    (['cut-angle', '--sigmas-deg', '1', '2', '--table'], '--sigmas-deg'),
    (['cut-angle', '--table', '--k1', '3'], '--k1'),
    (['cut-angle', '--k2-values', '0,1'], '--k2-values'),
    (['map', '--stations', '0,0,0,1d;20,0,0,1d;20,20,0,1d', '--altitude', '1000',
      '--sigma-deg', '1', '--model', 'ctls'], '--model'),
])
def test_bad_input_exits_2_naming_the_flag(capsys, argv, flag):
    rc, out, err = _run(capsys, *argv)
    assert rc == 2 and out == ''
    assert flag in err and len(err.strip().splitlines()) == 1


def test_map_png_and_csv_from_stations(capsys, tmp_path):
    png = tmp_path / 'map.png'
    rc, out, _ = _run(capsys, 'map', '--stations', STATIONS + ';0,-40,0,1d', '--altitude',
                      '5000', '--sigma-deg', '0.09', '--model', 'ctls', '--extent-km', '50',
                      '--resolution', '2500', '--png', str(png))
    assert rc == 0
    d = json.loads(out)
    assert d['grid']['width'] == 40 and d['grid']['height'] == 40
    assert [s['dims'] for s in d['stations']] == [2, 2, 2, 1]
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b'\x89PNG'
    data = np.loadtxt(tmp_path / 'map.csv', delimiter=',', skiprows=1)
    assert data.shape == (1600, 4)
    assert np.all(data[:, 2] == 5000.0)
    assert data[:, 3].max() == pytest.approx(d['stats']['max_m'], rel=1e-5)


def test_map_png_without_an_extension_reports_the_file_written(capsys, tmp_path):
    d = _json(capsys, 'map', '--stations', STATIONS, '--altitude', '5000', '--sigma-deg', '0.09',
              '--resolution', '6000', '--png', str(tmp_path / 'm'))
    assert d['png'] == str(tmp_path / 'm.png') and d['csv'] == str(tmp_path / 'm.csv')
    assert (tmp_path / 'm.png').read_bytes()[:4] == b'\x89PNG'


def test_place_draws_an_unobservable_before_map(capsys, tmp_path):
    # one station observes nothing: the documented null "before" with its map drawn
    d = _json(capsys, 'place', '--stations', '0,0,0', '--sigma-deg', '0.1', '--altitude', '3000',
              '--area-km', '-10,10,-10,10', '--area-cells', '10', '--candidates', '5',
              '--png-before', str(tmp_path / 'b.png'), '--png-after', str(tmp_path / 'a.png'))
    assert d['before_m'] is None and d['after_m'] > 0
    assert d['png_before'] == str(tmp_path / 'b.png')
    for name in ('a.png', 'b.png'):
        assert (tmp_path / name).read_bytes()[:4] == b'\x89PNG'


def test_place_assesses_an_azimuth_only_layout_with_its_own_solve(capsys, tmp_path):
    # Two 1D stations: horizontal (altitude known) on their own, as plan map says; with the
    # default 2D new station the layout is 3D. "before" was the 3D map: null, unobservable.
    layout = ['--stations', '20,0,0,1d;-20,0,0,1d', '--sigma-deg', '0.1', '--altitude', '3000']
    area = ['--area-km', '-10,10,-10,10', '--area-cells', '10', '--candidates', '5']
    m = _json(capsys, 'map', *layout, '--extent-km=-10,10,-10,10', '--resolution', '2000')
    d = _json(capsys, 'place', *layout, *area, '--png-before', str(tmp_path / 'b.png'))
    assert (m['solve'], d['solve_before'], d['solve']) == ('horizontal', 'horizontal', '3d')
    # the area grid of place is the map's grid: 10 x 10 cells of 2 km
    assert d['before'] == m['stats'] and d['before_m'] == pytest.approx(m['stats']['mean_m'])
    assert d['improvement_m'] == pytest.approx(d['before_m'] - d['after_m'])
    assert d['ratio'] == pytest.approx(d['after_m'] / d['before_m'])
    # a 1D new station: horizontal before and after, the same "before"
    d1 = _json(capsys, 'place', *layout, *area, '--new-1d')
    assert (d1['solve_before'], d1['solve']) == ('horizontal', 'horizontal')
    assert d1['before_m'] == pytest.approx(d['before_m'], rel=1e-9)
    assert d1['before'] == pytest.approx(d['before'], rel=1e-9)


def test_map_from_scenario_uses_the_scenario_loader(capsys, tmp_path):
    # seed000.yaml: 3 mrad stations at the Wang, Zhang & Wu (2006) positions; --sigma-deg
    # overrides σ.
    rc, out, _ = _run(capsys, 'map', '--scenario', SCENARIO, '--altitude', '5000',
                      '--extent-km', '60', '--resolution', '6000', '--csv',
                      str(tmp_path / 'g.csv'))
    assert rc == 0
    d = json.loads(out)
    assert [s['position_m'] for s in d['stations']][0] == [30000.0, -10000.0, 100.0]
    assert d['stations'][0]['sigma_az_mrad'] == pytest.approx(3.0)
    rc, out2, _ = _run(capsys, 'map', '--scenario', SCENARIO, '--altitude', '5000',
                       '--extent-km', '60', '--resolution', '6000',
                       '--sigma-deg', repr(math.degrees(1.5e-3)))
    d2 = json.loads(out2)
    assert d2['stats']['mean_m'] == pytest.approx(d['stats']['mean_m'] / 2, rel=1e-9)
    rc, _, err = _run(capsys, 'map', '--scenario', str(tmp_path / 'missing.yaml'),
                      '--altitude', '5000')
    assert rc == 2 and 'missing.yaml' in err


def test_place_json_and_maps(capsys, tmp_path):
    rc, out, _ = _run(capsys, 'place', '--stations', '20,0,0;-20,0,0;0,20,0;0,-20,0',
                      '--sigma-deg', '0.11', '--altitude', '3000', '--area-km=-10,10,-10,10',
                      '--region-km=-30,30,-30,30', '--height', '0', '--area-cells', '10',
                      '--candidates', '10', '--png-before', str(tmp_path / 'b.png'),
                      '--png-after', str(tmp_path / 'a.png'), '--resolution', '2000')
    assert rc == 0
    d = json.loads(out)
    assert np.hypot(*d['position_m'][:2]) < 50.0
    assert d['after_m'] < d['before_m'] and d['improvement_m'] > 0
    assert (tmp_path / 'b.png').stat().st_size > 10_000
    assert (tmp_path / 'a.png').stat().st_size > 10_000


def test_console_script_subprocess(tmp_path):
    exe = os.path.join(os.path.dirname(sys.executable), 'bearing_loc')
    if not os.path.exists(exe):
        pytest.skip('bearing_loc console script not installed in this environment')
    res = subprocess.run([exe, 'plan', 'cut-angle', '--k1', '0.8', '--k2', '0',
                          '--elevation-deg', '0'], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    d = json.loads(res.stdout)
    assert d['feasible'] is True and 90.0 < d['cut_angle_deg'] < 110.0
    res = subprocess.run([exe, 'plan', 'cut-angle', '--k1', '-3'], capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 2 and '--k1' in res.stderr


def test_documented_figures_exist_and_are_small():
    # The manual (README and docs/) shows the Wang, Zhang & Wu (2006) maps (and other
    # figures); each PNG must exist and be < 300 kB.
    import glob
    import re
    refs = set()
    for page in [os.path.join(ROOT, 'README.md')] + glob.glob(os.path.join(ROOT, 'docs',
                                                                           '*.md')):
        with open(page, encoding='utf-8') as f:
            for ref in re.findall(r'\(([^)\s]*img/[^)\s]+\.png)\)', f.read()):
                refs.add(os.path.normpath(os.path.join(os.path.dirname(page), ref)))
    assert len([r for r in refs if 'seed000_' in r]) >= 5
    for path in refs:
        assert os.path.exists(path), path
        assert os.path.getsize(path) < 300_000, path


def test_an_output_in_a_missing_directory_exits_2_naming_the_flag(capsys, tmp_path):
    # plan map --png /nonexistent/x.png created /nonexistent (and --csv likewise); docs/cli.md
    # promises exit 2 naming the flag, as for locate's outputs, before the work.
    missing = tmp_path / 'missing'
    base = ['--stations', STATIONS, '--sigma-deg', '0.1', '--altitude', '5000']
    small = ['--extent-km', '40', '--resolution', '4000']
    cases = [(['map', *base, *small, '--png', str(missing / 'x.png')], '--png'),
             (['map', *base, *small, '--csv', str(missing / 'x.csv')], '--csv'),
             (['map', *base, *small, '--csv', str(tmp_path)], '--csv'),
             (['place', *base, '--area-km', '-10,10,-10,10', '--area-cells', '4',
               '--candidates', '3', '--png-after', str(missing / 'a.png')], '--png-after'),
             (['place', *base, '--area-km', '-10,10,-10,10', '--area-cells', '4',
               '--candidates', '3', '--png-before', str(missing / 'b.png')], '--png-before')]
    for argv, flag in cases:
        rc, out, err = _run(capsys, *argv)
        assert rc == 2 and out == '' and err.count('\n') == 1, (argv, err)
        assert f'error: {flag}: cannot write ' in err, err
        assert not missing.exists()
