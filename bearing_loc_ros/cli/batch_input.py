"""Large ``bearing_loc locate`` batches: vectorised JSON checks and columnar CSV/NPZ input.

The problems of a request end up in a :class:`Problems`: for every bearing count N one
validated (M_N, N) :class:`BearingSet` and the indices of its problems, so that each group is
solved in one vectorised call and nothing is built per problem.

JSON batches (``{"problems": [...]}``) are checked column by column with numpy under the
same rules as the per-problem parser of ``cli.locate`` (finite JSON numbers, |coordinate| <=
MAX_ABS_POSITION = 1e12 m, |θ| <= MAX_ABS_ANGLE = 1e4 rad, σ in [SIGMA_MIN, SIGMA_MAX] rad,
|ψ| < π/2, at least two bearings per problem; azimuth-only problems need the target altitude,
which the solve checks).
A problem that fails any rule is handed to that parser, which raises the one error message
naming the problem index and the field; problems are visited in order, so the message is the
same as checking one problem after the other.

Columnar input has one row per bearing (units: m and rad, or degrees in the ``_deg``
columns)::

    problem, x, y, z, azimuth, elevation, sigma_azimuth, sigma_elevation[, station]

``problem`` is an integer id; the rows of a problem need not be contiguous, results come in
the order of each id's first row. An empty or NaN elevation marks an azimuth-only bearing
(its ``sigma_elevation`` is then ignored). Each angle column may be given in degrees instead
(``azimuth_deg``, ``elevation_deg``, ``sigma_azimuth_deg``, ``sigma_elevation_deg``), not
both. A CSV has a header line naming the columns (any order); an NPZ holds one 1-D array per
column (``station`` a string array). A station id appears at most once per problem (empty
station cells name no station).
"""

from collections.abc import Sequence
import io
import itertools
import math
from operator import itemgetter

import numpy as np

from ..core.bearings import (BearingSet, HALF_PI, MAX_ABS_ANGLE, MAX_ABS_POSITION, SIGMA_MAX,
                             SIGMA_MIN)
from . import InputError, read_input

BEARING_FIELDS = frozenset(('station', 'position', 'azimuth', 'elevation', 'sigma_azimuth',
                            'sigma_elevation'))
_NUMBER_TYPES = frozenset((float, int))
_MISSING = object()
_STATION_TYPES = frozenset((str, object))
_NAN3 = [math.nan] * 3

#: Columnar input: quantity -> (column in rad/m, column in degrees or None, required).
COLUMNS = {
    'problem': ('problem', None, True),
    'x': ('x', None, True), 'y': ('y', None, True), 'z': ('z', None, True),
    'azimuth': ('azimuth', 'azimuth_deg', True),
    'elevation': ('elevation', 'elevation_deg', False),
    'sigma_azimuth': ('sigma_azimuth', 'sigma_azimuth_deg', True),
    'sigma_elevation': ('sigma_elevation', 'sigma_elevation_deg', False),
    'station': ('station', None, False),
}
KNOWN_COLUMNS = tuple(c for names in COLUMNS.values() for c in names[:2] if c)
FORMATS = ('json', 'csv', 'npz')


class Problems(Sequence):
    """Validated problems of one request, grouped by bearing count for vectorised solves.

    ``groups``: list of (indices (M_N,) int array, (M_N, N) BearingSet); ``counts[k]``
    bearings in problem k. ``stations``: the station id of every bearing, problem after
    problem (anything but a string: the default ``station_<i>``), or None; ``ids``: the
    columnar problem ids (None for JSON). Indexing gives problem k as a one-problem
    BearingSet with its station ids (what the geographic exports draw).
    """

    def __init__(self, groups, counts, stations=None, ids=None):
        self.groups = groups
        self.ids = ids
        self._stations = stations
        self._offsets = np.concatenate([[0], np.cumsum(counts)]).tolist()
        count = len(counts)
        self._where = np.zeros((count, 2), dtype=np.int64)
        for g, (idx, _) in enumerate(groups):
            self._where[idx, 0] = g
            self._where[idx, 1] = np.arange(len(idx))

    @classmethod
    def from_sets(cls, sets):
        """Group a list of one-problem BearingSets (validated) by bearing count."""
        by_n = {}
        for k, bs in enumerate(sets):
            by_n.setdefault(bs.N, []).append(k)
        groups = []
        for idx in by_n.values():
            groups.append((np.array(idx, dtype=np.int64), BearingSet(
                *(np.concatenate([getattr(sets[k], a) for k in idx])
                  for a in ('positions', 'azimuth', 'elevation', 'sigma_az', 'sigma_el')))))
        stations = [s for bs in sets for s in (bs.stations or [None] * bs.N)]
        return cls(groups, [bs.N for bs in sets], stations)

    def __len__(self):
        return len(self._where)

    def __getitem__(self, k):
        if not -len(self) <= k < len(self):
            raise IndexError(k)
        g, j = self._where[k].tolist()
        bs = self.groups[g][1].problem(j)
        names = ([None] * bs.N if self._stations is None else
                 self._stations[self._offsets[k]:self._offsets[k + 1]])
        bs.stations = [s if type(s) is str else f'station_{i}' for i, s in enumerate(names)]
        return bs


def number_columns(values):
    """A list of JSON values -> (float64 array, ok mask): ok where a finite number (not bool).

    Anything else (bool, string, None, an integer beyond the float range) gives NaN and
    False; the per-problem parser then names it.
    """
    if set(map(type, values)) <= _NUMBER_TYPES:
        try:
            arr = np.array(values, dtype=float)
            return arr, np.isfinite(arr)
        except OverflowError:
            pass
    arr = np.array([_float_or_nan(v) for v in values], dtype=float)
    return arr, np.isfinite(arr)


def _float_or_nan(v):
    if type(v) in _NUMBER_TYPES:
        try:
            return float(v)
        except OverflowError:
            return math.nan
    return math.nan


def sigma_ok(values):
    """σ within the accepted range [SIGMA_MIN, SIGMA_MAX] rad (False for NaN)."""
    return (values >= SIGMA_MIN) & (values <= SIGMA_MAX)


def json_problems(problems, parse_problem):
    """Validate a JSON ``problems`` list column by column; return :class:`Problems`.

    ``parse_problem(prob, k)`` is the per-problem parser (one-problem BearingSet or
    InputError naming ``problems[k]...``); it is called only for problems that fail the
    vectorised rules, in order, so the first bad problem raises its own message.
    """
    items = [p.get('bearings') if type(p) is dict and len(p) == 1 else None
             for p in problems]
    shaped = [type(it) is list and len(it) >= 2 for it in items]
    counts = np.array([len(it) if ok else 0 for it, ok in zip(items, shaped)], dtype=np.int64)
    flat = list(itertools.chain.from_iterable(itertools.compress(items, shaped)))
    # Whole-column passes in C first (map, set); per-bearing checks only when one fails.
    if set(map(type, flat)) == {dict} and all(map(BEARING_FIELDS.issuperset, flat)):
        good = np.ones(len(flat), dtype=bool)
        try:
            pos, az, saz = (list(map(itemgetter(key), flat))
                            for key in ('position', 'azimuth', 'sigma_azimuth'))
        except KeyError:
            good = None
    else:
        good = None
    if good is None:
        good = np.array([type(b) is dict and b.keys() <= BEARING_FIELDS and 'position' in b
                         and 'azimuth' in b and 'sigma_azimuth' in b for b in flat],
                        dtype=bool)
        if not good.all():
            flat = [b if g else {} for b, g in zip(flat, good.tolist())]
        pos, az, saz = ([b.get(key) for b in flat]
                        for key in ('position', 'azimuth', 'sigma_azimuth'))
    station = [b.get('station', _MISSING) for b in flat]
    if not set(map(type, station)) <= _STATION_TYPES:
        good &= np.array([s is _MISSING or type(s) is str for s in station], dtype=bool)
    if not (set(map(type, pos)) == {list} and set(map(len, pos)) == {3}):
        pos = [p if type(p) is list and len(p) == 3 else _NAN3 for p in pos]
    coords, c_ok = number_columns(list(itertools.chain.from_iterable(pos)))
    good &= (c_ok & (np.abs(coords) <= MAX_ABS_POSITION)).reshape(-1, 3).all(axis=1)
    az, ok = number_columns(az)
    good &= ok & (np.abs(az) <= MAX_ABS_ANGLE)
    saz, ok = number_columns(saz)
    good &= sigma_ok(saz)
    el_raw = [b.get('elevation') for b in flat]
    has_el = np.array([e is not None for e in el_raw], dtype=bool)
    el, el_ok = number_columns([0.0 if e is None else e for e in el_raw])
    sel_raw = [b.get('sigma_elevation') for b in flat]
    sel, _ = number_columns(sel_raw if has_el.all() else
                            [v if e is not None else 1.0 for v, e in zip(sel_raw, el_raw)])
    good &= ~has_el | (el_ok & (np.abs(el) < HALF_PI) & sigma_ok(sel))
    el[~has_el] = np.nan
    sel[~has_el] = np.nan
    owner = np.repeat(np.arange(len(problems)), counts)
    bad = ~np.array(shaped, dtype=bool)
    bad |= np.bincount(owner, weights=~good, minlength=len(problems)) > 0
    offsets = np.concatenate([[0], np.cumsum(counts)])
    bad |= _duplicate_station_problems(station, offsets)
    columns = [coords.reshape(-1, 3), az, el, saz, sel]
    for k in np.flatnonzero(bad).tolist():
        bs = parse_problem(problems[k], k)      # raises, naming problems[k] and the field
        rows = slice(offsets[k], offsets[k + 1])   # valid after all: take the parser's values
        for col, attr in zip(columns, ('positions', 'azimuth', 'elevation', 'sigma_az',
                                       'sigma_el')):
            col[rows] = getattr(bs, attr)[0]
        station[rows] = bs.stations
    return grouped(columns, counts, station)


def _duplicate_station_problems(station, offsets):
    """(K,) bool: problems naming one station id twice (unnamed bearing i is station_<i>)."""
    count = len(offsets) - 1
    types = set(map(type, station))
    if str not in types:
        return np.zeros(count, dtype=bool)
    counts = np.diff(offsets)
    if types != {str}:
        within = (np.arange(len(station)) - np.repeat(offsets[:-1], counts)).tolist()
        station = [s if type(s) is str else f'station_{i}' for s, i in zip(station, within)]
    owner = np.repeat(np.arange(count), counts)
    return _repeated(owner, _codes(station), count)


def _codes(names):
    """(R,) int64: the same code for equal names (first-seen order)."""
    codes = {name: k for k, name in enumerate(dict.fromkeys(names))}
    return np.fromiter(map(codes.__getitem__, names), dtype=np.int64, count=len(names))


def _repeated(owner, code, count):
    """(count,) bool: owners holding one code twice (sort-based, no np.unique)."""
    span = int(code.max(initial=0)) + 1
    key = np.sort(owner * span + code)
    dup = np.zeros(count, dtype=bool)
    dup[key[1:][key[1:] == key[:-1]] // span] = True
    return dup


def _first_duplicate_row(problem, station):
    """First row (input order) whose (problem, station) pair an earlier row already has.

    An empty station cell names no station, so empty cells never count as duplicates.
    """
    code = _codes(station)
    key = problem.astype(np.int64) * (int(code.max()) + 1) + code
    key = np.where(np.array([s == '' for s in station], dtype=bool),
                   -1 - np.arange(len(key)), key)
    order = np.argsort(key, kind='stable')
    repeat = np.flatnonzero(key[order][1:] == key[order][:-1])
    return int(order[repeat + 1].min()) if repeat.size else None


def unique_first(values):
    """``np.unique(values, return_index=True, return_inverse=True)`` of a 1-D array.

    By a stable sort: np.unique would import numpy.ma (20 ms) on a command's first call.
    """
    order = np.argsort(values, kind='stable')
    ordered = values[order]
    new = np.empty(len(values), dtype=bool)
    new[:1] = True
    np.not_equal(ordered[1:], ordered[:-1], out=new[1:])
    inverse = np.empty(len(values), dtype=np.int64)
    inverse[order] = np.cumsum(new) - 1
    return ordered[new], order[new], inverse


def grouped(columns, counts, stations=None, ids=None):
    """Flat per-bearing columns (problems contiguous, ``counts`` rows each) -> Problems."""
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
    groups = []
    for n in np.flatnonzero(np.bincount(counts)).tolist():      # np.unique imports numpy.ma
        idx = np.flatnonzero(counts == n)
        rows = (offsets[idx][:, None] + np.arange(n)).ravel()
        arrays = [c[rows].reshape((len(idx), n) + c.shape[1:]) for c in columns]
        try:
            bs = BearingSet(*arrays).validate(require_elevation=False)
        except ValueError as exc:   # not reached: the callers check every rule, naming the row
            raise InputError(f'problems: {exc}') from None
        groups.append((idx, bs))
    return Problems(groups, counts, stations, ids)


def input_format(path, fmt):
    """The input format: ``fmt`` unless 'auto', else by the file name (stdin: JSON)."""
    if fmt and fmt != 'auto':
        return fmt
    lower = str(path).lower()
    for ext in ('csv', 'npz'):
        if lower.endswith('.' + ext):
            return ext
    return 'json'


def read_columnar(path, fmt):
    """Read a CSV or NPZ bearing table (module doc); return validated :class:`Problems`."""
    if fmt == 'csv':
        columns, row_name = _read_csv(path)
    else:
        columns, row_name = _read_npz(path)
    return _table_problems(columns, row_name)


def _read_source(path, binary):
    """The bytes of file ``path`` ('-': stdin), or (not ``binary``) its UTF-8 text without a
    leading byte order mark (Excel writes one) and without newline translation, the same
    from a file and from stdin. InputError naming ``input``."""
    data = read_input(path)
    if binary:
        return data
    try:
        return data.decode('utf-8-sig')
    except UnicodeDecodeError:
        raise InputError('input: the CSV is not UTF-8 text') from None


def _check_header(names):
    for name in names:
        if name not in KNOWN_COLUMNS:
            raise InputError(f'input: unknown column {name!r} (expected '
                             f'{", ".join(KNOWN_COLUMNS)})')
    if len(set(names)) != len(names):
        raise InputError('input: a column appears twice')
    for quantity, (rad, deg, required) in COLUMNS.items():
        if rad in names and deg in names:
            raise InputError(f'input: give {rad} or {deg}, not both')
        if required and rad not in names and deg not in names:
            raise InputError(f'input: missing column {rad}')


def _read_csv(path):
    import csv
    text = _read_source(path, binary=False)
    try:
        reader = csv.reader(io.StringIO(text))
        header = [h.strip() for h in next(reader, [])]
        if not header:
            raise InputError('input: empty CSV (expected a header line naming the columns)')
        _check_header(header)
        fast = False
        try:
            rows = list(reader)
            fast = set(map(len, rows)) == {len(header)} and reader.line_num == len(rows) + 1
        except csv.Error:
            pass
        if fast:
            lines = range(2, len(rows) + 2)     # one line per row, none blank or wrong
        else:       # row by row, so that the first problem met is the one reported
            rows, lines = _csv_rows(csv.reader(io.StringIO(text)), len(header))
    except csv.Error as exc:
        raise InputError(f'input: invalid CSV ({exc})') from None
    if not rows:
        raise InputError('input: no bearing rows')
    columns_text = list(zip(*rows))
    if fast and not _inner_space(text):     # no field has anything to strip
        columns_text = [list(col) for col in columns_text]
    else:
        columns_text = [[v.strip() for v in col] for col in columns_text]
    columns = {'problem': _csv_integers(columns_text[header.index('problem')], lines)}
    for name, col in zip(header, columns_text):
        if name == 'station':
            columns[name] = col
        elif name != 'problem':
            columns[name] = _csv_floats(col, name, lines, columns['problem'])
    return columns, lambda r: f'line {lines[r]}'


def _inner_space(text):
    """Whether a one-line-per-row CSV may hold what str.strip() removes from a field: any
    whitespace but the line ends (\\n, \\r\\n); non-ASCII text is assumed to."""
    if not text.isascii() or any(c in text for c in ' \t\x0b\x0c\x1c\x1d\x1e\x1f'):
        return True
    return text.count('\r') != text.count('\r\n')


def _csv_rows(reader, width):
    """The non-blank rows of ``reader`` and their line numbers; InputError at a row that has
    not ``width`` fields."""
    rows, lines = [], []
    next(reader, None)
    for row in reader:
        if not row:
            continue
        if len(row) != width:
            raise InputError(f'line {reader.line_num}: {len(row)} fields, the header has '
                             f'{width}')
        rows.append(row)
        lines.append(reader.line_num)
    return rows, lines


def _garbled(col):
    """Index of the first field with digit-group underscores or non-ASCII characters, or
    None. numpy and float() read '1_5' as 15 and full-width digits as digits: in a data file
    such a field is garbled, not that number."""
    text = ''.join(col)
    if text.isascii() and '_' not in text:
        return None
    return next(k for k, s in enumerate(col) if not s.isascii() or '_' in s)


def _csv_floats(col, name, lines, ids):
    """Text column -> float array; empty = NaN (a missing value, judged by the rules)."""
    bad = _garbled(col)
    if bad is None:
        try:
            return np.array([s or 'nan' for s in col], dtype=float)
        except ValueError:
            pass
    for k, (line, problem, s) in enumerate(zip(lines, ids.tolist(), col)):
        try:
            if k == bad:
                raise ValueError(s)
            float(s or 'nan')
        except ValueError:
            raise InputError(f'line {line} (problem {problem}): {name}: must be a number, got '
                             f'{s[:40]!r}') from None
    raise AssertionError('unreachable')


def _csv_integers(col, lines):
    bad = _garbled(col)
    if bad is None:
        try:
            return np.array(col, dtype=np.int64)
        except (ValueError, OverflowError):
            pass
    for k, (line, s) in enumerate(zip(lines, col)):
        try:
            if k == bad:
                raise ValueError(s)
            np.int64(int(s))
        except (ValueError, OverflowError):
            raise InputError(f'line {line}: problem: must be an integer id, got {s[:40]!r}') \
                from None
    raise AssertionError('unreachable')


#: Leading bytes of a zip archive (local file header, or the end record of an empty one).
ZIP_MAGIC = (b'PK\x03\x04', b'PK\x05\x06')


def _read_npz(path):
    import zipfile      # here: a JSON request does not need it
    data = _read_source(path, binary=True)
    # np.load would take any other bytes for a pickle (or a single .npy array) and report that
    if not data.startswith(ZIP_MAGIC):
        raise InputError('input: not an NPZ archive (expected a zip of .npy arrays, as '
                         'numpy.savez writes)')
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            names = list(npz.files)
            _check_header(names)
            arrays = {name: npz[name] for name in names}
    except (ValueError, OSError, zipfile.BadZipFile, EOFError) as exc:
        raise InputError(f'input: not a readable NPZ file ({str(exc)[:80]})') from None
    lengths = set()
    for name, a in arrays.items():
        if a.ndim != 1:
            raise InputError(f'{name}: must be a 1-D array, got shape {a.shape}')
        lengths.add(len(a))
        if name == 'station':
            if a.dtype.kind not in 'US':
                raise InputError('station: must be an array of strings')
        elif a.dtype.kind not in 'iuf':
            raise InputError(f'{name}: must be a numeric array, got dtype {a.dtype}')
    if len(lengths) != 1:
        raise InputError('input: the NPZ columns have different lengths')
    if not lengths.pop():
        raise InputError('input: no bearing rows')
    columns = {}
    for name, a in arrays.items():
        if name == 'station':
            columns[name] = [s.decode('utf-8', 'replace') if isinstance(s, bytes) else str(s)
                             for s in a.tolist()]
        elif name == 'problem':
            if a.dtype.kind == 'f':
                bad = ~(np.isfinite(a) & (a == np.round(a)) & (np.abs(a) < 2.0 ** 62))
                if bad.any():
                    r = int(np.argmax(bad))
                    raise InputError(f'row {r}: problem: must be an integer id, got '
                                     f'{a[r].item()!r}')
            elif a.dtype.kind == 'u' and a.max() > np.iinfo(np.int64).max:
                # (a CSV id must fit int64 too; unsigned 64-bit ids beyond it would wrap)
                r = int(np.argmax(a > np.iinfo(np.int64).max))
                raise InputError(f'row {r}: problem: integer id {int(a[r])} is beyond the '
                                 '64-bit signed range')
            columns[name] = a.astype(np.int64)
        else:
            columns[name] = a.astype(float)
    return columns, lambda r: f'row {r}'


def _table_problems(columns, row_name):
    """Checked, converted, grouped columnar bearings (rules and messages: module doc)."""
    def angle(quantity):
        rad, deg, _ = COLUMNS[quantity]
        if deg in columns:
            return np.radians(columns[deg]), deg
        return columns.get(rad), rad

    ids = columns['problem']
    n = len(ids)
    pos = np.stack([columns['x'], columns['y'], columns['z']], axis=1)
    az, az_name = angle('azimuth')
    saz, saz_name = angle('sigma_azimuth')
    el, el_name = angle('elevation')
    sel, sel_name = angle('sigma_elevation')
    if el is None:
        el, el_name = np.full(n, np.nan), COLUMNS['elevation'][0]
    if sel is None:
        sel, sel_name = np.full(n, np.nan), COLUMNS['sigma_elevation'][0]
    has_el = ~np.isnan(el)
    given = has_el & ~np.isnan(sel)
    checks = [(~np.isfinite(pos[:, k]), f'{c}: must be a finite number')
              for k, c in enumerate('xyz')]
    checks += [(np.abs(pos[:, k]) > MAX_ABS_POSITION,
                f'{c}: |coordinate| must be <= {MAX_ABS_POSITION:g} m')
               for k, c in enumerate('xyz')]
    az_bound = f'{MAX_ABS_ANGLE:g} rad' + (f' ({math.degrees(MAX_ABS_ANGLE):.0f} deg)'
                                           if az_name.endswith('_deg') else '')
    checks += [
        (~np.isfinite(az), f'{az_name}: must be a finite number'),
        (np.abs(az) > MAX_ABS_ANGLE, f'{az_name}: |azimuth| must be <= {az_bound}'),
        (~np.isfinite(saz), f'{saz_name}: must be a finite number'),
        (saz <= 0, f'{saz_name}: must be > 0'),
        (has_el & ~np.isfinite(el), f'{el_name}: must be a finite number or empty '
                                    '(azimuth-only)'),
        (has_el & (np.abs(el) >= HALF_PI), f'{el_name}: |elevation| must be < pi/2 rad'),
        (has_el & np.isnan(sel), f'{sel_name}: missing (required when elevation is given)'),
        (given & ~np.isfinite(sel), f'{sel_name}: must be a finite number'),
        (given & (sel <= 0), f'{sel_name}: must be > 0'),
        (~sigma_ok(saz), f'{saz_name}: must be in [{SIGMA_MIN:g}, {SIGMA_MAX:g}] rad'),
        (given & ~sigma_ok(sel), f'{sel_name}: must be in [{SIGMA_MIN:g}, {SIGMA_MAX:g}] rad'),
    ]
    bad = np.zeros(n, dtype=bool)
    for mask, _ in checks:
        bad |= mask
    if bad.any():
        r = int(np.argmax(bad))
        message = next(m for mask, m in checks if mask[r])
        raise InputError(f'{row_name(r)} (problem {ids[r]}): {message}')
    uniq, first, inverse = unique_first(ids)
    rank = np.empty(len(uniq), dtype=np.int64)
    rank[np.argsort(first, kind='stable')] = np.arange(len(uniq))
    problem = rank[inverse.ravel()]
    station = columns.get('station')
    if station is not None:
        r = _first_duplicate_row(problem, station)
        if r is not None:
            raise InputError(f'{row_name(r)} (problem {ids[r]}): station: duplicate station '
                             f'id {station[r]!r}')
    order = np.argsort(problem, kind='stable')
    counts = np.bincount(problem, minlength=len(uniq))
    in_order = ids[np.sort(first)]
    # Azimuth-only problems are valid input: the solve needs the stated target altitude
    # then (core.registry.solve names it), so only the count is checked here.
    for k in np.flatnonzero(counts < 2).tolist()[:1]:
        raise InputError(f'problem {in_order[k]}: {counts[k]} bearing(s); a fix needs at '
                         'least two')
    sel = np.where(has_el, sel, np.nan)
    cols = [pos[order], az[order], el[order], saz[order], sel[order]]
    if station is not None:
        station = [station[r] for r in order.tolist()]
    return grouped(cols, counts, station, in_order.tolist())
