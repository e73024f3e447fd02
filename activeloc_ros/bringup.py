"""Start the whole graph (camera, perception, controller, arm) from one script.

    python -m activeloc_ros.bringup                      # bundled bag on the virtual screen
    python -m activeloc_ros.bringup --mode lockstep --camera virtual:otb_crossing
    python -m activeloc_ros.bringup --camera device:0 --duration 60
    python -m activeloc_ros.bringup --record out/run1    # every topic to an MCAP bag

Each node runs in its own process (as a launch file would) with `params/robot.yaml` and
its `params/<node>.yaml`, or all in one executor with --in-process. With a virtual
camera (--camera virtual:SCENE, the default) the sim node stands in for the camera and
the arm: it shows the scene on the virtual screen and moves the simulated arm that aims
the camera. A status line shows frames/s, frame-to-command latency (lockstep: the
simulated time) and the action location; Ctrl-C stops the nodes in order (an arm node
last, holding still; the sim's arm stops with the sim) and a summary closes the run.
Exits non-zero if a node fails, logs an error, the recording fails or nothing was seen.

Ctrl-C (once or more) and SIGTERM stop the graph the same way and close the bag; the nodes
also end if bringup itself is killed (they get SIGTERM when their parent dies), and a bag
cut off by a kill is made readable by `python -m activeloc_ros.bag reindex PATH`. Every
node's parameters are checked before any node starts. Node errors appear on this console.
The source node (camera, sim or tracking) starts once the monitor and the recorder hear
perception and the controller, so they miss none of their messages.

    python -m activeloc_ros.bringup --ros-args -r __ns:=/robot1     # passed to every node

Arguments after --ros-args (up to an optional --) go to every node, as `ros2 run` takes
them: a namespace (-r __ns:=/robot1) lets two robots share a network; remaps, -p and
--params-file work too. The monitor and the recorder run in the same namespace.

--mode lockstep (virtual camera) runs every node on simulated time that the sim node steps
frame by frame, as `closed_loop` does; `camera/pose` holds, at each image's stamp, the pan
and tilt the camera rendered with (`lockstep.recorded_poses`).

    python -m activeloc_ros.bringup --world tracking:room --mode lockstep --record out/t1

--world tracking:SCENE[:SEED] runs the simulated active-tracking world (`bench tracking`'s
episode SEED, default 0) in place of a camera: tracking -> perception -> controller, the
controller driving the world's mobile base on `cmd_vel`; the run ends with the episode.
"""
import argparse
import ctypes
import importlib
import math
import os
from pathlib import Path
import re
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import yaml

from activeloc_ros.checks import argument, finite
from activeloc_ros.errors import ActivelocError, ConfigError, SourceError
from activeloc_ros.nodes.messages import stamp_s
from activeloc_ros.paths import NODE_NAMES, packaged_params_files
from activeloc_ros.screen import AIM_LIMITS
from activeloc_ros.sources import default_bag

MODES = ('realtime', 'lockstep')
DEFAULT_CAMERA = f'virtual:bag:{default_bag()}'
# What the nodes publish (README, "The graph"): a recording subscribes to these before any
# node starts, so it holds every message from the first on.
GRAPH_TOPICS = {
    'camera/image_raw': 'sensor_msgs/msg/Image',
    'camera/camera_info': 'sensor_msgs/msg/CameraInfo',
    'surprise_map': 'std_msgs/msg/Float32MultiArray',
    'surprise_map/image': 'sensor_msgs/msg/Image',
    'surprise_map/overlay': 'sensor_msgs/msg/Image',
    'action_location': 'geometry_msgs/msg/PointStamped',
    'action_region': 'geometry_msgs/msg/PolygonStamped',
    'action_location/ignored': 'geometry_msgs/msg/PointStamped',
    'joint_commands': 'sensor_msgs/msg/JointState',
    'joint_states': 'sensor_msgs/msg/JointState',
}
TRACKING_TOPICS = {             # and those of the tracking world (--world tracking:SCENE)
    'cmd_vel': 'geometry_msgs/msg/Twist',
    'odom': 'nav_msgs/msg/Odometry',
    'scan': 'sensor_msgs/msg/LaserScan',
    'target/position': 'geometry_msgs/msg/PointStamped',
}
STARTUP_DEADLINE_S = 180.0    # model and weights load before the first map
HEAR_DEADLINE_S = 60.0        # the source starts once bringup hears perception and the
#                               controller, or after this long regardless
DRAIN_QUIET_S = 2.0           # after the camera ends: stop once no map came for this long
STOP_DEADLINE_S = 10.0
ARM_STALE_S = 2.0             # realtime: no joint_states for this long at the end is reported
#                               (an arm node's; the sim's arm ends with its scene)
# A node's log line that bringup repeats on its console: errors, not warnings.
ERROR_LINE = re.compile(r'\[(ERROR|FATAL)\]|^error:|^\w*Error\b|^Traceback')
# and the warnings a node prints about itself (e.g. an encoder run slower than asked): shown,
# not counted as errors
WARNING_LINE = re.compile(r'^warning:')
MAX_ECHOED = 10               # error lines repeated per node; the rest stay in its log


def split_ros_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """bringup's own arguments, and those after --ros-args (up to an optional --)."""
    if '--ros-args' not in argv:
        return list(argv), []
    i = argv.index('--ros-args')
    rest = argv[i + 1:]
    if '--' in rest:
        j = rest.index('--')
        return argv[:i] + rest[j + 1:], rest[:j]
    return argv[:i], rest


def parse_args(argv):
    argv, ros_args = split_ros_args(list(argv))
    parser = argparse.ArgumentParser(prog='python -m activeloc_ros.bringup', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     usage='%(prog)s [options] [--ros-args ARGS... [--]]')
    parser.add_argument('--camera', default=DEFAULT_CAMERA,
                        help='camera source: bag:PATH, video:PATH, folder:PATH, device:N, '
                             'realsense or virtual:SCENE, the scene (bag:PATH, video:PATH, '
                             'folder:PATH, a sequence folder or name) on the virtual screen '
                             'the arm aims at (default: the bundled sample bag, virtual)')
    parser.add_argument('--world', metavar='tracking:SCENE[:SEED]',
                        help='a simulated world in place of the camera: tracking:SCENE runs '
                             'the active-tracking world (room, urban, snow, parking; episode '
                             'SEED, default 0) with the controller driving its mobile base')
    parser.add_argument('--mode', choices=MODES, default='realtime',
                        help="'realtime': every node on the wall clock, perception takes the "
                             "newest frame; 'lockstep': simulated time stepped frame by frame "
                             'by the sim node (virtual camera), every frame processed, as the '
                             'screen benchmark does (default: realtime)')
    parser.add_argument('--arm', default='sim',
                        help="arm back end: 'sim' or 'serial:PORT' (default: sim; a "
                             "virtual camera's arm is always the sim node's)")
    parser.add_argument('--aim-limits', choices=AIM_LIMITS, default='arm',
                        help="virtual camera: 'arm' (default) lets only the arm's joints "
                             "limit the aim, and past the screen's edge the camera sees the "
                             "plain wall, as the paper's rig and the screen benchmark; "
                             "'screen' keeps the whole view on the screen")
    parser.add_argument('--params', type=Path, action='append', default=[],
                        help='extra ROS 2 params file applied to every node after the '
                             'defaults in params/ (may be repeated)')
    parser.add_argument('--record', type=Path, help='record every topic to this MCAP bag folder')
    parser.add_argument('--duration', type=argument(finite), default=0.0,
                        help='stop after this many seconds (default: when the source ends)')
    parser.add_argument('--rate', type=argument(finite), default=1.0,
                        help='bag/video replay speed')
    parser.add_argument('--loop', action='store_true', help='loop recorded sources')
    parser.add_argument('--in-process', action='store_true',
                        help='run all nodes in this process, in one executor')
    parser.add_argument('--log-dir', type=Path, default=None,
                        help='where node logs go (default: out/bringup-<time>)')
    args = parser.parse_args(argv)
    args.ros_args = ros_args
    return args


def graph_nodes(args) -> tuple[str, ...]:
    """The nodes of the run, in start order: a virtual camera's sim node (camera and arm in
    one) or the camera and the arm, with perception and the controller."""
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
    for path in [*packaged_params_files(node), *args.params]:
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
    """The user's ROS arguments without the ``-p`` rules this node does not declare: each
    rule goes to the nodes it is for (`check_node_params` made sure some node is), as a
    node refuses a rule for a parameter it does not have."""
    from activeloc_ros.nodes.ros_params import cli_param_rule, undeclared
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
    """The --ros-args for bringup's own nodes (monitor, recorder): the user's, so they share
    the graph's namespace and remaps."""
    return ['--ros-args', *args.ros_args] if args.ros_args else None


def camera_screen(files=()):
    """The virtual screen a `virtual:` camera renders, from the sim node's `node_values`."""
    from activeloc_ros.nodes.settings import screen_from
    from activeloc_ros.screen import VirtualScreen
    return VirtualScreen(screen_from(node_values('sim', files)))


def screen_aim_limits(camera: str, files) -> dict[str, float]:
    """For a virtual camera, the controller's aim limits at which the view stays on the
    screen, as the screen benchmark sets them; limits set in the user's `files` win."""
    if not camera.startswith('virtual:'):
        return {}
    from activeloc_ros.nodes.ros_params import file_values
    screen = camera_screen(files)
    own = file_values('controller', files)
    return {name: limit
            for name, limit in zip(('pan_limit_deg', 'tilt_limit_deg'), screen.aim_limits_deg())
            if name not in own}


CAMERA_FORMS = {'bag': 'bag:PATH', 'video': 'video:PATH', 'folder': 'folder:PATH',
                'device': 'device:N', 'virtual': 'virtual:SCENE'}


def preflight(args) -> None:
    """Every check that can fail before a node starts, with a clear message."""
    from activeloc_ros.nodes.ros_params import ros_args_problem
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
        from activeloc_ros import bag
        bag.choose_image_topic(bag.bag_facts(Path(target)))
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
                          "serial:/dev/ttyACM0)")
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


def node_params(node: str) -> list:
    """The parameters a node declares."""
    return list(importlib.import_module(f'activeloc_ros.nodes.{node}_node').PARAMS)


def node_values(node: str, files=(), ros_args=()) -> dict:
    """A node's parameter values before it starts: its declared defaults, overlaid with its
    packaged params files (`paths.packaged_params_files`), the user's params `files`, then
    the ``-p`` settings among ``ros_args``."""
    from activeloc_ros.nodes.ros_params import file_values
    values = {p.name: p.default for p in node_params(node)}
    values.update(file_values(node, [*packaged_params_files(node), *files]))
    values.update(cli_values(list(ros_args)))
    return values


def cli_values(ros_args: list[str]) -> dict:
    """The ``-p name:=value`` settings among ROS arguments, typed as rcl types them."""
    from activeloc_ros.nodes.ros_params import cli_param_rules, parse_value
    return {name: parse_value(text) for name, text in cli_param_rules(ros_args)}


def check_node_params(args) -> None:
    """Check every node's parameters, from its files and bringup's options, as the node
    checks them at start, so that a bad value stops the run before any node starts."""
    from activeloc_ros.nodes.ros_params import files_problems, unknown_cli_params, validate
    # each -p setting goes to the nodes that declare it (`for_node`): one that none of
    # them declares (a typo) would change nothing, silently
    problems = unknown_cli_params(
        args.ros_args, [p.name for node in graph_nodes(args) for p in node_params(node)],
        unknown='no node of this graph declares it')
    for node in graph_nodes(args):
        params = node_params(node)
        found = files_problems(node, params, [*packaged_params_files(node), *args.params])
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
            from activeloc_ros.nodes.controller_node import config_from
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


class Monitor:
    """Watches the graph's topics from its own node: rates, latency, location, arm pose.

    In lockstep the graph's stamps are simulated time, in which a command takes no time:
    the monitor shows how far the simulated clock got instead of a latency.
    """

    def __init__(self, context, *, lockstep: bool = False, arm_node: bool = True,
                 base: bool = False, cli_args=None):
        from geometry_msgs.msg import PointStamped, Twist
        from rclpy.node import Node
        from sensor_msgs.msg import CameraInfo, JointState
        from std_msgs.msg import Float32MultiArray
        self.node = Node('bringup_monitor', context=context, cli_args=cli_args)
        self.lock = threading.Lock()
        self.frames, self.maps, self.commands = [], [], []
        self.latencies: list[float] = []
        self.location = None
        self.image_size = None
        self.lockstep = lockstep
        self.arm_node = arm_node       # the arm is a node of its own, not the sim's
        self.sim_time = 0.0            # lockstep: the newest frame's simulated time, s
        self.joints: dict[str, float] = {}
        self.joints_at = -math.inf     # when the last joint_states came
        sub = self.node.create_subscription
        sub(CameraInfo, 'camera/camera_info', self.on_info, 10)
        # what perception and the controller publish: heard before the source starts
        self.downstream = [
            sub(Float32MultiArray, 'surprise_map', lambda m: self._stamp(self.maps), 10),
            sub(PointStamped, 'action_location', self.on_location, 10)]
        if base:        # a mobile base's commands (the tracking world)
            self.downstream.append(
                sub(Twist, 'cmd_vel', lambda m: self._stamp(self.commands), 10))
        else:
            self.downstream.append(sub(JointState, 'joint_commands', self.on_command, 10))
            sub(JointState, 'joint_states', self.on_state, 10)
        from activeloc_ros.nodes.masters import PublisherWatch
        # a second controller beside the graph, said on this console (the nodes say it too)
        self.masters = PublisherWatch(
            self.node, 'cmd_vel' if base else 'joint_commands', diagnostics=False,
            say=lambda text: print(f'bringup: warning: {text}', file=sys.stderr, flush=True))

    def hears_downstream(self, recorder=None) -> bool:
        """Are the monitor's (and the recorder's) subscriptions to what perception and the
        controller publish matched with their publishers? Discovery is pairwise, so a node
        the source already talks to may not yet reach bringup's own nodes."""
        subs = list(self.downstream)
        if recorder is not None:
            subs += [recorder.subs.get(s.topic_name) for s in self.downstream]
        return all(s is not None and s.get_publisher_count() > 0 for s in subs)

    def _stamp(self, series):
        with self.lock:
            series.append(time.monotonic())

    def on_info(self, msg):
        self.image_size = (msg.width, msg.height)
        stamp = stamp_s(msg.header.stamp)
        self.sim_time = max(self.sim_time, stamp)
        self._stamp(self.frames)

    def on_location(self, msg):
        self.location = (msg.point.x, msg.point.y)

    def on_command(self, msg):
        sent = stamp_s(msg.header.stamp)
        if sent > 0 and not self.lockstep:
            now = self.node.get_clock().now().nanoseconds * 1e-9
            with self.lock:
                self.latencies.append(now - sent)
        self._stamp(self.commands)

    def on_state(self, msg):
        self.joints = dict(zip(msg.name, np.degrees(msg.position)))
        self.joints_at = time.monotonic()

    @staticmethod
    def rate(series, window=3.0) -> float:
        now = time.monotonic()
        recent = [t for t in series if now - t <= window]
        return len(recent) / window if recent else 0.0

    def latency_ms(self, recent: int = 0) -> tuple[float, float]:
        with self.lock:
            values = self.latencies[-recent:] if recent else list(self.latencies)
        if not values:
            return float('nan'), float('nan')
        p50, p95 = np.percentile(values, [50, 95])
        return p50 * 1e3, p95 * 1e3

    def status(self, elapsed: float) -> str:
        p50, p95 = self.latency_ms(recent=50)
        where = (f'({self.location[0]:.0f}, {self.location[1]:.0f})' if self.location
                 else '(none yet)')
        joints = ' '.join(f'{name} {deg:.0f}°' for name, deg in self.joints.items()
                          if name in ('base', 'shoulder', 'elbow', 'wrist_ver'))
        timing = (f'simulated {self.sim_time:6.1f} s' if self.lockstep
                  else f'frame->command p50 {p50:4.0f} ms p95 {p95:4.0f} ms')
        return (f'[{elapsed:6.1f}s] camera {self.rate(self.frames):4.1f} fps | '
                f'maps {self.rate(self.maps):4.1f} fps | {timing} | action {where} | '
                f'{joints or "arm: no state yet"}')


PR_SET_PDEATHSIG = 1          # prctl(2)


def _die_with_parent() -> None:
    """In a child before exec: SIGTERM it when bringup dies, even of SIGKILL (Linux)."""
    if sys.platform.startswith('linux'):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def stop_deadline(node: str, args) -> float:
    """How long a node gets to end after SIGINT before SIGTERM: the arm may take its own
    ``stop_timeout`` to hold or go home, which must never be cut short."""
    if node != 'arm':
        return STOP_DEADLINE_S
    values = node_values('arm', args.params, args.ros_args)
    return max(STOP_DEADLINE_S, float(values['stop_timeout']) + 2.0)


class Child:
    """One node process, in a session of its own (a terminal's Ctrl-C reaches bringup only,
    which stops the nodes in order) that ends when bringup ends, however it ends."""

    def __init__(self, node: str, args, log_dir: Path, env):
        self.name = node
        self.log_path = log_dir / f'{node}.log'
        self.log = open(self.log_path, 'w')
        # (nodes.start: a stop while the node's module loads ends it cleanly)
        self.process = subprocess.Popen(
            [sys.executable, '-u', '-m', 'activeloc_ros.nodes.start', node]
            + node_arguments(node, args),
            stdout=self.log, stderr=subprocess.STDOUT, env=env, start_new_session=True,
            preexec_fn=_die_with_parent)
        self.stop_deadline = stop_deadline(node, args)

    @property
    def returncode(self):
        return self.process.poll()

    def stop(self) -> int:
        """SIGINT (the node stops on purpose), then SIGTERM, then SIGKILL, each with a deadline."""
        for sig, wait in ((signal.SIGINT, self.stop_deadline), (signal.SIGTERM, 3.0),
                          (signal.SIGKILL, 3.0)):
            if self.process.poll() is not None:
                break
            self.process.send_signal(sig)
            try:
                self.process.wait(wait)
            except subprocess.TimeoutExpired:
                print(f'{self.name}: still running {wait:g} s after {sig.name}, which it '
                      f'did not end on (a hang? its log: {self.log_path})', file=sys.stderr,
                      flush=True)
                continue
        self.log.close()
        return self.process.returncode

    def tail(self, lines: int = 15) -> str:
        return '\n'.join(self.log_path.read_text(errors='replace').splitlines()[-lines:])

    def errors(self, pattern: re.Pattern = ERROR_LINE) -> list[str]:
        """The error lines of the node's log (ERROR_LINE), or those ``pattern`` finds."""
        try:
            text = self.log_path.read_text(errors='replace')
        except OSError:
            return []
        return [line for line in text.splitlines() if pattern.search(line)]


class InProcessGraph:
    """All nodes in one context and one multi-threaded executor."""

    def __init__(self, args, context):
        from rclpy.executors import MultiThreadedExecutor
        self.context = context
        self.executor = MultiThreadedExecutor(num_threads=4, context=context)
        self.nodes = {}
        for name in graph_nodes(args):
            module = importlib.import_module(f'activeloc_ros.nodes.{name}_node')
            node_class = getattr(module, f'{name.capitalize()}Node')
            self.nodes[name] = node_class(context=context, cli_args=node_arguments(name, args))
            self.executor.add_node(self.nodes[name])
        self.halt = threading.Event()
        self.crashed: BaseException | None = None    # what ended the executor's thread
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        from rclpy.executors import ExternalShutdownException
        try:
            while not self.halt.is_set() and self.context.ok():
                self.executor.spin_once(timeout_sec=0.05)
        except ExternalShutdownException:
            pass
        except BaseException as exc:      # a callback's exception ends every node's spin
            self.crashed = exc

    def failure(self) -> str | None:
        """Why the graph cannot go on, as a node process's exit code says it: a node that
        gave up (a camera stream that failed, an arm link down for give_up_timeout), or a
        callback that raised."""
        if self.crashed is not None:
            return f'a node callback raised {type(self.crashed).__name__}: {self.crashed}'
        for name, node in self.nodes.items():
            if getattr(node, 'failure', None):
                return f'{name}: {node.failure}'
        return None

    def camera_finished(self) -> bool:
        return next(iter(self.nodes.values())).finished    # the camera or the sim

    def stop(self):
        """The controller and the arm stop on purpose while the executor still runs them."""
        for name in ('controller', 'arm'):
            if name in self.nodes:
                self.nodes[name].stop_on_purpose()
        self.halt.set()
        self.thread.join(timeout=STOP_DEADLINE_S)
        self.executor.shutdown(timeout_sec=STOP_DEADLINE_S)
        for node in self.nodes.values():
            node.destroy_node()


def percentile_text(monitor: Monitor) -> str:
    if not monitor.latencies and monitor.commands:
        return ("not measured: a base's cmd_vel carries no stamp (the controller's log "
                'has its own figures)')
    p50, p95 = monitor.latency_ms()
    return f'p50 {p50:.0f} ms, p95 {p95:.0f} ms over {len(monitor.latencies)} commands'


class StopRequest:
    """SIGINT and SIGTERM ask bringup to stop; the graph is then stopped in order and the
    bag closed. A signal while stopping is told to wait, not obeyed. While the nodes of an
    in-process graph are being made (a first use of an int8 encoder builds it for a minute)
    the first signal ends that at once, unless OpenVINO's model conversion swallows it: then
    the graph stops once it is made (a node process ends in any case: `ros_params.run`)."""

    def __init__(self):
        self.reason: str | None = None
        self.starting = False
        self._previous = {}

    def install(self) -> None:
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self._on_signal)

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    def _on_signal(self, signum, frame) -> None:
        name = 'Ctrl-C' if signum == signal.SIGINT else signal.Signals(signum).name
        if self.reason is None:
            self.reason = name
            if self.starting:
                raise KeyboardInterrupt
        else:
            try:
                print(f'\n{name}: already stopping the nodes and closing the recording, '
                      'please wait', file=sys.stderr, flush=True)
            except RuntimeError:    # the signal came in the middle of another print
                pass


def make_log_dir(args) -> Path:
    log_dir = args.log_dir or Path('out') / time.strftime('bringup-%Y%m%d-%H%M%S')
    try:
        log_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f'--log-dir {log_dir}: cannot create it ({exc.strerror})') from exc
    return log_dir


def run(args, asked: list | tuple = ()) -> int:
    """`asked`: the stops noted before the graph's own handling was in place."""
    preflight(args)
    stop = StopRequest()
    stop.install()
    try:
        if asked:
            raise KeyboardInterrupt
        return run_graph(args, make_log_dir(args), stop)
    finally:
        stop.restore()


def run_graph(args, log_dir: Path, stop: StopRequest) -> int:
    import rclpy
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    from activeloc_ros.nodes.ros_params import lean_executor
    monitor = Monitor(context, lockstep=args.mode == 'lockstep',
                      arm_node='arm' in graph_nodes(args), base=bool(args.world),
                      cli_args=own_ros_args(args))
    watch = lean_executor(context)
    watch.add_node(monitor.node)
    recorder = None
    if args.record is not None:
        from activeloc_ros.nodes.recorder import RecorderNode
        expected = dict(GRAPH_TOPICS)
        if args.world:
            expected.update(TRACKING_TOPICS)
        elif args.camera.startswith('virtual:'):
            expected['camera/pose'] = 'sensor_msgs/msg/JointState'
        if args.mode == 'lockstep':
            expected['/clock'] = 'rosgraph_msgs/msg/Clock'
        recorder = RecorderNode(args.record, expected=expected, context=context,
                                cli_args=own_ros_args(args))
        watch.add_node(recorder)
    stop_watch = threading.Event()

    def spin_watch():
        while not stop_watch.is_set():
            watch.spin_once(timeout_sec=0.05)

    watcher = threading.Thread(target=spin_watch, daemon=True)
    watcher.start()

    children, graph, failed = [], None, []
    nodes = graph_nodes(args)
    first = nodes[0]                    # the source: camera, sim or tracking world
    start = time.monotonic()
    tty = sys.stdout.isatty()
    last_print = 0.0
    reason = 'source ended'
    try:
        if args.in_process:
            stop.starting = True
            graph = InProcessGraph(args, context)
            stop.starting = False
        else:
            env = dict(os.environ, PYTHONUNBUFFERED='1')
            # the source starts last, in the loop below
            children = [Child(node, args, log_dir, env) for node in nodes[1:]]
        source = (f'world {args.world}' if args.world
                  else f'camera {args.camera}; arm {args.arm}')
        print(f'bringup: {" -> ".join(nodes)}; {source}; {args.mode}; logs in '
              f'{log_dir}', flush=True)
        camera_done_at = None
        while True:
            time.sleep(0.2)
            elapsed = time.monotonic() - start
            if not graph and children[0].name != first:
                # A recording and the monitor miss what a node sends before they have
                # matched it; in lockstep a short run can end before that.
                heard = monitor.hears_downstream(recorder)
                if heard or elapsed > HEAR_DEADLINE_S:
                    if not heard:
                        print(f'bringup: not every node heard after {HEAR_DEADLINE_S:.0f} s; '
                              f'starting {first} anyway', flush=True)
                    children.insert(0, Child(first, args, log_dir, env))
            if stop.reason is not None:
                reason = stop.reason
                break
            if recorder is not None and recorder.error is not None:
                reason = f'recording failed: {recorder.error}'
                failed.append(None)
                break
            for child in children:
                code = child.returncode
                if code is not None and (child.name != first or code != 0) \
                        and child not in failed:
                    failed.append(child)
            if failed:
                reason = f'{failed[0].name} node exited with code {failed[0].returncode}'
                break
            failure = graph.failure() if graph is not None else None
            if failure:
                reason = failure
                failed.append(None)
                break
            if not monitor.maps and elapsed > STARTUP_DEADLINE_S:
                reason = f'no surprise map within {STARTUP_DEADLINE_S:.0f} s'
                failed.append(None)
                break
            camera_done = (graph.camera_finished() if graph else
                           children[0].name == first and children[0].returncode == 0)
            if camera_done and camera_done_at is None:
                camera_done_at = time.monotonic()
            if camera_done_at is not None:
                last_map = monitor.maps[-1] if monitor.maps else camera_done_at
                if time.monotonic() - max(last_map, camera_done_at) > DRAIN_QUIET_S:
                    break
            if args.duration and elapsed >= args.duration:
                reason = f'--duration {args.duration:g} s reached'
                break
            if elapsed - last_print >= (1.0 if tty else 5.0):
                last_print = elapsed
                line = monitor.status(elapsed)
                print(('\r' + line) if tty else line, end='' if tty else '\n', flush=True)
    except KeyboardInterrupt:     # a stop while the nodes were made (or a SIGINT before the
        # handler was in place)
        reason = stop.reason or 'Ctrl-C'
    except ActivelocError as exc:
        reason = str(exc)
        failed.append(None)
    finally:
        if tty:
            print()
        codes = {}
        if graph is not None:
            graph.stop()
        for child in children:
            codes[child.name] = child.stop()
            if codes[child.name] != 0 and child not in failed:
                failed.append(child)
        stop_watch.set()
        watcher.join(timeout=2.0)
        if recorder is not None:
            recorder.close()
        elapsed = time.monotonic() - start
    for child in failed:
        if child is not None:
            print(f'--- last lines of {child.log_path} ---\n{child.tail()}', file=sys.stderr)
    for child in children:
        for line in child.errors(WARNING_LINE)[:MAX_ECHOED]:
            print(f'{child.name}: {line}', file=sys.stderr)
    errors = {child.name: child.errors() for child in children if child not in failed}
    for name, lines in errors.items():
        for line in lines[:MAX_ECHOED]:
            print(f'{name}: {line}', file=sys.stderr)
        if len(lines) > MAX_ECHOED:
            print(f'{name}: ... {len(lines) - MAX_ECHOED} more error lines in '
                  f'{log_dir / (name + ".log")}', file=sys.stderr)
    if recorder is not None and recorder.error is not None and 'recording' not in reason:
        failed.append(None)
    print(summary(monitor, elapsed, reason, codes, recorder))
    perception = [c for c in children if c.name == 'perception' and c not in failed]
    stopped = stop.reason is not None and reason == stop.reason    # by the user, on purpose
    if not monitor.maps and perception and not stopped:   # why the run fails, when no node
        # failed
        print(f'bringup: no surprise map came; the last lines of {perception[0].log_path} '
              f'(a first use of an int8 encoder is built first, about a minute):\n'
              f'{perception[0].tail(3)}', file=sys.stderr)
    monitor.node.destroy_node()
    rclpy.try_shutdown(context=context)
    return 1 if failed or any(errors.values()) or not (monitor.maps or stopped) else 0


def summary(monitor: Monitor, elapsed: float, reason: str, codes: dict, recorder) -> str:
    span = (monitor.maps[-1] - monitor.maps[0]) if len(monitor.maps) > 1 else 0.0
    map_rate = (len(monitor.maps) - 1) / span if span > 0 else 0.0
    lines = [f'summary: stopped after {elapsed:.1f} s ({reason})',
             f'  camera frames heard {len(monitor.frames)}, surprise maps {len(monitor.maps)} '
             f'({map_rate:.1f} maps/s), commands {len(monitor.commands)}',
             (f'  simulated time {monitor.sim_time:.2f} s (lockstep: every frame processed, '
              'commands at their frame time)' if monitor.lockstep
              else f'  frame->command latency {percentile_text(monitor)}')]
    if monitor.location:
        lines.append(f'  last action location ({monitor.location[0]:.0f}, '
                     f'{monitor.location[1]:.0f}) in a {monitor.image_size} image')
    if monitor.joints:
        age = time.monotonic() - monitor.joints_at
        stale = (f' (STALE: the arm said nothing for its last {age:.1f} s)'
                 if monitor.arm_node and age > ARM_STALE_S else '')
        lines.append('  final arm pose (deg): ' + ', '.join(
            f'{n} {d:.1f}' for n, d in monitor.joints.items()) + stale)
    if codes:
        lines.append('  node exit codes: ' + ', '.join(f'{n} {c}' for n, c in codes.items()))
    if recorder is not None:
        counts = ', '.join(f'{t} {n}' for t, n in sorted(recorder.counts.items()))
        lines.append(f'  recorded {recorder.path}: '
                     + (counts or 'how many messages it holds is not known (below)'))
        for topic, why in sorted(recorder.unrecorded.items()):
            lines.append(f'  NOT RECORDED {topic}: {why}')
        if recorder.error is not None:
            lines.append(f'  RECORDING FAILED: {recorder.error}')
    return '\n'.join(lines)


def main(argv=None) -> int:
    started = time.monotonic()
    # until the graph's own stop handling is in place (`StopRequest`), a stop is only noted
    # and acted on at one check after the preflight: an exception raised inside an import
    # (cv2, torch, rclpy...) can abort the process (exit 134), or make Python end it with
    # SIGINT (-2) however it was handled
    asked: list[int] = []
    previous = {sig: signal.signal(sig, lambda signum, frame: asked.append(signum))
                for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        import cv2  # noqa: F401
        import torch  # noqa: F401
        args = parse_args(sys.argv[1:] if argv is None else argv)
        try:
            import rclpy  # noqa: F401
        except ModuleNotFoundError:
            print("bringup: error: rclpy is not installed: source a ROS 2 Jazzy (source "
                  "/opt/ros/jazzy/setup.bash) or install the PyPI wheels with pip install "
                  "'.[ros]'", file=sys.stderr)
            return 2
        return run(args, asked)
    except ActivelocError as exc:
        print(f'bringup: error: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f'\nsummary: stopped during start-up after {time.monotonic() - started:.1f} s '
              '(Ctrl-C or SIGTERM), before any node was started', flush=True)
        return 0
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


if __name__ == '__main__':
    sys.exit(main())
