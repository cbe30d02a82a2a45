"""``bearing_loc tma``: one moving station, target motion analysis (Lin et al.), JSON in/out.

Input (a file argument, or stdin when the argument is ``-`` or absent), one problem::

    {"estimator": "tma_ctls6",         # optional: tma_ple | tma_ctls | tma_ctls6 | tma_mle
     "speed": 380.0,                   # prior speed v_c, m/s (> 0)
     "speed_reference": "relative",    # optional: relative (Lin et al.) | ground
     "options": {"alpha": 1e-3},       # optional estimator options (core.tma.DEFAULTS)
     "sigma_azimuth": 0.0017,          # optional default σ_θ, rad
     "sigma_elevation": 0.0017,        # optional default σ_ψ, rad
     "observations": [{"t": 0.0,                 # s
                       "observer": [x, y, z],    # m, ENU world frame
                       "azimuth": 0.78,          # rad, ENU (CCW from East; --compass: CW
                                                 #   from North as in Lin et al.)
                       "elevation": 0.07,        # rad, above the horizontal (required)
                       "sigma_azimuth": 0.0017,  # rad, > 0 (or the default above)
                       "sigma_elevation": 0.0017},
                      ...]}

or a batch ``{"estimator": ..., "speed": ..., "problems": [{"observations": [...]}, ...]}``
(a problem may override ``speed``). The default estimator is ``tma_ctls6``. The former key
``method`` and the former names ``ple``, ``ctls``, ``ctls6``, ``mle`` are accepted with a
deprecation warning. Observations are sorted by time. Output (stdout), the target at the
last observation time: ``{"estimator", "method" (the same, deprecated), "t", "position",
"velocity", "covariance" (6x6 of position and velocity, the constrained CRLB at the
estimate), "status", "reason", "t0", "position0", "range", "iterations", "converged"}``
for one problem, ``{"results": [...]}`` in input order for a batch. Non-finite numbers
(no fix: status ``unobservable``) are ``null``. Exit 0 when every problem was processed (check each
``status``), 2 with one line on stderr naming the bad field (nothing on stdout).
"""

import math

import numpy as np

from ..core.bearings import Bearing, BearingSet
from ..core.conventions import compass_to_enu
from ..core import registry
from ..core.tma import SPEED_REFERENCES
from ..core.tma.model import MAX_ABS_TIME, MAX_SPEED
from . import InputError
from .deprecation import DeprecatedOption, tma_estimator
from .jsonio import (add_io_arguments, check_object, finite_or_none, number, read_json,
                     request_header, write_results)

#: The recommended closed form (core.tma: near the CRLB; the paper's tma_ctls is biased and
#: its fixes rarely pass the confidence checks).
DEFAULT_METHOD = 'tma_ctls6'
TOP_FIELDS = ('estimator', 'speed', 'speed_reference', 'options', 'sigma_azimuth',
              'sigma_elevation', 'observations', 'problems')
OBS_FIELDS = ('t', 'observer', 'azimuth', 'elevation', 'sigma_azimuth', 'sigma_elevation')


def add_arguments(parser):
    """Command line of ``bearing_loc tma``."""
    parser.description = ('Target motion analysis from one moving station with a speed prior '
                          '(Lin et al.): JSON in (file or stdin), JSON out. Format: '
                          'docs/cli.md "tma".')
    add_io_arguments(parser)
    parser.add_argument('--estimator', default=None, metavar='NAME',
                        help=f'TMA estimator: {", ".join(registry.names(registry.MODE_TMA))}; '
                             f'overrides the input\'s "estimator" (default: the input\'s, '
                             f'else {DEFAULT_METHOD})')
    parser.add_argument('--method', dest='estimator', action=DeprecatedOption,
                        replacement='--estimator')
    parser.add_argument('--speed', type=float, default=None,
                        help='prior speed v_c in m/s, overrides the input\'s "speed"')
    parser.add_argument('--compass', action='store_true',
                        help='azimuths are compass bearings (clockwise from North, as Lin et '
                             'al.); converted to ENU as pi/2 - azimuth')


def parse_observations(items, where, defaults, compass=False):
    """A JSON list of observations -> (BearingSet (1, K), times (1, K)), sorted by time."""
    if not isinstance(items, list) or not items:
        raise InputError(f'{where}: must be a non-empty list of observation objects')
    rows = []
    for i, ob in enumerate(items):
        f = f'{where}[{i}]'
        check_object(ob, f, OBS_FIELDS)
        ob = dict(defaults, **{k: v for k, v in ob.items() if v is not None or k not in
                               defaults})
        for key in OBS_FIELDS:
            if ob.get(key) is None:
                extra = (' (3-D TMA needs azimuth and elevation)' if key == 'elevation'
                         else '')
                raise InputError(f'{f}.{key}: missing{extra}')
        o = ob['observer']
        if not isinstance(o, list) or len(o) != 3:
            raise InputError(f'{f}.observer: must be a list [x, y, z] of 3 numbers (m)')
        obs = [number(v, f'{f}.observer[{k}]') for k, v in enumerate(o)]
        az = number(ob['azimuth'], f'{f}.azimuth')
        el = number(ob['elevation'], f'{f}.elevation')
        if abs(el) >= math.pi / 2:
            raise InputError(f'{f}.elevation: |elevation| must be < pi/2 rad')
        t = number(ob['t'], f'{f}.t')
        if abs(t) > MAX_ABS_TIME:
            raise InputError(f'{f}.t: |t| must be <= {MAX_ABS_TIME:g} s')
        row = (t, obs, compass_to_enu(az) if compass else az, el,
               number(ob['sigma_azimuth'], f'{f}.sigma_azimuth', positive=True),
               number(ob['sigma_elevation'], f'{f}.sigma_elevation', positive=True))
        try:        # the core's range checks, named by the observation's field
            Bearing('', 0, *row[1:]).validate()
        except ValueError as exc:
            field, _, problem = str(exc).partition(': ')
            raise InputError(f'{f}.{"observer" if field == "position" else field}: '
                             f'{problem}') from None
        rows.append(row)
    rows.sort(key=lambda r: r[0])
    t, obs, az, el, saz, sel = (np.array(c, dtype=float) for c in zip(*rows))
    bs = BearingSet.from_arrays(obs, az, el, saz, sel, validate=False)
    return bs, t[None]


def parse_request(doc, method_override=None, speed_override=None, compass=False):
    """Validate a request; return (method, options, [(BearingSet, times, speed)], is_batch)."""
    method, options = request_header(doc, TOP_FIELDS, 'observations',
                                     registry.names(registry.MODE_TMA), DEFAULT_METHOD,
                                     method_override, kind='TMA estimator',
                                     canonical=tma_estimator)
    options = dict(options)
    for key, value in options.items():
        if key in ('alpha', 'max_range_ratio', 'dtol', 'xtol', 'min_bearings',
                   'max_iterations', 'max_nonlinearity', 'max_ml_distance'):
            options[key] = number(value, f'options.{key}', positive=True)
            if key in ('min_bearings', 'max_iterations'):
                if options[key] != int(options[key]):
                    raise InputError(f'options.{key}: must be an integer >= 1')
                options[key] = int(options[key])
        elif key == 'covariance' and not isinstance(value, bool):
            raise InputError('options.covariance: must be true or false')
        elif key not in ('covariance', 'speed_reference'):
            raise InputError(f'options.{key}: unknown option')
    ref = doc.get('speed_reference', options.get('speed_reference', 'relative'))
    if ref not in SPEED_REFERENCES:
        raise InputError(f'speed_reference: must be one of {", ".join(SPEED_REFERENCES)}')
    options['speed_reference'] = ref
    defaults = {}
    for key in ('sigma_azimuth', 'sigma_elevation'):
        if doc.get(key) is not None:
            defaults[key] = number(doc[key], key, positive=True)

    def speed_of(d, where):
        if speed_override is not None:
            field, v = '--speed', number(speed_override, '--speed', positive=True)
        elif d.get('speed') is None:
            raise InputError(f'{where}speed: missing (prior speed v_c, m/s)')
        else:
            field, v = f'{where}speed', number(d['speed'], f'{where}speed', positive=True)
        if v > MAX_SPEED:
            raise InputError(f'{field}: must be <= {MAX_SPEED:g} m/s')
        return v

    if ('observations' in doc) == ('problems' in doc):
        raise InputError('input: give exactly one of "observations" (one problem) or '
                         '"problems" (a batch)')
    if 'observations' in doc:
        bs, t = parse_observations(doc['observations'], 'observations', defaults, compass)
        return method, options, [(bs, t, speed_of(doc, ''))], False
    problems = doc['problems']
    if not isinstance(problems, list) or not problems:
        raise InputError('problems: must be a non-empty list of {"observations": [...]} '
                         'objects')
    out = []
    for k, prob in enumerate(problems):
        where = f'problems[{k}]'
        if not isinstance(prob, dict) or 'observations' not in prob:
            raise InputError(f'{where}: must be an object with "observations"')
        for key in prob:
            if key not in ('observations', 'speed'):
                raise InputError(f'{where}.{key}: unknown field (expected observations, '
                                 'speed)')
        bs, t = parse_observations(prob['observations'], f'{where}.observations', defaults,
                                   compass)
        sp = speed_of(prob, f'{where}.') if 'speed' in prob else speed_of(doc, '')
        out.append((bs, t, sp))
    return method, options, out, True


def solve(method, options, problems):
    """Run ``method`` on every (BearingSet, times, speed); one output dict per problem."""
    out = []
    for bs, t, speed in problems:
        try:
            res = registry.solve(method, bs, times=t, speed=speed, **options)
        except ValueError as exc:
            raise InputError(str(exc)) from None
        d = res.single(0)
        out.append({
            'estimator': method,
            'method': method,
            't': d['t'],
            'position': finite_or_none(d['position']),
            'velocity': finite_or_none(d['velocity']),
            'covariance': finite_or_none(d['covariance']),
            'status': d['status'],
            'reason': d['reason'],
            't0': d['t0'],
            'position0': finite_or_none(d['position0']),
            'range': finite_or_none(d['range']),
            'iterations': d['iterations'],
            'converged': d['converged'],
        })
    return out


def run(args):
    """Entry point of the verb: read, validate, solve, print. Returns the exit code."""
    doc = read_json(args.input)
    method, options, problems, batch = parse_request(doc, args.estimator, args.speed,
                                                     args.compass)
    results = solve(method, options, problems)
    return write_results(results, batch, args.indent)
