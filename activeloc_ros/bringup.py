"""Start the whole graph (camera, perception, controller, arm) from one script.

    python -m activeloc_ros.bringup                      # bundled bag on the virtual screen
    python -m activeloc_ros.bringup --mode lockstep --camera virtual:otb_crossing
    python -m activeloc_ros.bringup --camera device:0 --duration 60
    python -m activeloc_ros.bringup --record out/run1    # every topic to an MCAP bag

Each node runs in its own process (as a launch file would) with its `params/<node>.yaml`,
or all in one executor with --in-process. A status line shows frames/s, frame-to-command
latency (lockstep: the simulated time) and the action location; Ctrl-C stops the nodes in
order (the arm last, holding still) and a summary closes the run. Exits non-zero if a node
fails or nothing was seen.

--mode lockstep (virtual camera, simulated arm) runs every node on simulated time that the
camera steps frame by frame, as `closed_loop` does; `camera/pose` then holds, at each
image's stamp, the pan and tilt the camera rendered with (`lockstep.recorded_poses`).
"""
import argparse
import os
from pathlib import Path
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import yaml

from activeloc_ros.errors import ActivelocError, ConfigError, SourceError
from activeloc_ros.paths import share_path
from activeloc_ros.sources import default_bag

MODES = ('realtime', 'lockstep')
NODES = ('camera', 'perception', 'controller', 'arm')   # start and stop order: the arm last
STARTUP_DEADLINE_S = 180.0    # model and weights load before the first map
DRAIN_QUIET_S = 2.0           # after the camera ends: stop once no map came for this long
STOP_DEADLINE_S = 10.0


def parse_args(argv):
    parser = argparse.ArgumentParser(prog='python -m activeloc_ros.bringup', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--camera', default=f'virtual:bag:{default_bag()}',
                        help='camera source: bag:PATH, video:PATH, folder:PATH, device:N, '
                             'realsense or virtual:SCENE, the scene (bag:PATH, video:PATH, '
                             'folder:PATH, a sequence folder or name) on the virtual screen '
                             'the arm aims at (default: the bundled sample bag, virtual)')
    parser.add_argument('--mode', choices=MODES, default='realtime',
                        help="'realtime': every node on the wall clock, perception takes the "
                             "newest frame; 'lockstep': simulated time stepped frame by frame "
                             'by the (virtual) camera, every frame processed, as the screen '
                             'benchmark does (default: realtime)')
    parser.add_argument('--arm', default='sim',
                        help="arm back end: 'sim' or 'serial:PORT' (default: sim)")
    parser.add_argument('--params', type=Path, action='append', default=[],
                        help='extra ROS 2 params file applied to every node after the '
                             'defaults in params/ (may be repeated)')
    parser.add_argument('--record', type=Path, help='record every topic to this MCAP bag folder')
    parser.add_argument('--duration', type=float, default=0.0,
                        help='stop after this many seconds (default: when the source ends)')
    parser.add_argument('--rate', type=float, default=1.0, help='bag/video replay speed')
    parser.add_argument('--loop', action='store_true', help='loop recorded sources')
    parser.add_argument('--in-process', action='store_true',
                        help='run all nodes in this process, in one executor')
    parser.add_argument('--log-dir', type=Path, default=None,
                        help='where node logs go (default: out/bringup-<time>)')
    return parser.parse_args(argv)


def node_arguments(node: str, args) -> list[str]:
    """The --ros-args of one node: its params file, the user's files, then the CLI choices."""
    ros_args = ['--ros-args', '--params-file', str(share_path(f'params/{node}.yaml'))]
    for extra in args.params:
        ros_args += ['--params-file', str(extra)]
    if args.mode == 'lockstep':
        ros_args += ['-p', 'use_sim_time:=true']
    if node == 'camera':
        ros_args += ['-p', f'source:={args.camera}', '-p', f'rate:={args.rate}',
                     '-p', f'loop:={str(args.loop).lower()}',
                     '-p', f'lockstep:={str(args.mode == "lockstep").lower()}']
    if node == 'controller':
        for name, value in screen_aim_limits(args.camera, args.params).items():
            ros_args += ['-p', f'{name}:={value!r}']
    if node == 'arm':
        backend, _, port = args.arm.partition(':')
        ros_args += ['-p', f'backend:={backend}']
        if port:
            ros_args += ['-p', f'port:={port}']
    return ros_args


def file_params(node: str, files) -> dict:
    """The parameters that ROS 2 params `files` give `node`, later files winning."""
    values = {}
    for path in files:
        for key, section in (yaml.safe_load(Path(path).read_text()) or {}).items():
            if key.lstrip('/') in ('**', node):
                values.update(section.get('ros__parameters') or {})
    return values


def screen_aim_limits(camera: str, files) -> dict[str, float]:
    """For a virtual camera, the controller's aim limits at which the view stays on the
    screen, as the screen benchmark sets them; limits set in the user's `files` win."""
    if not camera.startswith('virtual:'):
        return {}
    from activeloc_ros.camera_node import PARAMS, SCREEN_FIELDS
    from activeloc_ros.screen import ScreenConfig, VirtualScreen
    values = {p.name: p.default for p in PARAMS}
    values.update(file_params('camera', [share_path('params/camera.yaml'), *files]))
    screen = VirtualScreen(ScreenConfig(**{field: values[name]
                                           for name, field in SCREEN_FIELDS.items()}))
    own = file_params('controller', files)
    return {name: limit
            for name, limit in zip(('pan_limit_deg', 'tilt_limit_deg'), screen.aim_limits_deg())
            if name not in own}


def preflight(args) -> None:
    """Every check that can fail before a node starts, with a clear message."""
    kind, _, target = args.camera.partition(':')
    if kind == 'bag':
        from activeloc_ros import bag
        bag.choose_image_topic(bag.bag_facts(Path(target)))
    elif kind in ('video', 'folder', 'virtual'):
        from activeloc_ros.sources import open_source
        source = open_source(args.camera, clock=time.time)
        try:
            if source.read() is None:
                raise SourceError(f'{args.camera} holds no readable frame')
        finally:
            source.close()
    elif kind not in ('device', 'realsense'):
        raise ConfigError(f'unknown --camera {args.camera!r}')
    backend = args.arm.partition(':')[0]
    if backend not in ('sim', 'serial'):
        raise ConfigError(f"unknown --arm {args.arm!r}: use 'sim' or 'serial:PORT'")
    if args.mode == 'lockstep' and (kind != 'virtual' or backend != 'sim'):
        raise ConfigError('--mode lockstep steps a simulation: it needs --camera virtual:SCENE '
                          'and --arm sim')
    files = [share_path(f'params/{node}.yaml') for node in NODES] + list(args.params)
    for file in files:
        check_params_file(Path(file))
    if args.record is not None and args.record.exists():
        raise ConfigError(f'--record {args.record} exists already; choose a new path')
    if args.duration < 0 or args.rate <= 0:
        raise ConfigError('--duration must be >= 0 and --rate > 0')


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

    def __init__(self, context, *, lockstep: bool = False):
        from geometry_msgs.msg import PointStamped
        from rclpy.node import Node
        from sensor_msgs.msg import CameraInfo, JointState
        from std_msgs.msg import Float32MultiArray
        self.node = Node('bringup_monitor', context=context)
        self.lock = threading.Lock()
        self.frames, self.maps, self.commands = [], [], []
        self.latencies: list[float] = []
        self.location = None
        self.image_size = None
        self.lockstep = lockstep
        self.sim_time = 0.0            # lockstep: the newest frame's simulated time, s
        self.joints: dict[str, float] = {}
        sub = self.node.create_subscription
        sub(CameraInfo, 'camera/camera_info', self.on_info, 10)
        sub(Float32MultiArray, 'surprise_map', lambda m: self._stamp(self.maps), 10)
        sub(PointStamped, 'action_location', self.on_location, 10)
        sub(JointState, 'joint_commands', self.on_command, 10)
        sub(JointState, 'joint_states', self.on_state, 10)

    def _stamp(self, series):
        with self.lock:
            series.append(time.monotonic())

    def on_info(self, msg):
        self.image_size = (msg.width, msg.height)
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        self.sim_time = max(self.sim_time, stamp)
        self._stamp(self.frames)

    def on_location(self, msg):
        self.location = (msg.point.x, msg.point.y)

    def on_command(self, msg):
        sent = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        if sent > 0 and not self.lockstep:
            now = self.node.get_clock().now().nanoseconds * 1e-9
            with self.lock:
                self.latencies.append(now - sent)
        self._stamp(self.commands)

    def on_state(self, msg):
        self.joints = dict(zip(msg.name, np.degrees(msg.position)))

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


class Child:
    def __init__(self, node: str, args, log_dir: Path, env):
        self.name = node
        self.log_path = log_dir / f'{node}.log'
        module = f'activeloc_ros.{node}_node'
        self.log = open(self.log_path, 'w')
        self.process = subprocess.Popen(
            [sys.executable, '-u', '-m', module] + node_arguments(node, args),
            stdout=self.log, stderr=subprocess.STDOUT, env=env, start_new_session=True)

    @property
    def returncode(self):
        return self.process.poll()

    def stop(self) -> int:
        """SIGINT (the node stops on purpose), then SIGTERM, then SIGKILL, each with a deadline."""
        for sig, wait in ((signal.SIGINT, STOP_DEADLINE_S), (signal.SIGTERM, 3.0),
                          (signal.SIGKILL, 3.0)):
            if self.process.poll() is not None:
                break
            self.process.send_signal(sig)
            try:
                self.process.wait(wait)
            except subprocess.TimeoutExpired:
                continue
        self.log.close()
        return self.process.returncode

    def tail(self, lines: int = 15) -> str:
        return '\n'.join(self.log_path.read_text(errors='replace').splitlines()[-lines:])


class InProcessGraph:
    """All nodes in one context and one multi-threaded executor."""

    def __init__(self, args, context):
        from rclpy.executors import MultiThreadedExecutor
        from activeloc_ros.arm_node import ArmNode
        from activeloc_ros.camera_node import CameraNode
        from activeloc_ros.controller_node import ControllerNode
        from activeloc_ros.perception_node import PerceptionNode
        classes = {'camera': CameraNode, 'perception': PerceptionNode,
                   'controller': ControllerNode, 'arm': ArmNode}
        self.context = context
        self.executor = MultiThreadedExecutor(num_threads=4, context=context)
        self.nodes = {}
        for name in NODES:
            self.nodes[name] = classes[name](context=context,
                                             cli_args=node_arguments(name, args))
            self.executor.add_node(self.nodes[name])
        self.halt = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        from rclpy.executors import ExternalShutdownException
        try:
            while not self.halt.is_set() and self.context.ok():
                self.executor.spin_once(timeout_sec=0.05)
        except ExternalShutdownException:
            pass

    def camera_finished(self) -> bool:
        return self.nodes['camera'].finished

    def stop(self):
        """The controller and the arm stop on purpose while the executor still runs them."""
        for name in ('controller', 'arm'):
            self.nodes[name].stop_on_purpose()
        self.halt.set()
        self.thread.join(timeout=STOP_DEADLINE_S)
        self.executor.shutdown(timeout_sec=STOP_DEADLINE_S)
        for node in self.nodes.values():
            node.destroy_node()


def percentile_text(monitor: Monitor) -> str:
    p50, p95 = monitor.latency_ms()
    return f'p50 {p50:.0f} ms, p95 {p95:.0f} ms over {len(monitor.latencies)} commands'


def run(args) -> int:
    import rclpy
    preflight(args)
    log_dir = args.log_dir or Path('out') / time.strftime('bringup-%Y%m%d-%H%M%S')
    log_dir.mkdir(parents=True, exist_ok=True)
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    from rclpy.executors import SingleThreadedExecutor
    monitor = Monitor(context, lockstep=args.mode == 'lockstep')
    watch = SingleThreadedExecutor(context=context)
    watch.add_node(monitor.node)
    recorder = None
    if args.record is not None:
        from activeloc_ros.recorder import RecorderNode
        recorder = RecorderNode(args.record, context=context)
        watch.add_node(recorder)
    stop_watch = threading.Event()

    def spin_watch():
        while not stop_watch.is_set():
            watch.spin_once(timeout_sec=0.05)

    watcher = threading.Thread(target=spin_watch, daemon=True)
    watcher.start()

    children, graph, failed = [], None, []
    start = time.monotonic()
    tty = sys.stdout.isatty()
    last_print = 0.0
    reason = 'source ended'
    try:
        if args.in_process:
            graph = InProcessGraph(args, context)
        else:
            env = dict(os.environ, PYTHONUNBUFFERED='1')
            children = [Child(node, args, log_dir, env) for node in NODES]
        print(f'bringup: {" -> ".join(NODES)}; camera {args.camera}; arm {args.arm}; '
              f'{args.mode}; logs in {log_dir}', flush=True)
        camera_done_at = None
        while True:
            time.sleep(0.2)
            elapsed = time.monotonic() - start
            for child in children:
                code = child.returncode
                if code is not None and (child.name != 'camera' or code != 0) \
                        and child not in failed:
                    failed.append(child)
            if failed:
                reason = f'{failed[0].name} node exited with code {failed[0].returncode}'
                break
            if not monitor.maps and elapsed > STARTUP_DEADLINE_S:
                reason = f'no surprise map within {STARTUP_DEADLINE_S:.0f} s'
                failed.append(None)
                break
            camera_done = (graph.camera_finished() if graph else children[0].returncode == 0)
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
    except KeyboardInterrupt:
        reason = 'Ctrl-C'
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
    print(summary(monitor, elapsed, reason, codes, recorder))
    monitor.node.destroy_node()
    rclpy.try_shutdown(context=context)
    return 1 if failed or not monitor.maps else 0


def summary(monitor: Monitor, elapsed: float, reason: str, codes: dict, recorder) -> str:
    span = (monitor.maps[-1] - monitor.maps[0]) if len(monitor.maps) > 1 else 0.0
    map_rate = (len(monitor.maps) - 1) / span if span > 0 else 0.0
    lines = [f'summary: stopped after {elapsed:.1f} s ({reason})',
             f'  frames published {len(monitor.frames)}, surprise maps {len(monitor.maps)} '
             f'({map_rate:.1f} maps/s), joint commands {len(monitor.commands)}',
             (f'  simulated time {monitor.sim_time:.2f} s (lockstep: every frame processed, '
              'commands at their frame time)' if monitor.lockstep
              else f'  frame->command latency {percentile_text(monitor)}')]
    if monitor.location:
        lines.append(f'  last action location ({monitor.location[0]:.0f}, '
                     f'{monitor.location[1]:.0f}) in a {monitor.image_size} image')
    if monitor.joints:
        lines.append('  final arm pose (deg): ' + ', '.join(
            f'{n} {d:.1f}' for n, d in monitor.joints.items()))
    if codes:
        lines.append('  node exit codes: ' + ', '.join(f'{n} {c}' for n, c in codes.items()))
    if recorder is not None:
        counts = ', '.join(f'{t} {n}' for t, n in sorted(recorder.counts.items()))
        lines.append(f'  recorded {recorder.path}: {counts}')
    return '\n'.join(lines)


def main(argv=None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    try:
        return run(args)
    except ActivelocError as exc:
        print(f'bringup: error: {exc}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
