"""The station parameters of a receiver input: one table, read by the node, the CLI and tests.

Names are the station node's ROS parameters. ``input`` selects the receiver input; every
other receiver parameter is under ``kraken.`` (YAML: a nested ``kraken:`` mapping). Angles
are degrees in ``_deg`` names and dB in ``_db`` names; other values are SI without a suffix
(m, s, m/s, Hz), as in the node parameter schema.
:func:`receiver_from_params` builds the validated core objects from a plain dict of values
(defaults filled in), so the same parameter file configures the live node, ``bearing_loc
calibrate`` and ``bearing_loc bag import``.
"""

from .kraken import channel_map_from_params
from .receiver import (HEADING_REFERENCES, HEADING_SOURCES, LOW_SPEED_MODES, POSITION_SOURCES,
                       receiver_config, SENSES, SigmaModel)
from .station import ConfigError
from .text import short_repr

INPUTS = ('', 'kraken_xml_http', 'kraken_csv_http', 'kraken_json_post', 'kraken_csv_file')
STAMPS = ('receiver', 'receive')

#: (name, default, description, choices or (min, max) or None). The default fixes the type;
#: a list default of [] is a string array for ``kraken.channels`` and a double array else.
PARAMETERS = (
    ('input', '', "Receiver input: '' (raw_bearing topic / UDP only), kraken_xml_http, "
     'kraken_csv_http, kraken_json_post or kraken_csv_file', INPUTS),
    ('kraken.url', '', 'URL polled by kraken_xml_http (…:8081/doa.xml) or kraken_csv_http '
     '(…:8081/DOA_value.html); the only host contacted', None),
    ('kraken.poll_rate', 2.0, 'HTTP polls per second, Hz', (0.01, 100.0)),
    ('kraken.timeout', 2.0, 'HTTP request timeout, s', (0.05, 60.0)),
    ('kraken.post_address', '127.0.0.1', 'Address the JSON POST listener binds to '
     '(0.0.0.0 = every interface)', None),
    ('kraken.post_port', 8082, 'TCP port of the JSON POST listener', (1, 65535)),
    ('kraken.file', '', 'Recorded Kraken CSV file read by kraken_csv_file', None),
    ('kraken.file_from_start', True, 'Read the file from its start (false: only lines '
     'appended after start-up)', None),
    ('kraken.file_rate', 0.0, 'Replay pace of the file: 0 = as read, r > 0 = r x the '
     'recorded pace', (0.0, 1000.0)),
    ('kraken.stamp', 'receiver', "Bearing stamp: 'receiver' (the reading's TIME, unix) or "
     "'receive' (node clock on receipt)", STAMPS),
    ('kraken.max_age', 0.0, 'Readings older than this (node clock - TIME) are stale; '
     '0 = no check; needs kraken.stamp receiver', (0.0, 1.0e6)),
    ('kraken.receiver_id', '', "Accept only readings with this STATION_ID ('' = any)", None),
    ('kraken.sense', 'inverted', 'DOA sense: inverted (H + 360 - DOA), flipped '
     '(H + 180 + DOA) or plain (H + DOA)', SENSES),
    ('kraken.heading_source', 'fixed', 'Heading of the array front: fixed '
     '(array_heading_deg), gps (receiver heading) or odometry (platform_odometry yaw)',
     HEADING_SOURCES),
    ('kraken.array_heading_deg', 0.0, 'fixed: array front heading, degrees clockwise from '
     'North; gps/odometry: array front relative to the bow', (-360.0, 360.0)),
    ('kraken.heading_reference', 'true', 'true or magnetic (then declination_deg is added)',
     HEADING_REFERENCES),
    ('kraken.declination_deg', 0.0, 'Magnetic declination, degrees, East positive',
     (-180.0, 180.0)),
    ('kraken.heading_offset_deg', 0.0, 'Added to every compass bearing (the calibrated '
     'heading bias correction), degrees', (-360.0, 360.0)),
    ('kraken.min_speed', 1.0, 'Below this ground speed (m/s) the GPS heading is not used',
     (0.0, 1.0e3)),
    ('kraken.low_speed', 'hold', 'Below min_speed: hold the last good heading, or use '
     'odometry', LOW_SPEED_MODES),
    ('kraken.heading_hold_timeout', 0.0, 'A held heading expires after this long; 0 = '
     'never', (0.0, 1.0e7)),
    ('kraken.position_source', 'parameters', 'Station position: parameters (position / '
     'geodetic_position), gps (receiver lat/lon via geodetic_origin) or odometry',
     POSITION_SOURCES),
    ('kraken.gps_sigma', 5.0, 'Standard deviation of a GPS station position, m',
     (0.0, 1.0e5)),
    ('kraken.antenna_height', 0.0, 'Antenna height above the geodetic origin height for '
     'GPS positions, m', (-1.0e4, 1.0e5)),
    ('kraken.min_confidence', 0.0, 'Readings below this receiver confidence are rejected',
     (0.0, 1.0e4)),
    ('kraken.sigma_conf1_deg', 3.0, 'Azimuth sigma at full confidence, degrees',
     (1e-3, 180.0)),
    ('kraken.sigma_conf0_deg', 12.0, 'Azimuth sigma at zero confidence, degrees',
     (1e-3, 180.0)),
    ('kraken.sigma_snr_slope', 0.0, 'SNR term of the sigma model (1 = sigma ~ SNR^-1/2); '
     '0 = off', (0.0, 10.0)),
    ('kraken.sigma_snr_ref_db', 10.0, 'SNR at which the SNR term is 0, dB', (-300.0, 300.0)),
    ('kraken.sigma_min_deg', 0.5, 'Lower clip of the azimuth sigma, degrees', (1e-3, 180.0)),
    ('kraken.sigma_max_deg', 45.0, 'Upper clip of the azimuth sigma, degrees', (1e-3, 180.0)),
    ('kraken.channels', [], 'Channel names (one emitter each); empty = one channel on '
     'the bearing topic', None),
    ('kraken.channel_bands_mhz', [], 'Frequency band per channel, [low1, high1, low2, '
     'high2, ...] MHz', None),
)

DEFAULTS = {name: default for name, default, _, _ in PARAMETERS}
STRING_ARRAYS = ('kraken.channels',)
#: Unit of each receiver parameter with one (the names carry no suffix for SI units).
UNITS = {'kraken.poll_rate': 'Hz', 'kraken.timeout': 's', 'kraken.max_age': 's',
         'kraken.min_speed': 'm/s', 'kraken.heading_hold_timeout': 's',
         'kraken.gps_sigma': 'm', 'kraken.antenna_height': 'm', 'kraken.sigma_snr_ref_db': 'dB',
         'kraken.channel_bands_mhz': 'MHz'}
#: Values written in the shipped station parameter file (as comments: the defaults stay).
EXAMPLES = {'kraken.url': 'http://192.168.1.50:8081/doa.xml',
            'kraken.file': 'mydata.csv', 'kraken.channels': ['uhf', 'vhf'],
            'kraken.channel_bands_mhz': [430.0, 440.0, 144.0, 146.0]}


def node_params(param_class):
    """:data:`PARAMETERS` as station node schema entries, instances of ``param_class``
    (:class:`bearing_loc_ros.core.parameters.Param`, passed in so that this table does not
    import the schema that includes it), appended to the station node's schema: the type
    follows the default (``[]``: string array for :data:`STRING_ARRAYS`, double array
    else), a numeric rule is the inclusive range, a string rule the choices."""
    out = []
    for name, default, text, rule in PARAMETERS:
        if isinstance(default, bool):
            kind = 'bool'
        elif isinstance(default, int):
            kind = 'integer'
        elif isinstance(default, float):
            kind = 'double'
        elif isinstance(default, str):
            kind = 'string'
        else:
            kind = 'string_array' if name in STRING_ARRAYS else 'double_array'
        unit = UNITS.get(name, 'deg' if name.endswith('_deg') else '')
        lo = hi = None
        choices = ()
        if isinstance(rule, tuple) and rule and isinstance(rule[0], str):
            choices = rule
        elif isinstance(rule, tuple):
            lo, hi = rule
        out.append(param_class(name, kind, default, text, unit, lo, hi, choices=choices,
                               example=EXAMPLES.get(name), commented=name in EXAMPLES))
    return tuple(out)


def flatten(params, prefix=''):
    """Nested YAML mappings -> dotted ROS parameter names ({'kraken': {'url': u}} ->
    {'kraken.url': u})."""
    out = {}
    for key, value in params.items():
        name = f'{prefix}{key}'
        if isinstance(value, dict):
            out.update(flatten(value, name + '.'))
        else:
            out[name] = value
    return out


def nest(params):
    """Dotted names -> nested mappings (the inverse of :func:`flatten`)."""
    out = {}
    for name, value in params.items():
        node = out
        *parents, leaf = name.split('.')
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    return out


def _kind_problem(value, default, name):
    """Why ``value`` cannot be parameter ``name`` of ``default``'s ROS type (a node refuses
    a value of another type at start-up), or None. An integer is a double's value too."""
    if isinstance(default, bool):
        ok = isinstance(value, bool)
        kind = 'true or false'
    elif isinstance(default, (int, float)):
        ok = not isinstance(value, bool) and isinstance(value, (int, float)) and (
            isinstance(default, float) or isinstance(value, int))
        kind = 'a number' if isinstance(default, float) else 'an integer'
    elif isinstance(default, str):
        ok = isinstance(value, str)
        kind = 'a string'
    else:
        strings = name in STRING_ARRAYS
        ok = isinstance(value, list) and all(
            isinstance(v, str) if strings else
            not isinstance(v, bool) and isinstance(v, (int, float)) for v in value)
        kind = 'a list of strings' if strings else 'a list of numbers'
    return None if ok else f'expected {kind}, got {short_repr(value)}'


#: Station node parameters read by :func:`receiver_from_params` besides the ``kraken.*``
#: ones: name -> default (which fixes the type).
STATION_PARAMETERS = {'frame_id': 'map', 'position': [], 'geodetic_position': [],
                      'geodetic_origin': [], 'position_covariance': []}


def with_defaults(params):
    """Receiver parameter values (flat or nested) with the defaults filled in; ValueError
    naming an unknown ``kraken.*`` name, a value of the wrong type (``kraken: 5``, ``position:
    5.0``) or a value out of its range/choices."""
    p = dict(DEFAULTS)
    given = flatten(params)
    for name, value in given.items():
        if name == 'kraken':
            raise ValueError(f'kraken: expected a mapping of receiver parameters, got '
                             f'{short_repr(value)}')
        if name.startswith('kraken.') and name not in DEFAULTS:
            raise ValueError(f'{name}: not a receiver parameter')
        default = DEFAULTS.get(name, STATION_PARAMETERS.get(name))
        if default is not None and not (value is None and name in STATION_PARAMETERS):
            problem = _kind_problem(value, default, name)
            if problem is not None:
                raise ValueError(f'{name}: {problem}')
        p[name] = value
    for name, default, _, rule in PARAMETERS:
        v = p[name]
        if isinstance(rule, tuple) and len(rule) == 2 and not isinstance(rule[0], str):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not \
                    rule[0] <= v <= rule[1]:
                raise ValueError(f'{name}: {short_repr(v)} must be a number in [{rule[0]}, '
                                 f'{rule[1]}]')
        elif isinstance(rule, tuple) and v not in rule:
            raise ValueError(f'{name}: {short_repr(v)} is not one of {rule}')
    return p


def receiver_from_params(station, params):
    """(ReceiverConfig, ChannelMap) from station node parameter values (flat or nested).

    Uses the receiver parameters above plus the node's ``frame_id``, ``position``,
    ``geodetic_position``, ``geodetic_origin`` and ``position_covariance``. Raises
    :class:`~bearing_loc_ros.core.station.ConfigError` naming the parameter, also for
    ``kraken.max_age`` > 0 with ``kraken.stamp: receive`` (the age is measured from the
    receiver's TIME, which that stamp mode does not trust).
    """
    try:
        p = with_defaults(params)
    except ValueError as exc:
        name, _, problem = str(exc).partition(': ')
        raise ConfigError(name, problem) from None
    if p['kraken.stamp'] == 'receive' and p['kraken.max_age'] > 0:
        raise ConfigError('kraken.max_age', f"{p['kraken.max_age']:g} s has no effect with "
                          "kraken.stamp: receive (a reading stamped on receipt has no age); "
                          'set it to 0 or use kraken.stamp: receiver')
    sigma = SigmaModel(p['kraken.sigma_conf1_deg'], p['kraken.sigma_conf0_deg'],
                       p['kraken.sigma_snr_slope'], p['kraken.sigma_snr_ref_db'],
                       p['kraken.sigma_min_deg'], p['kraken.sigma_max_deg'])
    cfg = receiver_config(
        station, frame_id=p.get('frame_id', 'map') or 'map',
        position=list(p.get('position') or []),
        geodetic_position=list(p.get('geodetic_position') or []),
        geodetic_origin=list(p.get('geodetic_origin') or []),
        position_covariance=list(p.get('position_covariance') or []),
        sense=p['kraken.sense'], heading_source=p['kraken.heading_source'],
        array_heading_deg=p['kraken.array_heading_deg'],
        heading_reference=p['kraken.heading_reference'],
        declination_deg=p['kraken.declination_deg'],
        heading_offset_deg=p['kraken.heading_offset_deg'], min_speed=p['kraken.min_speed'],
        low_speed=p['kraken.low_speed'],
        heading_hold_timeout_s=p['kraken.heading_hold_timeout'],
        position_source=p['kraken.position_source'], gps_sigma_m=p['kraken.gps_sigma'],
        antenna_height_m=p['kraken.antenna_height'],
        min_confidence=p['kraken.min_confidence'], sigma=sigma)
    try:
        channels = channel_map_from_params(p['kraken.channels'], p['kraken.channel_bands_mhz'])
    except ValueError as exc:
        name, _, problem = str(exc).partition(': ')
        raise ConfigError('kraken.' + name if not name.startswith('channel ') else
                          'kraken.channel_bands_mhz', problem or str(exc)) from None
    return cfg, channels
