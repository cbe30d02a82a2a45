"""The compiler of the one-problem numerics: numba's ``njit``, cached on disk.

A function decorated with :data:`jit` is compiled to machine code on its first call and the
code is kept in numba's cache, so later processes load it instead of compiling. Python's
error model is kept (a float division by zero raises ZeroDivisionError), and no fast-math:
the compiled code performs the IEEE operations of the Python source in its order. Every
compiled function stays callable as Python through its ``py_func`` attribute, and with
``NUMBA_DISABLE_JIT=1`` the package runs the same source as plain Python (test/test_compiled.py
compares the two; under plain Python a :data:`jit_numpy` function's division by zero raises
instead of giving inf).

The cache lives in :data:`CACHE_DIR`: ``<base>/<fingerprint>``, with ``<base>``
``$NUMBA_CACHE_DIR`` when set, else ``$XDG_CACHE_HOME/bearing_loc_ros/numba`` (default
``~/.cache/bearing_loc_ros/numba``), and the fingerprint a hash of numba's version and of
every module of ``bearing_loc_ros/core``. numba checks only the stamp of the file a compiled
function is defined in, while its machine code also holds the constants and the compiled
functions it takes from other modules (``robust_model.TEST_INVERSION_Z``,
``horizontal_single.inverse2``): a change to any core module therefore selects a new
directory, and the code is compiled again once. Where no cache directory can be written
(a read-only home), the functions are compiled in each process instead.
"""

import hashlib
import os
from pathlib import Path
import tempfile

import numba
from numba import njit

_CORE = Path(__file__).resolve().parent


def cache_directory(core=_CORE, base=None):
    """The cache directory of the compiled code (module docstring), created; None where it
    cannot be created and written. ``core`` the directory whose modules are fingerprinted,
    ``base`` the directory above the fingerprint (default from the environment)."""
    if base is None:
        base = os.environ.get('NUMBA_CACHE_DIR')
    if not base:
        root = os.environ.get('XDG_CACHE_HOME')
        if not root:
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
    except OSError:
        return None
    return path


#: Where the compiled code is cached (None: not cached).
CACHE_DIR = cache_directory()


def _decorator(**options):
    """njit(cache=True, **options) caching in :data:`CACHE_DIR` (numba takes the directory
    from its configuration when a function is decorated; it is set for that moment only)."""
    def decorate(fn):
        if CACHE_DIR is None:
            return njit(cache=False, **options)(fn)
        saved = numba.config.CACHE_DIR
        numba.config.CACHE_DIR = CACHE_DIR
        try:
            return njit(cache=True, **options)(fn)
        finally:
            numba.config.CACHE_DIR = saved
    return decorate


#: Decorator: compile lazily on first call, cache on disk.
jit = _decorator()

#: The same with numpy's error model: a float division by zero gives ±inf or NaN, as the
#: array code a compiled function stands in for (``np.errstate(divide='ignore')``).
jit_numpy = _decorator(error_model='numpy')
