"""`colcon build` installs the package in the layout `ros2 run` uses.

`ros2 run bearing_loc_ros station_node` finds the package prefix through the ament index
(share/ament_index/resource_index/packages/bearing_loc_ros) and runs
<prefix>/lib/bearing_loc_ros/station_node; setup.cfg's install_scripts puts the console
scripts there. The build goes to a temporary directory (build, install and log bases all
outside the repository) and takes a few seconds.
"""

import glob
import os
import subprocess
import sys

import pytest
from ros_helpers import node_env, REPO

VENV_BIN = os.path.dirname(sys.executable)
COLCON = os.path.join(VENV_BIN, 'colcon')
PKG = 'bearing_loc_ros'


@pytest.fixture(scope='module')
def install(tmp_path_factory):
    if not os.path.exists(COLCON):
        pytest.skip('colcon is not installed in this environment (requirements.txt has it)')
    tmp = tmp_path_factory.mktemp('colcon')
    env = node_env(PATH=VENV_BIN + os.pathsep + os.environ.get('PATH', ''),
                   COLCON_HOME=str(tmp / 'colcon_home'), COLCON_LOG_PATH=str(tmp / 'log'))
    cmd = [COLCON, '--log-base', str(tmp / 'log'), 'build', '--base-paths', REPO,
           '--packages-select', PKG, '--build-base', str(tmp / 'build'),
           '--install-base', str(tmp / 'install')]
    before = set(os.listdir(REPO))
    res = subprocess.run(cmd, cwd=tmp, env=env, capture_output=True, text=True, timeout=240)
    assert res.returncode == 0, res.stdout + res.stderr
    # Nothing was written into the repository (build/, install/, log/ all went to tmp).
    assert not {'build', 'install', 'log'} & (set(os.listdir(REPO)) - before)
    return tmp / 'install'


@pytest.mark.parametrize('exe', ['station_node', 'simulator_node', 'fusion_node'])
def test_executables_in_ros2_run_layout(install, exe):
    path = install / PKG / 'lib' / PKG / exe
    assert path.is_file(), sorted(os.listdir(install / PKG / 'lib' / PKG))
    assert os.access(path, os.X_OK)


def test_ament_index_and_share(install):
    prefix = install / PKG
    assert (prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / PKG).is_file()
    assert (prefix / 'share' / PKG / 'package.xml').is_file()
    assert (prefix / 'share' / PKG / 'config' / 'station.yaml').is_file()


def test_installed_station_node_runs_from_the_install(install, tmp_path):
    prefix = install / PKG
    site = glob.glob(str(prefix / 'lib' / 'python3*' / 'site-packages'))
    assert len(site) == 1
    env = node_env(PYTHONPATH=site[0], AMENT_PREFIX_PATH=os.pathsep.join(
        [str(prefix), os.environ.get('AMENT_PREFIX_PATH', sys.prefix)]))
    # From a neutral cwd, PYTHONPATH wins over the repository's editable install.
    where = subprocess.run([sys.executable, '-c', f'import {PKG}; print({PKG}.__file__)'],
                           cwd=tmp_path, env=env, capture_output=True, text=True, timeout=30)
    assert where.stdout.strip().startswith(site[0]), where.stdout + where.stderr
    bad = tmp_path / 'bad.yaml'
    bad.write_text('/**:\n  ros__parameters:\n    position: [0.0, 0.0, 0.0]\n'
                   '    sigma_elevation_deg: 0.0\n')
    res = subprocess.run([str(prefix / 'lib' / PKG / 'station_node'), '--ros-args',
                          '-r', '__ns:=/colcon_test', '--params-file', str(bad)],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert res.returncode == 1, res.stdout + res.stderr
    assert "error: parameter 'sigma_elevation_deg'" in res.stderr
