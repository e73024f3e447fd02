"""
Every check of a bringup run that can fail before a node starts, each with a clear
message (`ConfigError` or `SourceError`).
"""
import os
from pathlib import Path
import time

import yaml

from activeloc_ros.errors import ConfigError, SourceError
from activeloc_ros.graph_plan import (DEFAULT_CAMERA, graph_nodes, node_params, node_values,
                                      tracking_world)
from activeloc_ros.paths import packaged_params_files

CAMERA_FORMS = {'bag': 'bag:PATH', 'video': 'video:PATH', 'folder': 'folder:PATH',
                'device': 'device:N', 'virtual': 'virtual:SCENE'}


def preflight(args) -> None:
    """Every check that can fail before a node starts, with a clear message."""
    from activeloc_ros.nodes.process import ros_args_problem
    problem = args.ros_args and ros_args_problem(['bringup', '--ros-args', *args.ros_args])
    if problem:
        raise ConfigError(problem)
    if args.world:
        tracking_world(args)
        if args.camera != DEFAULT_CAMERA or args.arm != 'sim':
            raise ConfigError(f'--world {args.world} is camera and base in one: it takes no '
                              '--camera and no --arm')
        args_files_checks(args)
        return
    kind, _, target = args.camera.partition(':')
    if kind in CAMERA_FORMS and not target:
        raise ConfigError(f'--camera {args.camera!r} names no {kind}: use '
                          f'{CAMERA_FORMS[kind]}')
    if kind == 'bag':
        from activeloc_ros.bag.read import bag_facts, choose_image_topic
        choose_image_topic(bag_facts(Path(target)))
    elif kind in ('video', 'folder', 'virtual'):
        from activeloc_ros.sources import open_scene, open_source
        source = (open_scene(target) if kind == 'virtual'
                  else open_source(args.camera, clock=time.time))
        try:
            if source.read() is None:
                raise SourceError(f'{args.camera} holds no readable frame')
        finally:
            source.close()
    elif kind == 'device':
        from activeloc_ros.sources import device_index
        device_index(target)
    elif kind != 'realsense':
        raise ConfigError(f'unknown --camera {args.camera!r}')
    backend, _, port = args.arm.partition(':')
    if backend not in ('sim', 'serial') or (backend == 'serial') != bool(port):
        raise ConfigError(f"--arm {args.arm!r}: use 'sim' or 'serial:PORT' (e.g. "
                          'serial:/dev/ttyACM0)')
    if kind == 'virtual' and backend != 'sim':
        raise ConfigError(f'--camera {args.camera}: the virtual camera rides on the sim '
                          "node's simulated arm, so --arm must be 'sim'")
    if args.mode == 'lockstep' and kind != 'virtual':
        raise ConfigError('--mode lockstep steps a simulation: it needs --camera virtual:SCENE '
                          'or --world tracking:SCENE')
    args_files_checks(args)


def args_files_checks(args) -> None:
    """The checks of params files, node parameters and the other options."""
    for file in [*packaged_params_files(), *args.params]:
        check_params_file(Path(file))
    check_node_params(args)
    if args.record is not None:
        if args.record.exists():
            raise ConfigError(f'--record {args.record} exists already; choose a new path')
        writable_folder(args.record.parent, '--record')
    if args.duration < 0 or args.rate <= 0:
        raise ConfigError('--duration must be >= 0 and --rate > 0')


def writable_folder(path: Path, option: str) -> None:
    """Raise ConfigError unless `path` is, or can become, a folder this process writes in."""
    existing = path
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise ConfigError(f'{option}: {existing} is not a folder, so {path} cannot be one')
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ConfigError(f'{option}: cannot write in {existing} (permission denied)')


def check_node_params(args) -> None:
    """
    Check every node's parameters, from its files and bringup's options, as the node
    checks them at start, so that a bad value stops the run before any node starts.
    """
    from activeloc_ros.checks import validate
    from activeloc_ros.nodes.params_files import files_problems, unknown_cli_params
    # each -p setting goes to the nodes that declare it (`for_node`): one that none of
    # them declares (a typo) would change nothing, silently
    problems = unknown_cli_params(
        args.ros_args, [p.name for node in graph_nodes(args) for p in node_params(node)],
        unknown='no node of this graph declares it')
    for node in graph_nodes(args):
        params = node_params(node)
        found = files_problems(node, params, [*packaged_params_files(), *args.params])
        if not found:
            values = node_values(node, args.params, args.ros_args)
            found = validate(params, values) or node_problems(node, values)
        problems += [f'{node}: {p}' for p in found]
    if problems:
        raise ConfigError('bad parameters, no node started:\n  ' + '\n  '.join(problems))


def node_problems(node: str, values: dict) -> list[str]:
    """The checks across parameters that a node makes at start."""
    try:
        if node == 'controller':
            from activeloc_ros.control.params import config_from
            config_from(values)
        elif node == 'perception':
            from activeloc_ros.perception.config import PerceptionConfig
            PerceptionConfig.from_dict(PerceptionConfig.fields_in(values))
    except ConfigError as exc:
        return [str(exc)]
    return []


def check_params_file(path: Path) -> None:
    if not path.is_file():
        raise ConfigError(f'params file not found: {path}')
    try:
        content = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f'params file {path} is not valid YAML: {exc}') from exc
    if not isinstance(content, dict) or not all(
            isinstance(v, dict) and 'ros__parameters' in v for v in content.values()):
        raise ConfigError(f'params file {path} is not in ROS 2 format '
                          '(<node or /**>: ros__parameters: {...})')
