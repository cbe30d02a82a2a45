"""The TMA estimators by name, and :func:`tma` to run one by name."""

from .closed_form import tma_ctls, tma_ctls6, tma_ple
from .mle import tma_mle


#: The TMA estimators by their registry names (core.registry, the fusion node and the CLI).
TMA_FUNCTIONS = {
    'tma_ple': tma_ple,
    'tma_ctls': tma_ctls,
    'tma_ctls6': tma_ctls6,
    'tma_mle': tma_mle,
}

_CLOSED_FORMS = {tma_ple: 'ple', tma_ctls: 'ctls', tma_ctls6: 'ctls6'}

#: Deprecated: the same functions by their former short names (accepted for one release).
TMA_ESTIMATORS = {
    'ple': tma_ple,
    'ctls': tma_ctls,
    'ctls6': tma_ctls6,
    'mle': tma_mle,
}


def tma_function(method):
    """The TMA estimator function called ``method`` (``tma_ple`` ..., or a former short name
    ``ple`` ...); ValueError naming the choices if unknown."""
    fn = TMA_FUNCTIONS.get(method) if isinstance(method, str) else None
    if fn is None and isinstance(method, str):
        fn = TMA_ESTIMATORS.get(method)
    if fn is None:
        raise ValueError(f'method: unknown TMA estimator {method!r}; choose one of '
                         f'{sorted(TMA_FUNCTIONS)}')
    return fn


def tma(method, bearings, times, speed, **options):
    """Run TMA estimator ``method`` (see :func:`tma_function`) -> FixResult with velocity."""
    return tma_function(method)(bearings, times, speed, **options)
