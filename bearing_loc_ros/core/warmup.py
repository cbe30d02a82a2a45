"""Compile the one-problem numerics before the first fix (or load them from numba's cache).

The one-fix paths of the robust steps (:mod:`.robust_single`, :mod:`.horizontal_robust`)
are compiled by numba (:mod:`.jit`) on first use: about 15-30 s of compilation on a 2-core
machine the first time after installation, then 0.3-1 s to load the cached machine code in
each new process. A node that solves fixes in real time calls :func:`warm_up` at start-up,
so neither falls on a fix; processes that start together compile once
(:func:`.jit.cache_lock`). ``make venv`` runs this module once after installing
(``python -m bearing_loc_ros.core.warmup``), so the cache is filled before the first run.
"""

import time

import numpy as np


def warm_up():
    """Solve one synthetic problem through every compiled path; returns the seconds it took.

    Four stations (one azimuth-only) around a target 3 km away, σ = 20 mrad with a 0.5 rad
    error on one azimuth (the robust steps then exclude it): ``wmle`` with ``robust`` (the
    3D steps 2-4), ``ctls_am`` (its iteration and consistency check), and the horizontal
    ``wmle`` with ``robust`` on the calm bearings (the compiled calm branch) and on those with
    the outlier (the refit's test inversion, called from Python). test/test_compiled.py
    checks that no fix compiles anything after this.
    """
    from .jit import cache_lock
    start = time.perf_counter()
    with cache_lock():
        _solve_every_path()
    return time.perf_counter() - start


def cache_note():
    """'' when the compiled code is cached, else a short note that each process compiles."""
    from .jit import CACHE_DIR
    return '' if CACHE_DIR is not None else ' (no writable cache directory: compiled here)'


def _solve_every_path():
    """The solves of :func:`warm_up`."""
    from .bearings import BearingSet, simulate_bearings
    from .estimators import locate
    from .horizontal import locate_horizontal
    stations = np.array([[0.0, 0.0, 0.0], [4000.0, 0.0, 10.0], [0.0, 4000.0, 20.0],
                         [4000.0, 4000.0, 0.0]])
    target = np.array([[1500.0, 2500.0, 800.0]])
    clean = simulate_bearings(target, stations, 0.02, rng=np.random.default_rng(0))
    el = clean.elevation.copy()
    el[0, 1] = np.nan
    calm = BearingSet.from_arrays(clean.positions, clean.azimuth, el, clean.sigma_az,
                                  clean.sigma_el)
    az = calm.azimuth.copy()
    az[0, 3] += 0.5
    outlier = BearingSet.from_arrays(calm.positions, az, el, calm.sigma_az, calm.sigma_el)
    locate('wmle', outlier, robust=True)
    locate('ctls_am', calm)
    for bearings in (calm, outlier):
        locate_horizontal('wmle', bearings, 800.0, 10.0, robust=True)


if __name__ == '__main__':
    print(f'one-fix numerics compiled or loaded in {warm_up():.1f} s{cache_note()}')
