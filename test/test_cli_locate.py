"""``bearing_loc locate``: JSON interface, batches, strict JSON output, bad input → exit 2."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from bearing_loc_ros.cli import main
from bearing_loc_ros.core.bearings import simulate_bearings
from bearing_loc_ros.core.crlb import crlb_for
from bearing_loc_ros.core.estimators import DEFAULT_ESTIMATOR, ESTIMATORS, locate

EXE = os.path.join(os.path.dirname(sys.executable), 'bearing_loc')
STATIONS = np.array([[30.0, -10.0, 0.1], [30.0, 20.0, 0.2], [-30.0, 5.0, 0.15]]) * 1e3
TARGET = np.array([10e3, 20e3, 5e3])


def bearings_json(target=TARGET, stations=STATIONS, sigma=1.5e-3, one_d=(), rng=None):
    bs = simulate_bearings(target, stations, sigma, rng=rng)
    out = []
    for i in range(bs.N):
        b = {'station': f's{i + 1}', 'position': bs.positions[0, i].tolist(),
             'azimuth': float(bs.azimuth[0, i]), 'sigma_azimuth': sigma}
        if i in one_d:
            b['elevation'] = None
        else:
            b['elevation'] = float(bs.elevation[0, i])
            b['sigma_elevation'] = sigma
        out.append(b)
    return out


def run_main(tmp_path, doc, *extra, capsys):
    path = tmp_path / 'in.json'
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    code = main(['locate', str(path), *extra])
    out, err = capsys.readouterr()
    return code, out, err


def test_single_problem_in_process(tmp_path, capsys):
    doc = {'estimator': 'mle', 'bearings': bearings_json(one_d=(1,))}
    code, out, err = run_main(tmp_path, doc, capsys=capsys)
    assert code == 0 and err == ''
    res = json.loads(out)
    assert set(res) == {'estimator', 'method', 'position', 'covariance', 'crlb', 'converged',
                        'iterations', 'status', 'solve', 'excluded'}
    assert res['estimator'] == 'mle' and res['status'] == 'ok' and res['converged'] is True
    assert res['excluded'] == []
    np.testing.assert_allclose(res['position'], TARGET, atol=1e-3)
    assert np.array(res['covariance']).shape == (3, 3) and np.array(res['crlb']).shape == (3, 3)
    # mle's covariance is the CRLB at the estimate, which is the "crlb" field.
    np.testing.assert_allclose(res['covariance'], res['crlb'], rtol=1e-9)


def test_an_excluded_angle_is_reported(tmp_path, capsys):
    # A 3 degree reflection on the third station's azimuth (35 sigma): the robust default
    # leaves that angle out and says so; an estimator without outlier handling has no
    # "excluded" key. The same through a bearing table, per problem.
    items = bearings_json(rng=np.random.default_rng(3))
    items[2]['azimuth'] += float(np.radians(3.0))
    code, out, _ = run_main(tmp_path, {'bearings': items}, capsys=capsys)
    res = json.loads(out)
    assert code == 0 and res['status'] == 'ok'
    assert res['excluded'] == [{'bearing': 2, 'angle': 'azimuth'}]
    assert np.linalg.norm(np.array(res['position']) - TARGET) < 3 * np.sqrt(
        np.trace(res['covariance']))
    code, out, _ = run_main(tmp_path, {'bearings': items}, '--estimator', 'ls', capsys=capsys)
    assert code == 0 and 'excluded' not in json.loads(out)
    rows = ['problem,x,y,z,azimuth,elevation,sigma_azimuth,sigma_elevation']
    for pid, its in ((7, bearings_json(rng=np.random.default_rng(4))), (8, items)):
        rows += [f"{pid},{','.join(map(repr, b['position']))},{b['azimuth']!r},"
                 f"{b['elevation']!r},{b['sigma_azimuth']},{b['sigma_elevation']}" for b in its]
    path = tmp_path / 'table.csv'
    path.write_text('\n'.join(rows) + '\n')
    assert main(['locate', str(path)]) == 0
    out = json.loads(capsys.readouterr()[0])['results']
    assert [r['problem'] for r in out] == [7, 8]
    assert out[0]['excluded'] == [] and out[1]['excluded'] == res['excluded']


def test_target_altitude_and_ignored_elevations_are_never_silently_unused(tmp_path, capsys):
    doc = {'bearings': bearings_json(rng=np.random.default_rng(6))}
    code, out, err = run_main(tmp_path, doc, '--target-altitude', '5000', capsys=capsys)
    assert code == 0 and json.loads(out)['solve'] == '3d'
    assert err.startswith('bearing_loc locate: warning: target_altitude not used')
    code, out, err = run_main(tmp_path, doc, '--target-altitude', '5000', '--dimension', '3d',
                              capsys=capsys)
    assert code == 0 and 'target_altitude not used for the problem: --dimension 3d' in err
    code, out, err = run_main(tmp_path, doc, '--target-altitude', '5000', '--dimension',
                              'horizontal', capsys=capsys)
    assert code == 0 and json.loads(out)['solve'] == 'horizontal' and err == ''
    code, out, err = run_main(tmp_path, doc, '--ignore-elevations', '--target-altitude',
                              '5000', capsys=capsys)
    assert code == 0 and err == ''
    res = json.loads(out)
    assert res['solve'] == 'horizontal' and res['position'][2] == 5000.0
    code, out, err = run_main(tmp_path, doc, '--ignore-elevations', capsys=capsys)
    assert code == 2 and out == '' and 'target_altitude: required' in err
    code, out, err = run_main(tmp_path, doc, '--ignore-elevations', '--dimension', '3d',
                              capsys=capsys)
    assert code == 2 and out == '' and 'error: use_elevations:' in err


@pytest.mark.parametrize('method', sorted(ESTIMATORS))
def test_every_method_matches_the_core(tmp_path, capsys, method):
    rng = np.random.default_rng(1)
    items = bearings_json(rng=rng)
    opts = {'reference_range': 5000.0} if method == 'wmle' else {}
    code, out, _ = run_main(tmp_path, {'estimator': method, 'options': opts, 'bearings': items},
                            capsys=capsys)
    assert code == 0
    res = json.loads(out)
    from bearing_loc_ros.cli.locate import parse_bearings
    core = locate(method, parse_bearings(items), **opts)
    np.testing.assert_allclose(res['position'], core.position[0], rtol=1e-12)
    np.testing.assert_allclose(res['covariance'], core.covariance[0], rtol=1e-12)
    assert res['iterations'] == int(core.iterations[0])


def test_default_method_and_override(tmp_path, capsys):
    code, out, _ = run_main(tmp_path, {'bearings': bearings_json()}, capsys=capsys)
    assert code == 0 and json.loads(out)['estimator'] == DEFAULT_ESTIMATOR
    code, out, _ = run_main(tmp_path, {'estimator': 'mle', 'bearings': bearings_json()},
                            '--estimator', 'ls', capsys=capsys)
    assert code == 0 and json.loads(out)['estimator'] == 'ls'


def test_batch_mixed_sizes_keeps_order(tmp_path, capsys):
    rng = np.random.default_rng(2)
    four = np.vstack([STATIONS, [[0.0, -40e3, 0.3]]])
    targets = [TARGET, TARGET + [5e3, 0, 0], TARGET + [0, 5e3, 1e3], TARGET - [3e3, 3e3, 0]]
    probs = [{'bearings': bearings_json(targets[0], rng=rng)},
             {'bearings': bearings_json(targets[1], four, rng=rng, one_d=(3,))},
             {'bearings': bearings_json(targets[2], rng=rng)},
             {'bearings': bearings_json(targets[3], four, rng=rng)}]
    code, out, _ = run_main(tmp_path, {'estimator': 'mle', 'problems': probs}, capsys=capsys)
    assert code == 0
    res = json.loads(out)['results']
    assert len(res) == 4
    for r, t in zip(res, targets):
        assert r['status'] == 'ok'
        # Within 5 sigma of the truth: proves the results are not shuffled between problems.
        err = np.array(r['position']) - t
        assert err @ np.linalg.solve(np.array(r['covariance']), err) < 25


def test_degenerate_fix_gives_strict_json_with_nulls(tmp_path, capsys):
    st = np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0]])
    doc = {'estimator': 'mle', 'bearings': bearings_json(np.array([3000.0, 0.0, 0.0]), st)}
    code, out, _ = run_main(tmp_path, doc, capsys=capsys)
    assert code == 0
    assert 'NaN' not in out and 'Infinity' not in out
    res = json.loads(out)
    assert res['status'] == 'degenerate_geometry' and res['converged'] is False
    assert res['position'] == [None, None, None]
    assert res['covariance'][0][0] is None


def test_crlb_field_is_the_crlb_at_the_estimate(tmp_path, capsys):
    items = bearings_json(rng=np.random.default_rng(3))
    code, out, _ = run_main(tmp_path, {'estimator': 'ls', 'bearings': items}, capsys=capsys)
    res = json.loads(out)
    from bearing_loc_ros.cli.locate import parse_bearings
    expect = crlb_for(np.array([res['position']]), parse_bearings(items))[0]
    np.testing.assert_allclose(res['crlb'], expect, rtol=1e-12)


def _bad(**change):
    items = bearings_json()
    for key, val in change.items():
        idx, field = key.split('__')
        if val is KeyError:
            del items[int(idx[1:])][field]
        else:
            items[int(idx[1:])][field] = val
    return {'estimator': 'mle', 'bearings': items}


BAD_CASES = [
    (_bad(b1__sigma_azimuth=0.0), 'bearings[1].sigma_azimuth: must be > 0'),
    (_bad(b1__sigma_azimuth=-1e-3), 'bearings[1].sigma_azimuth: must be > 0'),
    (_bad(b1__sigma_azimuth=1e-300), 'bearings[1].sigma_azimuth: must be finite and in'),
    (_bad(b2__position=[1e300, 0.0, 0.0]), 'bearings[2].position: |coordinate| must be <='),
    ({'estimator': 'mle', 'problems': [{'bearings': bearings_json()},
                                       {'bearings': _bad(b0__sigma_elevation=5e3)['bearings']}]},
     'problems[1].bearings[0].sigma_elevation: must be finite and in'),
    (_bad(b0__azimuth='north'), 'bearings[0].azimuth: must be a number'),
    (_bad(b2__position=[1.0, 2.0]), 'bearings[2].position: must be a list'),
    (_bad(b2__position=[1.0, 2.0, True]), 'bearings[2].position[2]: must be a number'),
    (_bad(b0__elevation=2.0), 'bearings[0].elevation: |elevation| must be < pi/2'),
    (_bad(b0__sigma_elevation=KeyError), 'bearings[0].sigma_elevation: missing'),
    (_bad(b1__azimuth=KeyError), 'bearings[1].azimuth: missing'),
    (_bad(b1__colour='red'), 'bearings[1].colour: unknown field'),
    ('{"bearings": [1, 2', 'input: invalid JSON'),
    ('[1, 2]', 'input: must be a JSON object'),
    ('{"estimator": "mle", "bearings": [{"position": [0, 0, 0], "azimuth": NaN, '
     '"sigma_azimuth": 0.01}, {"position": [1, 0, 0], "azimuth": 1, "sigma_azimuth": 0.01}]}',
     'bearings[0].azimuth: must be a finite number'),
    ({'estimator': 'best', 'bearings': bearings_json()}, 'estimator: unknown estimator'),
    ({'estimator': '', 'bearings': bearings_json()}, 'estimator: unknown estimator'),
    ({'estimator': 0, 'bearings': bearings_json()}, 'estimator: unknown estimator'),
    ({'estimator': False, 'bearings': bearings_json()}, 'estimator: unknown estimator'),
    ({'estimator': [], 'bearings': bearings_json()}, 'estimator: unknown estimator'),
    ({'estimator': 'mle', 'bearings': bearings_json(), 'options': {'bogus': 1}},
     'options.bogus: unknown option'),
    ({'estimator': 'mle', 'bearings': bearings_json(), 'options': {'initial': 'abc'}},
     'options.initial: must be 3 numbers (m)'),
    ({'estimator': 'mle', 'bearings': bearings_json(), 'options': {'initial': {'a': 1}}},
     'options.initial: must be 3 numbers (m)'),
    ({'estimator': 'mle', 'bearings': bearings_json(), 'options': {'initial': [1e300, 0, 0]}},
     'options.initial: |coordinate| above 1e+12 m'),
    ({'estimator': 'mle', 'bearings': bearings_json(), 'options': {'max_iterations': 0}},
     'options.max_iterations: must be an integer >= 1'),
    ({'estimator': 'mle', 'bearings': bearings_json()[:1]}, 'bearings: 1 bearing(s)'),
    ({'estimator': 'mle', 'bearings': bearings_json(one_d=(0, 1, 2))},
     'target_altitude: required because the bearings do not observe the height'),
    ({'estimator': 'mle', 'problems': [{'bearings': bearings_json()},
                                       {'bearings': _bad(b1__sigma_azimuth=0.0)['bearings']}]},
     'problems[1].bearings[1].sigma_azimuth: must be > 0'),
    ({'estimator': 'mle', 'bearings': bearings_json(), 'problems': []}, 'input: give exactly one'),
    ({'estimator': 'mle', 'bearing': bearings_json()}, 'bearing: unknown field'),
]


@pytest.mark.parametrize('doc, message', BAD_CASES)
def test_bad_input_in_process(tmp_path, capsys, doc, message):
    code, out, err = run_main(tmp_path, doc, capsys=capsys)
    assert code == 2
    assert out == ''
    lines = err.splitlines()
    assert len(lines) == 1 and message in lines[0], err


@pytest.mark.parametrize('data, message', [
    (b'\xff\xfe{"bearings": []}', 'input: invalid JSON'),
    (b'{"bearings": "\xc3"}', 'input: invalid JSON'),
    (b'', 'input: invalid JSON'),
    (b'[' * 100000 + b']' * 100000, 'input: invalid JSON (nested too deeply)'),
    # within orjson's 1024 levels but beyond Python's recursion limit in the checks
    (b'{"estimator": ' + b'[' * 1010 + b']' * 1010 + b', "bearings": []}',
     'input: nested too deeply'),
    # a UTF-8 byte order mark (as some editors write) is read past
    (b'\xef\xbb\xbf{"bearings": []}', 'bearings: 0 bearing(s)')])
def test_undecodable_input_is_invalid_json(tmp_path, capsys, data, message):
    (tmp_path / 'bad.json').write_bytes(data)
    assert main(['locate', str(tmp_path / 'bad.json')]) == 2
    out, err = capsys.readouterr()
    assert out == '' and len(err.splitlines()) == 1 and message in err, err


def test_missing_file_is_exit_2(tmp_path, capsys):
    assert main(['locate', str(tmp_path / 'nope.json')]) == 2
    out, err = capsys.readouterr()
    assert out == '' and len(err.splitlines()) == 1 and 'input: cannot read' in err


@pytest.mark.skipif(not os.path.exists(EXE), reason='bearing_loc console script not installed')
def test_subprocess_stdin_and_exit_codes():
    env = dict(os.environ)
    doc = json.dumps({'estimator': 'mle', 'bearings': bearings_json(one_d=(2,))})
    p = subprocess.run([EXE, 'locate'], input=doc, capture_output=True, text=True, env=env,
                       timeout=60)
    assert p.returncode == 0, p.stderr
    res = json.loads(p.stdout)
    assert res['status'] == 'ok'
    np.testing.assert_allclose(res['position'], TARGET, atol=1e-3)
    bad = json.dumps(_bad(b1__sigma_azimuth=0.0))
    p = subprocess.run([EXE, 'locate', '-'], input=bad, capture_output=True, text=True,
                       env=env, timeout=60)
    assert p.returncode == 2 and p.stdout == ''
    assert p.stderr.splitlines() == ['bearing_loc locate: error: bearings[1].sigma_azimuth: '
                                     'must be > 0']


def test_locate_imports_no_optional_heavy_modules(tmp_path):
    # The locate path needs numpy only: scipy.special alone costs ~0.2 s of start-up.
    path = tmp_path / 'in.json'
    path.write_text(json.dumps({'problems': [{'bearings': bearings_json()}] * 3}))
    code = ('import sys\nfrom bearing_loc_ros.cli import main\n'
            f'assert main(["locate", {str(path)!r}]) == 0\n'
            'heavy = {"scipy", "yaml", "matplotlib", "rosbags", "rclpy", "pymap3d"}\n'
            'print(sorted(m for m in sys.modules if m.split(".")[0] in heavy\n'
            '             or m == "numpy.ma"), file=sys.stderr)\n')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         env=dict(os.environ, AMENT_PREFIX_PATH=sys.prefix))
    assert out.returncode == 0, out.stderr
    assert out.stderr.strip() == '[]'
