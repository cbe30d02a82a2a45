"""One scenario lookup (bearing_loc_ros.scenarios) for the simulator node and every CLI verb."""

import ast
import json
import os

import pytest

from bearing_loc_ros import scenarios
from bearing_loc_ros.cli import main, VERBS
from bearing_loc_ros.scenarios import resolve_scenario, ScenarioNotFoundError

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PKG = os.path.join(REPO, 'bearing_loc_ros')
SHIPPED = os.path.join(REPO, 'config', 'scenarios', 'static3.yaml')


def test_shipped_name_with_and_without_extension(tmp_path):
    elsewhere = str(tmp_path)
    assert os.path.samefile(resolve_scenario('static3.yaml', cwd=elsewhere), SHIPPED)
    assert os.path.samefile(resolve_scenario('static3', cwd=elsewhere), SHIPPED)
    assert os.path.samefile(resolve_scenario('config/scenarios/static3.yaml', cwd=elsewhere),
                            SHIPPED)


def test_working_directory_comes_first(tmp_path):
    own = tmp_path / 'static3.yaml'
    own.write_text('duration: 1.0\n')
    assert resolve_scenario('static3.yaml', cwd=str(tmp_path)) == str(own)
    assert resolve_scenario(str(own)) == str(own)


def test_not_found_and_empty_name_one_clear_error(tmp_path):
    with pytest.raises(ScenarioNotFoundError, match=r"^scenario: file not found: 'nope'"):
        resolve_scenario('nope', cwd=str(tmp_path))
    with pytest.raises(ScenarioNotFoundError, match='^scenario: required'):
        resolve_scenario('')
    # an absolute path is tried as given only (plus .yaml)
    assert scenarios.scenario_candidates('/x/y') == ['/x/y', '/x/y.yaml']


@pytest.mark.parametrize('argv', [
    ['plan', 'map', '--altitude', '1000', '--extent-km', '5', '--resolution', '1000'],
    ['plan', 'place', '--altitude', '1000', '--area-km', '0,2,0,2', '--area-cells', '3',
     '--candidates', '3'],
])
def test_plan_resolves_scenario_names(argv, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(argv + ['--scenario', 'static3']) == 0
    out = json.loads(capsys.readouterr().out)
    assert [s['name'] for s in out['stations'][:3]] == ['station_1', 'station_2', 'station_3']
    assert main(argv + ['--scenario', 'no_such_scenario']) == 2
    err = capsys.readouterr().err
    assert 'scenario: file not found' in err and err.count('\n') == 1, err


def _imports(path):
    """Modules imported by a source file (absolute names, relative ones resolved)."""
    rel = os.path.relpath(path, REPO)[:-3].split(os.sep)
    found = set()
    for node in ast.walk(ast.parse(open(path, encoding='utf-8').read())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = rel[:len(rel) - node.level] if node.level else []
            mod = '.'.join(base + ([node.module] if node.module else []))
            found.add(mod)
            found.update(f'{mod}.{a.name}' for a in node.names)
    return found


def test_helpers_live_in_their_layer():
    """No CLI verb imports another verb's module (shared helpers are fine); the demo
    imports no node module."""
    cli = os.path.join(PKG, 'cli')
    for name in os.listdir(cli):
        if not name.endswith('.py') or name == '__init__.py':
            continue
        others = {f'bearing_loc_ros.cli.{v}' for v in VERBS if f'{v}.py' != name}
        assert not _imports(os.path.join(cli, name)) & others, name
    demo = _imports(os.path.join(PKG, 'demo.py'))
    assert not {m for m in demo if m.endswith('_node') or '_node.' in m}, demo
    for name in ('cli/bag.py', 'cli/evaluate.py', 'cli/plan_args.py', 'demo.py'):
        assert 'bearing_loc_ros.scenarios.resolve_scenario' in _imports(
            os.path.join(PKG, name)), name
