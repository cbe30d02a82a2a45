"""Helpers for tests that start nodes as separate processes or spin nodes in-process.

* :func:`start_node` starts ``python -m <module> --ros-args ...`` with the session's
  ROS_DOMAIN_ID (set in conftest) and returns a :class:`NodeProcess`.
* :class:`NodeProcess` stops its child with SIGINT, waits with a timeout, escalates to
  SIGTERM then SIGKILL, and always reaps it. Use it as a context manager.
* :func:`spin_until` spins an executor until a predicate holds or a timeout passes.
"""
import os
import sys
import time

from bearing_loc_ros.processes import ChildProcess

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


class NodeProcess(ChildProcess):
    """A child process running a node, started in the repository root."""

    def __init__(self, args, env=None):
        super().__init__(args, env=env, cwd=REPO)


def node_env(**extra):
    """The environment for a node child: inherits the session's ROS settings."""
    env = dict(os.environ)
    env['PYTHONUNBUFFERED'] = '1'
    env.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    env.update({k: str(v) for k, v in extra.items()})
    return env


def start_node(module, ros_args=(), args=(), env=None):
    """Start ``python -m module [args] --ros-args [ros_args]`` as a NodeProcess."""
    cmd = [sys.executable, '-m', module, *args]
    if ros_args:
        cmd += ['--ros-args', *ros_args]
    return NodeProcess(cmd, env=env or node_env())


def spin_until(executor, predicate, timeout):
    """Spin ``executor`` in 50 ms steps until ``predicate()`` is true; return its last value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
        value = predicate()
        if value:
            return value
    return predicate()
