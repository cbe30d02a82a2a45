"""Scenario YAML loader: validates a mapping into a :class:`.scenario_model.Scenario`.

Every error names the file and the key path (``<file>: <key path>: <problem>``). The format
and every key are described in docs/nodes.md, section "Scenario YAML". Re-exported from
:mod:`.simulation`.
"""

import math
import os
import re

import numpy as np

from .bearings import SIGMA_MIN
from .conventions import check_frame_id
from .geodesy import geodetic_to_enu
from .yaml_file import read_yaml
from .scenario_model import (DEFAULT_EPOCH, DEFAULT_FRAME, DEFAULT_TRUTH_RATE, Scenario,
                             SIGMA_REPORTS, SigmaGrowth, Station, Target, TARGET_KINDS,
                             Trajectory)
from .text import short_repr

_NAME_RE = re.compile(r'^[A-Za-z_][A-Za-z0-9_]*$')


SCENARIO_KEYS = ('name', 'description', 'frame_id', 'duration', 'epoch', 'truth_rate',
                 'geodetic_origin', 'station_defaults', 'stations', 'targets')
MOTION_KEYS = ('position', 'geodetic', 'velocity', 'waypoints', 'speed', 'times',
               'start_time')
STATION_KEYS = ('id', 'dims', 'sigma_az', 'sigma_az_deg', 'sigma_el', 'sigma_el_deg', 'rate',
                'phase', 'clock_offset', 'clock_jitter', 'clock_drift_ppm', 'latency',
                'latency_jitter', 'dropout', 'outlier', 'outlier_size', 'outlier_size_deg',
                'outlier_size_max', 'outlier_size_max_deg', 'position_sigma',
                'sigma_growth') + MOTION_KEYS
TARGET_KEYS = ('namespace', 'kind', 'box_min', 'box_max', 'count') + MOTION_KEYS
GROWTH_KEYS = ('range_ref', 'min_factor', 'max_factor', 'report')
GEODETIC_KEYS = ('lat_deg', 'lon_deg', 'alt')

# Bounds of the numeric keys (docs/nodes.md "Scenario YAML", stated to users there). Far
# beyond any deployment, they keep the simulator's arithmetic safe: every ROS stamp (epoch +
# t + clock_offset + drift·t + jitter, or epoch + t + latency + jitter) fits the int32
# seconds of builtin_interfaces/Time (2**31 − 1 s, January 2038): 2e9 + 1e7 + 1e8 + 1e6 +
# 100·z < 2.12e9 s; a period 1/rate fits int64 ns; a station stays within 1e8 + 1e4·1e7 =
# 1e11 m of the origin (core.bearings accepts |coordinate| <= 1e12 m) and σ within what a
# bearing carries.
#: Largest epoch, s (ROS time of scenario time 0; 2e9 s is May 2033).
MAX_EPOCH = 2e9
#: Largest duration, phase, |start_time| and |waypoint time|, s (about 116 days).
MAX_TIME = 1e7
#: Largest latency, s (an hour; it also lengthens a bag's /clock stream).
MAX_LATENCY = 3600.0
#: Largest |clock_offset|, s (about 3 years).
MAX_CLOCK_OFFSET = 1e8
#: Largest |clock_drift_ppm| (10 %; a quartz clock drifts < 100 ppm).
MAX_DRIFT_PPM = 1e5
#: Largest clock_jitter and latency_jitter (σ of a Gaussian), s.
MAX_JITTER = 100.0
#: Observation rate and non-zero truth_rate, Hz: a period from 1 µs to 11.6 days.
RATE_RANGE = (1e-6, 1e6)
#: Most truth samples of one run (truth_rate · duration · targets; ~0.5 kB each in memory).
MAX_TRUTH_SAMPLES = 1e6
#: Largest random_static ``count``. Each source is a target with its own topics (a bag
#: topic, simulator publishers per station): ``bag simulate`` takes about 5 ms per source, so
#: 1e6 sources (the former bound) ran for hours in gigabytes; 1000 take about 5 s.
MAX_COUNT = 1000
#: Largest distance of a position, waypoint, box corner or geodetic point from the ENU
#: origin, m (a quarter of the Earth-Moon distance); also the bound of |alt| and range_ref.
MAX_POSITION = 1e8
#: Speed (|velocity| or a waypoint speed) range, m/s: 1 mm/s to 10 km/s (above LEO speed).
SPEED_RANGE = (1e-3, 1e4)
#: Largest position_sigma (station survey σ), m.
MAX_POSITION_SIGMA = 1e6
#: σ of a bearing (sigma_az, sigma_el), rad: core.bearings' SIGMA_MIN to 180° (a larger σ
#: carries no information); also the bound of outlier_size.
SIGMA_RANGE = (SIGMA_MIN, math.pi)


class _Src:
    """Formats loader errors as ``<file>: <key path>: <problem>``."""

    def __init__(self, source):
        self.source = source

    def error(self, key, problem):
        return ValueError(f'{self.source}: {key}: {problem}')


def _mapping(src, value, key, allowed):
    if not isinstance(value, dict):
        raise src.error(key or 'scenario', f'expected a mapping, got {type(value).__name__}')
    for k in value:
        if k not in allowed:
            raise src.error(f'{key}.{k}' if key else str(k),
                            f'unknown key (allowed: {", ".join(allowed)})')
    return value


def _float(src, d, key, where, default=None, lo=None, hi=None, lo_open=False,
           required=False):
    """``d[key]`` as a finite float in the bounds lo (open if ``lo_open``) .. hi, in the
    key's own unit; ``default`` when absent or null. ``where`` prefixes the key path."""
    if key not in d or d[key] is None:
        if required:
            raise src.error(f'{where}{key}', 'required key is missing')
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise src.error(f'{where}{key}', f'expected a number, got {short_repr(v)}')
    try:
        v = float(v)
    except OverflowError:        # an integer beyond the float range
        v = math.inf
    if not math.isfinite(v):
        raise src.error(f'{where}{key}', f'must be finite (got {v})')
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise src.error(f'{where}{key}', f'must be {">" if lo_open else ">="} {lo} (got {v})')
    if hi is not None and v > hi:
        raise src.error(f'{where}{key}', f'must be <= {hi} (got {v})')
    return v


def _within(src, key, v, bounds, unit):
    """Raise the loader error for ``key`` unless bounds[0] <= v <= bounds[1] (``unit``, e.g.
    ' s'); None passes. The bounds keep the simulator's arithmetic finite (module constants).
    Returns v."""
    lo, hi = bounds
    if v is not None and not lo <= v <= hi:
        raise src.error(key, f'must be within [{lo:g}, {hi:g}]{unit} (got {v:g})')
    return v


def _bounded(src, d, key, where, default, bounds, unit, lo_open=False):
    """``d[key]`` (``unit``) checked by :func:`_float` (lower bound bounds[0]) and
    :func:`_within` (bounds[1]); ``default`` when absent."""
    v = _float(src, d, key, where, default, lo=bounds[0], lo_open=lo_open)
    return _within(src, f'{where}{key}', v, bounds, unit)


def _angle(src, d, key, where, default, lo=0.0, lo_open=True, bounds=None):
    """A radian value given as ``key`` (rad) or ``key_deg`` (degrees), not both.

    ``lo`` (in the unit given) as in :func:`_float`; ``bounds`` (rad, optional) the accepted
    range, reported in the unit given. Returns rad, or ``default`` when neither key is set.
    """
    if key in d and f'{key}_deg' in d:
        raise src.error(f'{where}{key}_deg', f'give either {key} (rad) or {key}_deg, not both')
    if f'{key}_deg' in d:
        v = _float(src, d, f'{key}_deg', where, lo=lo, lo_open=lo_open)
        if bounds is not None:
            _within(src, f'{where}{key}_deg', v, [math.degrees(b) for b in bounds], ' deg')
        return default if v is None else math.radians(v)
    v = _float(src, d, key, where, default, lo=lo, lo_open=lo_open)
    if bounds is not None and key in d:
        _within(src, f'{where}{key}', v, bounds, ' rad')
    return v


def _vec(src, value, key, n=3, max_norm=MAX_POSITION, unit=' m'):
    """``value`` as a finite float array of n numbers whose Euclidean norm is at most
    ``max_norm`` (``unit``; default: a position within MAX_POSITION m of the origin)."""
    if (not isinstance(value, (list, tuple)) or len(value) != n
            or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in value)):
        raise src.error(key, f'expected a list of {n} numbers, got {short_repr(value)}')
    try:
        v = np.array(value, dtype=float)
    except OverflowError:        # an integer beyond the float range
        v = np.array([math.inf])
    if not np.all(np.isfinite(v)):
        raise src.error(key, f'non-finite value in {str(value)[:80]}')
    if np.max(np.abs(v)) > max_norm or np.linalg.norm(v) > max_norm:
        raise src.error(key, f'norm must be <= {max_norm:g}{unit} (got {str(value)[:80]})')
    return v


def _geodetic(src, value, key):
    """(lat_deg, lon_deg, alt m) of a WGS84 mapping; |alt| <= MAX_POSITION m."""
    g = _mapping(src, value, key, GEODETIC_KEYS)
    lat = _float(src, g, 'lat_deg', f'{key}.', lo=-90.0, hi=90.0, required=True)
    lon = _float(src, g, 'lon_deg', f'{key}.', lo=-180.0, hi=360.0, required=True)
    alt = _bounded(src, g, 'alt', f'{key}.', 0.0, (-MAX_POSITION, MAX_POSITION), ' m')
    return lat, lon, alt


def _motion(src, d, where, origin, allow_random=False):
    """Parse the motion keys of a station or target into a Trajectory (or None for random).

    Positions m (ENU, within MAX_POSITION of the origin), speeds m/s (SPEED_RANGE), times s
    of scenario time (|t| <= MAX_TIME).
    """
    t_bounds = (-MAX_TIME, MAX_TIME)
    has = {k for k in MOTION_KEYS if k in d}
    if 'position' in has and 'geodetic' in has:
        raise src.error(f'{where}geodetic', 'give either position (ENU m) or geodetic')
    if 'waypoints' in has:
        bad = has & {'position', 'geodetic', 'velocity'}
        if bad:
            raise src.error(f'{where}{sorted(bad)[0]}', 'not allowed together with waypoints')
        pts_raw = d['waypoints']
        if not isinstance(pts_raw, (list, tuple)) or len(pts_raw) < 2:
            raise src.error(f'{where}waypoints', 'expected a list of at least 2 [x, y, z]')
        pts = np.array([_vec(src, p, f'{where}waypoints[{k}]') for k, p in enumerate(pts_raw)])
        legs = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        if 'speed' in has and 'times' in has:
            raise src.error(f'{where}times', 'give either speed or times, not both')
        if 'times' in has:
            if 'start_time' in has:
                raise src.error(f'{where}start_time', 'not allowed together with times')
            times = d['times']
            if not isinstance(times, (list, tuple)) or len(times) != len(pts):
                raise src.error(f'{where}times', f'expected {len(pts)} times (one per waypoint)')
            ts = np.array([_within(src, f'{where}times[{k}]',
                                   _float(src, {'t': x}, 't', f'{where}times[{k}]',
                                          required=True), t_bounds, ' s')
                           for k, x in enumerate(times)])
            if np.any(np.diff(ts) <= 0):
                raise src.error(f'{where}times', 'must be strictly increasing')
            return Trajectory.waypoints(pts, ts)
        if 'speed' not in has:
            raise src.error(f'{where}speed', 'required with waypoints (or give times)')
        sp = d['speed']
        if isinstance(sp, (list, tuple)):
            if len(sp) != len(legs):
                raise src.error(f'{where}speed', f'expected {len(legs)} speeds (one per leg)')
            speeds = np.array([_within(src, f'{where}speed[{k}]',
                                       _float(src, {'v': x}, 'v', f'{where}speed[{k}]',
                                              lo=0.0, lo_open=True, required=True),
                                       SPEED_RANGE, ' m/s') for k, x in enumerate(sp)])
        else:
            speeds = np.full(len(legs), _within(
                src, f'{where}speed', _float(src, d, 'speed', where, lo=0.0, lo_open=True),
                SPEED_RANGE, ' m/s'))
        k0 = np.flatnonzero(legs <= 0)
        if len(k0):
            raise src.error(f'{where}waypoints[{k0[0] + 1}]', 'repeats the previous waypoint')
        t0 = _bounded(src, d, 'start_time', where, 0.0, t_bounds, ' s')
        return Trajectory.waypoints(pts, t0 + np.concatenate([[0.0], np.cumsum(legs / speeds)]))
    for k in ('speed', 'times', 'start_time'):
        if k in has:
            raise src.error(f'{where}{k}', 'only allowed with waypoints')
    if 'geodetic' in has:
        if origin is None:
            raise src.error(f'{where}geodetic', 'needs a scenario-level geodetic_origin')
        lat, lon, alt = _geodetic(src, d['geodetic'], f'{where}geodetic')
        try:
            p = geodetic_to_enu(lat, lon, alt, origin).reshape(3)
        except ValueError as exc:
            raise src.error(f'{where}geodetic', str(exc)) from None
        if np.linalg.norm(p) > MAX_POSITION:
            raise src.error(f'{where}geodetic', f'{np.linalg.norm(p):.3g} m from '
                            f'geodetic_origin, more than {MAX_POSITION:g} m')
    elif 'position' in has:
        p = _vec(src, d['position'], f'{where}position')
    elif allow_random:
        return None
    else:
        raise src.error(f'{where}position', 'required (or geodetic, or waypoints)')
    if 'velocity' in has:
        return Trajectory.constant_velocity(p, _vec(src, d['velocity'], f'{where}velocity',
                                                    max_norm=SPEED_RANGE[1], unit=' m/s'))
    return Trajectory.static(p)


def _station(src, raw, k, defaults, origin):
    """Station k from its mapping over ``defaults`` (units: docs/nodes.md "Scenario YAML";
    rad, s, Hz, m; bounds: the module constants)."""
    where = f'stations[{k}].'
    _mapping(src, raw, f'stations[{k}]', STATION_KEYS)
    d = dict(defaults)
    for base in ('sigma_az', 'sigma_el', 'outlier_size', 'outlier_size_max'):
        if base in raw or f'{base}_deg' in raw:
            d.pop(base, None)
            d.pop(f'{base}_deg', None)
    d.update(raw)
    sid = d.get('id')
    if not isinstance(sid, str) or not _NAME_RE.match(sid):
        raise src.error(f'{where}id', f'expected a ROS name token ([A-Za-z_][A-Za-z0-9_]*), '
                        f'got {short_repr(sid)}')
    dims = d.get('dims', 2)
    if dims not in (1, 2) or isinstance(dims, bool):
        raise src.error(f'{where}dims', f'must be 1 (azimuth only) or 2 (got {short_repr(dims)})')
    sigma_az = _angle(src, d, 'sigma_az', where, 0.01, bounds=SIGMA_RANGE)
    # Checked on a 1D station too (docs/nodes.md: its bounds are sigma_az's), where it is not
    # used: a bad value is a mistake in the file, and station_defaults may set it for all.
    sigma_el = _angle(src, d, 'sigma_el', where, sigma_az, bounds=SIGMA_RANGE)
    if dims == 1:
        sigma_el = math.nan
    growth = None
    if d.get('sigma_growth') is not None:
        gw = f'{where}sigma_growth'
        g = _mapping(src, d['sigma_growth'], gw, GROWTH_KEYS)
        report = g.get('report', 'nominal')
        if report not in SIGMA_REPORTS:
            raise src.error(f'{gw}.report',
                            f'must be one of {SIGMA_REPORTS} (got {short_repr(report)})')
        fmin = _float(src, g, 'min_factor', f'{gw}.', 1e-3, lo=0.0, lo_open=True)
        fmax = _float(src, g, 'max_factor', f'{gw}.', math.inf, lo=fmin)
        floor = fmin * max(sigma_az, sigma_el if dims == 2 else 0.0)
        if floor > SIGMA_RANGE[1]:
            raise src.error(f'{gw}.min_factor', f'sigma x min_factor = {floor:g} rad, more '
                            f'than pi rad (180 deg) at every range')
        range_ref = _float(src, g, 'range_ref', f'{gw}.', lo=0.0, lo_open=True,
                           required=True)
        growth = SigmaGrowth(_within(src, f'{gw}.range_ref', range_ref,
                                     (1e-3, MAX_POSITION), ' m'), fmin, fmax, report)
    outlier_size = _angle(src, d, 'outlier_size', where, math.radians(10.0), lo_open=False,
                          bounds=(0.0, math.pi))
    size_max = None
    if 'outlier_size_max' in d or 'outlier_size_max_deg' in d:
        size_max = _angle(src, d, 'outlier_size_max', where, None, lo_open=False)
        if not outlier_size <= size_max <= math.pi:
            raise src.error(f'{where}outlier_size_max', 'must be in [outlier_size, 180 deg]')
    rate = _within(src, f'{where}rate', _float(src, d, 'rate', where, 1.0, lo=0.0,
                                               lo_open=True), RATE_RANGE, ' Hz')
    clock_offset = _within(src, f'{where}clock_offset',
                           _float(src, d, 'clock_offset', where, 0.0),
                           (-MAX_CLOCK_OFFSET, MAX_CLOCK_OFFSET), ' s')
    drift_ppm = _within(src, f'{where}clock_drift_ppm',
                        _float(src, d, 'clock_drift_ppm', where, 0.0),
                        (-MAX_DRIFT_PPM, MAX_DRIFT_PPM), ' ppm')
    return Station(
        id=sid, trajectory=_motion(src, d, where, origin), dims=dims, sigma_az=sigma_az,
        sigma_el=sigma_el, rate=rate,
        phase=_bounded(src, d, 'phase', where, 0.0, (0.0, MAX_TIME), ' s'),
        clock_offset=clock_offset,
        clock_jitter=_bounded(src, d, 'clock_jitter', where, 0.0, (0.0, MAX_JITTER), ' s'),
        clock_drift=drift_ppm * 1e-6,
        latency=_bounded(src, d, 'latency', where, 0.0, (0.0, MAX_LATENCY), ' s'),
        latency_jitter=_bounded(src, d, 'latency_jitter', where, 0.0, (0.0, MAX_JITTER),
                                ' s'),
        dropout=_float(src, d, 'dropout', where, 0.0, lo=0.0, hi=1.0),
        outlier=_float(src, d, 'outlier', where, 0.0, lo=0.0, hi=1.0),
        outlier_size=outlier_size, outlier_size_max=size_max,
        position_sigma=_bounded(src, d, 'position_sigma', where, 0.0,
                                (0.0, MAX_POSITION_SIGMA), ' m'),
        sigma_growth=growth)


def _namespace(src, value, key):
    if value is None:
        return ''
    if not isinstance(value, str):
        raise src.error(key, f'expected a string, got {short_repr(value)}')
    ns = value.strip('/')
    if ns and not all(_NAME_RE.match(p) for p in ns.split('/')):
        raise src.error(key, f'not a valid ROS namespace: {short_repr(value)}')
    return ns


def _targets(src, raw, k, origin):
    """Target(s) of ``targets[k]`` (several for a random_static ``count``); positions m."""
    where = f'targets[{k}].'
    _mapping(src, raw, f'targets[{k}]', TARGET_KEYS)
    ns = _namespace(src, raw.get('namespace', ''), f'{where}namespace')
    kind = raw.get('kind')
    if kind is not None and kind not in TARGET_KINDS:
        raise src.error(f'{where}kind', f'must be one of {TARGET_KINDS} (got {short_repr(kind)})')
    count = raw.get('count', 1)
    if isinstance(count, bool) or not isinstance(count, int) or not 1 <= count <= MAX_COUNT:
        raise src.error(f'{where}count',
                        f'must be an integer in [1, {MAX_COUNT:g}] (got {short_repr(count)})')
    if kind == 'random_static' or ('box_min' in raw or 'box_max' in raw):
        if kind not in (None, 'random_static'):
            raise src.error(f'{where}box_min', 'only allowed with kind random_static')
        extra = [m for m in MOTION_KEYS if m in raw]
        if extra:
            raise src.error(f'{where}{extra[0]}', 'not allowed for a random_static target')
        lo = _vec(src, raw.get('box_min'), f'{where}box_min')
        hi = _vec(src, raw.get('box_max'), f'{where}box_max')
        if np.any(hi < lo):
            raise src.error(f'{where}box_max', 'must be >= box_min on every axis')
        names = [ns] if count == 1 else [f'{ns}_{m}' if ns else f'source_{m}'
                                         for m in range(count)]
        return [Target(n, 'random_static', None, lo, hi) for n in names]
    if count != 1:
        raise src.error(f'{where}count', 'only allowed for random_static targets')
    traj = _motion(src, raw, where, origin)
    if kind is not None and kind != traj.kind:
        raise src.error(f'{where}kind', f'{short_repr(kind)} does not match the motion keys given '
                        f'(they describe a {traj.kind} target)')
    return [Target(ns, traj.kind, traj)]


def parse_scenario(data, source='<dict>'):
    """Validate a scenario mapping (the parsed YAML) and return a :class:`Scenario`.

    Units: m, s, rad (``_deg`` keys: degrees), Hz, ENU. Raises ValueError
    ``'<source>: <key path>: <problem>'`` naming the offending key, e.g.
    ``config/scenarios/x.yaml: stations[1].sigma_az: must be > 0.0 (got -1.0)``; every number
    must also lie within the bounds of the module constants (docs/nodes.md).
    """
    src = _Src(source)
    _mapping(src, data, '', SCENARIO_KEYS)
    name = data.get('name', '')
    description = data.get('description', '')
    for key, v in (('name', name), ('description', description)):
        if not isinstance(v, str):
            raise src.error(key, f'expected a string, got {short_repr(v)}')
    frame_id = data.get('frame_id', DEFAULT_FRAME)
    try:
        check_frame_id(frame_id if isinstance(frame_id, str) else None)
    except ValueError:                  # the fusion node refuses the same names
        raise src.error('frame_id', f'expected a non-empty name without spaces, got '
                                    f'{short_repr(frame_id)}') from None
    duration = _within(src, 'duration', _float(src, data, 'duration', '', lo=0.0, lo_open=True,
                                               required=True), (0.0, MAX_TIME), ' s')
    epoch = _bounded(src, data, 'epoch', '', DEFAULT_EPOCH, (0.0, MAX_EPOCH), ' s')
    truth_rate = _float(src, data, 'truth_rate', '', DEFAULT_TRUTH_RATE, lo=0.0)
    if truth_rate > 0:
        _within(src, 'truth_rate', truth_rate, RATE_RANGE, ' Hz (or 0 for none)')
    origin = None
    if data.get('geodetic_origin') is not None:
        origin = _geodetic(src, data['geodetic_origin'], 'geodetic_origin')
    defaults = data.get('station_defaults')
    if defaults is None:                        # absent or empty (`station_defaults:`)
        defaults = {}
    _mapping(src, defaults, 'station_defaults',
             tuple(k for k in STATION_KEYS if k != 'id' and k not in MOTION_KEYS))
    raw_st = data.get('stations')
    if not isinstance(raw_st, list) or not raw_st:
        raise src.error('stations', 'expected a non-empty list of stations')
    stations = tuple(_station(src, r, k, defaults, origin) for k, r in enumerate(raw_st))
    seen = set()
    for k, s in enumerate(stations):
        if s.id in seen:
            raise src.error(f'stations[{k}].id', f'duplicate station id {short_repr(s.id)}')
        seen.add(s.id)
        if epoch + s.clock_offset < 0:
            raise src.error(f'stations[{k}].clock_offset',
                            f'epoch + clock_offset must be >= 0 s (ROS time cannot be negative;'
                            f' got {epoch + s.clock_offset})')
    raw_tg = data.get('targets')
    if not isinstance(raw_tg, list) or not raw_tg:
        raise src.error('targets', 'expected a non-empty list of targets')
    targets = tuple(t for k, r in enumerate(raw_tg) for t in _targets(src, r, k, origin))
    seen = set()
    for t in targets:
        if t.namespace in seen:
            raise src.error('targets', f'duplicate target namespace {short_repr(t.namespace)}')
        seen.add(t.namespace)
    n_truth = truth_rate * duration * len(targets)
    if n_truth > MAX_TRUTH_SAMPLES:
        raise src.error('truth_rate', f'truth_rate x duration x targets = {n_truth:.3g} truth '
                        f'samples, more than {MAX_TRUTH_SAMPLES:g}: lower truth_rate '
                        f'(0 = no truth)')
    return Scenario(stations=stations, targets=targets, duration=duration, name=name,
                    description=description, frame_id=frame_id, epoch=epoch,
                    truth_rate=truth_rate, geodetic_origin=origin, source=source)


def load_scenario(path):
    """Read and validate a scenario YAML file (format: docs/nodes.md "Scenario YAML").

    Raises ValueError naming the file and the offending key (or the YAML syntax error).
    """
    path = os.fspath(path)
    data = read_yaml(path, path, 'scenario')
    if data is None:
        raise ValueError(f'{path}: empty scenario file')
    return parse_scenario(data, source=path)
