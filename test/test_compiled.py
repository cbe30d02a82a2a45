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


def test_warm_up_compiles_every_specialisation_a_fix_uses():
    # A fresh process: after warm_up(), solving varied problems (outliers, azimuth-only
    # stations, calm and not calm horizontal fixes, ctls_am) compiles nothing more.
    if numba.config.DISABLE_JIT:
        pytest.skip('NUMBA_DISABLE_JIT is set: nothing is compiled')
    code = (f'import json, sys, numba; sys.path.insert(0, {HERE!r}); import test_compiled\n'
            'from bearing_loc_ros.core import ctls_single, horizontal_robust, robust_single, '
            'warmup\n'
            'def signatures():\n'
            '    return {f"{m.__name__}.{k}": len(v.signatures) for m in (ctls_single, '
            'horizontal_robust, robust_single) for k, v in vars(m).items() '
            'if isinstance(v, numba.core.registry.CPUDispatcher)}\n'
            'warmup.warm_up()\n'
            'before = signatures()\n'
            'test_compiled.solve_all()\n'
            'print(json.dumps([before, signatures()]))\n')
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          check=True, timeout=600)
    before, after = json.loads(done.stdout.splitlines()[-1])
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
