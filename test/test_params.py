"""The parameter schema (core.parameters) is the one source of every node parameter: the
declared node parameters, the shipped parameter files, the docs tables and bag process must
all agree with it. Also: deprecated names, integers for doubles, and run_node's exit codes."""
import glob
import os
import subprocess
import sys

import pytest
from rcl_interfaces.msg import ParameterType
from rclpy.node import Node
from rclpy.parameter import Parameter
import yaml

from bearing_loc_ros import ros_common
from bearing_loc_ros.core import parameter_docs as docs
from bearing_loc_ros.core import parameters as schema
from bearing_loc_ros.processes import interrupt
from ros_helpers import node_env, REPO

pytestmark = pytest.mark.ros

TYPE_CODES = {schema.BOOL: ParameterType.PARAMETER_BOOL,
              schema.INTEGER: ParameterType.PARAMETER_INTEGER,
              schema.DOUBLE: ParameterType.PARAMETER_DOUBLE,
              schema.STRING: ParameterType.PARAMETER_STRING,
              schema.DOUBLE_ARRAY: ParameterType.PARAMETER_DOUBLE_ARRAY,
              schema.STRING_ARRAY: ParameterType.PARAMETER_STRING_ARRAY}
#: Parameters every rclpy node declares itself.
BUILTIN = {'use_sim_time', 'start_type_description_service'}
SCENARIO = os.path.join(REPO, 'config', 'scenarios', 'seed000.yaml')
#: Overrides a node needs to start (not compared with the defaults).
REQUIRED = {'fusion_node': {}, 'station_node': {'position': [1.0, 2.0, 3.0]},
            'simulator_node': {'scenario': SCENARIO, 'start_delay': 0.0},
            'view_node': {'port': 0}}


def make_node(ctx, node, **overrides):
    from bearing_loc_ros.fusion_node import FusionNode
    from bearing_loc_ros.simulator_node import SimulatorNode
    from bearing_loc_ros.station_node import StationNode
    from bearing_loc_ros.view_node import ViewNode
    cls = {'fusion_node': FusionNode, 'station_node': StationNode,
           'simulator_node': SimulatorNode, 'view_node': ViewNode}[node]
    params = {k: v for k, v in dict(REQUIRED[node], **overrides).items() if v is not None}
    return cls(context=ctx, namespace='/params_test',
               parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])


@pytest.mark.parametrize('node', schema.NODES)
def test_declared_parameters_match_the_schema(ros, node):
    n = make_node(ros, node)
    try:
        params = {p.name: p for p in schema.schema(node)}
        old = schema.renamed(node)
        assert set(n._parameters) == set(params) | set(old) | BUILTIN
        for name, p in params.items():
            d = n.describe_parameters([name])[0]
            assert d.type == TYPE_CODES[p.type], name
            assert d.read_only == p.read_only, name
            assert d.description == p.description + (f' [{p.unit}]' if p.unit else ''), name
            if p.choices:
                assert d.additional_constraints == 'one of: ' + ', '.join(p.choices), name
            rng = list(d.integer_range) + list(d.floating_point_range)
            if p.min is None and p.max is None or p.type not in ('integer', 'double'):
                assert not rng, name
            else:
                (r,) = rng
                if p.min is not None:
                    assert r.from_value == p.min, name
                if p.max is not None:
                    assert r.to_value == p.max, name
            if name not in REQUIRED[node]:
                value = n._parameters[name].value
                if isinstance(p.default, list) and not p.default:
                    assert value in (None, []), name     # rclpy: an unset array is None
                else:
                    assert value == p.default and type(value) is type(p.default), name
        for name in old:
            assert n._parameters[name].value is None     # declared, unset
    finally:
        n.destroy_node()


@pytest.mark.parametrize('node', [n for n in schema.NODES if schema.PARAMS_FILES[n]])
def test_shipped_parameter_files_are_generated_from_the_schema(node):
    path = os.path.join(REPO, 'config', schema.PARAMS_FILES[node])
    with open(path, encoding='utf-8') as f:
        text = f.read()
    assert text == schema.yaml_text(node), f'regenerate: python -m ' \
        f'bearing_loc_ros.core.parameters --yaml {node} > config/{schema.PARAMS_FILES[node]}'
    body = yaml.safe_load(text)['/**']['ros__parameters']
    flat = {}
    for k, v in body.items():
        flat.update({f'{k}.{kk}': vv for kk, vv in v.items()} if isinstance(v, dict) else {k: v})
    for name, value in flat.items():
        p = schema.param(node, name)
        assert p.check(value) == value or p.type == schema.DOUBLE_ARRAY, name
        assert type(value) is type(p.default) or isinstance(p.default, list), name
        if p.example is None:
            assert value == p.default, name


def test_docs_tables_are_generated_from_the_schema():
    found = {}
    for path in glob.glob(os.path.join(REPO, 'docs', '**', '*.md'), recursive=True):
        with open(path, encoding='utf-8') as f:
            text = f.read()
        for node in schema.NODES:
            region = docs.docs_region(text, node)
            if region is not None:
                found[node] = path
                assert region == schema.markdown_table(node), \
                    f'{path}: python -m bearing_loc_ros.core.parameters --update-docs {path}'
    assert set(found) == set(schema.NODES), found


def test_view_schema_backlog_default_is_the_servers():
    from bearing_loc_ros.foxglove_view import DEFAULT_BACKLOG
    assert schema.param('view_node', 'max_backlog').default == DEFAULT_BACKLOG


def test_markdown_command_prints_the_table():
    for node in schema.NODES:
        out = subprocess.run([sys.executable, '-m', 'bearing_loc_ros.core.parameters',
                              '--markdown', node], capture_output=True, text=True, cwd=REPO,
                             env=node_env(), timeout=60, check=True).stdout
        assert out == schema.markdown_table(node)
        assert out.count('\n') == len(schema.schema(node)) + 2


def test_schema_check_rules():
    p = schema.param('fusion_node', 'outlier_gate')
    assert p.check(1) == 1.0 and isinstance(p.check(1), float)
    for bad in (True, 'x', 0.2, 1.5, float('nan')):
        with pytest.raises(ValueError, match='^outlier_gate: '):
            p.check(bad)
    with pytest.raises(ValueError, match="^trigger: 'sometimes' is not one of"):
        schema.param('fusion_node', 'trigger').check('sometimes')
    with pytest.raises(ValueError, match='below the minimum'):
        schema.param('simulator_node', 'time_scale').check(0.0)
    assert schema.param('station_node', 'position').check([1, 2, 3]) == [1.0, 2.0, 3.0]
    with pytest.raises(ValueError, match='^rate: .* beyond the float range'):
        schema.param('fusion_node', 'rate').check(10 ** 400)
    with pytest.raises(ValueError, match='^buffer_size: .* beyond the int64 range'):
        schema.param('fusion_node', 'buffer_size').check(10 ** 30)
    # Arrays of doubles: every value finite (a NaN map centre ran without a map), and within
    # the parameter's range where it has one (1e300 drew a map of infinite cells).
    for node, name in (('station_node', 'position'), ('fusion_node', 'accuracy_map.center')):
        with pytest.raises(ValueError, match=f'^{name}: every value must be finite, got nan'):
            schema.param(node, name).check([float('nan'), 0.0])
    with pytest.raises(ValueError, match=r'^accuracy_map.center: 1e\+300 is outside '
                                         r'\[-1e\+12, 1e\+12\]'):
        schema.param('fusion_node', 'accuracy_map.center').check([1e300, 0.0])


def test_fusion_config_is_built_from_the_schema_for_node_and_bag_process(ros):
    from bearing_loc_ros import bag_process
    from bearing_loc_ros.core.fusion import FusionConfig
    assert FusionConfig() == FusionConfig.from_parameters().replace(estimator_options={})
    path = os.path.join(REPO, 'config', 'fusion.yaml')
    offline = bag_process.fusion_config(bag_process.fusion_params(path, ['rate=2']))
    given = {k: v for k, v in bag_process.read_params_file(path).items()
             if not isinstance(v, dict)}
    n = make_node(ros, 'fusion_node', **dict(given, rate=2.0))
    try:
        assert n.core.config == offline and offline.rate == 2.0
    finally:
        n.destroy_node()


def test_deprecated_names_are_mapped_with_a_warning(ros, capsys):
    n = make_node(ros, 'station_node', diagnostics_period_s=2.5, odometry_tolerance_s=0.3,
                  platform_odometry='odom', position=None)
    try:
        assert n.poses.tolerance_ns == 300_000_000
        assert n.get_parameter('diagnostics_period').value == 1.0   # the new name is unset
        timers = [t.timer_period_ns for t in n.timers]
        assert 2_500_000_000 in timers
    finally:
        n.destroy_node()
    with pytest.raises(ros_common.ParameterError, match="'diagnostics_period_s': deprecated"):
        make_node(ros, 'station_node', diagnostics_period_s=2.5, diagnostics_period=1.0)
    warned = []
    p = schema.resolve('station_node', {'odometry_tolerance_s': 0.2}, warned.append)
    assert p['odometry_tolerance'] == 0.2 and len(warned) == 1 and 'deprecated' in warned[0]
    with pytest.raises(ValueError, match='^nonsense: not a parameter'):
        schema.resolve('fusion_node', {'nonsense': 1})


def test_integer_values_are_accepted_for_double_parameters(ros):
    n = make_node(ros, 'station_node', position=[1, 2, 3], sigma_azimuth_deg=3)
    try:
        assert n.config.position.tolist() == [1.0, 2.0, 3.0]
        assert n.get_parameter('position').type_ == Parameter.Type.DOUBLE_ARRAY
        assert n.get_parameter('sigma_azimuth_deg').value == 3.0
    finally:
        n.destroy_node()
    f = make_node(ros, 'fusion_node', rate=5)
    try:
        assert f.core.config.rate == 5.0
        res = f.set_parameters([Parameter('outlier_gate', value=1)])[0]
        assert res.successful and f.core.config.outlier_gate == 1.0
        res = f.set_parameters([Parameter('outlier_gate', value='x')])[0]
        assert not res.successful
    finally:
        f.destroy_node()


def test_integer_array_on_the_command_line(tmp_path):
    """``position:=[1,2,3]`` (an INTEGER_ARRAY for rclpy) starts the node; misspelt names
    from the command line and a ``/**:`` parameter file are named in one warning, with the
    closest parameter, while rclpy's own parameters are not."""
    f = tmp_path / 'station.yaml'
    f.write_text('/**:\n  ros__parameters:\n    sigma_azimth_deg: 3.0\n'
                 '    use_sim_time: false\n')
    proc = subprocess.Popen(
        [sys.executable, '-m', 'bearing_loc_ros.station_node', '--ros-args', '-r',
         '__ns:=/int_array', '-p', 'position:=[1,2,3]', '-p', 'udp_prot:=5000',
         '--params-file', str(f)], cwd=REPO, env=node_env(),
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        out = ''
        for line in proc.stdout:
            out += line
            if "station 'int_array'" in line or 'error' in line:
                break
        assert 'position [1.0, 2.0, 3.0] m' in out, out
        warned = [x for x in out.splitlines() if 'ignored' in x]
        assert len(warned) == 1, out
        assert ("ignored 2 parameters that station_node does not have: 'sigma_azimth_deg' "
                "(did you mean 'sigma_azimuth_deg'?), 'udp_prot' (did you mean 'udp_port'?)"
                ) in warned[0]
    finally:
        interrupt(proc, 10)


def test_a_misspelt_name_is_named_also_when_another_value_stops_the_node(ros, capfd):
    with pytest.raises(ros_common.ParameterError, match="'sigma_azimuth_deg'"):
        make_node(ros, 'station_node', sigma_azimth_deg=3.0, sigma_azimuth_deg=-1.0)
    assert "'sigma_azimth_deg' (did you mean 'sigma_azimuth_deg'?)" in capfd.readouterr().err


def test_unknown_names_get_the_closest_parameter():
    assert schema.unknown_message('fusion_node', []) is None
    assert schema.unknown_message('fusion_node', ['zzzz']) == \
        "ignored 1 parameter that fusion_node does not have: 'zzzz'"
    assert schema.did_you_mean('station_node', 'diagnostics_period_sec') == \
        " (did you mean 'diagnostics_period_s'?)"
    with pytest.raises(ValueError, match="^estimater: not a parameter of fusion_node "
                                         "\\(did you mean 'estimator'\\?\\)$"):
        schema.resolve('fusion_node', {'estimater': 'mle'})


class _Failing(Node):
    def __init__(self):
        super().__init__('failing')
        self.create_timer(0.01, self._boom)

    def _boom(self):
        raise ValueError('boom in a callback')


def test_run_node_start_up_error_is_configuration_error(capsys):
    def factory():
        raise ros_common.ParameterError('rate', 'must be > 0')
    assert ros_common.run_node(factory, args=[]) == 1
    err = capsys.readouterr().err
    assert err == "error: parameter 'rate': must be > 0\n"


def test_run_node_callback_error_is_an_internal_error(capsys):
    assert ros_common.run_node(_Failing, args=[]) == ros_common.INTERNAL_ERROR
    err = capsys.readouterr().err
    assert err.startswith('internal error:') and 'configuration' in err
    assert 'Traceback' in err and 'ValueError: boom in a callback' in err
    assert not err.startswith('error:')


def test_a_huge_value_is_echoed_short():
    """A 5 MB estimator string was echoed whole: one 5 MB error line."""
    from bearing_loc_ros.bag_process import fusion_params
    from bearing_loc_ros.cli import InputError
    for value in ('x' * 5_000_000, '[' + ', '.join(['1.0'] * 100000) + ']'):
        with pytest.raises(InputError) as e:
            fusion_params(overrides=[f'estimator={value}'])
        assert len(str(e.value)) < 300 and 'estimator' in str(e.value)
