"""The compiler of the one-problem numerics: numba's ``njit``, cached on disk.

A function decorated with :data:`jit` is compiled to machine code on its first call and the
code is kept in numba's cache, so later processes load it instead of compiling. Python's
error model is kept (a float division by zero raises ZeroDivisionError), and no fast-math:
the compiled code performs the IEEE operations of the Python source in its order. Every
compiled function stays callable as Python through its ``py_func`` attribute, and with
``NUMBA_DISABLE_JIT=1`` the package runs the same source as plain Python (test/test_compiled.py
compares the two; under plain Python a :data:`jit_numpy` function's division by zero of
Python floats raises instead of giving inf).

The cache lives in :data:`CACHE_DIR`: ``<base>/<fingerprint>``, with ``<base>``
``$NUMBA_CACHE_DIR`` when set, else ``$XDG_CACHE_HOME/bearing_loc_ros/numba`` (default
``~/.cache/bearing_loc_ros/numba``), and the fingerprint a hash of numba's version and of
every module of ``bearing_loc_ros/core``. numba checks only the stamp of the file a compiled
function is defined in, while its machine code also holds the constants and the compiled
functions it takes from other modules (``robust_model.TEST_INVERSION_Z``,
``horizontal_single.inverse2``): a change to any core module therefore selects a new
directory, and the code is compiled again once. Where no cache directory can be written
(a read-only home), the functions are compiled in each process instead.

The cache never stops a fix. An entry that cannot be read (a file left empty by a power cut,
or damaged) is cleared and the function compiled, and one that cannot be written (a full
disk) is skipped, each with a RuntimeWarning naming the directory; where numba would put the
cache anywhere but :data:`CACHE_DIR` (its own subdirectory there not writable), nothing is
cached. :func:`cache_lock` lets processes that start together compile once: the first
compiles, the others wait and load. Each process marks its directory as used; directories of
other versions of the sources unused for :data:`PRUNE_AFTER_DAYS` days are removed.
"""

import contextlib
import hashlib
import os
from pathlib import Path
import re
import shutil
import tempfile
import time
import warnings

import numba
from numba import njit
from numba.core.caching import NullCache
import numpy as np

_CORE = Path(__file__).resolve().parent
#: Cache directories of other versions of the core sources unused for this many days are
#: removed (:func:`prune`).
PRUNE_AFTER_DAYS = 30
_FINGERPRINT = re.compile(r'[0-9a-f]{16}')


def cache_directory(core=_CORE, base=None):
    """The cache directory of the compiled code (module docstring), created and marked as
    used now (its modification time); None where it cannot be created and written. ``core``
    the directory whose modules are fingerprinted, ``base`` the directory above the
    fingerprint (default ``$NUMBA_CACHE_DIR/bearing_loc_ros``, else
    ``$XDG_CACHE_HOME/bearing_loc_ros/numba`` with an absolute ``XDG_CACHE_HOME``, else
    ``~/.cache/bearing_loc_ros/numba``)."""
    if base is None:
        base = os.environ.get('NUMBA_CACHE_DIR')
        if base:
            base = os.path.join(base, 'bearing_loc_ros')
    if not base:
        root = os.environ.get('XDG_CACHE_HOME')
        if not root or not os.path.isabs(root):     # the XDG rule: relative paths are ignored
            try:
                root = str(Path.home() / '.cache')
            except RuntimeError:            # no home directory to be found
                return None
        base = os.path.join(root, 'bearing_loc_ros', 'numba')
    digest = hashlib.sha256(numba.__version__.encode())
    for path in sorted(Path(core).glob('*.py')):
        digest.update(path.name.encode() + b'\0' + path.read_bytes() + b'\0')
    path = os.path.join(base, digest.hexdigest()[:16])
    try:
        os.makedirs(path, exist_ok=True)
        tempfile.TemporaryFile(dir=path).close()
        os.utime(path)
    except OSError:
        return None
    prune(base, keep=path)
    return path


def prune(base, keep, days=PRUNE_AFTER_DAYS, now=None):
    """Remove the fingerprint directories (16 hex digits) under ``base`` other than ``keep``
    whose modification time (the last process that used them) is more than ``days`` days
    before ``now`` (s since the epoch, default the clock). Errors are ignored: another
    process may be removing or using the same directory."""
    limit = (time.time() if now is None else now) - days * 86400.0
    try:
        entries = list(os.scandir(base))
    except OSError:
        return
    for entry in entries:
        try:
            if (_FINGERPRINT.fullmatch(entry.name) and entry.path != keep
                    and entry.is_dir(follow_symlinks=False)
                    and entry.stat(follow_symlinks=False).st_mtime < limit):
                shutil.rmtree(entry.path, ignore_errors=True)
        except OSError:
            continue


#: Where the compiled code is cached (None: not cached).
CACHE_DIR = cache_directory()


class _TolerantCache:
    """numba's cache of one function whose failures are warnings (module docstring): a load
    that raises clears the function's index (``flush``) and returns None (numba compiles);
    a save that raises is skipped. Everything else is the wrapped cache's."""

    def __init__(self, cache):
        self._wrapped = cache

    def __getattr__(self, name):
        return getattr(self._wrapped, name)

    def _warn(self, what, exc):
        warnings.warn(f'compiled-code cache {self._wrapped.cache_path}: could not {what} '
                      f'({type(exc).__name__}: {exc}); compiling instead', RuntimeWarning,
                      stacklevel=3)

    def load_overload(self, sig, target_context):
        try:
            return self._wrapped.load_overload(sig, target_context)
        except Exception as exc:            # a damaged or unreadable entry
            self._warn('read an entry', exc)
            with contextlib.suppress(Exception):
                self._wrapped.flush()
            return None

    def save_overload(self, sig, cres):
        try:
            self._wrapped.save_overload(sig, cres)
        except Exception as exc:            # a full disk, a directory removed
            self._warn('save an entry', exc)


def _decorator(**options):
    """njit(cache=True, **options) caching in :data:`CACHE_DIR` (numba takes the directory
    from its configuration when a function is decorated; it is set for that moment only),
    through :class:`_TolerantCache`; without caching where numba chose another directory."""
    def decorate(fn):
        if CACHE_DIR is None:
            return njit(cache=False, **options)(fn)
        saved = numba.config.CACHE_DIR
        numba.config.CACHE_DIR = CACHE_DIR
        try:
            compiled = njit(cache=True, **options)(fn)
        finally:
            numba.config.CACHE_DIR = saved
        cache = getattr(compiled, '_cache', None)       # absent with NUMBA_DISABLE_JIT
        if cache is not None:
            path = os.path.abspath(cache.cache_path or '')
            inside = path.startswith(os.path.join(os.path.abspath(CACHE_DIR), ''))
            compiled._cache = _TolerantCache(cache) if inside else NullCache()
        return compiled
    return decorate


@contextlib.contextmanager
def cache_lock():
    """Hold an exclusive lock on :data:`CACHE_DIR` (``fcntl.flock`` of a file in it) for the
    ``with`` block: processes that compile together take turns, and those after the first
    load what it cached. No lock where there is no cache or no ``fcntl``."""
    try:
        import fcntl
    except ImportError:                     # not POSIX
        fcntl = None
    handle = None
    if CACHE_DIR is not None and fcntl is not None:
        try:
            handle = open(os.path.join(CACHE_DIR, 'lock'), 'a')
            fcntl.flock(handle, fcntl.LOCK_EX)
        except OSError:
            if handle is not None:
                handle.close()
            handle = None
    try:
        yield
    finally:
        if handle is not None:
            handle.close()                  # releases the lock


def plain_array(a):
    """``a`` as the array type the compiled functions are specialised for: C-contiguous,
    aligned, writeable float64; ``a`` itself when it is one, else a copy. (numba compiles
    one version per array type: a float32, Fortran-ordered or read-only array would compile
    again during a fix.)"""
    a = np.asarray(a)
    f = a.flags
    if a.dtype == np.float64 and f.c_contiguous and f.aligned and f.writeable:
        return a
    return np.array(a, dtype=np.float64, order='C')


#: Decorator: compile lazily on first call, cache on disk.
jit = _decorator()

#: The same with numpy's error model: a float division by zero gives ±inf or NaN, as the
#: array code a compiled function stands in for (``np.errstate(divide='ignore')``). Run as
#: plain Python (``NUMBA_DISABLE_JIT=1``), a division of Python floats by zero raises and
#: one of numpy floats gives ±inf with a RuntimeWarning.
jit_numpy = _decorator(error_model='numpy')
