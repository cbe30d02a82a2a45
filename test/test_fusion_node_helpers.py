"""The fusion node's parameter helpers: station ids (core.fusion.config), the accuracy map
settings (core.display) and core errors as ParameterError (ros_common)."""

import time

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
    assert m.update(two, 0.0) is not None and m.update(two, 0.1) is None
    two['b'] = (np.array([1010.0, 0, 0]), 0.01, 0.01)
    assert m.update(two, 100.0) is not None
    one = {'car': (np.zeros(3), 0.05, float('nan'))}
    grid, data = m.update(one)
    assert np.all(data == 100)
    for x in (10.0, 100.0, 1000.0):
        assert m.update({'car': (np.array([x, 0, 0]), 0.05, float('nan'))}, 200.0 + x) is None


def test_accuracy_map_recomputations_for_moving_stations_are_spaced():
    """A station whose position jumps on every bearing recomputed the map on every tick: a
    2000 x 2000 map (seconds each) starved the fusion. Moves wait MIN_MOVE_INTERVAL_S and
    MOVE_COST_FACTOR x the compute time; a new station set does not wait."""
    from bearing_loc_ros.core import display
    m = AccuracyMap(AccuracyMapConfig.from_parameters({'accuracy_map.enabled': True}))
    geo = {'a': (np.zeros(3), 0.01, 0.01), 'b': (np.array([1000.0, 0, 0]), 0.01, 0.01)}
    assert m.update(geo, 0.0) is not None
    moved = dict(geo, b=(np.array([101000.0, 0, 0]), 0.01, 0.01))
    assert m.update(moved, 0.5) is None and m.pending            # due at >= 1 s: pending
    assert m.update(moved, 1.5) is not None and not m.pending    # the same geometry, later
    m.update(geo, 10.0)
    assert m.update(dict(moved, c=geo['a']), 0.6) is not None    # a new set at once
    due = m._next_move_s
    assert due >= 0.6 + display.MIN_MOVE_INTERVAL_S
    assert m.update(geo | {'c': geo['a']}, due - 1e-3) is None
    grid, _ = m.update(geo | {'c': geo['a']}, due)               # the same set, moved back
    assert grid.width == 100


def test_a_slow_accuracy_map_waits_longer_before_it_follows_moves(monkeypatch):
    from bearing_loc_ros.core import display
    real = display.occupancy_error_map

    def slow(*args, **kwargs):                  # a map that takes 0.1 s to compute
        time.sleep(0.1)
        return real(*args, **kwargs)
    monkeypatch.setattr(display, 'occupancy_error_map', slow)
    m = AccuracyMap(AccuracyMapConfig.from_parameters({'accuracy_map.enabled': True}))
    geo = {'a': (np.zeros(3), 0.01, 0.01), 'b': (np.array([1000.0, 0, 0]), 0.01, 0.01)}
    t = time.monotonic()
    assert m.update(geo, t) is not None
    moved = dict(geo, b=(np.array([2000.0, 0, 0]), 0.01, 0.01))
    # due after at least 0.1 + 20 x 0.1 s (a fast map: after 1 s)
    assert m._next_move_s >= t + 0.1 + display.MOVE_COST_FACTOR * 0.1
    assert m.update(moved, t + 0.1 + 1.5) is None
    assert m.update(moved, m._next_move_s) is not None


def test_core_errors_name_the_parameter():
    e = core_parameter_error(ValueError('options.max_iterations: must be >= 1'), 'estimator')
    assert e.name == 'max_iterations' and str(e) == \
        "parameter 'max_iterations': must be >= 1"
    e = core_parameter_error(ValueError('accuracy_map.model: bad'), 'estimator')
    assert e.name == 'accuracy_map.model'
    e = core_parameter_error(ValueError('unknown estimator foo'), 'estimator')
    assert e.name == 'estimator' and str(e).endswith('unknown estimator foo')
