"""Throttled logging for threads that have no ROS logger throttle (receiver inputs, the
Foxglove server's callbacks): at most one line per key and period."""

import threading
import time

#: Seconds between two log lines of one key.
LOG_THROTTLE_S = 10.0


class Throttle:
    """At most one log line per key and ``period`` s (monotonic clock); the next line after
    a quiet period can say how many were left out. Bounded: keys idle for a period are pruned
    once more than ``max_keys`` are held. Thread-safe."""

    def __init__(self, period=LOG_THROTTLE_S, max_keys=1024, clock=time.monotonic):
        self.period, self.max_keys, self.clock = float(period), int(max_keys), clock
        self._last = {}           # key -> (time of the last line, lines left out since)
        self._lock = threading.Lock()

    def allow(self, key):
        """None when a line of ``key`` is to be left out, else the number left out before."""
        now = self.clock()
        with self._lock:
            last = self._last.get(key)
            if last is not None and now - last[0] < self.period:
                self._last[key] = (last[0], last[1] + 1)
                return None
            if len(self._last) >= self.max_keys:
                self._last = {k: v for k, v in self._last.items() if now - v[0] < self.period}
            self._last[key] = (now, 0)
            return 0 if last is None else last[1]
