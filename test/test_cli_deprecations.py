"""Former option spellings, JSON keys and estimator names: accepted for one release, warned."""

import io
import json
import math
import os

import numpy as np
import pytest

from bearing_loc_ros.cli import main
from bearing_loc_ros.cli.deprecation import OLD_TMA_NAMES
from bearing_loc_ros.core import registry

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SEED003 = os.path.join(REPO, 'config', 'scenarios', 'seed003.yaml')
B = [{'position': [0.0, 0.0, 0.0], 'azimuth': 0.7, 'elevation': 0.1, 'sigma_azimuth': 0.01,
      'sigma_elevation': 0.01},
     {'position': [1000.0, 0.0, 0.0], 'azimuth': 1.3, 'elevation': 0.1, 'sigma_azimuth': 0.01,
      'sigma_elevation': 0.01}]


def _run(capsys, monkeypatch, argv, stdin=None):
    if stdin is not None:
        monkeypatch.setattr('sys.stdin', io.StringIO(json.dumps(stdin)))
    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


def _warnings(err):
    return [line for line in err.splitlines() if line.startswith('bearing_loc: warning:')]


def test_locate_method_flag_and_key(capsys, monkeypatch):
    rc, new, err = _run(capsys, monkeypatch, ['locate', '--estimator', 'ls'], {'bearings': B})
    assert rc == 0 and err == ''
    rc, old, err = _run(capsys, monkeypatch, ['locate', '--method', 'ls'], {'bearings': B})
    assert rc == 0 and json.loads(old) == json.loads(new)
    assert _warnings(err) == [line for line in err.splitlines()]
    assert '--method is deprecated, use --estimator' in err
    rc, old, err = _run(capsys, monkeypatch, ['locate'], {'method': 'ls', 'bearings': B})
    assert rc == 0 and json.loads(old) == json.loads(new)
    assert len(_warnings(err)) == 1 and '"method" is deprecated, use "estimator"' in err
    res = json.loads(new)
    assert res['estimator'] == res['method'] == 'ls'
    # both keys: refused, naming the key
    rc, out, err = _run(capsys, monkeypatch, ['locate'],
                        {'method': 'ls', 'estimator': 'mle', 'bearings': B})
    assert rc == 2 and out == '' and err.startswith('bearing_loc locate: error: method:')


def _tma_doc(estimator_key, name):
    t = np.arange(0.0, 60.0, 2.0)
    obs = [{'t': float(k), 'observer': [0.0, 200.0 * k, 0.0],
            'azimuth': math.atan2(50e3 - 0.0, 40e3 - 200.0 * k), 'elevation': 0.05}
           for k in t]
    return {estimator_key: name, 'speed': 300.0, 'sigma_azimuth': 0.002,
            'sigma_elevation': 0.002, 'observations': obs}


@pytest.mark.parametrize('old,new', sorted(OLD_TMA_NAMES.items()))
def test_tma_short_names_are_the_node_names(capsys, monkeypatch, old, new):
    assert new in registry.names(registry.MODE_TMA)
    rc, ref, err = _run(capsys, monkeypatch, ['tma'], _tma_doc('estimator', new))
    assert rc == 0 and err == '' and json.loads(ref)['estimator'] == new
    for argv, doc in ((['tma'], _tma_doc('method', old)),
                      (['tma', '--method', old], _tma_doc('estimator', new)),
                      (['tma', '--estimator', old], _tma_doc('estimator', 'tma_ple'))):
        rc, out, err = _run(capsys, monkeypatch, argv, doc)
        assert rc == 0 and json.loads(out) == json.loads(ref), argv
        assert _warnings(err) and _warnings(err) == err.splitlines(), err


def test_evaluate_estimators_flag(capsys, monkeypatch):
    argv = ['evaluate', '--scenario', SEED003, '--sigma-deg', '1', '--trials', '3',
            '--sweep', 'none', '--quiet', '--no-plots']
    rc, new, err = _run(capsys, monkeypatch, argv + ['--estimator', 'ls,wmle'])
    assert rc == 0 and err == ''
    rc, old, err = _run(capsys, monkeypatch, argv + ['--estimators', 'ls,wmle'])
    assert rc == 0 and '--estimators is deprecated, use --estimator' in err
    table = new.splitlines()[1:]
    # same figures (the timing column differs from run to run)
    assert [line.split()[:-1] for line in table] == \
        [line.split()[:-1] for line in old.splitlines()[1:]]


PLAN = ['plan', 'map', '--stations', '0,0,0;10,0,0;0,10,0,1d', '--altitude', '2000',
        '--extent-km', '20', '--resolution', '4000']


def _stations(out):
    def r(v):
        return None if v is None else round(v, 9)
    return [(r(s['sigma_az_mrad']), r(s['sigma_el_mrad'])) for s in json.loads(out)['stations']]


def test_plan_sigma_flags(capsys, monkeypatch):
    one = repr(math.degrees(1.5e-3))
    two = repr(math.degrees(3e-3))
    rc, both, err = _run(capsys, monkeypatch, PLAN + ['--sigma-deg', one])
    assert rc == 0 and err == ''
    assert _stations(both) == [(1.5, 1.5), (1.5, 1.5), (1.5, None)]
    rc, old, err = _run(capsys, monkeypatch, PLAN + ['--sigma-mrad', '1.5'])
    assert rc == 0 and '--sigma-mrad is deprecated, use --sigma-deg' in err
    assert json.loads(old)['stats'] == pytest.approx(json.loads(both)['stats'], rel=1e-12)
    rc, split, err = _run(capsys, monkeypatch, PLAN + ['--sigma-azimuth-deg', one,
                                                       '--sigma-elevation-deg', two])
    assert rc == 0 and err == ''
    assert _stations(split) == [(1.5, 3.0), (1.5, 3.0), (1.5, None)]
    rc, old, err = _run(capsys, monkeypatch, PLAN + ['--sigma-deg', one,
                                                     '--sigma-el-mrad', '3'])
    assert rc == 0 and '--sigma-el-mrad is deprecated, use --sigma-elevation-deg' in err
    assert json.loads(old)['stats'] == pytest.approx(json.loads(split)['stats'], rel=1e-12)
    # with --stations, the elevation σ defaults to the azimuth σ
    rc, az_only, _ = _run(capsys, monkeypatch, PLAN + ['--sigma-azimuth-deg', one])
    assert rc == 0 and _stations(az_only) == _stations(both)


def test_plan_azimuth_sigma_keeps_the_scenario_elevation_sigma(capsys, monkeypatch):
    argv = ['plan', 'map', '--scenario', 'static3', '--altitude', '1000', '--extent-km', '5',
            '--resolution', '2500']
    rc, base, _ = _run(capsys, monkeypatch, argv)
    rc2, az, err = _run(capsys, monkeypatch, argv + ['--sigma-azimuth-deg',
                                                     repr(math.degrees(2e-3))])
    assert rc == rc2 == 0 and err == ''
    assert [s[0] for s in _stations(az)] == [2.0, 2.0, 2.0]
    assert [s[1] for s in _stations(az)] == [s[1] for s in _stations(base)]


@pytest.mark.parametrize('argv', [
    ['plan', 'map', '--scenario', 'seed000', '--altitude', '5000', '--sigma-mrad', '1.5',
     '--sigma-deg', '0.1'],
    ['plan', 'map', '--scenario', 'seed000', '--altitude', '5000', '--sigma-deg=0.1',
     '--sigma-mrad', '1.5'],
    ['plan', 'map', '--scenario', 'seed000', '--altitude', '5000', '--sigma-mrad', '1.5',
     '--sigma-de', '0.1'],
    ['locate', '--method', 'ls', '--estimator', 'tls', 'x.json'],
    ['evaluate', '--scenario', 'seed003', '--estimator', 'mle', '--estimators', 'ls'],
    ['tma', '--method', 'tma_mle', '--estimator', 'tma_ple', 'x.json'],
])
def test_a_deprecated_flag_with_its_replacement_is_an_error(capsys, argv):
    # the later one used to win silently
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and 'is deprecated' in err[0]
    assert 'error: --' in err[1] and ': give only --' in err[1]
