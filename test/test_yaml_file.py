"""YAML read as the ROS 2 parameter files are: ``1e3`` is a number (YAML 1.2), not a string.

PyYAML alone follows YAML 1.1, where ``1e3`` and ``1.0e7`` are strings; rcl's parser (what
``--params-file`` of the nodes reads) takes them as doubles. The package's readers must see
the same values the nodes see.
"""

import math
import os

import pytest

from bearing_loc_ros.bag_process import fusion_params
from bearing_loc_ros.cli import InputError
from bearing_loc_ros.core.scenario_loader import load_scenario
from bearing_loc_ros.core.yaml_file import load_text, read_yaml

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.parametrize('text, value', [
    ('1e3', 1000.0), ('1.0e7', 1e7), ('2E-6', 2e-6), ('-1e-9', -1e-9), ('+1e3', 1000.0),
    ('1e+3', 1000.0), ('.5', 0.5), ('1.5', 1.5), ('10', 10), ('1_000', 1000),
    ('[1e3, 2]', [1000.0, 2]), ('abc', 'abc'), ('1e', '1e'), ('e3', 'e3'), ('1.2.3', '1.2.3'),
    ('-.5', -0.5), ('._', '._'), ('-._', '-._'), ('1_e3', '1_e3'), ('1_000.5', 1000.5),
])
def test_numbers_as_yaml_1_2_reads_them(text, value):
    got = load_text(text)
    assert got == value and type(got) is type(value)


def test_inf_and_nan_stay_floats():
    assert load_text('.inf') == math.inf and load_text('-.inf') == -math.inf
    assert math.isnan(load_text('.nan'))


def test_no_python_objects():
    with pytest.raises(Exception):
        load_text('!!python/object/apply:os.system ["true"]')


def test_a_scenario_with_exponent_numbers_loads(tmp_path):
    with open(os.path.join(REPO, 'config', 'scenarios', 'seed000.yaml'), encoding='utf-8') as f:
        text = f.read()
    text = text.replace('duration: 100.0', 'duration: 1e2').replace('truth_rate: 10.0',
                                                                    'truth_rate: 1.0e1')
    path = tmp_path / 's.yaml'
    path.write_text(text, encoding='utf-8')
    sc = load_scenario(path)
    assert sc.duration == 100.0 and sc.truth_rate == 10.0


def test_parameter_files_and_overrides_with_exponents(tmp_path):
    path = tmp_path / 'fusion.yaml'
    path.write_text('fusion:\n  ros__parameters:\n    tolerance: 1e-6\n    buffer_age: 2e1\n')
    params = fusion_params(str(path), ['max_latency=1.5e0'])
    assert params['tolerance'] == 1e-6 and params['buffer_age'] == 20.0
    assert params['max_latency'] == 1.5
    assert read_yaml(path, 'x')['fusion']['ros__parameters']['tolerance'] == 1e-6
    with pytest.raises(InputError, match='^param: tolerance: invalid YAML'):
        fusion_params(None, ['tolerance=[1,'])


def test_station_parameter_files_read_as_the_station_node_reads_them(tmp_path):
    # bag import and calibrate read the station nodes' parameter file: a receiver bound
    # written 1e3 (accepted by station_node --params-file) used to reach them as the string
    # '1e3' and be refused ("must be a number").
    from bearing_loc_ros.cli.calibrate import load_station_params, station_params
    path = tmp_path / 'station.yaml'
    path.write_text('/**:\n  ros__parameters:\n    kraken:\n      max_age: 1e3\n')
    assert station_params(load_station_params(str(path)), 's1')['kraken.max_age'] == 1000.0
