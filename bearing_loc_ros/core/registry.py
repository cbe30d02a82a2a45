"""The estimator registry: the one place that knows which estimators exist and what they need.

Fusion, the CLI and ``evaluate`` ask this module about an estimator and never compare its
name with a string. Every estimator declares itself at its definition
(:func:`~bearing_loc_ros.core.estimator_spec.declare`): its options with defaults and
validation, its noise model, its mode and its result type. For each name this module answers:

* :func:`names` and :func:`mode_of`: ``multistation`` (one fix from the bearings of several
  stations: ``ls``, ``tls``, ``ctls``, ``ctls_am``, ``mle``, ``wmle``) or ``tma`` (one moving
  station, target motion analysis with a speed prior, Lin et al.: ``tma_ple``, ``tma_ctls``,
  ``tma_ctls6``, ``tma_mle``).
* :func:`spec`, :func:`option_defaults`, :func:`scoped_options` and :func:`check`: the
  accepted options, their defaults, the subset of a shared option set an estimator accepts,
  and validation without running anything (``ValueError('options.<name>: ...')``).
* :func:`noise_sigmas` and :func:`noise_crlb`: the bearing noise model the estimator assumes
  (the σ it weights with) and hence the Cramér-Rao bound it is measured against.
* :func:`solve`: run it; every estimator returns a :class:`~bearing_loc_ros.core.fix.FixResult`.

Every multi-station estimator also takes the solve-level options
(:data:`~bearing_loc_ros.core.estimator_spec.SOLVE_OPTIONS`): ``dimension`` (``auto | 3d |
horizontal``), ``target_altitude`` (m, world frame), ``target_altitude_sigma`` (m) and
``use_elevations``; :func:`solve` then runs the dimension selection of
:mod:`~bearing_loc_ros.core.horizontal` and the fix says which solve produced it
(``FixResult.solve``).
"""

import numpy as np

from . import estimators as _estimators
from . import horizontal as _horizontal
from . import tma as _tma
from .estimator_spec import (BEARING_SIGMA, COMMON_OPTIONS, EstimatorSpec, MULTISTATION,
                             SOLVE_OPTIONS, TMA)
from .fix import FixResult
from .horizontal_crlb import horizontal_crlb

#: Fusion modes an estimator belongs to.
MODE_MULTISTATION = MULTISTATION
MODE_TMA = TMA

#: Single-station TMA estimators (Lin et al., speed-prior 3D TMA) -> former core.tma name
#: (accepted by core.tma.tma and TmaAccumulator.estimate).
TMA_ESTIMATORS = {name: name[len('tma_'):] for name in _tma.TMA_FUNCTIONS}


def _table():
    """{name: function} of every estimator (read live: a test may register one)."""
    table = dict(_estimators.ESTIMATORS)
    table.update(_tma.TMA_FUNCTIONS)
    return table


def names(mode=None):
    """Registered estimator names (sorted), all or those of one ``mode``."""
    multi = sorted(_estimators.ESTIMATORS)
    tma = sorted(_tma.TMA_FUNCTIONS)
    if mode is None:
        return tuple(multi + tma)
    if mode == MODE_MULTISTATION:
        return tuple(multi)
    if mode == MODE_TMA:
        return tuple(tma)
    raise ValueError(f'mode: unknown mode {mode!r}')


def default_estimator():
    """The estimator used when none is configured (``mle``, estimators.DEFAULT_ESTIMATOR)."""
    return _estimators.DEFAULT_ESTIMATOR


def spec(name):
    """The :class:`~bearing_loc_ros.core.estimator_spec.EstimatorSpec` of estimator ``name``.

    ValueError for an unknown name. A function registered without a declaration gets the
    closed-form options and the bearings' own σ.
    """
    fn = _table().get(name) if isinstance(name, str) else None
    if fn is None:
        raise ValueError(f'estimator: unknown estimator {name!r}; choose one of '
                         f'{list(names())}')
    declared = getattr(fn, 'spec', None)
    if declared is not None:
        return declared
    return EstimatorSpec(name, MULTISTATION, COMMON_OPTIONS, BEARING_SIGMA, FixResult, fn)


def _option_scope():
    """{option: estimators accepting it} over every declared estimator."""
    scope = {}
    for name, fn in sorted(_table().items()):
        for opt in spec(name).options:
            scope.setdefault(opt.name, []).append(name)
    return {k: tuple(v) for k, v in scope.items()}


#: Options and the estimators that accept them (derived from the declarations), so one set of
#: node parameters serves every estimator: an option goes only to the estimators listed.
OPTION_SCOPE = _option_scope()
#: Solve-level options (every multi-station estimator): name -> Option.
SOLVE_OPTION_SPECS = {o.name: o for o in SOLVE_OPTIONS}


def split_solve_options(options, M=None):
    """(validated solve options with defaults, the other options) of a multi-station call.

    ValueError('options.<name>: ...') for a bad dimension, altitude or σ.
    """
    solve_opts = {name: o.default for name, o in SOLVE_OPTION_SPECS.items()}
    rest = {}
    for k, v in options.items():
        if k in SOLVE_OPTION_SPECS:
            solve_opts[k] = SOLVE_OPTION_SPECS[k].validate(v, M)
        else:
            rest[k] = v
    return solve_opts, rest


def mode_of(name):
    """The fusion mode estimator ``name`` belongs to; ValueError for an unknown name."""
    return spec(name).mode


def option_defaults(name):
    """{option: default} of the options estimator ``name`` accepts."""
    return spec(name).defaults()


def scoped_options(name, options):
    """The subset of ``options`` that estimator ``name`` accepts.

    An option that some registered estimator declares is passed only to the estimators that
    declare it (:data:`OPTION_SCOPE`); an option no estimator declares is passed through
    unchanged, so the estimator rejects it by name.
    """
    own = spec(name)
    multi = own.mode == MULTISTATION
    return {k: v for k, v in options.items()
            if own.accepts(k) or (k in SOLVE_OPTION_SPECS and multi)
            or (k not in OPTION_SCOPE and k not in SOLVE_OPTION_SPECS)}


def check(name, options):
    """Validate an estimator name and its options without side effects or a trial run.

    Returns the scoped options; raises ``ValueError`` (``estimator: ...`` or
    ``options.<name>: ...``).
    """
    kwargs = scoped_options(name, options)
    own = spec(name)
    if own.mode == MULTISTATION:
        own.parse(split_solve_options(kwargs)[1])
    else:
        own.parse(kwargs)
    return kwargs


def solve(name, bearings, **options):
    """Run estimator ``name`` on ``bearings`` -> FixResult.

    Multi-station: the dimension selection of core.horizontal.locate with the solve-level
    options (``dimension``, default ``auto``; ``target_altitude``, required when a problem is
    solved horizontally; ``target_altitude_sigma``; ``use_elevations``), then the estimator
    (see estimators.locate for its errors; ``method: unknown estimator ...`` for an unknown
    name); the result's ``solve`` says ``3d`` or ``horizontal`` per problem. TMA: pass the
    bearing times (``times``, (K,) or (M, K) s) and the prior speed (``speed``, m/s) as
    keywords (see core.tma).
    """
    fn = _tma.TMA_FUNCTIONS.get(name) if isinstance(name, str) else None
    if fn is not None:
        own = fn.spec
        try:
            inputs = [options.pop(k) for k in own.inputs]
        except KeyError as exc:
            raise ValueError(f'{exc.args[0]}: required by TMA estimator {name!r}') from None
        return own.function(bearings, *inputs, **options)
    solve_opts, rest = split_solve_options(options, getattr(bearings, 'M', None))
    if isinstance(name, str) and name in _estimators.ESTIMATORS \
            and name not in _horizontal.ESTIMATORS:
        # An estimator without a horizontal form (registered by a test or a plug-in).
        if solve_opts['dimension'] == _horizontal.SOLVE_HORIZONTAL:
            raise ValueError(f'dimension: estimator {name!r} has no horizontal solve')
        return _estimators.locate(name, bearings, **rest)
    return _horizontal.locate(name, bearings, **solve_opts, **rest)


def noise_sigmas(name, bearings, position, options):
    """(σ_θ, σ_ψ) (M, N), rad, that estimator ``name`` assumes at ``position`` (M, 3).

    From the estimator's declared noise model: ``wmle`` grows σ with range (Zong & Cui 2015
    eqs. (9)-(10), option ``reference_range``); every other estimator uses the bearings' σ.
    """
    return spec(name).noise.sigmas(bearings, np.asarray(position, dtype=float), options)


def noise_crlb(name, position, bearings, solve=None, **options):
    """CRLB (M, 3, 3), m², at ``position`` under the noise model estimator ``name`` assumes.

    Multi-station estimators only (a TMA bound needs the state and times: core.tma.tma_crlb).
    ``solve`` ((M,) ``'3d'``/``'horizontal'``, a result's ``FixResult.solve``; None = 3D):
    for horizontal problems the bound of the horizontal solve (core.horizontal_crlb: the 3D
    Fisher information plus the prior 1/σ_z² on z, ``target_altitude_sigma``), with the σ
    of the noise model at ``position`` (``wmle``: grown with range first, Zong & Cui 2015
    eqs. (9)-(10)); elevations count unless ``use_elevations`` is false.
    """
    if mode_of(name) != MODE_MULTISTATION:
        raise ValueError(f'estimator: {name} is a tma estimator; its bound is '
                         'core.tma.tma_crlb')
    position = np.asarray(position, dtype=float)
    solve_opts, rest = split_solve_options(options, position.shape[0])
    out = _estimators.noise_model_crlb(name, position, bearings, **rest)
    if solve is None:
        return out
    horiz = np.asarray(solve) == _horizontal.SOLVE_HORIZONTAL
    if not np.any(horiz):
        return out
    idx = np.flatnonzero(horiz)
    finite = np.all(np.isfinite(position), axis=1)
    pos = np.where(finite[:, None], position, 0.0)
    saz, sel = noise_sigmas(name, bearings, pos, rest)
    has_el = bearings.has_elevation & bool(solve_opts['use_elevations'])
    sz = np.broadcast_to(np.asarray(solve_opts['target_altitude_sigma'], dtype=float),
                         (position.shape[0],))
    h = horizontal_crlb(pos[idx], bearings.positions[idx], saz[idx], sel[idx], has_el[idx],
                        sz[idx])
    h[~finite[idx]] = np.inf
    out[idx] = h
    return out
