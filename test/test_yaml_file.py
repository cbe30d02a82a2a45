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
    ('1e+3', 1000.0), ('.5', 0.5), ('1.5', 1.5), ('10', 10),
    ('[1e3, 2]', [1000.0, 2]), ('abc', 'abc'), ('1e', '1e'), ('e3', 'e3'), ('1.2.3', '1.2.3'),
    ('-.5', -0.5), ('._', '._'), ('-._', '-._'), ('1_e3', '1_e3'),
    # YAML 1.1 read these as 1000, 1000.5, 8 (octal) and 90 (base 60)
    ('1_000', '1_000'), ('1_000.5', '1_000.5'), ('010', 10), ('1:30', '1:30'),
    ('0o10', 8), ('0x1F', 31),
])
def test_numbers_as_yaml_1_2_reads_them(text, value):
    got = load_text(text)
    assert got == value and type(got) is type(value)


def test_a_key_given_twice_is_an_error_naming_its_line(tmp_path):
    """`duration: 2.0` then `duration: 5.0` simulated 5 s without a word."""
    path = tmp_path / 'twice.yaml'
    path.write_text('duration: 2.0\nstations: []\nduration: 5.0\n')
    with pytest.raises(ValueError, match=r"invalid YAML \(.*key 'duration' given twice in "
                                         r"one mapping.*line 3"):
        read_yaml(path, 'x')
    # a merge key is not a duplicate, and its keys may be overridden
    assert load_text('a: &x {k: 1, j: 2}\nb:\n  <<: *x\n  k: 3\n')['b'] == {'k': 3, 'j': 2}


def test_a_huge_or_endless_file_is_refused_before_parsing(tmp_path):
    """A 200 MB scenario was still being parsed after 120 s."""
    from bearing_loc_ros.core.yaml_file import MAX_BYTES
    path = tmp_path / 'huge.yaml'
    line = 'key: "' + 'x' * 1000 + '"\n'
    path.write_text('a:\n' + ('  - ' + line) * (MAX_BYTES // 1000 + 10))
    with pytest.raises(ValueError, match=r'^x: scenario larger than 8 MiB$'):
        read_yaml(path, 'x', kind='scenario')
    if os.path.exists('/dev/zero'):
        with pytest.raises(ValueError, match=r'^x: file larger than'):
            read_yaml('/dev/zero', 'x')
    ok = tmp_path / 'ok.yaml'
    ok.write_text('a: 1\n')
    assert read_yaml(ok, 'x') == {'a': 1}


@pytest.mark.parametrize('params', [False, True])
def test_aliases_that_expand_to_a_billion_values_are_refused(tmp_path, params):
    """A 441-byte file of nested aliases ("billion laughs") made a MemoryError after 45 s
    and 3 GB (a scenario error echoing the value) or in the parameter flattening."""
    keys = [f'k{j}' for j in range(10)]
    levels = ['&b0 {' + ', '.join(f'{k}: 1' for k in keys) + '}'] + [
        f'&b{i} {{' + ', '.join(f'{k}: *b{i - 1}' for k in keys) + '}' for i in range(1, 9)]
    path = tmp_path / 'bomb.yaml'
    path.write_text('\n'.join(f'l{i}: {v}' for i, v in enumerate(levels)) + '\n')
    with pytest.raises(ValueError, match=r'^x: invalid YAML \(more than 1,000,000 values '
                                         r'once its aliases'):
        read_yaml(path, 'x', params=params)
    small = tmp_path / 'small.yaml'                 # aliases as such are fine
    small.write_text('a: &p [1.0, 2.0]\nb: *p\n')
    assert read_yaml(small, 'x', params=params) == {'a': [1.0, 2.0], 'b': [1.0, 2.0]}


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


#: Plain scalars whose type rcl decides differently from YAML 1.1 or 1.2, and ordinary ones.
RCL_SCALARS = ('1_000', '12:30', 'nan', 'NaN', '.nan', 'nan(x)', '-nan', 'inf', '-inf', '+inf',
               '.inf', '-.inf', '+.Inf', '.NAN', '.nAn', '-.nan', '.infinity',
               'Infinity', 'INF', 'y', 'Y', 'n', 'N', 'yes', 'No', 'on', 'OFF',
               'True', 'tRue', 'yES', '1e3', '1.0e7', '2E-6', '0x10', '-0x1F', '010', '08',
               '0o10', '0b11', '+5', '-0', '00', '1.', '.5', '5.', '+.5', '1e', '1d', '~',
               'null', '1_0.5', '1.2.3', '0x1p3', '0x1.8p1', '1e400', '1e-310', '1e-400',
               '0e400', '2.2250738585072014e-308', '9223372036854775807',
               '9223372036854775808', '-9223372036854775809', '0xFFFFFFFFFFFFFFFF', 'a b',
               '0x1p1024', '0x1.fffffffffffff8p1023', '-0x1p1024',
               '[1, 2]', '[y, n]', '[nan, 1.0]', '[a, "1"]', "'1'", '"yes"', '!!str 5')
#: Values rcl refuses: no value, an empty list, lists mixing types.
RCL_REFUSED = ('', '[]', '[1, 2.5]', "['1', 2]", '[true, 1]', '[[1], [2]]')


def _same(a, b):
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a):
        return math.isnan(b)
    return type(a) is type(b) and a == b


def _rcl_parameters(tmp_path, texts, cli):
    """{name: value} rclpy's node gets for p0, p1, ... = ``texts``, by a parameter file or
    by ``-p`` (None when rcl refuses the arguments)."""
    rclpy = pytest.importorskip('rclpy')
    from rclpy.context import Context
    from rclpy.node import Node
    if cli:
        args = ['--ros-args'] + [a for k, t in enumerate(texts) for a in ('-p', f'p{k}:={t}')]
    else:
        path = tmp_path / 'rcl.yaml'
        path.write_text('probe:\n  ros__parameters:\n'
                        + ''.join(f'    p{k}: {t}\n' for k, t in enumerate(texts)))
        args = ['--ros-args', '--params-file', str(path)]
    ctx = Context()
    try:
        rclpy.init(context=ctx, args=args)
    except Exception:       # rcl's parse error (RCLError)
        return None
    try:
        try:
            node = Node('probe', context=ctx,
                        automatically_declare_parameters_from_overrides=True)
        except ValueError:      # parsed without a type ([]): no node can declare it
            return None
        got = {f'p{k}': node.get_parameter(f'p{k}').value for k in range(len(texts))}
        node.destroy_node()
        return got
    finally:
        rclpy.shutdown(context=ctx)


@pytest.mark.parametrize('cli', [False, True], ids=['params-file', '-p'])
def test_parameter_values_are_typed_as_rcl_types_them(tmp_path, cli):
    # bag process --params-file / -p, calibrate --params and bag import --params must see
    # what the nodes see: rclpy's own parse of the same text is the reference.
    from bearing_loc_ros.core.yaml_file import load_param_text, read_yaml
    rcl = _rcl_parameters(tmp_path, RCL_SCALARS, cli)
    assert rcl is not None
    if cli:
        ours = {f'p{k}': load_param_text(t) for k, t in enumerate(RCL_SCALARS)}
    else:
        ours = read_yaml(tmp_path / 'rcl.yaml', 'x', params=True)['probe']['ros__parameters']
    wrong = {RCL_SCALARS[int(k[1:])]: (ours[k], v) for k, v in rcl.items()
             if not _same(ours[k], v)}
    assert not wrong


@pytest.mark.parametrize('text', RCL_REFUSED)
def test_values_rcl_refuses_are_errors(tmp_path, text):
    import yaml
    from bearing_loc_ros.core.yaml_file import load_param_text
    assert _rcl_parameters(tmp_path, [text], cli=False) is None
    path = tmp_path / 'rcl.yaml'
    with pytest.raises(ValueError, match=r'^x: invalid YAML \(.*line 3'):
        read_yaml(path, 'x', params=True)
    if text:        # an empty -p value is not even an argument rcl accepts
        with pytest.raises(yaml.YAMLError):
            load_param_text(text)


def test_bag_process_overrides_name_what_rcl_refuses():
    with pytest.raises(InputError, match=r'^param: ema_alpha: a list must hold items of one '):
        fusion_params(None, ['ema_alpha=[1, 2.5]'])
    params = fusion_params(None, ['publish_low_confidence=y'])
    assert params['publish_low_confidence'] is True
