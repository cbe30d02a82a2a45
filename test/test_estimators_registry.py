"""core.registry: names, modes, declared options, noise models and one result type per fix."""
import ast
import os

import numpy as np
import pytest

from bearing_loc_ros.core import estimators, registry, tma
from bearing_loc_ros.core.bearings import simulate_bearings
from bearing_loc_ros.core.crlb import crlb, crlb_for
from bearing_loc_ros.core.fix import FixResult

MULTI = ('ctls', 'ctls_am', 'ls', 'mle', 'tls', 'wmle')
TMA = ('tma_ctls', 'tma_ctls6', 'tma_mle', 'tma_ple')
STATIONS = np.array([[0.0, 0.0, 0.0], [3000.0, 0.0, 10.0], [0.0, 4000.0, 20.0],
                     [2500.0, 3500.0, 0.0]])
TARGET = np.array([1500.0, 6000.0, 800.0])
PACKAGE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                       'bearing_loc_ros')


def bearings(M=3, sigma=2e-3, seed=0):
    return simulate_bearings(np.tile(TARGET, (M, 1)), STATIONS, sigma,
                             rng=np.random.default_rng(seed))


def tma_problem():
    t = np.arange(0.0, 100.0, 5.0)
    obs = np.stack([np.zeros_like(t), 100.0 * t, np.zeros_like(t)], axis=1)
    bs, times = tma.simulate_tma(t, [2e4, 2e4, 3000.0], [-200.0, 0.0, 0.0], obs, 1e-3,
                                 rng=np.random.default_rng(1), M=2)
    return bs, times, float(np.hypot(200.0, 100.0))


def test_names_and_modes():
    assert registry.names(registry.MODE_MULTISTATION) == MULTI
    assert registry.names(registry.MODE_TMA) == TMA
    assert registry.names() == MULTI + TMA
    assert registry.default_estimator() in MULTI
    for name in MULTI:
        assert registry.mode_of(name) == 'multistation'
    for name in TMA:
        assert registry.mode_of(name) == 'tma'
        assert registry.spec(name).function is tma.TMA_FUNCTIONS[name]
    for bad in ('nope', None, 3, 'ple'):
        with pytest.raises(ValueError, match='^estimator: unknown estimator'):
            registry.mode_of(bad)
    with pytest.raises(ValueError, match='mode'):
        registry.names('fast')


def test_declared_options_and_defaults():
    iterative = {'max_iterations': 50, 'tolerance': 1e-9, 'initial': None}
    assert registry.option_defaults('mle').items() >= iterative.items()
    assert registry.option_defaults('wmle').items() >= dict(iterative,
                                                            reference_range=1000.0).items()
    assert registry.option_defaults('ctls').items() >= dict(iterative, step_decay=1.0).items()
    assert registry.option_defaults('ls').items() >= {'max_iterations': 50,
                                                      'tolerance': 1e-9}.items()
    assert 'initial' not in registry.option_defaults('ls')
    assert 'reference_range' not in registry.option_defaults('mle')
    # robust: on by default for the default estimator mle, opt-in for wmle (core.robust);
    # estimators without the consistency assessment do not declare it.
    assert registry.option_defaults('mle')['robust'] is True
    assert registry.option_defaults('wmle')['robust'] is False
    assert estimators.DEFAULT_ESTIMATOR == 'mle'
    for name in ('ls', 'tls', 'ctls', 'ctls_am'):
        assert 'robust' not in registry.option_defaults(name)
    d = registry.option_defaults('tma_ctls')
    assert d['speed_reference'] == 'relative' and d['min_bearings'] == 3 and d['alpha'] == 1e-3
    assert registry.spec('tma_mle').inputs == ('times', 'speed')
    # Every declared default passes its own validation.
    for name in registry.names():
        s = registry.spec(name)
        assert s.parse({}) == s.defaults()
        assert s.function is (tma.TMA_FUNCTIONS.get(name) or estimators.ESTIMATORS[name])


def test_check_validates_without_running_the_estimator(monkeypatch):
    def never(spec):
        def run(*_, **__):
            raise AssertionError('check ran the estimator')
        run.spec = spec
        return run

    for name in ('mle', 'wmle', 'ctls'):
        monkeypatch.setitem(estimators.ESTIMATORS, name, never(estimators.ESTIMATORS[name].spec))
        assert registry.check(name, {'max_iterations': 5}) == {'max_iterations': 5}
    for name, opts, field in [('mle', {'tolerance': -1.0}, 'tolerance'),
                              ('mle', {'max_iterations': 2.5}, 'max_iterations'),
                              ('wmle', {'reference_range': float('nan')}, 'reference_range'),
                              ('ctls', {'step_decay': 1.5}, 'step_decay'),
                              ('mle', {'bogus': 1}, 'bogus'),
                              ('tma_ctls', {'alpha': 1.0}, 'alpha'),
                              ('tma_mle', {'speed_reference': 'north'}, 'speed_reference'),
                              ('tma_ple', {'covariance': 'yes'}, 'covariance'),
                              ('tma_mle', {'min_bearings': 0}, 'min_bearings')]:
        with pytest.raises(ValueError, match=rf'^options\.{field}: '):
            registry.check(name, opts)


def test_one_shared_option_set_serves_every_estimator():
    shared = {'max_iterations': 20, 'tolerance': 1e-8, 'reference_range': 900.0,
              'step_decay': 0.9}
    assert registry.scoped_options('wmle', shared) == {'max_iterations': 20,
                                                       'tolerance': 1e-8,
                                                       'reference_range': 900.0}
    assert registry.scoped_options('ctls_am', shared) == {'max_iterations': 20,
                                                          'tolerance': 1e-8,
                                                          'step_decay': 0.9}
    assert registry.scoped_options('mle', shared) == {'max_iterations': 20, 'tolerance': 1e-8}
    assert registry.scoped_options('tma_mle', shared) == {'max_iterations': 20}
    assert registry.OPTION_SCOPE['reference_range'] == ('wmle',)
    assert set(registry.OPTION_SCOPE['step_decay']) == {'ctls', 'ctls_am'}
    assert set(registry.OPTION_SCOPE['tolerance']) == set(MULTI)
    assert set(registry.OPTION_SCOPE['max_iterations']) == set(MULTI + TMA)
    for name in registry.names():
        assert registry.check(name, shared) == registry.scoped_options(name, shared)
    # An option nobody declares is passed on and rejected by name.
    with pytest.raises(ValueError, match=r'^options\.sigma: unknown option'):
        registry.check('mle', dict(shared, sigma=1.0))


def test_noise_models_give_the_bound_each_estimator_is_measured_against():
    bs = bearings()
    x = np.tile(TARGET, (bs.M, 1))
    for name in MULTI:
        if name == 'wmle':
            continue
        np.testing.assert_allclose(registry.noise_crlb(name, x, bs), crlb_for(x, bs))
        saz, sel = registry.noise_sigmas(name, bs, x, {})
        np.testing.assert_array_equal(saz, bs.sigma_az)
    # wmle: σ_k = σ_ref · d_k / d_ref (Zong & Cui 2015 eqs. (9)-(10)).
    d = np.linalg.norm(TARGET - STATIONS, axis=1)
    saz, sel = registry.noise_sigmas('wmle', bs, x, {'reference_range': 500.0})
    np.testing.assert_allclose(saz, bs.sigma_az * d / 500.0)
    np.testing.assert_allclose(registry.noise_crlb('wmle', x, bs, reference_range=500.0),
                               crlb(x, bs.positions, saz, sel, bs.has_elevation))
    assert registry.spec('wmle').noise.range_option == 'reference_range'
    assert registry.spec('mle').noise.range_option is None
    nan = x.copy()
    nan[1] = np.nan
    assert np.all(np.isinf(registry.noise_crlb('mle', nan, bs)[1]))
    with pytest.raises(ValueError, match='tma estimator'):
        registry.noise_crlb('tma_mle', x, bs)


def test_solve_returns_one_result_type_for_both_modes():
    bs = bearings()
    for name in MULTI:
        r = registry.solve(name, bs)
        assert type(r) is registry.spec(name).result is FixResult
        assert r.method == name and not r.has_velocity and r.state_covariance is None
        assert r.position_covariance.shape == (bs.M, 3, 3)
        ref = estimators.locate(name, bs)
        np.testing.assert_array_equal(r.position, ref.position)
    tb, times, speed = tma_problem()
    for name in TMA:
        r = registry.solve(name, tb, times=times, speed=speed, speed_reference='ground')
        assert type(r) is FixResult and r.method == name and r.has_velocity
        assert r.position_covariance.shape == (2, 3, 3) and r.state_covariance.shape == (2, 6, 6)
        ref = tma.tma(name, tb, times, speed, speed_reference='ground')
        np.testing.assert_array_equal(r.position, ref.position)
        with pytest.raises(ValueError, match='^speed: required'):
            registry.solve(name, tb, times=times)


def _imports(path, module):
    """Modules of the package imported anywhere in ``path`` (module-level or lazy)."""
    pkg = module if path.endswith('__init__.py') else module.rsplit('.', 1)[0]
    out = set()
    for node in ast.walk(ast.parse(open(path, encoding='utf-8').read())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split('.')[:len(pkg.split('.')) - node.level + 1]
                target = '.'.join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ''
            out |= {target} | {f'{target}.{a.name}' for a in node.names}
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
    return out


def test_no_import_cycle_in_the_package():
    # Lazy imports count too: core/ctls.py and core/estimators.py used to import each other.
    modules = {}
    root = os.path.dirname(PACKAGE)
    for dirpath, _, files in os.walk(PACKAGE):
        for f in files:
            if f.endswith('.py'):
                path = os.path.join(dirpath, f)
                name = os.path.relpath(path, root)[:-3].replace(os.sep, '.')
                modules[name.removesuffix('.__init__')] = path
    graph = {m: {d for d in _imports(p, m) if d in modules and d != m}
             for m, p in modules.items()}
    state = {}

    def visit(m, stack):
        state[m] = 'open'
        for d in sorted(graph[m]):
            if state.get(d) == 'open':
                cycle = stack[stack.index(d):] + [d]
                raise AssertionError('import cycle: ' + ' -> '.join(cycle))
            if d not in state:
                visit(d, stack + [d])
        state[m] = 'done'

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])


def test_estimator_modules_do_not_compare_estimator_names():
    # Knowledge about an estimator comes from its declaration, never from its name.
    for f in ('estimators.py', 'registry.py', 'constrained_tls.py', 'pseudo_linear.py',
              'estimator_spec.py', 'fix.py'):
        src = open(os.path.join(PACKAGE, 'core', f), encoding='utf-8').read()
        for name in MULTI + TMA:
            for pattern in (f"== '{name}'", f"!= '{name}'", f"'{name}' in "):
                assert pattern not in src, (f, pattern)
