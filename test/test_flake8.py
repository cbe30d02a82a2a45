"""The ROS build farm's flake8 check (99-character lines), run as part of the suite."""
import subprocess
import sys

from ros_helpers import REPO


def test_flake8_clean():
    paths = ['bearing_loc_ros', 'test', 'bench', 'launch', 'setup.py']
    proc = subprocess.run([sys.executable, '-m', 'flake8', '--max-line-length', '99', *paths],
                          cwd=REPO, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
