"""Declarations of estimators: their options, noise model, mode and result, in one place each.

Every estimator function is declared with :func:`declare`, right at its definition::

    @declare('mle', MULTISTATION, ITERATIVE_OPTIONS, BEARING_SIGMA)
    def mle(bearings, **options): ...

which attaches an :class:`EstimatorSpec` as ``mle.spec``. The spec validates the options
(:meth:`EstimatorSpec.parse`, no trial run of the estimator), names the noise model the
estimator assumes (hence the Cramér-Rao bound it is measured against) and the result type.
:mod:`bearing_loc_ros.core.registry` answers every question about an estimator from these
specs; nothing outside compares estimator names.

Noise models (σ in rad):

* :data:`BEARING_SIGMA`: the σ the bearings carry, as given (Zong & Cui 2015 eq. (4)).
* :data:`RANGE_GROWN_SIGMA`: σ_k(d) = σ_ref,k · d_k / d_ref, d_k the slant range from station
  k to the target, d_ref the option ``reference_range`` (Zong & Cui 2015 eqs. (9)-(10)).

This module imports nothing from the estimator modules (no import cycle).
"""

from dataclasses import dataclass
import numbers

import numpy as np

from .bearings import MAX_ABS_POSITION
from .fix import FixResult

MULTISTATION = 'multistation'
TMA = 'tma'
MODES = (MULTISTATION, TMA)

#: Default reference range d_ref (m) of the range-grown noise model (``wmle``).
DEFAULT_REFERENCE_RANGE = 1000.0


@dataclass(frozen=True)
class Option:
    """One estimator option: name, default, kind of value and a one-line description.

    ``kind``: ``'count'`` (integer ≥ 1), ``'positive'`` (finite > 0, at most ``upper`` when
    set; +inf too when ``allow_inf``), ``'probability'`` (in (0, 1)), ``'flag'`` (bool),
    ``'choice'`` (one of
    ``choices``), ``'point'`` ((3,) or (M, 3) finite coordinates, m), ``'altitude'`` (None
    or a finite length, m, scalar or (M,)), ``'nonnegative'`` (finite ≥ 0, m, scalar or
    (M,)) or ``'object'`` (checked by the estimator itself).
    """

    name: str
    default: object
    kind: str
    doc: str
    upper: float = None
    choices: tuple = ()
    allow_inf: bool = False

    def validate(self, value, M=None):
        """The checked (and normalised) value; ValueError('options.<name>: ...') if bad."""
        name = self.name
        if self.kind == 'count':
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
                raise ValueError(f'options.{name}: must be an integer >= 1')
            return int(value)
        if self.kind in ('positive', 'probability'):
            upper = 1.0 if self.kind == 'probability' else self.upper
            if self.allow_inf and isinstance(value, numbers.Real) and value == np.inf:
                return float(value)
            if isinstance(value, bool) or not isinstance(value, numbers.Real) \
                    or not np.isfinite(value) or value <= 0 or (upper is not None and (
                        value > upper or (self.kind == 'probability' and value == upper))):
                rng = ('> 0' if upper is None else '(0, 1)' if self.kind == 'probability'
                       else f'in (0, {upper:g}]')
                raise ValueError(f'options.{name}: must be a finite number {rng}')
            return float(value)
        if self.kind == 'flag':
            if not isinstance(value, (bool, np.bool_)):
                raise ValueError(f'options.{name}: must be true or false')
            return bool(value)
        if self.kind == 'choice':
            if value not in self.choices:
                raise ValueError(f'options.{name}: must be one of {", ".join(self.choices)}, '
                                 f'got {value!r}')
            return value
        if self.kind == 'point':
            return None if value is None else _initial(value, M)
        if self.kind in ('altitude', 'nonnegative'):
            return _metres(name, value, self.kind == 'altitude', self.upper)
        return value


def _metres(name, value, optional, upper=None):
    """A finite length (m, scalar or (M,)) or None (``optional``); ``nonnegative``: ≥ 0;
    |value| ≤ ``upper`` when given."""
    if value is None and optional:
        return None
    if isinstance(value, (bool, np.bool_)) or isinstance(value, str):
        raise ValueError(f'options.{name}: must be a number (m), got {value!r}')
    try:
        v = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f'options.{name}: must be a number (m), got {value!r}') from None
    if v.ndim > 1:
        raise ValueError(f'options.{name}: expected a number or a list of one per problem')
    if not np.all(np.isfinite(v)):
        raise ValueError(f'options.{name}: must be finite (m), got NaN or inf')
    if not optional and np.any(v < 0):
        raise ValueError(f'options.{name}: must be >= 0 (m)')
    if upper is not None and np.any(np.abs(v) > upper):
        raise ValueError(f'options.{name}: |value| must be <= {upper:g} m')
    return float(v) if v.ndim == 0 else v


def _initial(value, M):
    """The starting point(s) (M, 3), m: finite, within ±MAX_ABS_POSITION (the stations'
    bound), given as (3,) or (M, 3); else ValueError naming ``options.initial``."""
    if isinstance(value, (str, bytes)):
        raise ValueError(f'options.initial: must be 3 numbers (m), got {value!r}'[:120])
    try:
        x0 = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f'options.initial: must be 3 numbers (m), got {value!r}'[:120]) \
            from None
    if x0.ndim == 1:
        x0 = x0[None]
    if x0.ndim != 2 or x0.shape[1] != 3 or (M is not None and x0.shape[0] not in (1, M)):
        raise ValueError(f'options.initial: expected shape (3,) or ({M}, 3), got '
                         f'{np.shape(value)}')
    if not np.all(np.isfinite(x0)):
        raise ValueError('options.initial: non-finite coordinate')
    if np.any(np.abs(x0) > MAX_ABS_POSITION):
        raise ValueError(f'options.initial: |coordinate| above {MAX_ABS_POSITION:g} m')
    return np.broadcast_to(x0, (M if M is not None else x0.shape[0], 3)).copy()


MAX_ITERATIONS = Option('max_iterations', 50, 'count', 'iteration limit')
TOLERANCE = Option('tolerance', 1e-9, 'positive',
                   'converged when the full step is shorter than tolerance x rms range')
INITIAL = Option('initial', None, 'point', 'starting point (3,) or (M, 3), m (default: ls)')
REFERENCE_RANGE = Option('reference_range', DEFAULT_REFERENCE_RANGE, 'positive',
                         'd_ref of the range-grown noise model, m')
STEP_DECAY = Option('step_decay', 1.0, 'positive', 'mu of the Newton step decay mu^n',
                    upper=1.0)
ROBUST = Option('robust', False, 'flag',
                'screen the fix; on doubt, consensus over station subsets and a full-likelihood '
                'refit without outlier bearings; status ok or low_confidence (core.robust)')
#: ``robust`` on by default (the default estimator, ``mle``: at high SNR the screen keeps
#: the paper's fix, so the default changes only fixes that are in doubt).
ROBUST_ON = Option('robust', True, 'flag', ROBUST.doc)

#: Status rule of the estimators without ``robust`` (``ls``, ``tls``, ``ctls``, ``ctls_am``).
CONSISTENCY = Option('consistency', True, 'flag',
                     'status low_confidence for an ok fix that, one Gauss-Newton step toward '
                     'the likelihood optimum, fails the 0.999 chi-square test, lies outside its '
                     'own covariance from that optimum, has an angle beyond 3.9 sigma or a '
                     'nonlinearity above 0.2, and for a fix that passes the covariance P + '
                     'delta delta^T with delta that step (its estimated bias; '
                     'core.robust.consistency_status); false: the published statuses and '
                     'covariances')

#: Dimension choices of the solve (core.horizontal): 3D when the bearings observe the height,
#: forced 3D, or the horizontal solve with the target altitude stated.
DIMENSIONS = ('auto', '3d', 'horizontal')
DIMENSION = Option('dimension', 'auto', 'choice',
                   'auto (3d when the bearings observe the height, else horizontal), 3d or '
                   'horizontal', choices=DIMENSIONS)
#: Bounds of the stated altitude (the stations' coordinate bound) and of its σ, m (beyond
#: it σ_z² and the σ_z terms of the covariances overflow or lose every digit: σ_z = 1e155
#: gave NaN); horizontal_estimators.prepare checks the same.
MAX_ABS_ALTITUDE = MAX_ABS_POSITION
MAX_ALTITUDE_SIGMA = 1.0e6
TARGET_ALTITUDE = Option('target_altitude', None, 'altitude',
                         'target altitude z0 of the horizontal solve, m, world frame (None: '
                         'not stated)', upper=MAX_ABS_ALTITUDE)
TARGET_ALTITUDE_SIGMA = Option('target_altitude_sigma', 0.0, 'nonnegative',
                               'standard deviation of the stated altitude, m (0: exact)',
                               upper=MAX_ALTITUDE_SIGMA)
USE_ELEVATIONS = Option('use_elevations', True, 'flag',
                        'use measured elevations; false ignores them, so every set is solved '
                        'horizontally (needs target_altitude; dimension 3d is an error)')
#: Solve-level options of every multi-station estimator (not TMA): the dimension selection
#: and the horizontal solve's stated altitude (core.horizontal, core.registry.solve).
SOLVE_OPTIONS = (DIMENSION, TARGET_ALTITUDE, TARGET_ALTITUDE_SIGMA, USE_ELEVATIONS)

#: Options of the closed-form multi-station estimators (accepted and ignored, so one option
#: set serves every estimator).
COMMON_OPTIONS = (MAX_ITERATIONS, TOLERANCE)
#: Options of the iterative multi-station estimators.
ITERATIVE_OPTIONS = COMMON_OPTIONS + (INITIAL,)


@dataclass(frozen=True)
class NoiseModel:
    """The bearing σ an estimator assumes: as given, or grown with range from a reference.

    ``range_option``: None (σ as carried by the bearings) or the name of the option holding
    d_ref (σ grows linearly with the slant range, Zong & Cui 2015 eqs. (9)-(10)).
    """

    name: str
    range_option: str = None

    def sigmas(self, bearings, position, options):
        """(σ_θ, σ_ψ), each (M, N) rad, assumed at targets ``position`` (M, 3), m."""
        if self.range_option is None:
            return bearings.sigma_az, bearings.sigma_el
        d_ref = options.get(self.range_option, DEFAULT_REFERENCE_RANGE)
        return range_scaled_sigmas(bearings, position, d_ref)


BEARING_SIGMA = NoiseModel('bearing_sigma')
RANGE_GROWN_SIGMA = NoiseModel('range_grown_sigma', 'reference_range')


def range_scaled_sigmas(bearings, position, reference_range):
    """σ of every bearing grown with range: σ(d) = σ_ref · d / d_ref (Zong & Cui 2015 (9)-(10)).

    ``position`` (M, 3) is the target (estimate), d = |X − S_k| the slant range from station
    k, ``reference_range`` d_ref (m); σ_ref is the σ stored in the BearingSet (rad).
    Returns (sigma_az, sigma_el), each (M, N), rad (sigma_el NaN for 1D bearings).
    """
    d = np.linalg.norm(np.asarray(position, dtype=float)[:, None, :] - bearings.positions,
                       axis=-1)
    f = d / float(reference_range)
    return bearings.sigma_az * f, bearings.sigma_el * f


@dataclass
class EstimatorSpec:
    """What one estimator is: name, mode, accepted options, noise model, result type, function.

    ``inputs`` names the problem data besides the bearings that the function takes
    positionally (TMA: the bearing times and the prior speed).
    """

    # Fields and lookups by name: alike the scenario's in shape only (different records).
    name: str
    mode: str
    options: tuple
    noise: NoiseModel
    result: type
    function: object = None
    inputs: tuple = ()

    def defaults(self):
        """{option: default} of the accepted options."""
        return {o.name: o.default for o in self.options}

    def option(self, name):
        """The :class:`Option` called ``name``; KeyError if not accepted."""
        for o in self.options:
            if o.name == name:
                return o
        raise KeyError(name)

    def accepts(self, name):
        """True when option ``name`` is accepted."""
        return any(o.name == name for o in self.options)

    def parse(self, options, M=None):
        """Defaults merged with ``options``, every given value validated.

        Raises ``ValueError('options.<name>: ...')`` for an unknown option or a bad value.
        ``M`` (number of problems) checks the shape of a ``point`` option (``initial``).
        """
        out = self.defaults()
        for name, value in options.items():
            if not self.accepts(name):
                raise ValueError(f'options.{name}: unknown option for estimator '
                                 f'{self.name!r} (accepted: '
                                 f'{", ".join(sorted(out)) or "none"})')
            out[name] = self.option(name).validate(value, M)
        return out


def declare(name, mode, options, noise, result=None, inputs=()):
    """Decorator: attach an :class:`EstimatorSpec` to an estimator function as ``fn.spec``.

    ``result`` defaults to :class:`~bearing_loc_ros.core.fix.FixResult`.
    """
    if mode not in MODES:
        raise ValueError(f'mode: expected one of {MODES}, got {mode!r}')
    result = FixResult if result is None else result

    def wrap(fn):
        fn.spec = EstimatorSpec(name, mode, tuple(options), noise, result, fn, tuple(inputs))
        return fn

    return wrap
