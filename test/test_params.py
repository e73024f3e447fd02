"""
The nodes' parameters: declared with a description, set by the package only where several
nodes must agree (params/robot.yaml), and the other configurations' files valid.
"""
import math

import pytest
import yaml

from activeloc_ros.paths import NODE_NAMES
from conftest import PARAMS, params_args


def node_class(name):
    import importlib
    module = importlib.import_module(f'activeloc_ros.nodes.{name}_node')
    return getattr(module, f'{name.capitalize()}Node')


@pytest.mark.parametrize('name', NODE_NAMES)
def test_every_declared_parameter_has_a_description(context, name):
    node = node_class(name)(context=context, cli_args=params_args())
    try:
        for key in node._parameters:
            if key not in ('use_sim_time', 'start_type_description_service'):
                assert node.describe_parameter(key).description, f'{key} has no description'
    finally:
        node.destroy_node()


def test_the_package_gives_its_nodes_only_the_robot_file():
    """
    Defaults live in the declarations alone: a params file that repeated them would be a
    second place a value has to be changed, and a stale copy would win over the code.
    """
    from activeloc_ros.paths import packaged_params_files
    assert [p.name for p in packaged_params_files()] == ['robot.yaml']
    for name in NODE_NAMES:
        assert not (PARAMS / f'{name}.yaml').exists(), f'params/{name}.yaml repeats defaults'


def test_robot_yaml_is_declared_by_the_nodes_that_share_it(context):
    """
    params/robot.yaml holds what several nodes must agree on, once: every key is a
    parameter of at least two nodes, and each of them starts with the file's value.
    """
    content = yaml.safe_load((PARAMS / 'robot.yaml').read_text())
    values = content['/**']['ros__parameters']
    sharing = {key: [] for key in values}
    for name in NODE_NAMES:
        node = node_class(name)(context=context, cli_args=params_args())
        try:
            for key, value in values.items():
                if node.has_parameter(key):
                    sharing[key].append(name)
                    assert node.get_parameter(key).value == value, f'{name}: {key}'
        finally:
            node.destroy_node()
    assert all(len(names) >= 2 for names in sharing.values()), sharing


@pytest.mark.parametrize('name, expected', [
    ('mirrored_border.yaml', {'encoder_pad': 32, 'conv_padding': 'zeros'}),
    ('two_lstms.yaml', {'layers': 2}),
    ('fast.yaml', {'input_height': 160, 'layers': 2, 'location_prior': 3.57}),
])
def test_each_other_configuration_passes_bringups_checks_and_sets_its_values(name, expected):
    from activeloc_ros.bringup import parse_args
    from activeloc_ros.graph_plan import node_values
    from activeloc_ros.preflight import check_node_params
    path = str(PARAMS / name)
    check_node_params(parse_args(['--params', path]))      # raises on any bad key or value
    values = node_values('perception', [path])
    assert {key: values[key] for key in expected} == expected


def test_the_fast_configuration_acts_only_on_maps_above_twice_its_uniform_peak():
    """Its 10 x 10 grid's uniform map peaks at 1 / 100: the controller's min_peak follows."""
    from activeloc_ros.graph_plan import node_values
    assert node_values('controller', [str(PARAMS / 'fast.yaml')])['min_peak'] == 2 / 100


# -- params files: nothing in them passes in silence (issue 13, item 9) ---------------------

def user_file(tmp_path, text: str) -> str:
    path = tmp_path / 'user.yaml'
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize('node, text, message', [
    ('controller', "/**:\n  ros__parameters:\n    kp: 'fast'\n",
     r"'kp' must be a double, got 'fast' \(string\)"),
    ('controller', '/controller:\n  ros__parameters:\n    kp: 1\n',
     r"'kp' must be a double \(write 1.0\), got 1 \(integer\)"),
    ('controller', '/controller:\n  ros__parameters:\n    kpp: 0.5\n',
     r"'kpp' is not a parameter of node 'controller' \(did you mean 'kp'\?\)"),
    ('controller', '/**:\n  ros__parameters:\n    kpp: 0.5\n',
     r"'kpp' is not a parameter of node 'controller'"),
    ('arm', "/arm_node:\n  ros__parameters:\n    stop_mode: 'home'\n",
     r"section '/arm_node' names no node of activeloc_ros.*did you mean /arm\?"),
    ('arm', '/arm:\n  ros__parameters:\n    home_deg: [90.0, 90.0]\n',
     r"'home_deg' must be a integer array"),
])
def test_a_params_file_mistake_stops_the_node_naming_file_and_key(context, tmp_path, node,
                                                                  text, message):
    from activeloc_ros.errors import ConfigError
    path = user_file(tmp_path, text)
    with pytest.raises(ConfigError, match=message) as error:
        node_class(node)(context=context,
                         cli_args=params_args() + ['--params-file', path])
    assert path in str(error.value)


@pytest.mark.parametrize('text', [
    # a shared file: each node takes its own keys, the others' are for them
    "/**:\n  ros__parameters:\n    kp: 0.5\n    stop_mode: 'home'\n    overlay_alpha: 0.3\n",
    '/robot1/controller:\n  ros__parameters:\n    kp: 0.5\n/arm:\n  ros__parameters:\n'
    "    stop_mode: 'home'\n",
    '/**:\n  ros__parameters:\n    kd: 1.0e-1\n    derivative_tau: 1e-2\n'])  # rcl's numbers
def test_a_shared_params_file_is_accepted(context, tmp_path, text):
    path = user_file(tmp_path, text)
    node = node_class('controller')(context=context,
                                    cli_args=params_args() + ['--params-file', path])
    try:
        assert node.get_parameter('kp').value in (0.5, 1.0)
    finally:
        node.destroy_node()


def test_an_unreadable_params_file_stops_the_process_with_its_line(tmp_path, capsys):
    from activeloc_ros.nodes.arm_node import main
    path = user_file(tmp_path, '/arm:\n  ros__parameters:\n    stop_mode: [1\n')
    assert main(['arm_node', '--ros-args', '--params-file', path]) == 1
    error = capsys.readouterr().err
    assert f'params file {path} cannot be read' in error and 'line 4' in error


def test_params_file_problems_is_a_pure_function():
    from rclpy.parameter import Parameter
    from activeloc_ros.nodes.params_files import params_file_problems
    declared = {'kp': Parameter.Type.DOUBLE, 'tilt_joints': Parameter.Type.STRING_ARRAY}
    content = {'/**': {'ros__parameters': {'kp': 2.0, 'stop_mode': 'home',
                                           'tilt_joints': ['a', 1]}},
               'contoller': {'ros__parameters': {}},
               '/controller': {'ros__parameters': {'qos': {'depth': 1}}}}
    problems = params_file_problems(content, 'controller', declared, {'stop_mode'})
    assert len(problems) == 3, problems
    assert "'tilt_joints' must be a string array" in problems[0]
    assert 'did you mean /controller?' in problems[1]
    assert "'qos.depth' is not a parameter" in problems[2]
    assert params_file_problems([1, 2], 'arm', declared) != []


# -- descriptors carry the ranges (item 16), rclpy enforces them ----------------------------

@pytest.mark.parametrize('node, name, kind, bounds', [
    ('controller', 'pan_limit_deg', 'floating_point_range', (0.0, 180.0)),
    ('controller', 'step_delay_ms', 'integer_range', (10, 30)),
    ('controller', 'kp', 'floating_point_range', (0.0, None)),
    ('arm', 'state_rate', 'floating_point_range', (1.0, 500.0)),
    ('camera', 'hfov_deg', 'floating_point_range', (1.0, 170.0)),
    ('arm', 'step_delay_ms', 'integer_range', (10, 30)),
    ('perception', 'overlay_alpha', 'floating_point_range', (0.0, 1.0))])
def test_ranges_are_in_the_descriptors(context, node, name, kind, bounds):
    made = node_class(node)(context=context, cli_args=params_args())
    try:
        ranges = getattr(made.describe_parameter(name), kind)
        assert len(ranges) == 1
        assert ranges[0].from_value == bounds[0]
        if bounds[1] is not None:
            assert ranges[0].to_value == bounds[1]
    finally:
        made.destroy_node()


def test_rclpy_enforces_the_descriptor_ranges(context):
    from rclpy.parameter import Parameter
    node = node_class('controller')(context=context, cli_args=params_args())
    try:
        for value in (-0.1, 180.5, math.nan, math.inf):
            result = node.set_parameters([Parameter('pan_limit_deg', value=value)])[0]
            assert not result.successful and 'out of range' in result.reason, value
        assert node.set_parameters([Parameter('kp', value=math.inf)])[0].successful is False
        assert node.get_parameter('pan_limit_deg').value == 180.0
    finally:
        node.destroy_node()


@pytest.mark.parametrize('node, name', [('arm', 'stop_timeout'), ('arm', 'silence_timeout'),
                                        ('camera', 'rate'), ('controller', 'watchdog_timeout')])
def test_an_open_ended_parameter_refuses_infinity(context, node, name):
    """
    A positive parameter without an upper bound still needs a finite value: an infinite
    silence timeout never notices a hung Arduino, an infinite stop timeout overflows the wait.
    """
    from rclpy.parameter import Parameter
    made = node_class(node)(context=context, cli_args=params_args())
    try:
        before = made.get_parameter(name).value
        for value in (math.inf, math.nan, 0.0):
            result = made.set_parameters([Parameter(name, value=value)])[0]
            assert not result.successful and 'finite' in result.reason, (name, value)
        assert made.get_parameter(name).value == before
    finally:
        made.destroy_node()


def test_a_command_line_parameter_no_node_declares_is_refused_not_ignored(context):
    from activeloc_ros.errors import ConfigError
    from activeloc_ros.nodes.controller_node import ControllerNode
    with pytest.raises(ConfigError, match="-p kpp: no such parameter \\(did you mean 'kp'"):
        ControllerNode(context=context, cli_args=params_args('kpp:=0.5'))
    made = ControllerNode(context=context, cli_args=params_args('kp:=0.5', 'use_sim_time:=false')
                          + ['-p', 'camera:rate:=2.0'])
    assert made.get_parameter('kp').value == 0.5          # (a node-prefixed rule is rcl's)
    made.destroy_node()


def test_bringup_waits_for_the_arms_own_stop_timeout_before_sigterm(tmp_path):
    """
    It sent SIGTERM after 10 s and SIGKILL 3 s later whatever the arm's stop_timeout:
    an arm going home slowly was killed on the way, its serial link still open.
    """
    from activeloc_ros.bringup import parse_args
    from activeloc_ros.supervisor import stop_deadline, STOP_DEADLINE_S
    assert stop_deadline('arm', parse_args([])) == 12.0     # its default 10 s, and 2 to spare
    slow = tmp_path / 'slow.yaml'
    slow.write_text('arm:\n  ros__parameters:\n    stop_timeout: 30.0\n')
    assert stop_deadline('arm', parse_args(['--params', str(slow)])) == 32.0
    assert stop_deadline('arm', parse_args(['--ros-args', '-p', 'stop_timeout:=20.0'])) == 22.0
    assert stop_deadline('perception', parse_args(['--params', str(slow)])) == STOP_DEADLINE_S


def test_bringup_gives_each_node_only_the_settings_it_declares():
    from activeloc_ros.graph_plan import for_node
    ros_args = ['-r', '__ns:=/r1', '-p', 'kp:=0.5', '--param', 'rate:=2.0',
                '-p', 'use_sim_time:=true', '-p', 'camera:loop:=true']
    assert for_node(ros_args, {'kp', 'use_sim_time'}) == [
        '-r', '__ns:=/r1', '-p', 'kp:=0.5', '-p', 'use_sim_time:=true',
        '-p', 'camera:loop:=true']


@pytest.mark.parametrize('node_name', NODE_NAMES)
def test_every_node_refuses_unknown_ros_arguments_with_a_message(node_name, capsys):
    import importlib
    module = importlib.import_module(f'activeloc_ros.nodes.{node_name}_node')
    assert module.main([f'{node_name}_node', '--ros-args', '--garbage']) == 2
    assert "unknown ROS arguments ['--garbage']" in capsys.readouterr().err


@pytest.mark.parametrize('node_name', NODE_NAMES)
def test_every_node_prints_its_help_instead_of_starting(node_name, capsys):
    import importlib
    module = importlib.import_module(f'activeloc_ros.nodes.{node_name}_node')
    assert module.main([f'{node_name}_node', '--help']) == 0
    out = capsys.readouterr().out
    assert out.startswith(f'usage: ros2 run activeloc_ros {node_name}_node')
    from activeloc_ros.graph_plan import node_params
    keys = [p.name for p in node_params(node_name)]
    assert keys and all(f'\n  {name} ' in out for name in keys)
