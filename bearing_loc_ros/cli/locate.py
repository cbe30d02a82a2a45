"""``bearing_loc locate``: localize emitters from bearings, JSON in, JSON out.

Input (a file argument, or stdin when the argument is ``-`` or absent), one problem::

    {"estimator": "mle",                           # optional, default mle
     "options": {"max_iterations": 50},            # optional, estimator options
     "bearings": [{"station": "s1",                # optional id, unique per problem
                   "position": [x, y, z],          # m, ENU world frame
                   "azimuth": 0.52,                # rad, ENU (CCW from East)
                   "elevation": 0.1,               # rad, or null/absent (azimuth-only)
                   "sigma_azimuth": 0.002,         # rad, > 0
                   "sigma_elevation": 0.002},      # rad, > 0 (required with elevation)
                  ...]}

or a batch ``{"estimator": ..., "options": ..., "problems": [{"bearings": [...]}]}``.
Azimuth-only bearings need the target altitude: options ``target_altitude`` (m, world
frame), ``target_altitude_sigma`` (m), ``dimension`` (``auto | 3d | horizontal``) and
``use_elevations`` (core.horizontal), or the flags ``--target-altitude``,
``--target-altitude-sigma``, ``--dimension`` and ``--ignore-elevations``.
The former key ``method`` is accepted with a deprecation warning. Large batches may come as a
CSV or NPZ table with one row per bearing (``--format``, columns in cli.batch_input); the
estimator and its options then come from ``--estimator`` and ``--options``.
Output (stdout): ``{"estimator", "method" (the same, deprecated), "position", "covariance",
"crlb", "converged", "iterations", "status", "solve"}`` for one problem (``solve``: ``3d`` or
``horizontal``; a horizontal fix also gives ``target_altitude`` and
``target_altitude_sigma``; a robust estimator's fix (``mle`` by default) also gives
``excluded``, the angles left out as outliers, :func:`excluded_angles`), ``{"results": [...]}``
(same order) for a batch (for a table, each result also carries its ``problem`` id).
Non-finite numbers (the inf covariance of a degenerate fix, its NaN
position) are written as ``null``, so the output is always strict JSON. Exit 0 when every
problem was processed (check each ``status``), 2 with one line on stderr naming the bad
field (nothing on stdout) for bad input.
Problems with the same number of bearings are checked and solved in one vectorised call.
"""

import json
import math
import sys

import numpy as np

from ..core.bearings import Bearing, BearingSet
from ..core import registry
from . import InputError
from . import batch_input
from .deprecation import DeprecatedOption
from .jsonio import (add_io_arguments, check_object, finite_rows, number, read_json,
                     request_header, write_results)

BEARING_FIELDS = ('station', 'position', 'azimuth', 'elevation', 'sigma_azimuth',
                  'sigma_elevation')
TOP_FIELDS = ('estimator', 'options', 'bearings', 'problems')


def add_arguments(parser):
    """Command line of ``bearing_loc locate``."""
    parser.description = ('Localize emitters from bearings: JSON in (file or stdin), JSON out '
                          '(stdout). Format: docs/cli.md "locate".')
    add_io_arguments(parser)
    from .gisargs import add_gis_arguments
    add_gis_arguments(parser)
    parser.add_argument('--estimator', choices=registry.names(registry.MODE_MULTISTATION),
                        default=None,
                        help='estimator, overrides the input\'s "estimator" (default: the '
                             f'input\'s, else {registry.default_estimator()})')
    parser.add_argument('--method', dest='estimator', action=DeprecatedOption,
                        replacement='--estimator',
                        choices=registry.names(registry.MODE_MULTISTATION))
    add_table_arguments(parser)
    add_dimension_arguments(parser)


def add_dimension_arguments(parser):
    """``--dimension``, ``--target-altitude``, ``--target-altitude-sigma`` and
    ``--ignore-elevations``: the solve-level options (core.horizontal), overriding the
    input's ``options`` of the same names."""
    parser.add_argument('--dimension', choices=('auto', '3d', 'horizontal'), default=None,
                        help='auto (3d when the bearings observe the height, else '
                             'horizontal), 3d, or horizontal (needs --target-altitude)')
    parser.add_argument('--target-altitude', type=float, default=None, metavar='M',
                        help='target altitude (m, world frame) of the horizontal solve')
    parser.add_argument('--target-altitude-sigma', type=float, default=None, metavar='M',
                        help='its standard deviation, m (default 0: exactly known)')
    parser.add_argument('--ignore-elevations', action='store_true',
                        help='do not use measured elevations: the horizontal solve '
                             '(needs --target-altitude)')


def dimension_options(args, options):
    """``options`` with the dimension flags of ``args`` applied (flags win)."""
    out = dict(options)
    for flag, key in (('dimension', 'dimension'), ('target_altitude', 'target_altitude'),
                      ('target_altitude_sigma', 'target_altitude_sigma')):
        v = getattr(args, flag, None)
        if v is not None:
            out[key] = v
    if getattr(args, 'ignore_elevations', False):
        out['use_elevations'] = False
    return out


def add_table_arguments(parser):
    """``--format`` (JSON or a CSV/NPZ bearing table) and ``--options`` of ``locate``."""
    parser.add_argument('--format', choices=('auto',) + batch_input.FORMATS, default='auto',
                        help='input format (default auto: .csv and .npz files are bearing '
                             'tables, anything else and stdin JSON)')
    parser.add_argument('--options', default=None, metavar='JSON',
                        help='estimator options as a JSON object, e.g. '
                             '\'{"max_iterations": 50}\' (replaces the input\'s "options")')


def parse_bearings(items, where='bearings'):
    """A JSON list of bearing objects → one-problem BearingSet (ValueError names the field)."""
    if not isinstance(items, list):
        raise InputError(f'{where}: must be a list of bearing objects')
    if len(items) < 2:
        raise InputError(f'{where}: {len(items)} bearing(s); a fix needs at least two')
    pos, az, el, saz, sel, names = [], [], [], [], [], []
    for i, b in enumerate(items):
        f = f'{where}[{i}]'
        check_object(b, f, BEARING_FIELDS)
        for key in ('position', 'azimuth', 'sigma_azimuth'):
            if key not in b:
                raise InputError(f'{f}.{key}: missing')
        station = b.get('station', f'station_{i}')
        if not isinstance(station, str):
            raise InputError(f'{f}.station: must be a string')
        if station in names:
            raise InputError(f'{f}.station: duplicate station id {station!r}')
        p = b['position']
        if not isinstance(p, list) or len(p) != 3:
            raise InputError(f'{f}.position: must be a list [x, y, z] of 3 numbers (m)')
        pos.append([number(v, f'{f}.position[{k}]') for k, v in enumerate(p)])
        az.append(number(b['azimuth'], f'{f}.azimuth'))
        saz.append(number(b['sigma_azimuth'], f'{f}.sigma_azimuth', positive=True))
        e = b.get('elevation')
        if e is None:
            el.append(math.nan)
            sel.append(math.nan)
        else:
            e = number(e, f'{f}.elevation')
            if abs(e) >= math.pi / 2:
                raise InputError(f'{f}.elevation: |elevation| must be < pi/2 rad')
            if b.get('sigma_elevation') is None:
                raise InputError(f'{f}.sigma_elevation: missing (required when elevation is '
                                 'given)')
            el.append(e)
            sel.append(number(b['sigma_elevation'], f'{f}.sigma_elevation', positive=True))
        names.append(station)
    arrays = (np.array(pos), np.array(az), np.array(el), np.array(saz), np.array(sel))
    try:
        return BearingSet.from_arrays(*arrays, stations=names, require_elevation=False)
    except ValueError as exc:
        raise InputError(_first_bad_bearing(arrays, where) or f'{where}: {exc}') from None


def _first_bad_bearing(arrays, where):
    """``<where>[i].<field>: <problem>`` of the first bearing whose fields fail the core's
    checks on their own (a range such as 1e-12 <= sigma <= 1000 rad), or None when only the
    set as a whole is bad."""
    for i, (p, az, el, saz, sel) in enumerate(zip(*arrays)):
        try:
            Bearing('', 0, p, float(az), float(el), float(saz), float(sel)).validate()
        except ValueError as exc:
            return f'{where}[{i}].{exc}'
    return None


def parse_request(doc, method_override=None):
    """Validate a request document; return (method, options, problems, is_batch).

    ``problems``: a list holding the one BearingSet of a one-problem request, or the
    :class:`batch_input.Problems` of a batch (checked column by column, same messages).
    """
    method, options = request_header(doc, TOP_FIELDS, 'bearings',
                                     registry.names(registry.MODE_MULTISTATION),
                                     registry.default_estimator(), method_override)
    if ('bearings' in doc) == ('problems' in doc):
        raise InputError('input: give exactly one of "bearings" (one problem) or "problems" '
                         '(a batch)')
    if 'bearings' in doc:
        return method, options, [parse_bearings(doc['bearings'])], False
    problems = doc['problems']
    if not isinstance(problems, list) or not problems:
        raise InputError('problems: must be a non-empty list of {"bearings": [...]} objects')
    return method, options, batch_input.json_problems(problems, parse_problem), True


def parse_problem(prob, k):
    """Problem ``k`` of a batch → one-problem BearingSet (InputError names problems[k])."""
    if not isinstance(prob, dict) or 'bearings' not in prob:
        raise InputError(f'problems[{k}]: must be an object with "bearings"')
    for key in prob:
        if key != 'bearings':
            raise InputError(f'problems[{k}].{key}: unknown field (expected bearings)')
    return parse_bearings(prob['bearings'], f'problems[{k}].bearings')


def solve(method, options, sets):
    """Run ``method`` on every problem; problems of equal N in one vectorised call.

    ``sets``: a :class:`batch_input.Problems` or a list of one-problem BearingSets.
    Returns one output dict per problem, in order (see module docstring).
    """
    return solve_groups(method, options, sets).dicts()


def solve_groups(method, options, sets):
    """Solve as :func:`solve` does; return the per-group arrays as :class:`Solved`."""
    if not isinstance(sets, batch_input.Problems):
        sets = batch_input.Problems.from_sets(sets)
    groups = []
    for idx, batch in sets.groups:
        try:
            res = registry.solve(method, batch, **options)
        except ValueError as exc:
            raise InputError(_name_problem(str(exc), idx, batch, sets.ids)) from None
        bound = registry.noise_crlb(method, res.position, batch, solve=res.solve, **options)
        groups.append((idx, res, bound))
    return Solved(method, groups, len(sets), sets.ids)


class Solved:
    """The fixes of one request, group by group: (indices, FixResult, CRLB) per bearing count.

    :meth:`dicts` gives the output objects of :func:`solve`.
    """

    def __init__(self, method, groups, count, ids=None):
        self.method = method
        self.groups = groups
        self.count = count
        self.ids = ids

    def dicts(self):
        """One output dict per problem, in order (module docstring)."""
        method = self.method
        out = [None] * self.count
        for idx, res, bound in self.groups:
            solved = res.solve.tolist() if res.solve is not None else ['3d'] * len(idx)
            for j, (k, pos, cov, crlb, conv, it, status) in enumerate(zip(
                    idx.tolist(), finite_rows(res.position), finite_rows(res.covariance),
                    finite_rows(bound), res.converged.tolist(), res.iterations.tolist(),
                    res.status.tolist())):
                out[k] = {'estimator': method, 'method': method, 'position': pos,
                          'covariance': cov, 'crlb': crlb, 'converged': bool(conv),
                          'iterations': int(it), 'status': str(status), 'solve': solved[j]}
                if solved[j] == 'horizontal':
                    out[k]['target_altitude'] = float(res.target_altitude[j])
                    out[k]['target_altitude_sigma'] = float(res.target_altitude_sigma[j])
                if res.excluded is not None:
                    out[k]['excluded'] = excluded_angles(res.excluded[j])
        if self.ids is not None:
            for r, problem in zip(out, self.ids):
                r['problem'] = problem
        return out


def excluded_angles(mask):
    """The ``excluded`` list of one robust fix: ``{"bearing": k, "angle": "azimuth" |
    "elevation"}`` for each angle the fix left out as an outlier (``mask`` (N, 2) bool of
    FixResult.excluded; k the bearing's index in the problem, 0-based)."""
    return [{'bearing': int(n), 'angle': ('azimuth', 'elevation')[int(a)]}
            for n, a in zip(*np.nonzero(mask))]


def _name_problem(message, idx, batch, ids):
    """Prefix a solve error about a missing target altitude with the first problem that has
    no elevation (``problem <id>`` of a table, ``problems[k]`` of a JSON batch)."""
    if not message.startswith('target_altitude:') or len(idx) < 1:
        return message
    az_only = np.flatnonzero(~np.any(batch.has_elevation, axis=1))
    if az_only.size == 0 or (len(idx) == 1 and ids is None):
        return message
    k = int(idx[az_only[0]])
    return f'problem {ids[k]}: {message}' if ids is not None else f'problems[{k}]: {message}'


def read_request(args):
    """The request of ``args.input``: (estimator, options, problems, is_batch).

    JSON documents go through :func:`parse_request`; CSV/NPZ bearing tables
    (cli.batch_input) take the estimator from ``--estimator`` (else the default) and its
    options from ``--options``, and always give a batch.
    """
    fmt = batch_input.input_format(args.input, getattr(args, 'format', 'auto'))
    override = getattr(args, 'options', None)
    if override is not None:
        try:
            override = json.loads(override)
        except (ValueError, RecursionError) as exc:
            raise InputError(f'--options: invalid JSON ({exc})') from None
        if not isinstance(override, dict):
            raise InputError('--options: must be a JSON object')
    if fmt == 'json':
        method, options, sets, batch = parse_request(read_json(args.input), args.estimator)
        return method, options if override is None else override, sets, batch
    method, options = request_header({'options': override or {}}, TOP_FIELDS, 'bearings',
                                     registry.names(registry.MODE_MULTISTATION),
                                     registry.default_estimator(), args.estimator)
    return method, options, batch_input.read_columnar(args.input, fmt), True


def run(args):
    """Entry point of the verb: read, validate, solve, print. Returns the exit code."""
    from . import gisargs
    gisargs.check(args)
    method, options, sets, batch = read_request(args)
    options = dimension_options(args, options)
    results = solve_groups(method, options, sets).dicts()
    unused_altitude_warning(options, results)
    gisargs.export_locate(args, results, sets)
    return write_results(results, batch, args.indent)


def unused_altitude_warning(options, results):
    """One stderr line when a stated target altitude went unused: the 3D solve (forced, or
    with ``dimension`` auto where the elevations observe the height) does not use it
    (core.horizontal)."""
    if options.get('target_altitude') is None:
        return
    n = sum(r['solve'] == '3d' for r in results)
    if n:
        what = 'the problem' if len(results) == 1 else f'{n} of {len(results)} problems'
        why = ('--dimension 3d' if options.get('dimension') == '3d' else
               'the elevations observe the height (solve 3d)')
        print(f'bearing_loc locate: warning: target_altitude not used for {what}: {why}; '
              '--dimension horizontal applies it', file=sys.stderr)
