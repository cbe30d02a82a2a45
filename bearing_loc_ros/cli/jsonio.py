"""JSON plumbing shared by the JSON-in/JSON-out verbs (``locate``, ``tma``).

Strict JSON both ways: input numbers must be finite reals; output NaN/inf become ``null``
so every consumer's parser accepts the result. Errors are :class:`InputError` naming the
field (exit code 2 through the dispatcher).
"""

import argparse
import json
import math
import numbers
import sys

import numpy as np
import orjson

from . import InputError, read_input
from .deprecation import json_key


def add_io_arguments(parser):
    """The positional ``input`` (file or stdin) and ``--indent`` flags of a JSON verb."""
    parser.add_argument('input', nargs='?', default='-',
                        help='input JSON file ("-" or absent: stdin)')
    parser.add_argument('--indent', type=_indent, default=None,
                        help='pretty-print the output with this indent (0-16 spaces)')


def _indent(text):
    """``--indent``: an integer number of spaces, 0 to 16."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected an integer, got {text!r}') from None
    if not 0 <= value <= 16:
        raise argparse.ArgumentTypeError(f'must be within 0..16 (got {value})')
    return value


def number(value, field, positive=False):
    """A finite real from JSON (bools rejected); ``positive`` requires > 0."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise InputError(f'{field}: must be a number, got {json.dumps(value)[:40]}')
    try:
        value = float(value)
    except OverflowError:       # a JSON integer beyond the float range (1e400)
        value = math.inf
    if not math.isfinite(value):
        raise InputError(f'{field}: must be a finite number')
    if positive and value <= 0:
        raise InputError(f'{field}: must be > 0')
    return value


def request_header(doc, top_fields, problem_key, names, default, override, kind='estimator',
                   canonical=None):
    """Check a request's top level; return (estimator name, options dict).

    ``doc`` must be an object whose keys are all in ``top_fields`` (the former key
    ``method`` is read as ``estimator``, with a deprecation warning). The estimator is
    ``override``, else ``doc["estimator"]``, else ``default``, mapped through ``canonical``
    (former names to current ones) when given, and must be one of ``names``; ``options``
    (default {}) must be an object.
    """
    if not isinstance(doc, dict):
        raise InputError(f'input: must be a JSON object with "{problem_key}" or "problems"')
    try:
        json_key(doc, 'method', 'estimator')
    except ValueError as exc:
        raise InputError(str(exc)) from None
    for key in doc:
        if key not in top_fields:
            raise InputError(f'{key}: unknown field (expected one of {", ".join(top_fields)})')
    given = doc.get('estimator')
    name = override or (default if given is None else given)
    if canonical is not None:
        name = canonical(name)
    if not isinstance(name, str) or name not in names:
        raise InputError(f'estimator: unknown {kind} {str(name)[:60]!r}; choose one of '
                         f'{", ".join(sorted(names))}')
    options = doc.get('options', {})
    if not isinstance(options, dict):
        raise InputError('options: must be an object')
    return name, options


def check_object(obj, where, fields):
    """Require ``obj`` to be a JSON object whose keys are all in ``fields`` (typos are errors)."""
    if not isinstance(obj, dict):
        raise InputError(f'{where}: must be an object')
    for key in obj:
        if key not in fields:
            raise InputError(f'{where}.{key}: unknown field (expected one of '
                             f'{", ".join(fields)})')


def finite_or_none(x):
    """Nested lists of floats with NaN/inf replaced by None (strict JSON null)."""
    if isinstance(x, list):
        return [finite_or_none(v) for v in x]
    return x if math.isfinite(x) else None


def finite_rows(array):
    """``array.tolist()`` row by row (first axis), NaN/inf as None, for JSON output.

    Equal to ``[finite_or_none(row.tolist()) for row in array]``; only rows holding a
    non-finite number are walked in Python (10,000 fixes: ~10 ms instead of ~250 ms).
    """
    rows = array.tolist()
    flat = array.reshape(len(array), -1)
    for j in np.flatnonzero(~np.isfinite(flat).all(axis=1)).tolist():
        rows[j] = finite_or_none(rows[j])
    return rows


def read_json(path):
    """Parse the JSON document in file ``path`` ('-' = stdin); InputError when unreadable
    (:func:`~bearing_loc_ros.cli.read_input`).

    orjson parses (an integer beyond 64 bits becomes a float); a document it rejects goes
    to the standard library's parser, which gives the error message and also reads what
    strict JSON lacks (NaN literals, a UTF-8 byte order mark) for the field checks to name.
    """
    data = read_input(path)
    try:
        return orjson.loads(data)
    except orjson.JSONDecodeError:
        pass
    try:
        return json.loads(data)
    except ValueError as exc:
        raise InputError(f'input: invalid JSON ({exc})') from None
    except RecursionError:
        raise InputError('input: invalid JSON (nested too deeply)') from None


def write_results(results, batch, indent=None):
    """Print ``{"results": [...]}`` for a batch request, else the single result.

    Compact JSON by orjson (NaN/inf written as ``null``), or ``json`` with ``indent``. A
    stdout that cannot be written is the dispatcher's (cli.main) one-line error.
    """
    payload = {'results': results} if batch else results[0]
    if indent is None:
        text = orjson.dumps(payload, option=orjson.OPT_SERIALIZE_NUMPY).decode()
    else:
        text = json.dumps(payload, allow_nan=False, indent=indent)
    sys.stdout.write(text + '\n')
    return 0
