"""Giving freed heap back to the operating system after subscriptions are dropped.

A node that subscribes to many short-lived publishers (fusion discovery under publisher
churn) frees the memory of the departed ones, but glibc keeps freed heap pages mapped in its
arenas (the middleware's threads have their own), so the process RSS stays at its peak.
glibc ``malloc_trim(0)`` returns the free pages of every arena to the system. :data:`HEAP`
calls it when the number of subscriptions a caller holds has fallen since the last trim (and
once more a little later), at most once per ``min_interval`` seconds for the process.
Elsewhere (musl, macOS, Windows) it does nothing. It never raises: a failing trim is counted
and ignored. What stays resident after a trim is memory still in use or pages shared with
live allocations (with rclpy and Fast DDS, about 6-8 MiB after the first 200 subscriptions
to departed publishers, little after further ones): the fusion node's discovery therefore
watches unproven topics in a child process (``discovery_probe``) and subscribes itself only
to those that delivered a valid bearing.

No numerics and no ROS here; the caller passes its logger (``debug`` is used).
"""

import ctypes
import math
import sys
import time
import weakref

#: Seconds between two trims at least (a trim walks the free lists of every arena).
MIN_TRIM_INTERVAL = 10.0


def glibc_malloc_trim():
    """glibc's ``int malloc_trim(size_t pad)`` as a ctypes function, or None where the C
    library is not glibc (or is not found)."""
    if not sys.platform.startswith('linux'):
        return None
    try:
        libc = ctypes.CDLL(None)
        libc.gnu_get_libc_version               # glibc only: musl has malloc_trim as a stub
        trim = libc.malloc_trim
    except (OSError, AttributeError):
        return None
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return trim


def _rss_bytes():
    """Resident set size of this process in bytes (Linux /proc), or None."""
    try:
        with open('/proc/self/statm', 'rb') as f:
            return int(f.read().split()[1]) * _PAGE
    except (OSError, ValueError, IndexError):
        return None


try:
    import resource
    _PAGE = resource.getpagesize()
except ImportError:     # not on POSIX
    _PAGE = 4096


class HeapTrimmer:
    """Calls ``trim(0)`` when a caller's held count has fallen below its largest value since
    the last trim, and once more ``min_interval`` s after such a trim (the middleware frees
    part of a departed publisher's state on its own threads, after the subscription is
    gone); never twice within ``min_interval`` s (``clock``: seconds, monotonic).

    ``trim``: the C function (default :func:`glibc_malloc_trim`; None: never trims).
    Counters: ``trims`` made, ``failures`` (the call raised), ``deferred`` (updates that saw
    a fall inside the interval; the trim follows at the first :meth:`update` after it).
    Callers are held by weak reference, so a destroyed node leaves nothing behind.
    """

    def __init__(self, trim=None, min_interval=MIN_TRIM_INTERVAL, clock=time.monotonic):
        self.trim = glibc_malloc_trim() if trim is None else trim
        self.min_interval, self.clock = float(min_interval), clock
        self.trims = self.failures = self.deferred = 0
        self._last = -math.inf
        self._follow_up = False
        self._high = weakref.WeakKeyDictionary()

    @property
    def available(self):
        """True where a trim function exists (glibc)."""
        return self.trim is not None

    def update(self, owner, count, log=None):
        """Record that ``owner`` (any weak-referenceable object) now holds ``count``
        subscriptions; trim when ``count`` is below the owner's largest count since the last
        trim, or a follow-up trim is due, and the interval has passed. Returns True when it
        trimmed."""
        high = max(self._high.get(owner, 0), count)
        self._high[owner] = high
        fell = count < high
        if self.trim is None or not (fell or self._follow_up):
            return False
        now = self.clock()
        if now - self._last < self.min_interval:
            self.deferred += fell
            return False
        self._last = now
        self._follow_up = fell          # one more trim after a fall, none after a follow-up
        for key in list(self._high.keys()):     # every owner's fall is served by this trim
            self._high[key] = count if key is owner else 0
        before = _rss_bytes()
        try:
            self.trim(0)
        except Exception as exc:  # noqa: B902 - a failed trim must never reach the node
            self.failures += 1
            if log is not None:
                log.debug(f'malloc_trim failed: {exc!r}')
            return False
        self.trims += 1
        after = _rss_bytes()
        if log is not None:
            rss = (f', RSS {before / 2 ** 20:.1f} -> {after / 2 ** 20:.1f} MiB'
                   if before and after else '')
            log.debug(f'subscriptions {high} -> {count}: freed heap returned to the system '
                      f'in {1e3 * (self.clock() - now):.1f} ms{rss}')
        return True


#: The process's trimmer (the heap is per process, whatever the number of nodes in it).
HEAP = HeapTrimmer()
