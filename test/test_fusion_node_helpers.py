"""The fusion node's parameter helpers: station ids (core.fusion.config), the accuracy map
settings (core.display) and core errors as ParameterError (ros_common)."""

import pytest

from bearing_loc_ros.core.display import AccuracyMapConfig
from bearing_loc_ros.core.fusion.config import check_station_ids
from bearing_loc_ros.ros_common import core_parameter_error


def test_station_ids_are_ros_name_paths_listed_once():
    assert check_station_ids(('s1', 'site_a/s2')) == ['s1', 'site_a/s2']
    for bad in ('1st', 's1/', '/s1', 's-1', ''):
        with pytest.raises(ValueError, match=f'stations: {bad!r} is not a valid station id'):
            check_station_ids(['s1', bad])
    with pytest.raises(ValueError, match="stations: 's1' is listed twice"):
        check_station_ids(['s1', 's2', 's1'])


def test_accuracy_map_settings_from_parameter_values():
    cfg = AccuracyMapConfig.from_parameters({
        'accuracy_map.enabled': True, 'accuracy_map.center': [1.0, 2.0],
        'accuracy_map.size': 500.0, 'estimator': 'mle'})
    assert cfg.center == (1.0, 2.0) and cfg.size == 500.0 and cfg.model == 'crlb'


def test_core_errors_name_the_parameter():
    e = core_parameter_error(ValueError('options.max_iterations: must be >= 1'), 'estimator')
    assert e.name == 'max_iterations' and str(e) == \
        "parameter 'max_iterations': must be >= 1"
    e = core_parameter_error(ValueError('accuracy_map.model: bad'), 'estimator')
    assert e.name == 'accuracy_map.model'
    e = core_parameter_error(ValueError('unknown estimator foo'), 'estimator')
    assert e.name == 'estimator' and str(e).endswith('unknown estimator foo')
