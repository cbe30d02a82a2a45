"""``bearing_loc calibrate``: heading biases and confidence -> σ from a calibration run.

Input: one recorded "Kraken App" CSV log per station (``--station NAME=FILE``), taken while a
transmitter sat at a known position (``--transmitter X Y Z`` in the ENU frame, or
``--transmitter-geodetic LAT LON ALT`` with a ``geodetic_origin``), and the stations' current
parameters (``--params FILE``: a station parameter YAML with ``/NAME/station_node:``,
``/NAME/**:`` or ``/**:`` entries). Each reading becomes a bearing with the station's current
geometry (:mod:`bearing_loc_ros.core.receiver`); its compass residual against the true
bearing feeds the maximum-likelihood fit of :mod:`bearing_loc_ros.core.calibration`.

Output (``--out FILE``): a station parameter YAML, one ``/NAME/station_node:`` entry per
station holding its given parameters with ``kraken.heading_offset_deg`` corrected by the
fitted bias and ``kraken.sigma_conf1_deg`` / ``kraken.sigma_conf0_deg`` set to the fitted
σ model; pass it to each station node with ``--params-file``.
"""

from collections import Counter
import math
import os
import sys

from . import InputError, load_yaml

STATION_NODE = 'station_node'


def add_arguments(parser):
    """Register the ``calibrate`` options."""
    parser.add_argument('--station', action='append', required=True, metavar='NAME=CSV',
                        help='a station and its recorded Kraken CSV log (repeat per station)')
    parser.add_argument('--params', metavar='YAML', help='station parameter file (position, '
                        'geodetic_origin, kraken.* of every station)')
    g = parser.add_mutually_exclusive_group(required=True)
    g.add_argument('--transmitter', nargs=3, type=float, metavar=('X', 'Y', 'Z'),
                   help='transmitter position in the ENU world frame, m')
    g.add_argument('--transmitter-geodetic', nargs=3, type=float,
                   metavar=('LAT', 'LON', 'ALT'), help='transmitter position, WGS84 degrees '
                   'and ellipsoidal height (needs geodetic_origin in --params)')
    parser.add_argument('--max-residual-deg', type=float, default=45.0, help='readings '
                        'further than this from the station median are outliers (default 45)')
    parser.add_argument('--out', required=True, help='station parameter YAML to write')


def load_station_params(path):
    """The parsed parameter YAML (dict) of ``path``; InputError naming the file."""
    data = load_yaml(path, 'params', params=True)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InputError(f'params: {path}: expected "<node>: ros__parameters:" mappings')
    return data


def station_params(data, station):
    """ros__parameters for ``station`` (flat dotted names): ``/**`` < ``/NAME/**`` <
    ``NAME`` < ``/NAME/station_node`` (later keys override earlier ones)."""
    from ..core.receiver_params import flatten
    out = {}
    for key in ('/**', f'/{station}/**', station, f'/{station}/{STATION_NODE}'):
        body = data.get(key)
        if isinstance(body, dict) and isinstance(body.get('ros__parameters'), dict):
            out.update(flatten(body['ros__parameters']))
    return out


def warn_unknown_params(params):
    """Warn on stderr, per station, about names in its parameters that a station node does
    not have (they would be ignored by the node, and are ignored here)."""
    from ..core import parameters
    known = {p.name for p in parameters.schema(STATION_NODE)} | set(
        parameters.renamed(STATION_NODE))
    for s, given in params.items():
        text = parameters.unknown_message(STATION_NODE, [
            n for n in given if n not in known and not parameters.ros_builtin(n)])
        if text is not None:
            print(f'warning: {s}: {text}', file=sys.stderr)


def read_log(path):
    """(records, rejections Counter) of a Kraken CSV file; InputError when unreadable."""
    from ..core import kraken
    records, bad = [], Counter()
    try:
        with open(path, encoding='utf-8', errors='replace') as f:
            for line in f:
                if not line.strip():
                    continue
                try:
                    records.append(kraken.parse_csv_line(line))
                except kraken.KrakenError as exc:
                    bad[exc.reason] += 1
    except OSError as exc:
        raise InputError(f'station: cannot read {path} ({exc.strerror})') from None
    return records, bad


def parse_station_args(items):
    """``NAME=CSV`` items -> {name: path}; InputError for a malformed or repeated item."""
    out = {}
    for item in items:
        name, sep, path = item.partition('=')
        name = name.strip().strip('/')
        if not sep or not name or not path:
            raise InputError(f'station: expected NAME=CSV, got {item!r}')
        if name in out:
            raise InputError(f'station: {name} given twice')
        out[name] = path
    return out


#: Largest |ENU coordinate| of the transmitter, m (the Earth's diameter is 1.3e7 m).
MAX_TRANSMITTER_COORDINATE = 1e7
#: Closest horizontal distance between a station and the transmitter, m (the bearing to a
#: transmitter at the station is undefined).
MIN_TRANSMITTER_DISTANCE = 1.0
#: A fitted heading bias above this (deg) is reported as a likely wrong transmitter or
#: heading parameter.
LARGE_BIAS_DEG = 30.0


def residuals(station, records, params, transmitter_enu):
    """Compass residuals (rad) and confidences of one station's readings.

    Each reading -> bearing with the station's parameters (azimuth θ in the world ENU
    axes) -> residual from :func:`core.calibration.compass_residuals`. Returns (r list,
    c list, rejections Counter).
    """
    from ..core.calibration import compass_residuals
    from ..core.kraken import KrakenError
    from ..core.receiver import ReceiverGeometry
    from ..core.receiver_params import receiver_from_params
    from ..core.station import ConfigError
    try:
        cfg, _ = receiver_from_params(station, params)
    except ConfigError as exc:
        raise InputError(f'params: station {station}: {exc}') from None
    geo = ReceiverGeometry(cfg)
    if cfg.needs_odometry:
        raise InputError(f'params: station {station}: calibration needs a fixed or GPS '
                         'heading and position (no odometry)')
    az, xy, c, bad = [], [], [], Counter()
    for rec in records:
        try:
            b = geo.to_bearing(rec)
        except KrakenError as exc:
            bad[exc.reason] += 1
            continue
        if math.dist(b.position[:2], transmitter_enu[:2]) < MIN_TRANSMITTER_DISTANCE:
            raise InputError(f'transmitter: within {MIN_TRANSMITTER_DISTANCE:g} m of station '
                             f'{station} (horizontally): its bearing is undefined')
        az.append(b.azimuth)
        xy.append(b.position[:2])
        c.append(rec.confidence)
    r = compass_residuals(az, xy, transmitter_enu[:2]) if az else []
    return list(r), c, bad


def transmitter_position(args, params):
    """Transmitter ENU (3,) from --transmitter or --transmitter-geodetic."""
    import numpy as np
    from ..core import geodesy
    if args.transmitter is not None:
        t = np.asarray(args.transmitter, dtype=float)
        if not np.all(np.isfinite(t)):
            raise InputError('transmitter: expected finite X Y Z')
        return _bounded(t, 'transmitter')
    origins = {tuple(p.get('geodetic_origin') or ()) for p in params.values()}
    origins.discard(())
    if len(origins) != 1:
        raise InputError('transmitter-geodetic: needs one geodetic_origin shared by every '
                         'station in --params')
    try:
        t = geodesy.geodetic_to_enu(*args.transmitter_geodetic, list(origins.pop()),
                                    field='transmitter-geodetic')
    except ValueError as exc:
        raise InputError(str(exc)) from None
    return _bounded(np.asarray(t, dtype=float), 'transmitter-geodetic')


def _bounded(t, flag):
    """``t`` (3,) ENU m, or InputError naming ``flag`` beyond MAX_TRANSMITTER_COORDINATE."""
    import numpy as np
    if not np.all(np.abs(t) <= MAX_TRANSMITTER_COORDINATE):
        raise InputError(f'{flag}: the transmitter must lie within '
                         f'{MAX_TRANSMITTER_COORDINATE:g} m of the ENU origin')
    return t


def corrected_params(params, result):
    """{station: nested ros__parameters} with the fitted correction applied."""
    from ..core.calibration import corrected_heading_offset_deg
    from ..core.receiver_params import DEFAULTS, nest
    out = {}
    for k, s in enumerate(result.stations):
        p = dict(params[s])
        old = float(p.get('kraken.heading_offset_deg', DEFAULTS['kraken.heading_offset_deg']))
        new = corrected_heading_offset_deg(old, result.bias[k])
        p['kraken.heading_offset_deg'] = round(new, 6)
        p['kraken.sigma_conf1_deg'] = round(result.sigma_conf1_deg, 6)
        p['kraken.sigma_conf0_deg'] = round(result.sigma_conf0_deg, 6)
        out[s] = nest(p)
    return out


def write_params(path, corrected, header):
    """Write ``/NAME/station_node: ros__parameters:`` entries to ``path`` (YAML)."""
    import yaml
    doc = {f'/{s}/{STATION_NODE}': {'ros__parameters': p} for s, p in corrected.items()}
    text = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)
    try:
        with open(path, 'w', encoding='utf-8') as f:
            f.write(''.join(f'# {line}\n' for line in header) + text)
    except OSError as exc:
        raise InputError(f'out: cannot write {path} ({exc.strerror})') from None


def run(args):
    """``calibrate``: fit, write --out, then print the estimates with standard errors."""
    from ..core.calibration import fit_calibration
    stations = parse_station_args(args.station)
    data = load_station_params(args.params) if args.params else {}
    params = {s: station_params(data, s) for s in stations}
    warn_unknown_params(params)
    if not (math.isfinite(args.max_residual_deg) and 0.0 < args.max_residual_deg <= 180.0):
        raise InputError('max-residual-deg: must be in (0, 180]')
    parent = os.path.dirname(os.path.abspath(args.out))
    if not os.path.isdir(parent):
        raise InputError(f'out: directory {parent} does not exist')
    if args.out.endswith(('/', os.sep)) or os.path.isdir(args.out):
        raise InputError(f'out: cannot write {args.out} (is a directory; give a file name)')
    if not os.access(parent, os.W_OK):
        raise InputError(f'out: cannot write {args.out} (directory {parent} is not writable)')
    tx = transmitter_position(args, params)
    res, conf, notes = {}, {}, {}
    for s, path in stations.items():
        records, bad = read_log(path)
        r, c, rej = residuals(s, records, params[s], tx)
        res[s], conf[s], notes[s] = r, c, bad + rej
    try:
        fit = fit_calibration(res, conf, math.radians(args.max_residual_deg))
    except ValueError as exc:
        # Say why a station has too few readings: the rejection reasons of its log.
        why = '; '.join(f'{s} rejected ' + ', '.join(f'{r} {n}' for r, n in sorted(
            notes[s].items())) for s in stations if notes[s])
        raise InputError(f'{exc}' + (f' ({why})' if why else '')) from None
    cov = fit.covariance
    S = len(fit.stations)
    se0 = fit.sigma_conf0_deg * math.sqrt(max(cov[S, S] + cov[S + 1, S + 1]
                                              + 2.0 * cov[S, S + 1], 0.0))
    status = 'converged' if fit.converged else 'NOT converged'
    lines = [f'bearing_loc calibrate: transmitter at ENU ({tx[0]:.2f}, {tx[1]:.2f}, '
             f'{tx[2]:.2f}) m, maximum likelihood ({status})',
             f'sigma(confidence) = exp(a + b (1 - c)): sigma at c=1 {fit.sigma_conf1_deg:.3f} '
             f'+- {fit.sigma_conf1_deg * fit.a_se:.3f} deg, at c=0 {fit.sigma_conf0_deg:.3f} '
             f'+- {se0:.3f} deg']
    for k, s in enumerate(fit.stations):
        rejected = ', '.join(f'{r} {n}' for r, n in sorted(notes[s].items())) or 'none'
        lines.append(f'{s}: heading bias {math.degrees(fit.bias[k]):+.3f} +- '
                     f'{math.degrees(fit.bias_se[k]):.3f} deg (clockwise), {fit.n_used[s]} '
                     f'readings, {fit.n_outliers[s]} outliers, rejected: {rejected}')
    if not fit.converged:
        lines.append('warning: the fit did not converge; the values above are not an optimum')
    for k, s in enumerate(fit.stations):
        if abs(math.degrees(fit.bias[k])) > LARGE_BIAS_DEG:
            lines.append(f'warning: {s}: heading bias {math.degrees(fit.bias[k]):+.1f} deg is '
                         'large: check the transmitter position and the station\'s position '
                         'and heading parameters')
    # The report goes to stdout only once the file is written: a failed write prints nothing.
    write_params(args.out, corrected_params(params, fit), lines)
    for line in lines:
        print(line)
    print(f'wrote {args.out}')
    return 0
