"""The fusion node's parameter helpers: station ids (core.fusion.config), the accuracy map
settings (core.display) and core errors as ParameterError (ros_common)."""

import pytest

import numpy as np

from bearing_loc_ros.core.display import AccuracyMap, AccuracyMapConfig
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


def test_accuracy_map_follows_moving_stations_only_when_it_can_change():
    # Two stations: a move beyond move_threshold recomputes the map. One station (a DF car
    # driving): every cell is unobservable wherever it is, so its moves recompute nothing
    # (it used to recompute and log about 10 maps a second).
    cfg = AccuracyMapConfig.from_parameters({'accuracy_map.enabled': True,
                                             'accuracy_map.move_threshold': 1.0})
    m = AccuracyMap(cfg)
    two = {'a': (np.zeros(3), 0.01, 0.01), 'b': (np.array([1000.0, 0, 0]), 0.01, 0.01)}
    assert m.update(two) is not None and m.update(two) is None
    two['b'] = (np.array([1010.0, 0, 0]), 0.01, 0.01)
    assert m.update(two) is not None
    one = {'car': (np.zeros(3), 0.05, float('nan'))}
    grid, data = m.update(one)
    assert np.all(data == 100)
    for x in (10.0, 100.0, 1000.0):
        assert m.update({'car': (np.array([x, 0, 0]), 0.05, float('nan'))}) is None


def test_core_errors_name_the_parameter():
    e = core_parameter_error(ValueError('options.max_iterations: must be >= 1'), 'estimator')
    assert e.name == 'max_iterations' and str(e) == \
        "parameter 'max_iterations': must be >= 1"
    e = core_parameter_error(ValueError('accuracy_map.model: bad'), 'estimator')
    assert e.name == 'accuracy_map.model'
    e = core_parameter_error(ValueError('unknown estimator foo'), 'estimator')
    assert e.name == 'estimator' and str(e).endswith('unknown estimator foo')
