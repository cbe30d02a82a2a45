"""The compiled one-fix numerics (core/jit.py, numba) compute what their Python source does.

The same problems are solved in this process (compiled) and in a child process with
NUMBA_DISABLE_JIT=1, where numba leaves every decorated function as the Python it was
written in: the statuses, exclusions and fallbacks must be the same, and the numbers equal
to rounding (the compiled code performs the same IEEE operations in the same order, without
fast-math; libm's functions are the same in both).
"""
import json
import math
import os
import subprocess
import sys
import time

import numba
import numpy as np
import pytest

from bearing_loc_ros.core.bearings import BearingSet

HERE = os.path.dirname(os.path.abspath(__file__))


def problems():
    """One-problem BearingSets: 3-8 stations (every third azimuth-only), σ 5 and 40 mrad,
    a quarter of them with one azimuth 0.6 rad off; with the target's altitude."""
    rng = np.random.default_rng(2024)
    out = []
    for n in (3, 4, 5, 6, 8):
        for sigma in (0.005, 0.04):
            for k in range(8):
                st = np.column_stack([rng.uniform(-8e3, 8e3, (n, 2)), rng.uniform(0, 200, n)])
                tgt = np.array([*rng.uniform(-5e3, 5e3, 2), rng.uniform(300, 3000)])
                d = tgt - st
                az = np.arctan2(d[:, 1], d[:, 0]) + rng.normal(0, sigma, n)
                el = np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])) + rng.normal(0, sigma, n)
                el[1::3] = np.nan
                if k % 4 == 0:
                    az[0] += 0.6
                out.append((BearingSet.from_arrays(st, az, el, sigma, sigma), float(tgt[2])))
    return out


def solve_all():
    """Per problem: 3D robust steps (constant and range-grown σ), horizontal robust wmle and
    the ctls_am iteration."""
    from bearing_loc_ros.core import robust_single
    from bearing_loc_ros.core.estimators import locate
    from bearing_loc_ros.core.horizontal import locate_horizontal
    rows = []
    for bs, z in problems():
        for d_ref in (None, 1000.0):
            x = locate('wmle' if d_ref else 'mle', bs, robust=False).position[0].tolist()
            try:
                pos, cov, ok, nu, excluded, finite = robust_single.refine(bs, x, d_ref)
                rows.append(['3d', pos.tolist(), cov.tolist(), bool(ok), float(nu),
                             excluded.tolist(), bool(finite)])
            except robust_single.Fallback as exc:
                rows.append(['fallback', str(exc)])
        h = locate_horizontal('wmle', bs, z, 10.0, robust=True)
        rows.append(['h', h.position.tolist(), h.covariance.tolist(), str(h.status[0]),
                     float(h.nonlinearity[0]), h.excluded.tolist()])
        c = locate('ctls_am', bs, consistency=False)
        rows.append(['ctls', c.position.tolist(), c.covariance.tolist(), str(c.status[0]),
                     int(c.iterations[0])])
    return rows


def test_compiled_numerics_equal_their_python_source(tmp_path):
    if numba.config.DISABLE_JIT:
        pytest.skip('NUMBA_DISABLE_JIT is set: this process runs the Python source itself')
    out = tmp_path / 'python.json'
    env = dict(os.environ, NUMBA_DISABLE_JIT='1')
    code = (f'import json, sys; sys.path.insert(0, {HERE!r}); import test_compiled; '
            f'json.dump(test_compiled.solve_all(), open({str(out)!r}, "w"))')
    subprocess.run([sys.executable, '-c', code], env=env, check=True, timeout=600)
    python = json.loads(out.read_text())
    compiled = json.loads(json.dumps(solve_all()))
    assert len(python) == len(compiled) == 320
    kinds = [r[0] for r in compiled]
    assert kinds.count('3d') > 100 and kinds.count('h') == kinds.count('ctls') == 80
    worst = 0.0
    for p, c in zip(python, compiled):
        assert p[0] == c[0]
        if p[0] == 'fallback':
            continue            # (the messages differ: 'float division by zero' in Python)
        if p[0] == '3d':
            assert p[3:4] + p[5:] == c[3:4] + c[5:]            # ok, exclusions, finite
            nus = (p[4], c[4])
        elif p[0] == 'h':
            assert p[3] == c[3] and p[5] == c[5]                # status, exclusions
            nus = (p[4], c[4])
        else:
            assert p[3:] == c[3:]                               # status, iterations
            nus = (0.0, 0.0)
        a = np.array(p[1] + sum(p[2], []), dtype=float)
        b = np.array(c[1] + sum(c[2], []), dtype=float)
        fin = np.isfinite(a)
        assert np.array_equal(fin, np.isfinite(b))
        scale = np.abs(a[fin]).max() if fin.any() else 1.0
        worst = max(worst, float(np.abs(a[fin] - b[fin]).max(initial=0.0)) / scale)
        assert (math.isnan(nus[0]) and math.isnan(nus[1])) or math.isclose(*nus, rel_tol=1e-12)
    assert worst <= 1e-12


def signatures_around(step):
    """In a fresh process: the number of compiled signatures of every entry point after
    warm_up(), then after test_compiled.<step>() ({name: count} twice)."""
    code = (f'import json, sys, numba; sys.path.insert(0, {HERE!r}); import test_compiled\n'
            'from bearing_loc_ros.core import ctls_single, horizontal_robust, robust_single, '
            'warmup\n'
            'def signatures():\n'
            '    return {f"{m.__name__}.{k}": len(v.signatures) for m in (ctls_single, '
            'horizontal_robust, robust_single) for k, v in vars(m).items() '
            'if isinstance(v, numba.core.registry.CPUDispatcher)}\n'
            'warmup.warm_up()\n'
            'before = signatures()\n'
            f'test_compiled.{step}()\n'
            'print(json.dumps([before, signatures()]))\n')
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          check=True, timeout=600)
    return json.loads(done.stdout.splitlines()[-1])


def test_warm_up_compiles_every_specialisation_a_fix_uses():
    # A fresh process: after warm_up(), solving varied problems (outliers, azimuth-only
    # stations, calm and not calm horizontal fixes, ctls_am) compiles nothing more.
    if numba.config.DISABLE_JIT:
        pytest.skip('NUMBA_DISABLE_JIT is set: nothing is compiled')
    before, after = signatures_around('solve_all')
    # (the entry points called from Python; the functions they call are compiled into them)
    assert len(before) >= 30 and sum(before.values()) >= 8
    assert after == before


def test_one_horizontal_wmle_fix_shortcut_equals_the_general_path(monkeypatch):
    # One robust horizontal wmle fix with calm residuals takes a compiled shortcut
    # (horizontal_robust.calm_grown_one); without it, robust_fix's calm branch decides. The
    # same fix, status, covariance and ν either way, also where the widened region's ν is
    # not finite and the plain ν is reported, as the general path fills it in (four stations
    # in a square, the target above its centre: no outward direction, Σ ∇ log ρ_k = 0).
    from bearing_loc_ros.core import horizontal_robust
    from bearing_loc_ros.core.horizontal import locate_horizontal
    square = np.array([[-1000.0, -1000.0, 0.0], [1000.0, 1000.0, 0.0], [1000.0, -1000.0, 0.0],
                       [-1000.0, 1000.0, 0.0]])
    d = np.array([0.0, 0.0, 500.0]) - square
    az, el = np.arctan2(d[:, 1], d[:, 0]), np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))
    cases = [(BearingSet.from_arrays(square, az, el, 0.01, 0.01), 500.0)] + problems()
    shortcut = [locate_horizontal('wmle', bs, z, 10.0, robust=True) for bs, z in cases]
    taken = []
    real = horizontal_robust.calm_grown_one

    def spy(*args):
        out = real(*args)
        taken.append(out is not None)
        return None                      # the general path decides
    monkeypatch.setattr(horizontal_robust, 'calm_grown_one', spy)
    general = [locate_horizontal('wmle', bs, z, 10.0, robust=True) for bs, z in cases]
    assert sum(taken) >= 20 and taken[0]                # the shortcut applies to these
    assert np.isnan(shortcut[0].nonlinearity[0]) is np.False_
    for a, b in zip(shortcut, general):
        assert a.status[0] == b.status[0] and a.converged[0] == b.converged[0]
        assert np.array_equal(a.excluded, b.excluded)
        np.testing.assert_allclose(a.position, b.position, rtol=1e-12)
        np.testing.assert_allclose(a.covariance, b.covariance, rtol=1e-9, atol=1e-9 * np.abs(
            b.covariance).max())
        np.testing.assert_allclose(a.nonlinearity, b.nonlinearity, rtol=1e-9)


def test_the_cache_directory_follows_the_core_sources(tmp_path):
    # numba checks only the file a compiled function is defined in; its code also holds
    # constants and functions of other core modules, so the cache directory is named by a
    # hash of all of them (core/jit.py).
    from bearing_loc_ros.core.jit import cache_directory
    core = tmp_path / 'core'
    core.mkdir()
    (core / 'a.py').write_text('X = 1.5\n')
    (core / 'b.py').write_text('def f(): pass\n')
    first = cache_directory(core, str(tmp_path / 'cache'))
    assert first is not None and os.path.isdir(first)
    assert cache_directory(core, str(tmp_path / 'cache')) == first
    (core / 'a.py').write_text('X = 3.0\n')
    second = cache_directory(core, str(tmp_path / 'cache'))
    assert second != first and os.path.dirname(second) == os.path.dirname(first)
    # A base that cannot be written: no cache (each process compiles) rather than an error.
    (tmp_path / 'file').write_text('')
    assert cache_directory(core, str(tmp_path / 'file' / 'cache')) is None


def odd_arrays():
    """One-problem BearingSets built directly with float32, Fortran-ordered and read-only
    arrays (the constructor keeps what it is given)."""
    sets = []
    for bs, z in problems()[:24:6]:
        arrays = [bs.positions, bs.azimuth, bs.elevation, bs.sigma_az, bs.sigma_el]
        sets.append(BearingSet(*[a.astype(np.float32) for a in arrays]))
        sets.append(BearingSet(*[np.asfortranarray(a) for a in arrays]))
        frozen = [a.copy() for a in arrays]
        for a in frozen:
            a.flags.writeable = False
        sets.append(BearingSet(*frozen))
    return sets


def solve_odd_arrays():
    from bearing_loc_ros.core.estimators import locate
    from bearing_loc_ros.core.horizontal import locate_horizontal
    for bs in odd_arrays():
        locate('wmle', bs, robust=True)
        locate('mle', bs)
        locate_horizontal('wmle', bs, 1000.0, 10.0, robust=True)


def test_arrays_of_other_types_compile_nothing_after_warm_up():
    # The compiled entry points take C-contiguous writeable float64 (core/jit.plain_array):
    # a BearingSet built directly from float32, Fortran-ordered or read-only arrays must not
    # compile new versions during a fix.
    if numba.config.DISABLE_JIT:
        pytest.skip('NUMBA_DISABLE_JIT is set: nothing is compiled')
    before, after = signatures_around('solve_odd_arrays')
    assert after == before


def test_cache_failures_are_warnings_not_errors():
    # A damaged entry (a file left empty by a power cut) or a full disk must not stop a fix:
    # the read failure clears the function's index and compiles, the save failure is skipped.
    from bearing_loc_ros.core.jit import _TolerantCache

    class Broken:
        cache_path = '/var/cache/x'
        flushed = 0

        def load_overload(self, sig, target_context):
            raise EOFError('Ran out of input')

        def save_overload(self, sig, cres):
            raise OSError(28, 'No space left on device')

        def flush(self):
            self.flushed += 1

    broken = Broken()
    cache = _TolerantCache(broken)
    with pytest.warns(RuntimeWarning, match='could not read an entry .*Ran out of input'):
        assert cache.load_overload('sig', None) is None
    assert broken.flushed == 1
    with pytest.warns(RuntimeWarning, match='/var/cache/x: could not save .*No space left'):
        cache.save_overload('sig', None)
    assert cache.cache_path == '/var/cache/x'


TINY = '''from bearing_loc_ros.core.jit import jit


@jit
def plus_one(x):
    return x + 1.0
'''


def run_tiny(tmp_path, cache):
    """Run plus_one of a module in tmp_path in a child with NUMBA_CACHE_DIR=cache."""
    code = ('import sys, warnings; warnings.simplefilter("always"); '
            f'sys.path.insert(0, {str(tmp_path)!r}); import tiny; '
            'print(tiny.plus_one(1.5), sum(tiny.plus_one.stats.cache_hits.values()))')
    return subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=300, env=dict(os.environ, NUMBA_CACHE_DIR=str(cache)))


def test_a_damaged_cache_entry_is_compiled_again_and_repaired(tmp_path):
    if numba.config.DISABLE_JIT:
        pytest.skip('NUMBA_DISABLE_JIT is set: nothing is compiled')
    (tmp_path / 'tiny.py').write_text(TINY)
    cache = tmp_path / 'cache'
    first = run_tiny(tmp_path, cache)
    assert first.returncode == 0 and first.stdout.split()[0] == '2.5', first.stderr
    entries = list(cache.rglob('tiny.plus_one-*.nbi'))
    assert len(entries) == 1 and 'bearing_loc_ros' in entries[0].parts
    for damaged in (b'', b'\x80\x04garbage'):
        entries[0].write_bytes(damaged)
        again = run_tiny(tmp_path, cache)
        assert again.returncode == 0 and again.stdout.split() == ['2.5', '0'], again.stderr
        assert 'could not read an entry' in again.stderr
    repaired = run_tiny(tmp_path, cache)         # the entry was written again
    assert repaired.returncode == 0 and 'could not' not in repaired.stderr
    assert repaired.stdout.split()[1] == '1'      # loaded from the cache


def test_no_cache_where_numba_would_cache_elsewhere(tmp_path, monkeypatch):
    # numba falls back to __pycache__ beside the source when its directory under CACHE_DIR
    # cannot be made; there the fingerprint of the core sources would not apply.
    if numba.config.DISABLE_JIT:
        pytest.skip('NUMBA_DISABLE_JIT is set: nothing is compiled')
    from bearing_loc_ros.core import jit
    (tmp_path / 'file').write_text('')
    monkeypatch.setattr(jit, 'CACHE_DIR', str(tmp_path / 'file' / 'cache'))
    src = tmp_path / 'src'
    src.mkdir()
    (src / 'tiny_elsewhere.py').write_text(TINY)
    monkeypatch.syspath_prepend(str(src))
    import tiny_elsewhere
    assert isinstance(tiny_elsewhere.plus_one._cache, numba.core.caching.NullCache)
    assert tiny_elsewhere.plus_one(1.0) == 2.0
    assert not list(src.rglob('*.nbi'))


def test_processes_that_start_together_take_turns(tmp_path, monkeypatch):
    # While one process holds the cache lock (compiling), another waits for it.
    from bearing_loc_ros.core import jit
    pytest.importorskip('fcntl')
    monkeypatch.setattr(jit, 'CACHE_DIR', str(tmp_path))
    probe = ('import fcntl, sys; f = open(sys.argv[1], "a")\n'
             'try:\n    fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB); print("free")\n'
             'except BlockingIOError:\n    print("held")\n')

    def other():
        return subprocess.run([sys.executable, '-c', probe, str(tmp_path / 'lock')],
                              capture_output=True, text=True, timeout=60).stdout.strip()

    with jit.cache_lock():
        assert other() == 'held'
    assert other() == 'free'


def test_old_cache_directories_are_pruned(tmp_path):
    from bearing_loc_ros.core.jit import cache_directory, PRUNE_AFTER_DAYS
    core = tmp_path / 'core'
    core.mkdir()
    (core / 'a.py').write_text('X = 1\n')
    base = tmp_path / 'cache'
    old = time.time() - (PRUNE_AFTER_DAYS + 1) * 86400.0
    recent = time.time() - (PRUNE_AFTER_DAYS - 1) * 86400.0
    for name, when in (('0123456789abcdef', old), ('fedcba9876543210', recent),
                       ('not-a-fingerprint', old)):
        (base / name / 'core_x').mkdir(parents=True)
        os.utime(base / name, (when, when))
    mine = cache_directory(core, str(base))
    left = sorted(p.name for p in base.iterdir())
    assert left == sorted([os.path.basename(mine), 'fedcba9876543210', 'not-a-fingerprint'])
    assert time.time() - os.stat(mine).st_mtime < 60      # marked as used
