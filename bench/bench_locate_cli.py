"""End-to-end time of ``bearing_loc locate`` on a large batch (prints figures; no assertions).

Writes M (default 10,000) three-station problems (mle, σ = 1.5 mrad, one azimuth-only
station in every fourth problem) as a JSON request, a CSV bearing table and an NPZ bearing
table, then times, in one run and interleaved so machine load hits every row alike:

* ``bearing_loc locate --help``: interpreter start-up and imports, the floor of any call;
  the commands run with a bytecode cache (in the temporary folder), as an installed package
  does, unless ``--no-bytecode-cache``;
* ``bearing_loc locate`` on each input (subprocess wall clock and CPU time, output to a
  file; on a shared machine the CPU time is the steadier figure);
* ``python -c pass``: the interpreter and its site start-up alone (in this virtualenv
  that includes the ROS wheels' re-exec of the interpreter and the editable-install finder);
* in-process: reading the JSON request (``jsonio.read_json``), checking it, the solve
  (``registry.solve`` and ``registry.noise_crlb`` per bearing count) and the JSON output.

Each figure is the median of ``--repeat`` runs with its min-max spread. The three inputs must
give the same fixes (checked and printed).

Run: ``.venv/bin/python bench/bench_locate_cli.py [--problems 10000] [--repeat 5]``.
"""

import argparse
import contextlib
import csv
import io
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from bearing_loc_ros.core.bearings import simulate_bearings  # noqa: E402

STATIONS = np.array([[30.0, -10.0, 0.1], [30.0, 20.0, 0.2], [-30.0, 5.0, 0.15]]) * 1e3
SIGMA = 1.5e-3


def write_inputs(folder, m, seed=0):
    """The same M problems as input.json, input.csv and input.npz in ``folder``."""
    rng = np.random.default_rng(seed)
    targets = np.array([10e3, 20e3, 5e3]) + rng.normal(0.0, 2e3, (m, 3))
    bs = simulate_bearings(targets, STATIONS, SIGMA, rng=rng)
    el = bs.elevation.copy()
    el[::4, 2] = np.nan
    probs = []
    for k in range(m):
        items = []
        for i in range(3):
            b = {'station': f's{i}', 'position': bs.positions[k, i].tolist(),
                 'azimuth': float(bs.azimuth[k, i]), 'sigma_azimuth': SIGMA}
            if np.isfinite(el[k, i]):
                b.update(elevation=float(el[k, i]), sigma_elevation=SIGMA)
            items.append(b)
        probs.append({'bearings': items})
    paths = {fmt: os.path.join(folder, 'input.' + fmt) for fmt in ('json', 'csv', 'npz')}
    with open(paths['json'], 'w') as f:
        json.dump({'estimator': 'mle', 'problems': probs}, f)
    cols = {'problem': np.repeat(np.arange(m), 3), 'x': bs.positions[..., 0].ravel(),
            'y': bs.positions[..., 1].ravel(), 'z': bs.positions[..., 2].ravel(),
            'azimuth': bs.azimuth.ravel(), 'elevation': el.ravel(),
            'sigma_azimuth': np.full(3 * m, SIGMA),
            'sigma_elevation': np.where(np.isnan(el.ravel()), np.nan, SIGMA),
            'station': np.tile(['s0', 's1', 's2'], m)}
    np.savez(paths['npz'], **cols)
    with open(paths['csv'], 'w', newline='') as f:
        w = csv.writer(f)
        w.writerow(list(cols))
        for r in range(3 * m):
            w.writerow([cols['problem'][r]] + [
                '' if np.isnan(cols[c][r]) else repr(float(cols[c][r]))
                for c in list(cols)[1:8]] + [cols['station'][r]])
    return paths


def timed(cmd, out_path, env):
    """(wall clock, CPU user + system) seconds of one run of ``cmd``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    with open(out_path, 'w') as out:
        proc = subprocess.run(cmd, stdout=out, stderr=subprocess.PIPE, env=env, text=True)
    elapsed = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f'{" ".join(cmd)} failed: {proc.stderr.strip()}')
    return elapsed, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def in_process(path):
    """Seconds of (read, check, solve, output) of the JSON request in this process."""
    from bearing_loc_ros.cli import jsonio, locate
    t0 = time.perf_counter()
    doc = jsonio.read_json(path)
    t1 = time.perf_counter()
    method, options, problems, _ = locate.parse_request(doc)
    t2 = time.perf_counter()
    solved = locate.solve_groups(method, options, problems)
    t3 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()) as out:
        jsonio.write_results(solved.dicts(), True)
    t4 = time.perf_counter()
    assert out.getvalue().startswith('{"results":[')
    return t1 - t0, t2 - t1, t3 - t2, t4 - t3


def fmt(values):
    v = np.asarray(values) * 1e3
    return f'{np.median(v):8.0f} ms  [{v.min():.0f}-{v.max():.0f}]'


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--problems', type=int, default=10000)
    ap.add_argument('--repeat', type=int, default=5)
    ap.add_argument('--no-bytecode-cache', action='store_true',
                    help='run the commands in this environment as it is (with '
                         'PYTHONDONTWRITEBYTECODE set, every run compiles the package again)')
    args = ap.parse_args()
    exe = os.path.join(os.path.dirname(sys.executable), 'bearing_loc')
    base = [exe] if os.path.exists(exe) else [
        sys.executable, '-c', 'import sys; from bearing_loc_ros.cli import main; sys.exit(main())']
    env = dict(os.environ, AMENT_PREFIX_PATH=os.environ.get('AMENT_PREFIX_PATH',
                                                            sys.prefix))
    with tempfile.TemporaryDirectory() as tmp:
        if not args.no_bytecode_cache:
            # As an installed package runs: compiled once (here into tmp, not the tree).
            env.pop('PYTHONDONTWRITEBYTECODE', None)
            env['PYTHONPYCACHEPREFIX'] = os.path.join(tmp, 'pycache')
            subprocess.run(base + ['locate', '--help'], env=env, capture_output=True)
        paths = write_inputs(tmp, args.problems)
        sizes = {k: os.path.getsize(p) / 1e6 for k, p in paths.items()}
        runs = {'interpreter alone (python -c pass)': [sys.executable, '-c', 'pass'],
                'startup (locate --help)': base + ['locate', '--help']}
        runs.update({f'locate {k} ({sizes[k]:.1f} MB)': base + ['locate', p]
                     for k, p in paths.items()})
        times = {k: [] for k in runs}
        parts = []
        for _ in range(args.repeat):
            for name, cmd in runs.items():
                times[name].append(timed(cmd, os.path.join(tmp, 'out.json'), env))
            parts.append(in_process(paths['json']))
        outs = []
        for k, p in paths.items():
            timed(base + ['locate', p], os.path.join(tmp, k + '.out'), env)
            with open(os.path.join(tmp, k + '.out')) as f:
                outs.append([r['position'] for r in json.load(f)['results']])
    same = outs[0] == outs[1] == outs[2]
    print(f'bearing_loc locate, {args.problems} three-station problems (mle), median of '
          f'{args.repeat} runs [min-max]; bytecode '
          f'{"as the environment has it" if args.no_bytecode_cache else "cached"}')
    print('| run | wall clock | CPU (user + sys) |')
    print('|---|---|---|')
    for name, t in times.items():
        t = np.array(t)
        print(f'| {name} | {fmt(t[:, 0])} | {fmt(t[:, 1])} |')
    parts = np.array(parts)
    for j, name in enumerate(('in-process: read JSON (jsonio.read_json)', 'in-process: check',
                              'in-process: solve + CRLB', 'in-process: JSON output')):
        print(f'| {name} | {fmt(parts[:, j])} | |')
    print(f'JSON, CSV and NPZ fixes identical: {same}')


if __name__ == '__main__':
    main()
