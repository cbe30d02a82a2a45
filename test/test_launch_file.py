"""The native-ROS launch file: valid Python, names only executables and files that exist.

launch/launch_ros are not on PyPI, so the file cannot be run here; this checks what can go
wrong without them (syntax, executable names, the installed config it loads).
"""
import ast
import os

from ros_helpers import REPO

LAUNCH = os.path.join(REPO, 'launch', 'demo.launch.py')


def _calls(tree, name):
    return [n for n in ast.walk(tree)
            if isinstance(n, ast.Call) and getattr(n.func, 'id', None) == name]


def test_launch_file_names_real_executables_and_config():
    with open(LAUNCH, encoding='utf-8') as f:
        tree = ast.parse(f.read(), LAUNCH)
    with open(os.path.join(REPO, 'setup.py'), encoding='utf-8') as f:
        setup_src = f.read()
    nodes = _calls(tree, 'Node')
    assert len(nodes) == 2
    for call in nodes:
        kw = {k.arg: k.value for k in call.keywords}
        assert kw['package'].value == 'bearing_loc_ros'
        exe = kw['executable'].value
        assert f"'{exe} = bearing_loc_ros." in setup_src, exe
    assert "glob('launch/*.py')" in setup_src
    assert os.path.isfile(os.path.join(REPO, 'config', 'fusion.yaml'))
    assert os.path.isfile(os.path.join(REPO, 'config', 'scenarios', 'seed000.yaml'))
