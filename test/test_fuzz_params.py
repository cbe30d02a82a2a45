"""Fuzzing the parameter and scenario file parsers and the station configuration.

* The fusion params file as ``bearing_loc bag process --params-file`` reads it
  (read_params_file -> fusion_params -> fusion_config): arbitrary bytes, invalid YAML, and
  the shipped config/fusion.yaml with values replaced by hostile ones (10^400, .nan, .inf,
  strings, lists, mappings, null). Property: an InputError (a ValueError) with a message, or
  a FusionConfig that passes its own validate().
* The simulator scenario (core.simulation.parse_scenario) with hostile values: a ValueError
  naming the key, or a Scenario.
* station_config (the station node's parameters, as rcl hands them over and beyond: NaN,
  ±inf, 10^400, wrong types): a ConfigError naming the parameter, or a valid StationConfig.

Nothing else may escape (OverflowError, TypeError, KeyError...). Hypothesis runs
derandomised with no example database and a fixed budget.
"""

import math
import os
import tempfile

from hypothesis import example, given, HealthCheck, settings, strategies as st
import numpy as np
import pytest
import yaml

from bearing_loc_ros.cli import InputError
from bearing_loc_ros.core.simulation import parse_scenario
from bearing_loc_ros.core.station import ConfigError, station_config

try:  # the params-file functions live in bag_process (earlier: the bag CLI module)
    from bearing_loc_ros.bag_process import fusion_config, fusion_params
except ImportError:
    from bearing_loc_ros.cli.bag import fusion_config, fusion_params

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FUZZ = settings(max_examples=150, derandomize=True, database=None, deadline=None,
                suppress_health_check=list(HealthCheck))
with open(os.path.join(REPO, 'config', 'fusion.yaml'), encoding='utf-8') as _f:
    FUSION_YAML = yaml.safe_load(_f)
with open(os.path.join(REPO, 'config', 'scenarios', 'static3.yaml'), encoding='utf-8') as _f:
    SCENARIO = yaml.safe_load(_f)

hostile = st.one_of(
    st.sampled_from([None, True, False, 0, -1, 10 ** 400, -10 ** 400, 2 ** 63, math.nan,
                     math.inf, -math.inf, 1e308, -0.0, 5e-324, '', 'x', '1e999', [], {},
                     [math.nan], [10 ** 400] * 3, {'a': 1}]),
    st.integers(), st.floats(), st.text(max_size=8),
    st.lists(st.floats(), max_size=4))


def _params_file(text):
    fd, path = tempfile.mkstemp(suffix='.yaml')
    with os.fdopen(fd, 'wb') as f:
        f.write(text if isinstance(text, bytes) else text.encode('utf-8', 'surrogatepass'))
    return path


def check_fusion_params(text):
    path = _params_file(text)
    try:
        try:
            config = fusion_config(fusion_params(path))
        except ValueError as exc:  # InputError is a ValueError
            assert str(exc)
            return None
    finally:
        os.unlink(path)
    return config.validate()


@FUZZ
@given(st.binary(max_size=200))
@example(b'/**:\n  ros__parameters: [1, 2]\n')
@example(b'\xff\xfe')
@example(b'a: &x [*x]\n')
def test_params_file_bytes(data):
    check_fusion_params(data)


# Every hostile value, integers beyond the float range included (10 ** 400).
fusion_values = hostile


@FUZZ
@given(st.dictionaries(st.sampled_from(sorted(FUSION_YAML['/**']['ros__parameters'])),
                       fusion_values, min_size=1, max_size=3))
@example({'station_timeout': math.nan})
@example({'buffer_size': math.inf})
@example({'min_stations': -math.inf})
@example({'buffer_size': 'many'})
def test_params_file_hostile_values(changes):
    body = dict(FUSION_YAML['/**']['ros__parameters'], **changes)
    check_fusion_params(yaml.safe_dump({'/**': {'ros__parameters': body}}))


@pytest.mark.parametrize('key, value, kind', [
    ('sync_tolerance', 10 ** 400, 'double'), ('rate', 10 ** 400, 'double'),
    ('rate', -10 ** 400, 'double'), ('buffer_size', 10 ** 400, 'integer'),
    ('buffer_size', 2 ** 63, 'integer')])
def test_params_file_numbers_beyond_float_range(key, value, kind):
    """An integer that no double (or int64) holds is refused naming the parameter, never
    escapes as OverflowError (float(10 ** 400) raises it). rcl reads 10 ** 400 as a string
    (strtol and strtod both overflow) and 2 ** 63 as a double, so the node refuses their
    type; so does bag process (the Python API's range check: test_params)."""
    body = dict(FUSION_YAML['/**']['ros__parameters'], **{key: value})
    path = _params_file(yaml.safe_dump({'/**': {'ros__parameters': body}}))
    try:
        with pytest.raises(InputError) as err:
            fusion_config(fusion_params(path))
    finally:
        os.unlink(path)
    assert str(err.value).startswith(f'{key}: expected {kind}, got ')
    assert len(str(err.value)) <= 200


@FUZZ
@given(st.sampled_from(['duration', 'epoch', 'truth_rate', 'frame_id', 'stations',
                        'targets', 'station_defaults', 'geodetic_origin', 'name']), hostile,
       st.sampled_from(['position', 'sigma_az', 'rate', 'dims', 'id', 'clock_offset']),
       hostile)
def test_scenario_hostile_values(key, value, station_key, station_value):
    data = yaml.safe_load(yaml.safe_dump(SCENARIO))
    data[key] = value
    if isinstance(data.get('stations'), list) and data['stations'] \
            and isinstance(data['stations'][0], dict):
        data['stations'][0][station_key] = station_value
    try:
        parse_scenario(data, 'fuzz.yaml')
    except ValueError as exc:
        assert str(exc).startswith('fuzz.yaml')


STATION_PARAMS = ('position', 'geodetic_position', 'geodetic_origin', 'position_covariance',
                  'sigma_azimuth_deg', 'sigma_elevation_deg', 'azimuth_offset_deg',
                  'azimuth_reference', 'frame_id', 'moving', 'measures_elevation')


@FUZZ
@given(st.dictionaries(st.sampled_from(STATION_PARAMS), hostile, max_size=3))
@example({'position': [10 ** 400, 0, 0]})
@example({'sigma_azimuth_deg': 10 ** 400})
@example({'sigma_azimuth_deg': 'x'})
@example({'position_covariance': [10 ** 400, 1, 1]})
@example({'azimuth_offset_deg': None})
def test_station_config_hostile_values(changes):
    kwargs = dict({'position': [1.0, 2.0, 3.0]}, **changes)
    try:
        c = station_config('st', **kwargs)
    except ConfigError as exc:
        assert exc.field in STATION_PARAMS + ('station_id',), exc
        return
    assert c.moving or np.all(np.isfinite(c.position))
    assert 0 < c.sigma_azimuth <= math.pi and 0 < c.sigma_elevation <= math.pi
    assert math.isfinite(c.azimuth_offset) and np.all(np.isfinite(c.position_covariance))
