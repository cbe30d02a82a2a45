"""``bearing_loc locate`` on large batches: the vectorised JSON checks give the same problems
and the same error messages as checking problem by problem (also deep inside a batch), and
the CSV/NPZ bearing tables give the same fixes as the JSON request."""
import copy
import csv
import json

import numpy as np
import pytest

from bearing_loc_ros.cli import InputError, main
from bearing_loc_ros.cli import batch_input
from bearing_loc_ros.cli.locate import parse_problem, parse_request
from bearing_loc_ros.core.bearings import simulate_bearings

STATIONS = np.array([[30.0, -10.0, 0.1], [30.0, 20.0, 0.2], [-30.0, 5.0, 0.15],
                     [0.0, -40.0, 0.3]]) * 1e3
SIGMA = 1.5e-3


def make_problems(m, seed=0):
    """m problems of 3 or 4 bearings, some azimuth-only, some with station ids or ints."""
    rng = np.random.default_rng(seed)
    targets = np.array([10e3, 20e3, 5e3]) + rng.normal(0, 2e3, (m, 3))
    probs = []
    for k in range(m):
        n = 3 + k % 2
        bs = simulate_bearings(targets[k], STATIONS[:n], SIGMA, rng=rng)
        items = []
        for i in range(n):
            b = {'position': bs.positions[0, i].tolist(), 'azimuth': float(bs.azimuth[0, i]),
                 'sigma_azimuth': SIGMA if k % 3 else 2}       # an int sigma (2 rad) is valid
            if k % 5:
                b['station'] = f's{i}'
            if i == 2 and k % 4 == 0:
                b['elevation'] = None
                b['sigma_elevation'] = 'ignored without an elevation'
            elif not (i == 3 and k % 7 == 0):
                b['elevation'] = float(bs.elevation[0, i])
                b['sigma_elevation'] = SIGMA
            if k % 11 == 0:
                b['position'] = [int(round(v)) for v in b['position']]
            items.append(b)
        probs.append({'bearings': items})
    return probs


def slow_problems(probs):
    """The reference: every problem through the per-problem parser."""
    return [parse_problem(p, k) for k, p in enumerate(probs)]


def test_vectorised_batch_equals_problem_by_problem():
    probs = make_problems(300)
    _, _, fast, batch = parse_request({'problems': probs})
    slow = slow_problems(probs)
    assert batch and len(fast) == len(slow) == 300
    assert {bs.N for _, bs in fast.groups} == {3, 4}
    for k in range(300):
        a, b = fast[k], slow[k]
        for attr in ('positions', 'azimuth', 'elevation', 'sigma_az', 'sigma_el'):
            np.testing.assert_array_equal(getattr(a, attr), getattr(b, attr))
        assert a.stations == b.stations


MUTATIONS = [
    (lambda b: b[1].update(sigma_azimuth=0.0), 'bearings[1].sigma_azimuth: must be > 0'),
    (lambda b: b[1].update(sigma_azimuth=1e-300), 'bearings[1].sigma_azimuth: must be finite'),
    (lambda b: b[0].update(sigma_azimuth=True), 'bearings[0].sigma_azimuth: must be a number'),
    (lambda b: b[0].update(azimuth='north'), 'bearings[0].azimuth: must be a number'),
    (lambda b: b[0].update(azimuth=10 ** 400), 'bearings[0].azimuth: must be a finite number'),
    (lambda b: b[2].update(position=[1.0, 2.0]), 'bearings[2].position: must be a list'),
    (lambda b: b[2].update(position=[1.0, 2.0, None]),
     'bearings[2].position[2]: must be a number'),
    (lambda b: b[0].update(elevation=2.0), 'bearings[0].elevation: |elevation| must be < pi/2'),
    (lambda b: b[0].update(elevation='up'), 'bearings[0].elevation: must be a number'),
    (lambda b: b[1].pop('sigma_elevation'), 'bearings[1].sigma_elevation: missing'),
    (lambda b: b[1].update(sigma_elevation=-1), 'bearings[1].sigma_elevation: must be > 0'),
    (lambda b: b[1].pop('azimuth'), 'bearings[1].azimuth: missing'),
    (lambda b: b[1].update(colour='red'), 'bearings[1].colour: unknown field'),
    (lambda b: b[1].update(station=7), 'bearings[1].station: must be a string'),
    (lambda b: b[2].update(station='s0'), "bearings[2].station: duplicate station id 's0'"),
    (lambda b: b.__setitem__(0, 5), 'bearings[0]: must be an object'),
    (lambda b: b.__delitem__(slice(1, None)), 'bearings: 1 bearing(s)'),
    # the core's bounds on finite numbers (core.bearings MAX_ABS_POSITION, MAX_ABS_ANGLE)
    (lambda b: b[2]['position'].__setitem__(0, 2e12),
     'bearings[2].position: |coordinate| must be <= 1e+12 m'),
    (lambda b: b[1].update(azimuth=-2e4), 'bearings[1].azimuth: |azimuth| must be <= 10000 rad'),
]


@pytest.mark.parametrize('mutate, message', MUTATIONS)
def test_error_deep_in_a_batch_names_problem_and_field(mutate, message):
    probs = make_problems(2000, seed=1)
    mutate(probs[1733]['bearings'])
    with pytest.raises(InputError) as fast:
        parse_request({'problems': probs})
    with pytest.raises(InputError) as slow:
        parse_problem(probs[1733], 1733)
    assert str(fast.value) == str(slow.value)
    assert str(fast.value).startswith('problems[1733].' + message), str(fast.value)


@pytest.mark.parametrize('bad, message', [
    (5, 'problems[1500]: must be an object with "bearings"'),
    ({'bearings': [], 'note': 1}, 'problems[1500].note: unknown field'),
    ({'bearings': {}}, 'problems[1500].bearings: must be a list'),
])
def test_bad_problem_object_deep_in_a_batch(bad, message):
    probs = make_problems(1600)
    probs[1500] = bad
    with pytest.raises(InputError, match=message.replace('[', r'\[').replace(']', r'\]')):
        parse_request({'problems': probs})


def test_first_bad_problem_is_reported(tmp_path, capsys):
    probs = make_problems(1200)
    probs[900]['bearings'][0]['azimuth'] = 'x'
    probs[400]['bearings'][2]['sigma_azimuth'] = -1.0
    path = tmp_path / 'in.json'
    path.write_text(json.dumps({'problems': probs}))
    assert main(['locate', str(path)]) == 2
    out, err = capsys.readouterr()
    assert out == ''
    assert err.splitlines() == ['bearing_loc locate: error: problems[400].bearings[2].'
                                'sigma_azimuth: must be > 0']


def table_rows(probs, degrees=False):
    """The problems as bearing-table rows (problem id 100 + k), columns of the module doc."""
    rows = []
    for k, p in enumerate(probs):
        for b in p['bearings']:
            el = b.get('elevation')
            angles = [b['azimuth'], np.nan if el is None else el, b['sigma_azimuth'],
                      np.nan if el is None else b['sigma_elevation']]
            if degrees:
                angles = np.degrees(angles).tolist()
            rows.append([100 + k, *b['position'], *angles, b.get('station', '')])
    return rows


def header(degrees=False):
    angles = ['azimuth', 'elevation', 'sigma_azimuth', 'sigma_elevation']
    return ['problem', 'x', 'y', 'z'] + [a + '_deg' if degrees else a for a in angles] + [
        'station']


def write_csv(path, head, rows):
    with open(path, 'w', newline='') as f:
        w = csv.writer(f)
        w.writerow(head)
        for r in rows:
            w.writerow(['' if isinstance(v, float) and np.isnan(v) else
                        (repr(v) if isinstance(v, float) else v) for v in r])


def run(argv, capsys):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def json_results(tmp_path, probs, capsys, *extra):
    path = tmp_path / 'in.json'
    path.write_text(json.dumps({'estimator': 'mle', 'problems': probs}))
    code, out, err = run(['locate', str(path), *extra], capsys)
    assert code == 0, err
    return json.loads(out)['results']


def valid_problems(m):
    """make_problems without the NaN-free quirks tables cannot express (int sigma kept)."""
    probs = make_problems(m, seed=3)
    for p in probs:
        for b in p['bearings']:
            if b.get('elevation') is None:
                b.pop('sigma_elevation', None)
    return probs


def test_csv_table_gives_the_json_results(tmp_path, capsys):
    probs = valid_problems(60)
    expect = json_results(tmp_path, probs, capsys)
    rows = table_rows(probs)
    order = np.random.default_rng(0).permutation(len(rows))   # rows of a problem scattered
    first_seen = list(dict.fromkeys(rows[i][0] for i in order))
    write_csv(tmp_path / 't.csv', header(), [rows[i] for i in order])
    code, out, err = run(['locate', str(tmp_path / 't.csv'), '--estimator', 'mle'], capsys)
    assert code == 0, err
    got = json.loads(out)['results']
    assert [r['problem'] for r in got] == first_seen
    by_id = {r['problem']: r for r in got}
    for k, r in enumerate(expect):
        t = by_id[100 + k]
        # Bearing order inside a problem is kept, so the solve is the same to rounding (a
        # fix in doubt is refitted by the robust default of mle from the estimator's fix,
        # and the refit stops within 1e-10 of the rms range: equal to that).
        np.testing.assert_allclose(t['position'], r['position'], rtol=1e-9)
        np.testing.assert_allclose(t['covariance'], r['covariance'], rtol=1e-9)
        assert t['status'] == r['status'] and t['iterations'] == r['iterations']


def test_degree_columns_and_npz_equal_the_radian_csv(tmp_path, capsys):
    probs = valid_problems(30)
    rows = table_rows(probs)
    write_csv(tmp_path / 'rad.csv', header(), rows)
    write_csv(tmp_path / 'deg.csv', header(True), table_rows(probs, degrees=True))
    cols = list(zip(*rows))
    np.savez(tmp_path / 't.npz', problem=np.array(cols[0]),
             **{h: np.array(c, dtype=float) for h, c in zip(header()[1:8], cols[1:8])},
             station=np.array(cols[8]))
    outs = []
    for name in ('rad.csv', 'deg.csv', 't.npz'):
        code, out, err = run(['locate', str(tmp_path / name)], capsys)
        assert code == 0, err
        outs.append(json.loads(out)['results'])
    for a, b, c in zip(*outs):
        assert a['problem'] == b['problem'] == c['problem']
        assert a['position'] == c['position']
        np.testing.assert_allclose(b['position'], a['position'], rtol=1e-9)


def test_table_station_ids_reach_the_problems(tmp_path):
    probs = valid_problems(5)
    write_csv(tmp_path / 't.csv', header(), table_rows(probs))
    problems = batch_input.read_columnar(str(tmp_path / 't.csv'), 'csv')
    assert problems.ids == [100, 101, 102, 103, 104]
    assert problems[1].stations == ['s0', 's1', 's2', 's3']
    assert problems[0].stations == ['', '', '']      # an empty station cell is kept as ''


def test_options_flag_reaches_the_estimator(tmp_path, capsys):
    probs = valid_problems(4)
    write_csv(tmp_path / 't.csv', header(), table_rows(probs))
    code, out, _ = run(['locate', str(tmp_path / 't.csv'), '--options',
                        '{"max_iterations": 1}'], capsys)
    assert code == 0
    assert {r['iterations'] for r in json.loads(out)['results']} == {1}
    code, out, err = run(['locate', str(tmp_path / 't.csv'), '--options', '{"bogus": 1}'],
                         capsys)
    assert code == 2 and out == '' and 'options.bogus: unknown option' in err


def table_error(tmp_path, capsys, rows, head=None, name='t.csv'):
    write_csv(tmp_path / name, head or header(), rows)
    code, out, err = run(['locate', str(tmp_path / name)], capsys)
    assert code == 2 and out == '' and len(err.splitlines()) == 1, err
    return err.strip().removeprefix('bearing_loc locate: error: ')


@pytest.mark.parametrize('column, value, message', [
    (7, 0.0, 'sigma_elevation: must be > 0'),
    (6, -1e-3, 'sigma_azimuth: must be > 0'),
    (6, 1e-300, 'sigma_azimuth: must be in [1e-12, 1000] rad'),
    (4, float('inf'), 'azimuth: must be a finite number'),
    (5, 2.0, 'elevation: |elevation| must be < pi/2 rad'),
    (7, float('nan'), 'sigma_elevation: missing (required when elevation is given)'),
    (1, 'east', 'x: must be a number'),
    (0, '1.5', 'problem: must be an integer id'),
    (0, '1_5', 'problem: must be an integer id'),           # int() would read 15
    (3, '1_0', 'z: must be a number'),                      # float() would read 10
    (3, '\uff11\uff10', 'z: must be a number'),                 # full-width digits
    (2, -2e12, 'y: |coordinate| must be <= 1e+12 m'),
    (4, 2e4, 'azimuth: |azimuth| must be <= 10000 rad'),
])
def test_table_error_names_line_problem_and_column(tmp_path, capsys, column, value, message):
    rows = table_rows(valid_problems(1500))
    r = 4000
    rows[r][column] = value
    # Line numbers count the header: data row r is on line r + 2.
    expect = f'line {r + 2}' + ('' if column == 0 else f' (problem {rows[r][0]})')
    err = table_error(tmp_path, capsys, rows)
    assert err.startswith(f'{expect}: {message}'), err


@pytest.mark.parametrize('edit, message', [
    (lambda h, rows: (h + ['colour'], [r + ['red'] for r in rows]),
     "input: unknown column 'colour'"),
    (lambda h, rows: ([c for c in h if c != 'azimuth'], [r[:4] + r[5:] for r in rows]),
     'input: missing column azimuth'),
    (lambda h, rows: (h + ['azimuth_deg'], [r + [1.0] for r in rows]),
     'input: give azimuth or azimuth_deg, not both'),
    (lambda h, rows: (h, [r for r in rows if not (r[0] == 103 and r[-1] != 's0')]),
     'problem 103: 1 bearing(s); a fix needs at least two'),
    (lambda h, rows: (h, [r[:5] + [float('nan')] + r[6:] if r[0] == 102 else r
                          for r in rows]),
     'problem 102: target_altitude: required'),
    (lambda h, rows: (h, rows[:3] + [rows[3][:-2]] + rows[4:]),
     'line 5: 7 fields, the header has 9'),
])
def test_table_structure_errors(tmp_path, capsys, edit, message):
    h, rows = edit(header(), table_rows(valid_problems(6)))
    assert table_error(tmp_path, capsys, rows, h).startswith(message)


def test_one_problem_with_a_station_twice_is_refused(tmp_path, capsys):
    probs = make_problems(2)
    probs[1]['bearings'][1]['station'] = 's0'
    path = tmp_path / 'one.json'
    path.write_text(json.dumps(probs[1]))
    code, out, err = run(['locate', str(path)], capsys)
    assert code == 2 and out == ''
    assert err.splitlines() == ["bearing_loc locate: error: bearings[1].station: duplicate "
                                "station id 's0'"]
    # an unnamed bearing i is station_<i>: naming another one so is a duplicate too
    bearings = make_problems(1)[0]['bearings']
    bearings[1]['station'] = 'station_0'
    with pytest.raises(InputError, match=r"bearings\[1\]\.station: duplicate station id"):
        parse_request({'bearings': bearings})


def test_table_station_named_twice_in_a_problem(tmp_path, capsys):
    rows = table_rows(valid_problems(1500))
    # the first row from 4000 on that follows a named row of its own problem
    r = next(r for r in range(4000, len(rows))
             if rows[r][-1] and rows[r - 1][0] == rows[r][0] and rows[r - 1][-1])
    rows[r][-1] = rows[r - 1][-1]
    err = table_error(tmp_path, capsys, rows)
    assert err == (f'line {r + 2} (problem {rows[r][0]}): station: duplicate station id '
                   f'{rows[r][-1]!r}'), err
    # the same id in different problems, and empty cells, are fine
    rows = table_rows(valid_problems(6))
    write_csv(tmp_path / 'ok.csv', header(), rows)
    assert main(['locate', str(tmp_path / 'ok.csv')]) == 0


def test_npz_errors(tmp_path, capsys):
    base = {'problem': np.array([0, 0]), 'x': np.zeros(2), 'y': np.array([0.0, 1e3]),
            'z': np.zeros(2), 'azimuth': np.array([0.5, 1.0]), 'elevation': np.array([0.1, 0.1]),
            'sigma_azimuth': np.full(2, 1e-3), 'sigma_elevation': np.full(2, 1e-3)}
    cases = [({'x': np.array(['a', 'b'])}, 'x: must be a numeric array'),
             ({'y': np.zeros(3)}, 'input: the NPZ columns have different lengths'),
             ({'problem': np.array([0.0, 0.5])}, 'row 1: problem: must be an integer id'),
             ({'problem': np.array([2**63 - 1, 2**63], dtype=np.uint64)},
              'row 1: problem: integer id 9223372036854775808 is beyond the 64-bit'),
             ({'sigma_azimuth': np.array([1e-3, 0.0])},
              'row 1 (problem 0): sigma_azimuth: must be > 0')]
    for change, message in cases:
        np.savez(tmp_path / 'b.npz', **dict(base, **change))
        code, out, err = run(['locate', str(tmp_path / 'b.npz')], capsys)
        assert code == 2 and out == '' and message in err, (message, err)
    # text, a single .npy array and a damaged zip: one line naming the problem, exit 2
    np.save(tmp_path / 'one.npy', np.zeros(3))
    for name, data in (('c.npz', b'not a zip'), ('d.npz', b''),
                       ('e.npz', (tmp_path / 'one.npy').read_bytes()),
                       ('f.npz', b'PK\x03\x04' + b'\0' * 40)):
        (tmp_path / name).write_bytes(data)
        code, out, err = run(['locate', str(tmp_path / name)], capsys)
        assert code == 2 and out == '' and len(err.splitlines()) == 1, (name, err)
        assert 'pickle' not in err, (name, err)
        expect = 'not a readable NPZ file' if name == 'f.npz' else 'not an NPZ archive'
        assert f'input: {expect}' in err, (name, err)
    np.savez(tmp_path / 'ok.npz', **base)
    code, out, err = run(['locate', str(tmp_path / 'ok.npz')], capsys)
    assert code == 0 and json.loads(out)['results'][0]['problem'] == 0


def test_json_batch_and_export_see_the_same_problems(tmp_path):
    probs = make_problems(12)
    _, _, fast, _ = parse_request({'problems': copy.deepcopy(probs)})
    names = [bs.stations for bs in fast]
    assert names[0] == ['station_0', 'station_1', 'station_2']     # no ids given
    assert names[1] == ['s0', 's1', 's2', 's3']


def _mixed_solved(ids=None):
    """Solved groups with finite, degenerate (NaN / inf) and horizontal fixes."""
    from bearing_loc_ros.cli.locate import solve_groups
    probs = make_problems(40, seed=7)
    # two degenerate problems: the target on the baseline of two stations (no fix: NaN/inf)
    for k in (5, 12):
        probs[k]['bearings'] = [
            {'position': [x, 0.0, 0.0], 'azimuth': 0.0, 'elevation': 0.0,
             'sigma_azimuth': SIGMA, 'sigma_elevation': SIGMA} for x in (0.0, 1000.0)]
    _, _, problems, _ = parse_request({'problems': probs})
    if ids is not None:
        problems.ids = ids
    options = {'target_altitude': 5000.0, 'target_altitude_sigma': 10.0}
    return solve_groups('mle', options, problems)


def _strict(text):
    """json.loads that refuses NaN/Infinity literals (the output must be strict JSON)."""
    def refuse(name):
        raise AssertionError(f'non-strict JSON constant {name}')
    return json.loads(text, parse_constant=refuse)


@pytest.mark.parametrize('ids', [None, list(range(100, 140))])
@pytest.mark.parametrize('indent', [None, 2])
def test_json_output_is_the_result_dicts(ids, indent, capsys):
    from bearing_loc_ros.cli.jsonio import write_results
    dicts = _mixed_solved(ids).dicts()
    assert {r['solve'] for r in dicts} == {'3d', 'horizontal'}
    assert any(r['position'] is None or None in r['position'] for r in dicts)
    assert any(None in sum(r['covariance'], []) for r in dicts)
    for batch, expect in ((True, {'results': dicts}), (False, dicts[0])):
        assert write_results(dicts, batch, indent) == 0
        out = capsys.readouterr().out
        assert out.endswith('}\n')
        if indent is None:
            assert out.count('\n') == 1        # compact: one line
        # every float read back to the bit, every non-finite number as null
        assert _strict(out) == expect
