"""``bearing_loc evaluate``: Monte Carlo evaluation of estimators (Zong & Cui (2015), sec. 3).

Example (Zong & Cui (2015), figs. 2-4)::

    bearing_loc evaluate --scenario config/scenarios/seed003.yaml \\
        --estimators ls,tls,ctls,mle,wmle --sigma-deg 0.5,1,1.5,2,2.5,3 --trials 1000 \\
        --out results/

Prints a table and writes ``<out>/evaluation.csv``, ``<out>/evaluation.json`` and PNG
plots ``eval_rmse_joint.png`` (σ_θ = σ_ψ = σ, Zong & Cui (2015) fig. 2),
``eval_rmse_azimuth.png`` and ``eval_rmse_elevation.png`` (one angle's σ varies, the other
fixed at ``--fixed-sigma-deg``; figs. 3-4) and ``eval_az_vs_el.png`` (the two single-angle
sweeps on one plot). The maths is core.evaluation; docs/benchmarks.md "Evaluation" has the results.
"""

import csv
import json
import math
import os
import sys
import time

from . import InputError
from .deprecation import DeprecatedOption

DEFAULT_ESTIMATORS = 'ls,tls,ctls,mle,wmle'
DEFAULT_SIGMAS = '0.5,1,1.5,2,2.5,3'
SWEEP_CHOICES = ('none', 'azimuth', 'elevation', 'both')
CSV_NAME = 'evaluation.csv'
JSON_NAME = 'evaluation.json'
#: Upper bound of --trials: the trials of one noise level are one batch held in memory.
MAX_TRIALS = 1_000_000
#: Most bearings of one noise level, trials × targets × stations: they are one batch held in
#: memory with every estimator's work arrays (measured: 6e5 bearings, seed003 at 1e5 trials,
#: the five default estimators, 1.7 GB and 34 s). A scenario with a ``random_static``
#: ``count`` of 1000 (1000 targets per trial) and three stations reaches it at 333 trials.
MAX_BEARINGS = 1_000_000


def add_arguments(parser):
    """Register the ``evaluate`` options."""
    parser.add_argument('--scenario', required=True,
                        help='scenario YAML: stations, targets (random_static: a new draw '
                             'per trial), σ growth (docs/nodes.md "Scenario YAML")')
    parser.add_argument('--estimator', default=DEFAULT_ESTIMATORS,
                        help=f'comma-separated estimator names (default {DEFAULT_ESTIMATORS})')
    parser.add_argument('--estimators', dest='estimator', action=DeprecatedOption,
                        replacement='--estimator')
    parser.add_argument('--sigma-deg', default=DEFAULT_SIGMAS,
                        help=f'comma-separated σ values, degrees (default {DEFAULT_SIGMAS})')
    parser.add_argument('--trials', type=int, default=1000,
                        help='Monte Carlo trials per noise level (default 1000)')
    parser.add_argument('--seed', type=int, default=0,
                        help='seed; trial m uses simulator seed SEED+m (default 0)')
    parser.add_argument('--sweep', choices=SWEEP_CHOICES, default='both',
                        help='single-angle sweeps to run besides the joint one (σ_θ = σ_ψ): '
                             'azimuth, elevation, both (default) or none')
    parser.add_argument('--fixed-sigma-deg', type=float, default=0.5,
                        help='σ of the angle held fixed in a single-angle sweep, degrees '
                             '(default 0.5, as Zong & Cui 2015 figs. 3-4)')
    parser.add_argument('--range-ref', type=float, default=None, metavar='M',
                        help="override the stations' σ growth reference range r_ref, m "
                             '(σ(r) = σ · r / r_ref, Zong & Cui 2015 eqs. (9)-(10)); 0: '
                             'constant σ')
    paper_or_robust = parser.add_mutually_exclusive_group()
    paper_or_robust.add_argument(
        '--paper', dest='robust', action='store_false', default=None,
        help='the papers\' estimators alone: mle/wmle without option robust (mle is robust by '
             'default), ls/tls/ctls/ctls_am without option consistency (their '
             'low_confidence status)')
    paper_or_robust.add_argument(
        '--robust', dest='robust', action='store_true', default=None,
        help='run mle/wmle with option robust and the others with option consistency '
             '(consensus, outlier exclusion, full likelihood, ok/low_confidence status; as '
             'the fusion node)')
    parser.add_argument('--outliers', default=None, metavar='F,MIN_DEG,MAX_DEG',
                        help='outlier bearings: a fraction F of the bearings get an extra '
                             'error of ±U(MIN_DEG, MAX_DEG) on azimuth and elevation, e.g. '
                             '0.1,20,90 (default none)')
    parser.add_argument('--dimension', choices=('auto', '3d', 'horizontal'), default=None,
                        help='solve: auto (3d when the bearings observe the height, else '
                             'horizontal), 3d or horizontal (default: auto, and horizontal '
                             'for a scenario of azimuth-only stations)')
    parser.add_argument('--target-altitude', type=float, default=None, metavar='M',
                        help='target altitude of the horizontal solve, m (default: the '
                             "scenario target's own altitude in each trial)")
    parser.add_argument('--target-altitude-sigma', type=float, default=0.0, metavar='M',
                        help='its standard deviation, m (default 0: exactly known)')
    parser.add_argument('--out', default=None,
                        help='output directory for CSV, JSON and PNG files (created)')
    parser.add_argument('--no-plots', action='store_true', help='skip the PNG plots')
    parser.add_argument('--quiet', action='store_true',
                        help='no progress bar (it is also off when stderr is not a TTY)')


def _csv_list(text, name, conv):
    """The values of a comma-separated option (``conv`` each); InputError naming ``name``
    for an empty list, an empty item (``1,,2``: a typo, not a list of two) or a bad value."""
    items = [x.strip() for x in str(text).split(',')]
    if not any(items):
        raise InputError(f'{name}: empty list')
    if not all(items):
        raise InputError(f'{name}: empty item in {text!r}')
    try:
        return [conv(x) for x in items]
    except ValueError:
        raise InputError(f'{name}: expected a comma-separated list, got {text!r}') from None


class Progress:
    """Plain-text progress bar on stderr: ``[#####.....]  12/30  4.1 s``, redrawn with \\r.

    Disabled (no output at all) when ``enabled`` is false, for example when stderr is not a
    terminal or with --quiet.
    """

    def __init__(self, enabled, width=30, stream=None):
        self.enabled = enabled
        self.width = width
        self.stream = stream or sys.stderr
        self.t0 = time.perf_counter()

    def __call__(self, done, total):
        if not self.enabled:
            return
        n = int(self.width * done / max(total, 1))
        dt = time.perf_counter() - self.t0
        self.stream.write(f'\r[{"#" * n}{"." * (self.width - n)}] {done:4d}/{total} '
                          f'{dt:6.1f} s')
        if done >= total:
            self.stream.write('\n')
        self.stream.flush()


#: Largest σ accepted, degrees (every σ in (0, MAX_SIGMA_DEG] completes).
MAX_SIGMA_DEG = 10.0


def parse_outliers(text):
    """``F,MIN_DEG,MAX_DEG`` -> (fraction, min, max) with min/max in rad; None for None."""
    if text is None:
        return None
    vals = _csv_list(text, 'outliers', float)
    if len(vals) != 3:
        raise InputError(f'outliers: expected F,MIN_DEG,MAX_DEG, got {text!r}')
    f, a, b = vals
    if not (math.isfinite(f) and 0.0 <= f <= 1.0):
        raise InputError(f'outliers: fraction must be in [0, 1], got {f}')
    if not (math.isfinite(a) and math.isfinite(b) and 0.0 <= a <= b <= 180.0):
        raise InputError(f'outliers: need 0 <= MIN_DEG <= MAX_DEG <= 180, got {a}, {b}')
    return (f, math.radians(a), math.radians(b))


def _solve_options(tr, dimension, target_altitude, target_altitude_sigma):
    """Solve-level options of the study (:func:`run_evaluation`); {} = the 3D solve."""
    from ..core import evaluation as ev
    horizontal = dimension == 'horizontal' or (dimension in (None, 'auto')
                                               and not tr.has_elevation.any())
    for flag, v in (('target_altitude', target_altitude),
                    ('target_altitude_sigma', target_altitude_sigma)):
        if v is not None and not math.isfinite(v):
            raise InputError(f'{flag}: must be a finite number (m), got {v}')
    if target_altitude_sigma is not None and target_altitude_sigma < 0:
        raise InputError(f'target_altitude_sigma: must be >= 0 m (got {target_altitude_sigma})')
    if not horizontal and target_altitude is None:
        return {} if dimension in (None, 'auto') else {'dimension': dimension}
    # Without --target-altitude each trial states its true altitude measured with σ_z
    # (core.evaluation.stated_altitudes, drawn per noise level from its seeded generator).
    z0 = ev.TRUTH if target_altitude is None else float(target_altitude)
    return {'dimension': dimension or 'auto', 'target_altitude': z0,
            'target_altitude_sigma': float(target_altitude_sigma or 0.0)}


def run_evaluation(scenario_path, estimators, sigmas, trials, seed=0, sweep='both',
                   fixed_sigma_deg=0.5, progress=None, range_ref=None, outliers=None,
                   robust=None, dimension=None, target_altitude=None,
                   target_altitude_sigma=0.0):
    """Run the study; returns (rows: list of Stats, meta: dict).

    ``outliers``: None or (fraction, min, max magnitude in rad) (:func:`parse_outliers`).
    ``robust``: None runs each estimator with its own default (``mle`` robust, ``wmle``
    not, the others with ``consistency``); True or False passes option ``robust`` and
    ``consistency`` to the estimators that accept them.
    ``dimension``, ``target_altitude``, ``target_altitude_sigma`` (m): the solve
    (core.horizontal). A horizontal solve (forced, or a scenario whose stations are all
    azimuth-only, ``dims: 1``) states the altitude: ``target_altitude`` as given, else each
    trial's true target altitude plus an error drawn from N(0, σ_z²) (seeded; exact for
    σ_z = 0); RMSE/CRLB then uses the horizontal bound and NEES has 2 degrees of freedom
    (σ_z = 0) or 3.
    """
    from ..core import evaluation as ev
    from ..core import registry
    from ..core.simulation import load_scenario
    from ..scenarios import resolve_scenario
    known = registry.names(registry.MODE_MULTISTATION)
    unknown = [e for e in estimators if e not in known]
    if unknown:
        raise InputError(f'--estimator: unknown {", ".join(unknown)}; choose from '
                         f'{", ".join(known)}')
    if len(set(estimators)) != len(estimators):
        raise InputError('--estimator: a name is repeated')
    if not 1 <= trials <= MAX_TRIALS:
        raise InputError(f'--trials: must be in 1..{MAX_TRIALS} (got {trials})')
    if not 0 <= seed <= 2 ** 63 - 1 - trials:
        raise InputError(f'--seed: must be in 0..2**63-1-trials (got {seed})')
    path = resolve_scenario(scenario_path)
    scenario = load_scenario(path)
    n_tg, n_st = len(scenario.targets), len(scenario.stations)
    if trials * n_tg * n_st > MAX_BEARINGS:
        raise InputError(
            f'--trials: {trials} trials x {n_tg} targets x {n_st} stations = '
            f'{trials * n_tg * n_st:.3g} bearings per noise level, more than the '
            f'{MAX_BEARINGS:.0e} one batch holds in memory; ' +
            (f'use --trials {MAX_BEARINGS // (n_tg * n_st)} or fewer'
             if n_tg * n_st <= MAX_BEARINGS else 'use a scenario with fewer targets'))
    if range_ref is not None and not (math.isfinite(range_ref)
                                      and (range_ref == 0 or range_ref >= 1.0)):
        raise InputError(f'--range-ref: must be 0 (constant σ) or >= 1 m (got {range_ref})')
    tr = ev.trials_from_scenario(scenario, trials, seed, range_ref)
    sweeps = ('joint',) + {'none': (), 'azimuth': ('azimuth',), 'elevation': ('elevation',),
                           'both': ('azimuth', 'elevation')}[sweep]
    if not tr.has_elevation.any():
        # Azimuth-only stations: the azimuth sweep repeats the joint one and the elevation
        # sweep varies nothing that is measured.
        sweeps = ('joint',)
    options = {}
    ref = tr.reference_range()
    if ref is not None:     # d_ref of Zong & Cui 2015 eqs. (9)-(10), for who models it
        for e in estimators:
            scoped = registry.check(e, {'reference_range': ref})
            if scoped:
                options[e] = scoped
    if robust is not None:
        for e in estimators:
            scoped = registry.check(e, dict(options.get(e, {}), robust=bool(robust),
                                            consistency=bool(robust)))
            if 'robust' in scoped or 'consistency' in scoped:
                options[e] = scoped
    unobserved = tr.unobserved()
    if unobserved:
        print('bearing_loc evaluate: warning: bearings not made (target on or straight above '
              'the station, no azimuth; the problem is solved with the other stations, as the '
              f'simulator drops them), of {tr.M} problems per level: '
              + ', '.join(f'{st} {n}' for st, n in unobserved.items()), file=sys.stderr)
    solve_options = _solve_options(tr, dimension, target_altitude, target_altitude_sigma)
    if target_altitude is not None and dimension != 'horizontal' and tr.has_elevation.any():
        why = ('--dimension 3d' if dimension == '3d' else
               "the scenario's elevations observe the height (solve 3d)")
        print(f'bearing_loc evaluate: warning: --target-altitude not used: {why}; '
              '--dimension horizontal applies it', file=sys.stderr)
    t0 = time.perf_counter()
    rows = ev.evaluate(estimators, tr, sigmas, sweeps, seed, fixed_sigma_deg, options,
                       progress, outliers=outliers, solve_options=solve_options)
    elapsed = time.perf_counter() - t0
    meta = {'scenario': path, 'scenario_name': scenario.name, 'seed': seed,
            'trials': trials, 'problems_per_level': int(tr.M), 'estimators': estimators,
            'sigma_deg': sigmas, 'sweeps': list(sweeps), 'fixed_sigma_deg': fixed_sigma_deg,
            'options': options, 'elapsed_s': elapsed,
            'stations': tr.station_ids, 'reference_range_m': ref,
            'unobserved_bearings': unobserved,
            'range_ref_override_m': range_ref, 'robust': robust,
            'dimension': solve_options.get('dimension', dimension or 'auto'),
            'target_altitude_m': (None if solve_options.get('target_altitude') is None else
                                  'truth' if target_altitude is None else target_altitude),
            'target_altitude_sigma_m': solve_options.get('target_altitude_sigma'),
            'outliers': (None if outliers is None else
                         [outliers[0], math.degrees(outliers[1]), math.degrees(outliers[2])])}
    return rows, meta


def format_table(rows):
    """The result table as text (one line per sweep × σ × estimator)."""
    head = (f'{"sweep":9s} {"σθ°":>5s} {"σψ°":>5s} {"estimator":9s} {"RMSE m":>10s} '
            f'{"bias m":>9s} {"CRLB m":>9s} {"RMSE/CRLB":>9s} {"NEES":>9s} {"conv %":>7s} '
            f'{"RMSEall":>8s} {"median":>8s} {"p95 m":>8s} {"ok %":>6s} {"low %":>6s} '
            f'{"RMSEok":>8s} {"NEESok":>7s} {"wrong%":>7s} {"µs/fix":>7s}')
    lines = [head, '-' * len(head)]
    for r in rows:
        lines.append(
            f'{r.sweep:9s} {r.sigma_az_deg:5.2f} {r.sigma_el_deg:5.2f} {r.estimator:9s} '
            f'{r.rmse:10.1f} {r.bias:9.1f} {r.crlb:9.1f} {r.rmse_over_crlb:9.2f} '
            f'{r.mean_nees:9.3g} {100 * r.convergence_rate:7.1f} '
            f'{r.rmse_all:8.1f} {r.median_error:8.1f} {r.p95_error:8.1f} '
            f'{100 * r.ok_fraction:6.1f} {100 * r.low_confidence_fraction:6.1f} '
            f'{r.rmse_ok:8.1f} {r.nees_ok:7.3g} {100 * r.confident_wrong_fraction:7.3f} '
            f'{1e6 * r.time_per_fix_s:7.1f}')
    return '\n'.join(lines)


def _json_safe(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    return x


def write_outputs(rows, meta, out, plots=True):
    """Write CSV, JSON (NaN as null) and, with ``plots``, the PNG files into ``out``."""
    from ..core.evaluation import findings
    os.makedirs(out, exist_ok=True)
    table = [r.row() for r in rows]
    with open(os.path.join(out, CSV_NAME), 'w', newline='', encoding='utf-8') as f:
        w = csv.DictWriter(f, fieldnames=list(table[0]))
        w.writeheader()
        w.writerows(table)
    doc = dict(meta, rows=table, findings=findings(rows))
    with open(os.path.join(out, JSON_NAME), 'w', encoding='utf-8') as f:
        json.dump(_json_safe(doc), f, indent=1, allow_nan=False)
    files = [CSV_NAME, JSON_NAME]
    if plots:
        files += plot_results(rows, meta, out)
    return files


ESTIMATOR_STYLE = {'ls': ('tab:red', 's'), 'tls': ('tab:orange', 'v'),
                   'ctls': ('tab:purple', 'D'), 'ctls_am': ('tab:brown', 'P'),
                   'mle': ('tab:blue', 'o'), 'wmle': ('tab:green', '^')}


def plot_results(rows, meta, out):
    """PNG plots in the style of Zong & Cui (2015) figs. 2-4 (log RMSE against σ, CRLB dashed)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    names = []
    title = {'joint': 'σθ = σψ = σ (Zong & Cui 2015 fig. 2)',
             'azimuth': f'azimuth σθ = σ, elevation σψ = {meta["fixed_sigma_deg"]:g}°',
             'elevation': f'elevation σψ = σ, azimuth σθ = {meta["fixed_sigma_deg"]:g}°'}
    for sw in meta['sweeps']:
        sub = [r for r in rows if r.sweep == sw]
        fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=100)
        for est in meta['estimators']:
            rs = [r for r in sub if r.estimator == est]
            col, mk = ESTIMATOR_STYLE.get(est, (None, 'x'))
            ax.plot([_x(r) for r in rs], [r.rmse for r in rs], marker=mk, color=col,
                    label=est)
        rs = [r for r in sub if r.estimator == meta['estimators'][0]]
        ax.plot([_x(r) for r in rs], [r.crlb for r in rs], 'k--', label='CRLB')
        _decorate(ax, f'{meta["scenario_name"] or "scenario"}: {title[sw]}', meta)
        name = f'eval_rmse_{sw}.png'
        fig.tight_layout()
        fig.savefig(os.path.join(out, name))
        plt.close(fig)
        names.append(name)
    if {'azimuth', 'elevation'} <= set(meta['sweeps']):
        fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=100)
        for sw, ls in (('azimuth', '-'), ('elevation', ':')):
            for est in meta['estimators']:
                rs = [r for r in rows if r.sweep == sw and r.estimator == est]
                col, mk = ESTIMATOR_STYLE.get(est, (None, 'x'))
                ax.plot([_x(r) for r in rs], [r.rmse for r in rs], ls, marker=mk, color=col,
                        label=f'{est}, {sw} σ varies', alpha=0.8)
            rs = [r for r in rows if r.sweep == sw and r.estimator == meta['estimators'][0]]
            ax.plot([_x(r) for r in rs], [r.crlb for r in rs], 'k' + ls, lw=2.5,
                    label=f'CRLB, {sw} σ varies')
        _decorate(ax, f'azimuth (solid) vs elevation (dotted) error, other σ = '
                      f'{meta["fixed_sigma_deg"]:g}°', meta, ncol=2, fontsize=7)
        fig.tight_layout()
        fig.savefig(os.path.join(out, 'eval_az_vs_el.png'))
        plt.close(fig)
        names.append('eval_az_vs_el.png')
    return names


def _x(r):
    return r.sigma_el_deg if r.sweep == 'elevation' else r.sigma_az_deg


def _decorate(ax, title, meta, ncol=1, fontsize=8):
    ax.set_yscale('log')
    ax.set_xlabel('σ of the varied angle (degrees)')
    ax.set_ylabel('RMSE (m)')
    ax.set_title(title, fontsize=9)
    ax.grid(True, which='both', alpha=0.3)
    ax.legend(fontsize=fontsize, ncol=ncol)
    ax.text(0.99, 0.01, f'{meta["trials"]} trials/level, seed {meta["seed"]}',
            transform=ax.transAxes, ha='right', va='bottom', fontsize=7, color='0.4')


def run(args):
    """``bearing_loc evaluate``."""
    estimators = _csv_list(args.estimator, '--estimator', str)
    sigmas = _csv_list(args.sigma_deg, '--sigma-deg', float)
    if any(not math.isfinite(s) or s <= 0 or s > MAX_SIGMA_DEG for s in sigmas):
        raise InputError(f'--sigma-deg: every value must be in (0, {MAX_SIGMA_DEG:g}] '
                         f'(got {args.sigma_deg})')
    if len(set(sigmas)) != len(sigmas):
        raise InputError(f'--sigma-deg: a value is repeated (got {args.sigma_deg})')
    outliers = parse_outliers(args.outliers)
    if not (math.isfinite(args.fixed_sigma_deg) and 0 < args.fixed_sigma_deg <= MAX_SIGMA_DEG):
        raise InputError(f'--fixed-sigma-deg: must be in (0, {MAX_SIGMA_DEG:g}] '
                         f'(got {args.fixed_sigma_deg})')
    if args.out:    # checked before the (long) run, so nothing is printed for a bad --out
        try:
            os.makedirs(args.out, exist_ok=True)
        except OSError as exc:
            raise InputError(f'out: cannot create directory {args.out!r} '
                             f'({exc.strerror or exc})') from None
        if not os.access(args.out, os.W_OK):
            raise InputError(f'out: directory {args.out!r} is not writable')
    progress = Progress(enabled=not args.quiet and sys.stderr.isatty())
    rows, meta = run_evaluation(args.scenario, estimators, sigmas, args.trials, args.seed,
                                args.sweep, args.fixed_sigma_deg, progress, args.range_ref,
                                outliers, args.robust, args.dimension, args.target_altitude,
                                args.target_altitude_sigma)
    if args.sweep != 'none' and meta['sweeps'] == ['joint']:
        print('bearing_loc evaluate: note: no station measures elevation, so only the joint '
              'sweep (σ_θ) is run', file=sys.stderr)
    print(f'{meta["scenario"]}: {args.trials} trials x {len(sigmas)} σ x '
          f'{len(meta["sweeps"])} sweeps x {len(estimators)} estimators, seed {args.seed}, '
          f'{meta["elapsed_s"]:.2f} s')
    print(format_table(rows))
    if rows and not any(math.isfinite(r.crlb) for r in rows):
        why = ('co-located stations, azimuth-only stations in line with them, or too few '
               'bearings left where the target is on or above a station'
               if meta['unobserved_bearings'] else
               'co-located stations, or azimuth-only stations in line with them')
        print('bearing_loc evaluate: warning: the CRLB is infinite for every trial: these '
              f'stations cannot locate the targets ({why}); the figures are not meaningful',
              file=sys.stderr)
    if args.out:
        try:
            files = write_outputs(rows, meta, args.out, plots=not args.no_plots)
        except OSError as exc:
            raise InputError(f'out: cannot write to {args.out!r} '
                             f'({exc.strerror or exc})') from None
        print(f'wrote {", ".join(os.path.join(args.out, f) for f in files)}')
    return 0
