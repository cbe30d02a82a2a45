"""The TMA estimators by their registry names, and :func:`tma` to run one by name."""

from .closed_form import tma_ctls, tma_ctls6, tma_ple
from .mle import tma_mle


#: The TMA estimators by their registry names (core.registry, the fusion node and the CLI).
TMA_FUNCTIONS = {
    'tma_ple': tma_ple,
    'tma_ctls': tma_ctls,
    'tma_ctls6': tma_ctls6,
    'tma_mle': tma_mle,
}

#: The closed forms and the method name :func:`~.closed_form.estimate_from_sums` knows them by.
_CLOSED_FORMS = {tma_ple: 'ple', tma_ctls: 'ctls', tma_ctls6: 'ctls6'}


def tma_function(method):
    """The TMA estimator function registered as ``method`` (``tma_ple``, ``tma_ctls``,
    ``tma_ctls6``, ``tma_mle``); ValueError naming the choices if unknown."""
    fn = TMA_FUNCTIONS.get(method) if isinstance(method, str) else None
    if fn is None:
        raise ValueError(f'method: unknown TMA estimator {method!r}; choose one of '
                         f'{sorted(TMA_FUNCTIONS)}')
    return fn


def tma(method, bearings, times, speed, **options):
    """Run TMA estimator ``method`` (see :func:`tma_function`) -> FixResult with velocity."""
    return tma_function(method)(bearings, times, speed, **options)
