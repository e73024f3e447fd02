"""
The nodes of a bringup run and what each is given: which nodes, in what order, their
--ros-args, and their parameter values before they start (declared defaults, packaged params
files, the user's files, then ``-p`` rules, in rcl's order).
"""
import importlib

from activeloc_ros.errors import ConfigError
from activeloc_ros.paths import NODE_NAMES, packaged_params_files
from activeloc_ros.sources import default_bag

MODES = ('realtime', 'lockstep')
DEFAULT_CAMERA = f'virtual:bag:{default_bag()}'
# where each node's parameters are declared, ROS-free
PARAMS_MODULES = {'camera': 'activeloc_ros.camera_params', 'sim': 'activeloc_ros.sim_params',
                  'tracking': 'activeloc_ros.tracking.params',
                  'perception': 'activeloc_ros.perception.params',
                  'controller': 'activeloc_ros.control.params',
                  'arm': 'activeloc_ros.control.arm_params'}


def graph_nodes(args) -> tuple[str, ...]:
    """
    The nodes of the run, in start order: a virtual camera's sim node (camera and arm in
    one) or the camera and the arm, with perception and the controller.
    """
    if args.world:
        return ('tracking', 'perception', 'controller')
    if args.camera.startswith('virtual:'):
        return ('sim', 'perception', 'controller')
    return tuple(name for name in NODE_NAMES if name not in ('sim', 'tracking'))


def tracking_world(args) -> tuple[str, int]:
    """(scene, seed) of --world tracking:SCENE[:SEED]; ConfigError for anything else."""
    from activeloc_ros.tracking.scenes import SCENES
    kind, _, rest = args.world.partition(':')
    scene, _, seed = rest.partition(':')
    if kind != 'tracking' or scene not in SCENES or not (seed == '' or seed.isdigit()):
        raise ConfigError(f'--world {args.world!r}: use tracking:SCENE[:SEED] with SCENE one '
                          f'of {", ".join(SCENES)} and SEED a whole number')
    return scene, int(seed or 0)


def node_arguments(node: str, args) -> list[str]:
    """The --ros-args of one node: its params files, the user's files, then the CLI choices."""
    ros_args = ['--ros-args']
    for path in [*packaged_params_files(), *args.params]:
        ros_args += ['--params-file', str(path)]
    if args.mode == 'lockstep':
        ros_args += ['-p', 'use_sim_time:=true']
    if node in ('camera', 'sim', 'tracking'):
        ros_args += ['-p', f'rate:={args.rate}']
        if node != 'tracking':
            ros_args += ['-p', f'loop:={str(args.loop).lower()}']
        if args.record is not None:         # perception and the recorder
            ros_args += ['-p', 'min_subscribers:=2']
    if node == 'tracking':
        scene, seed = tracking_world(args)
        ros_args += ['-p', f'scene:={scene}', '-p', f'seed:={seed}',
                     '-p', f'lockstep:={str(args.mode == "lockstep").lower()}']
    if node == 'camera':
        ros_args += ['-p', f'source:={args.camera}']
    if node == 'sim':
        ros_args += ['-p', f'scene:={args.camera.partition(":")[2]}',
                     '-p', f'lockstep:={str(args.mode == "lockstep").lower()}']
    if node == 'controller' and args.world:
        ros_args += ['-p', 'actuator:=base']
    elif node == 'controller':
        limits = (screen_aim_limits(args.camera, args.params) if args.aim_limits == 'screen'
                  else {})
        for name, value in limits.items():
            ros_args += ['-p', f'{name}:={value!r}']
    if node == 'arm':
        backend, _, port = args.arm.partition(':')
        ros_args += ['-p', f'backend:={backend}']
        if port:
            ros_args += ['-p', f'port:={port}']
    return ros_args + for_node(args.ros_args, {p.name for p in node_params(node)})


def for_node(ros_args: list[str], declared: set[str]) -> list[str]:
    """
    The user's ROS arguments without the ``-p`` rules this node does not declare: each
    rule goes to the nodes it is for (`check_node_params` made sure some node is), as a
    node refuses a rule for a parameter it does not have.
    """
    from activeloc_ros.nodes.params_files import cli_param_rule, undeclared
    out, skip = [], False
    for flag, item in zip(ros_args, [*ros_args[1:], None]):
        if skip:
            skip = False
            continue
        rule = cli_param_rule(flag, item)
        if rule is not None and undeclared(rule[0], declared):
            skip = True
            continue
        out.append(flag)
    return out


def own_ros_args(args) -> list[str] | None:
    """
    The --ros-args for bringup's own nodes (monitor, recorder): the user's, so they share
    the graph's namespace and remaps.
    """
    return ['--ros-args', *args.ros_args] if args.ros_args else None


def camera_screen(files=()):
    """The virtual screen a `virtual:` camera renders, from the sim node's `node_values`."""
    from activeloc_ros.settings import screen_from
    from activeloc_ros.screen import VirtualScreen
    return VirtualScreen(screen_from(node_values('sim', files)))


def screen_aim_limits(camera: str, files) -> dict[str, float]:
    """
    For a virtual camera, the controller's aim limits at which the view stays on the
    screen, as the screen benchmark sets them; limits set in the user's `files` win.
    """
    if not camera.startswith('virtual:'):
        return {}
    from activeloc_ros.nodes.params_files import file_values
    screen = camera_screen(files)
    own = file_values('controller', files)
    return {name: limit
            for name, limit in zip(('pan_limit_deg', 'tilt_limit_deg'), screen.aim_limits_deg())
            if name not in own}


def node_params(node: str) -> list:
    """The parameters a node declares (`PARAMS_MODULES`)."""
    return list(importlib.import_module(PARAMS_MODULES[node]).PARAMS)


def node_values(node: str, files=(), ros_args=()) -> dict:
    """
    A node's parameter values before it starts: its declared defaults, overlaid with its
    packaged params files (`paths.packaged_params_files`), the user's params `files`, then
    the ``-p`` settings among ``ros_args``.
    """
    from activeloc_ros.nodes.params_files import file_values
    values = {p.name: p.default for p in node_params(node)}
    values.update(file_values(node, [*packaged_params_files(), *files]))
    values.update(cli_values(list(ros_args)))
    return values


def cli_values(ros_args: list[str]) -> dict:
    """The ``-p name:=value`` settings among ROS arguments, typed as rcl types them."""
    from activeloc_ros.nodes.params_files import cli_param_rules, parse_value
    return {name: parse_value(text) for name, text in cli_param_rules(ros_args)}
