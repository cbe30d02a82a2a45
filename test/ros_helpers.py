"""Helpers for tests that start nodes as separate processes or spin nodes in-process.

* :func:`start_node` starts ``python -m <module> --ros-args ...`` with the session's
  ROS_DOMAIN_ID (set in conftest) and returns a :class:`NodeProcess`.
* :class:`NodeProcess` stops its child with SIGINT, waits with a timeout, escalates to
  SIGTERM then SIGKILL, and always reaps it. Use it as a context manager.
* :func:`spin_until` spins an executor until a predicate holds or a timeout passes.
"""
import os
import signal
import subprocess
import sys
import tempfile
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


class NodeProcess:
    """A child process running a node; stop() reaps it and returns its exit code."""

    def __init__(self, args, env=None):
        self.args = list(args)
        self._log = tempfile.TemporaryFile(mode='w+')
        self.proc = subprocess.Popen(self.args, stdout=self._log, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, env=env, cwd=REPO,
                                     start_new_session=True)

    def output(self):
        """Everything the child printed so far (stdout and stderr), also after exit."""
        if self._log.closed:
            return self._final_output
        self._log.flush()
        self._log.seek(0)
        return self._log.read()

    def wait(self, timeout):
        """Wait for the child to exit by itself; return its exit code (or None on timeout)."""
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None

    def stop(self, timeout=5.0):
        """SIGINT, then SIGTERM, then SIGKILL; always reaps. Returns the exit code."""
        for sig in (signal.SIGINT, signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            if self.proc.poll() is not None:
                break
            try:
                os.killpg(self.proc.pid, sig)
            except ProcessLookupError:
                break
            try:
                self.proc.wait(timeout=timeout / 2 if sig == signal.SIGINT else timeout)
            except subprocess.TimeoutExpired:
                continue
        return self.proc.wait()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
        self._final_output = self.output()
        self._log.close()


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
