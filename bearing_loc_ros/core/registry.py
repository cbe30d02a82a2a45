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
"""

import numpy as np

from . import estimators as _estimators
from . import tma as _tma
from .estimator_spec import (BEARING_SIGMA, COMMON_OPTIONS, EstimatorSpec, MULTISTATION,
                             TMA)
from .fix import FixResult

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
    return {k: v for k, v in options.items()
            if own.accepts(k) or k not in OPTION_SCOPE}


def check(name, options):
    """Validate an estimator name and its options without side effects or a trial run.

    Returns the scoped options; raises ``ValueError`` (``estimator: ...`` or
    ``options.<name>: ...``).
    """
    kwargs = scoped_options(name, options)
    spec(name).parse(kwargs)
    return kwargs


def solve(name, bearings, **options):
    """Run estimator ``name`` on ``bearings`` -> FixResult.

    Multi-station: see estimators.locate (its errors, ``method: unknown estimator ...`` for
    an unknown name). TMA: pass the bearing times (``times``, (K,) or
    (M, K) s) and the prior speed (``speed``, m/s) as keywords (see core.tma).
    """
    fn = _tma.TMA_FUNCTIONS.get(name) if isinstance(name, str) else None
    if fn is not None:
        own = fn.spec
        try:
            inputs = [options.pop(k) for k in own.inputs]
        except KeyError as exc:
            raise ValueError(f'{exc.args[0]}: required by TMA estimator {name!r}') from None
        return own.function(bearings, *inputs, **options)
    return _estimators.locate(name, bearings, **options)


def noise_sigmas(name, bearings, position, options):
    """(σ_θ, σ_ψ) (M, N), rad, that estimator ``name`` assumes at ``position`` (M, 3).

    From the estimator's declared noise model: ``wmle`` grows σ with range (Zong & Cui 2015
    eqs. (9)-(10), option ``reference_range``); every other estimator uses the bearings' σ.
    """
    return spec(name).noise.sigmas(bearings, np.asarray(position, dtype=float), options)


def noise_crlb(name, position, bearings, **options):
    """CRLB (M, 3, 3), m², at ``position`` under the noise model estimator ``name`` assumes.

    Multi-station estimators only (a TMA bound needs the state and times: core.tma.tma_crlb).
    """
    if mode_of(name) != MODE_MULTISTATION:
        raise ValueError(f'estimator: {name} is a tma estimator; its bound is '
                         'core.tma.tma_crlb')
    return _estimators.noise_model_crlb(name, np.asarray(position, dtype=float), bearings,
                                        **options)
