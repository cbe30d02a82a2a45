"""Child node processes that are always stopped and reaped (demo, tests, benchmarks).

A child runs in its own session so a signal reaches its whole process group. Stopping
escalates SIGINT -> SIGINT -> SIGTERM -> SIGKILL (a background ROS child sometimes ignores the
first SIGINT) and always waits for the exit code, so no zombie or orphan is left behind.
"""

import os
import signal
import subprocess
import tempfile


def interrupt(proc, timeout):
    """Stop a ``subprocess.Popen`` child: SIGINT, then SIGKILL if it has not exited within
    ``timeout`` s; always reap it. Returns its exit code (for children read through a pipe,
    which :class:`ChildProcess` does not offer)."""
    proc.send_signal(signal.SIGINT)
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait()


class ChildProcess:
    """A child process whose stdout+stderr go to ``log_path`` (or a temporary file).

    Use as a context manager, or call :meth:`stop` in a ``finally``. :meth:`output` returns
    everything the child printed, also after it was stopped.
    """

    def __init__(self, args, env=None, cwd=None, log_path=None, name=None):
        self.args = list(args)
        self.name = name or os.path.basename(self.args[0])
        self.log_path = log_path
        self._log = (open(log_path, 'w+', encoding='utf-8') if log_path
                     else tempfile.TemporaryFile(mode='w+'))
        self._final_output = None
        self.proc = subprocess.Popen(self.args, stdout=self._log, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, env=env, cwd=cwd,
                                     start_new_session=True)

    def running(self):
        """True while the child has not exited."""
        return self.proc.poll() is None

    def wait(self, timeout):
        """Wait for the child to exit by itself; its exit code, or None on timeout."""
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None

    def output(self):
        """Everything the child printed so far (stdout and stderr)."""
        if self._log.closed:
            return self._final_output or ''
        self._log.flush()
        self._log.seek(0)
        text = self._log.read()
        self._log.seek(0, os.SEEK_END)
        return text

    def tail(self, n=15):
        """The last ``n`` lines of :meth:`output`."""
        return ''.join(self.output().splitlines(keepends=True)[-n:])

    def stop(self, timeout=5.0):
        """SIGINT, SIGINT, SIGTERM, then SIGKILL until it exits; reap; return the exit code."""
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
        code = self.proc.wait()
        if not self._log.closed:
            self._final_output = self.output()
            self._log.close()
        return code

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
