"""
Start the whole graph (camera, perception, controller, arm) from one script.

    python -m activeloc_ros.bringup                      # bundled bag on the virtual screen
    python -m activeloc_ros.bringup --mode lockstep --camera virtual:otb_crossing
    python -m activeloc_ros.bringup --camera device:0 --duration 60
    python -m activeloc_ros.bringup --record out/run1    # every topic to an MCAP bag

Each node runs in its own process (as a launch file would) with `params/robot.yaml` and
the --params files, or all in one executor with --in-process. With a virtual
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
import os
from pathlib import Path
import signal
import sys
import threading
import time

from activeloc_ros.checks import argument, finite
from activeloc_ros.errors import ActivelocError, ConfigError
from activeloc_ros.graph_plan import DEFAULT_CAMERA, graph_nodes, MODES, own_ros_args
from activeloc_ros.nodes.monitor import Monitor, percentile_text
from activeloc_ros.preflight import preflight
from activeloc_ros.screen import AIM_LIMITS
from activeloc_ros.supervisor import Child, StopRequest, WARNING_LINE

# What the nodes publish (README, "Nodes and topics"): a recording subscribes to these before
# any node starts, so it holds every message from the first on.
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
ARM_STALE_S = 2.0             # realtime: no joint_states for this long at the end is reported
#                               (an arm node's; the sim's arm ends with its scene)
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
    from activeloc_ros.nodes.in_process import InProcessGraph
    from activeloc_ros.nodes.process import lean_executor
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
            print('bringup: error: rclpy is not installed: source a ROS 2 Jazzy (source '
                  '/opt/ros/jazzy/setup.bash) or install the PyPI wheels with pip install '
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
