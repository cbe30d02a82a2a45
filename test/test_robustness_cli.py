"""CLI robustness: malformed input exits 2 with one line on stderr naming the field, nothing
on stdout, never a traceback (in-process calls of the dispatcher, fixed cases)."""
import json

import pytest

from bearing_loc_ros.cli import main

SCENARIO = 'config/scenarios/static3.yaml'
B = {'position': [0, 0, 0], 'azimuth': 0.785, 'elevation': 0.05, 'sigma_azimuth': 0.01,
     'sigma_elevation': 0.01}
B2 = dict(B, position=[1000, 0, 0], azimuth=1.57)
OBS = {'t': 0.0, 'observer': [0, 0, 0], 'azimuth': 0.78, 'elevation': 0.07}


def run(capsys, argv, stdin=None, monkeypatch=None):
    if stdin is not None:
        import io
        monkeypatch.setattr('sys.stdin', io.StringIO(stdin))
    rc = main(argv)
    out, err = capsys.readouterr()
    assert 'Traceback' not in err
    return rc, out, err


def assert_bad(rc, out, err, field):
    assert rc == 2 and out == ''
    lines = err.strip().splitlines()
    assert len(lines) == 1 and field in lines[0], err


BIG = '1' + '0' * 400          # a JSON integer beyond the float range (was OverflowError)


@pytest.mark.parametrize('text,field', [
    ('{"bearings": [%s, %s]}' % (json.dumps(B).replace('0.785', BIG), json.dumps(B2)),
     'azimuth'),
    ('{"bearings": [%s, %s]}' % (json.dumps(B).replace('"sigma_azimuth": 0.01',
                                                       '"sigma_azimuth": ' + BIG),
                                 json.dumps(B2)), 'sigma_azimuth'),
    ('{"bearings": [%s, %s]}' % (json.dumps(B).replace('0.05', 'NaN'), json.dumps(B2)),
     'elevation'),
    ('{"bearings": [%s, %s]}' % (json.dumps(B).replace('0.785', 'Infinity'), json.dumps(B2)),
     'azimuth'),
    (json.dumps({'bearings': [dict(B, sigma_azimuth=1e-300), B2]}), 'sigma_azimuth'),
    (json.dumps({'bearings': [B]}), 'bearings'),
    (json.dumps({'bearings': [dict(B, elevation=None), dict(B2, elevation=None)]}),
     'elevation'),
    (json.dumps({'bearings': [dict(B, position=[0, 0]), B2]}), 'position'),
    (json.dumps({'bearings': [dict(B, position=None), B2]}), 'position'),
    (json.dumps({'bearings': []}), 'bearings'), (json.dumps({'problems': []}), 'problems'),
    (json.dumps({'bearings': [B, B2], 'options': {'max_iterations': 'x'}}), 'max_iterations'),
    ('null', 'input'), ('[1, 2]', 'input'), ('{', 'input'), ('', 'input'),
])
def test_locate_bad_input(capsys, monkeypatch, text, field):
    assert_bad(*run(capsys, ['locate', '-'], text, monkeypatch), field)


def test_locate_colocated_stations_is_not_a_confident_fix(capsys, monkeypatch):
    # Bug: co-located stations gave status ok at the station with ~1e-13 m² covariance (ls).
    doc = {'estimator': 'ls', 'bearings': [dict(B, position=[5, 5, 5]),
                                           dict(B, position=[5, 5, 5], azimuth=1.0)]}
    rc, out, err = run(capsys, ['locate', '-'], json.dumps(doc), monkeypatch)
    res = json.loads(out)
    assert rc == 0 and res['status'] == 'degenerate_geometry' and not res['converged']


def tma_doc(**kw):
    obs = [dict(OBS, t=5.0 * k, observer=[0, 500.0 * k, 0], azimuth=0.78 - 0.01 * k)
           for k in range(10)]
    return dict({'speed': 200.0, 'sigma_azimuth': 0.001, 'sigma_elevation': 0.001,
                 'observations': obs}, **kw)


@pytest.mark.parametrize('doc,field', [
    (tma_doc(sigma_azimuth=1e-300), 'sigma_azimuth'),   # was "Eigenvalues did not converge"
    (tma_doc(speed=None), 'speed'), (tma_doc(speed='x'), 'speed'),
    (tma_doc(speed=-1), 'speed'), (tma_doc(observations=[]), 'observations'),
    (tma_doc(observations=[dict(OBS, elevation=None)]), 'elevation'),
    (tma_doc(options={'alpha': 'x'}), 'alpha'), (tma_doc(options={'zz': 1}), 'zz'),
    (tma_doc(estimator=5), 'estimator'), (tma_doc(speed_reference='x'), 'speed_reference'),
])
def test_tma_bad_input(capsys, monkeypatch, doc, field):
    assert_bad(*run(capsys, ['tma', '-'], json.dumps(doc), monkeypatch), field)


def test_tma_huge_integer(capsys, monkeypatch):
    text = json.dumps(tma_doc()).replace('"speed": 200.0', '"speed": ' + BIG)
    assert_bad(*run(capsys, ['tma', '-'], text, monkeypatch), 'speed')


@pytest.fixture
def bad_files(tmp_path):
    files = {'empty': b'', 'list': b'- a\n- b\n', 'binary': b'\xff\xfe\x00bad',
             'broken': b'stations: [\n', 'bigint': (open(SCENARIO).read().replace(
                 'position: [0.0, 0.0, 0.0]', 'position: [' + '9' * 400 + ', 0, 0]')
                 .encode())}
    out = {}
    for k, v in files.items():
        (tmp_path / f'{k}.yaml').write_bytes(v)
        out[k] = str(tmp_path / f'{k}.yaml')
    (tmp_path / 'afile').write_text('x')
    out['afile'] = str(tmp_path / 'afile')
    out['dir'] = str(tmp_path)
    return out


@pytest.mark.parametrize('kind,field', [('empty', 'empty'), ('list', 'scenario'),
                                        ('binary', 'UTF-8'), ('broken', 'invalid YAML'),
                                        ('bigint', 'position'), ('dir', 'scenario')])
@pytest.mark.parametrize('verb', ['evaluate', 'plan', 'bag'])
def test_bad_scenario_files(capsys, bad_files, tmp_path, kind, field, verb):
    f = bad_files[kind]
    argv = {'evaluate': ['evaluate', '--scenario', f, '--trials', '2', '--quiet'],
            'plan': ['plan', 'map', '--scenario', f, '--altitude', '300'],
            'bag': ['bag', 'simulate', '--scenario', f, '--out', str(tmp_path / 'bag')]}[verb]
    assert_bad(*run(capsys, argv), field)


EVAL = ['evaluate', '--scenario', SCENARIO, '--estimator', 'ls', '--sigma-deg', '1',
        '--sweep', 'none', '--quiet', '--no-plots']
STD = ['--stations', '0,0,0;1,0,0', '--altitude', '1000', '--sigma-deg', '0.06',
       '--extent-km', '2']


@pytest.mark.parametrize('argv,field', [
    (EVAL + ['--trials', '0'], '--trials'), (EVAL + ['--trials', str(10 ** 12)], '--trials'),
    (EVAL + ['--trials', '2', '--seed', str(2 ** 70)], '--seed'),
    (EVAL + ['--trials', '2', '--range-ref', '1e-300'], '--range-ref'),
    (EVAL + ['--trials', '2', '--fixed-sigma-deg', '0'], '--fixed-sigma-deg'),
    (EVAL[:5] + ['--sigma-deg', '0', '--trials', '2'], '--sigma-deg'),
    (['plan', 'cut-angle', '--k1', '1e308', '--k2', '1e308'], '--k1'),
    (['plan', 'cut-angle', '--table', '--k1-values', '0.1:1e9:1e-9'], '--k1-values'),
    (['plan', 'cut-angle', '--table', '--k1-values', '0:inf:1'], '--k1-values'),
    (['plan', 'map'] + STD + ['--altitude', '1e308'], '--altitude'),
    (['plan', 'map'] + STD + ['--sigma-deg', '1e-300'], '--sigma-deg'),
    (['plan', 'map'] + STD + ['--extent-km', '1e-300'], '--resolution'),
])
def test_bad_flags(capsys, argv, field):
    assert_bad(*run(capsys, argv), field)


def test_unwritable_outputs(capsys, bad_files, tmp_path):
    afile = bad_files['afile']
    # Bugs: FileExistsError / IsADirectoryError / NotADirectoryError tracebacks.
    assert_bad(*run(capsys, EVAL + ['--trials', '2', '--out', afile]), 'out')
    assert_bad(*run(capsys, ['plan', 'map'] + STD + ['--png', afile + '/x.png']), '--png')
    assert_bad(*run(capsys, ['plan', 'map'] + STD + ['--csv', str(tmp_path)]), '--csv')
    assert_bad(*run(capsys, ['bag', 'simulate', '--scenario', SCENARIO, '--out',
                             afile + '/sub']), 'out')
    assert_bad(*run(capsys, ['bag', 'simulate', '--scenario', SCENARIO, '--out',
                             str(tmp_path / 'b'), '--duration', '1e300']), 'duration')
