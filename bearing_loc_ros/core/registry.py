"""The estimator registry: the one place that knows which estimators exist and what they need.

Fusion, the CLI and ``evaluate`` ask this module about an estimator and never compare its
name with a string. For each estimator name it answers:

* :func:`mode_of`: ``multistation`` (one fix from the bearings of several stations) or
  ``tma`` (one moving station, target motion analysis with a speed prior).
* :func:`scoped_options`: the subset of a shared option set the estimator accepts.
* :func:`check`: the validated options (``ValueError('options.<name>: ...')``).
* :func:`noise_sigmas` and :func:`noise_crlb`: the bearing noise model the estimator assumes
  (the σ it weights with) and hence the Cramér-Rao bound it is measured against.
* :func:`solve`: run it on a :class:`~bearing_loc_ros.core.bearings.BearingSet`.
"""

import numpy as np

from . import estimators as _estimators

#: Fusion modes an estimator belongs to.
MODE_MULTISTATION = 'multistation'
MODE_TMA = 'tma'

#: Single-station TMA estimators (Lin et al., speed-prior 3D TMA) -> core.tma method.
TMA_ESTIMATORS = {'tma_ple': 'ple', 'tma_ctls': 'ctls', 'tma_ctls6': 'ctls6',
                  'tma_mle': 'mle'}

#: Estimator options and the estimators that accept them: None = every estimator; the others
#: are passed only to the listed ones, so one set of node parameters serves every estimator.
OPTION_SCOPE = {
    'max_iterations': None,
    'tolerance': None,
    'reference_range': ('wmle',),
    'step_decay': ('ctls', 'ctls_am'),
}


def names(mode=None):
    """Registered estimator names (sorted), all or those of one ``mode``."""
    multi = sorted(_estimators.ESTIMATORS)
    tma = sorted(TMA_ESTIMATORS)
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


def mode_of(name):
    """The fusion mode estimator ``name`` belongs to; ValueError for an unknown name."""
    if name in TMA_ESTIMATORS:
        return MODE_TMA
    if name in _estimators.ESTIMATORS:
        return MODE_MULTISTATION
    raise ValueError(f'estimator: unknown estimator {name!r}; choose one of {list(names())}')


def scoped_options(name, options):
    """The subset of ``options`` that estimator ``name`` accepts (:data:`OPTION_SCOPE`).

    Options not listed in the scope table are passed through unchanged (the estimator
    validates them).
    """
    out = {}
    for k, v in options.items():
        scope = OPTION_SCOPE.get(k)
        if scope is None or name in scope:
            out[k] = v
    return out


def check(name, options):
    """Validate an estimator name and its options without side effects.

    Returns the scoped options; raises ``ValueError`` with the estimator's own message
    (``estimator: ...`` or ``options.<name>: ...``).
    """
    mode = mode_of(name)
    kwargs = scoped_options(name, options)
    if mode == MODE_MULTISTATION:
        _estimators.parse_options(name, kwargs, _estimators.option_defaults(name))
    return kwargs


def solve(name, bearings, **options):
    """Run multi-station estimator ``name`` on ``bearings`` (see estimators.locate)."""
    return _estimators.locate(name, bearings, **options)


def noise_sigmas(name, bearings, position, options):
    """(σ_θ, σ_ψ) (M, N), rad, that estimator ``name`` assumes at ``position`` (M, 3).

    ``wmle`` grows σ with range (Zong & Cui 2015 eqs. (9)-(10), option ``reference_range``);
    every other estimator uses the bearings' σ as given.
    """
    d_ref = _reference_range(name, options)
    if d_ref is not None:
        return _estimators.range_scaled_sigmas(bearings, position, d_ref)
    return bearings.sigma_az, bearings.sigma_el


def noise_crlb(name, position, bearings, **options):
    """CRLB (M, 3, 3), m², at ``position`` under the noise model estimator ``name`` assumes."""
    return _estimators.noise_model_crlb(name, np.asarray(position, dtype=float), bearings,
                                        **options)


def _reference_range(name, options):
    """d_ref (m) when estimator ``name`` models σ growing with range, else None."""
    if 'reference_range' in _estimators.option_defaults(name):
        return options.get('reference_range', _estimators.DEFAULT_REFERENCE_RANGE)
    return None
