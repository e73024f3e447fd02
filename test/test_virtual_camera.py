"""
The virtual camera (the sim node: a scene on the virtual screen, the arm that aims the
camera) and lockstep: core, nodes and the graph.
"""
import json
import math
from pathlib import Path
import subprocess
import sys

import cv2
import numpy as np
import pytest

from activeloc_ros.control import JOINT_NAMES, SimArm
from activeloc_ros.control.braccio import ArmMapping, HOME_DEG
from activeloc_ros.data import FrameTruth
from activeloc_ros.errors import ConfigError, SourceError
from activeloc_ros.nodes.lockstep import (
    LATE_COMMAND, Lockstep, NO_COMMAND, NO_LOCATION, NO_POSE, time_ns)
from activeloc_ros.screen import VirtualScreen
from activeloc_ros.sources import default_bag, open_scene, open_source, SequenceSource
from activeloc_ros.world import ScreenWorld
from conftest import params_args, REPO, spin_until

SCENE_WH = (320, 180)


def scene_image(x: int, y: int) -> np.ndarray:
    """A grey scene (RGB) with a white 20x20 square centred on (x, y)."""
    rgb = np.full((SCENE_WH[1], SCENE_WH[0], 3), 60, np.uint8)
    rgb[y - 10:y + 10, x - 10:x + 10] = 255
    return rgb


def write_folder(path: Path, n: int = 3) -> Path:
    path.mkdir(parents=True)
    bgr = cv2.cvtColor(scene_image(160, 90), cv2.COLOR_RGB2BGR)
    for i in range(n):
        cv2.imwrite(str(path / f'{i:03d}.png'), bgr)
    return path


def write_sequence(root: Path, name: str = 'tiny', *, n: int = 3, fps: str = '25') -> Path:
    path = write_folder(root / name / 'img', n).parent
    (path / 'gt_xywh.txt').write_text('150,80,20,20\n' * n)
    meta = {'W': SCENE_WH[0], 'H': SCENE_WH[1], 'frames': n, 'camera': 'STATIC',
            'frames_glob': 'img/*.png', 'fps': fps}
    (path / 'meta.json').write_text(json.dumps(meta))
    return path


def bright_centroid(rgb: np.ndarray) -> tuple[float, float]:
    rows, cols = np.nonzero(rgb[..., 0] > 200)
    assert len(cols), 'the square is out of view'
    return float(cols.mean()), float(rows.mean())


def pose(pan_deg: float = 0.0, tilt_deg: float = 0.0) -> list[float]:
    return list(ArmMapping().joints_deg(math.radians(pan_deg), math.radians(tilt_deg)))


# -- the world and its scenes ------------------------------------------------------------


def test_the_world_renders_the_screen_and_follows_the_arm():
    screen = VirtualScreen()
    world = ScreenWorld((), fps=5.0, screen=screen, home_deg=HOME_DEG, step_delay_ms=20)
    scene = scene_image(160, 90)
    assert world.show(0, scene, FrameTruth(0, None, ())) == 0.0
    world.advance(world.t)
    home = world.observe()
    assert (home.index, home.t) == (0, 0.0) and home.rgb.shape == (480, 640, 3)
    np.testing.assert_array_equal(home.rgb, screen.render(scene, 0.0, 0.0))
    x0, y0 = bright_centroid(home.rgb)
    assert (x0, y0) == pytest.approx((319.5, 239.5), abs=1.0)   # screen centre at home

    world.act(pose(pan_deg=10.0), 0.0)              # pan > 0 turns the camera left ...
    assert world.show(1, scene, FrameTruth(1, None, ())) == 0.2
    world.advance(world.t)                          # 10 degrees at 50 deg/s
    left = world.observe()
    x1, y1 = bright_centroid(left.rgb)
    assert x1 > x0 + 50 and y1 == pytest.approx(y0, abs=2.0)   # ... so the scene moves right
    assert (left.pan, left.tilt) == pytest.approx((math.radians(10.0), 0.0))

    world.act(pose(tilt_deg=8.0), 0.2)              # tilt > 0 raises it: the scene goes down
    world.show(2, scene, FrameTruth(2, None, ()), t=0.5)    # a wall clock's time
    world.advance(world.t)
    x2, y2 = bright_centroid(world.observe().rgb)
    assert y2 > y0 + 40 and x2 == pytest.approx(x0, abs=2.0)


def test_sequence_scenes_by_folder_and_by_name(tmp_path, monkeypatch):
    folder = write_sequence(tmp_path, fps='25 (header)')
    by_path = open_scene(str(folder))
    assert isinstance(by_path, SequenceSource) and by_path.fps == 25.0
    monkeypatch.setenv('ACTIVELOC_DATA', str(tmp_path))
    by_name = open_scene('tiny')
    frames = [by_name.read() for _ in range(4)]
    assert [f.index for f in frames[:3]] == [0, 1, 2] and frames[3] is None
    assert frames[2].stamp == pytest.approx(2 / 25.0)
    np.testing.assert_array_equal(frames[0].rgb, by_path.read().rgb)


def test_the_bundled_bag_as_a_scene():
    source = open_scene(f'bag:{default_bag()}')
    assert source.fps == pytest.approx(10.0, abs=0.1)    # 300 frames over 29.9 s
    assert source.read().rgb.shape == (480, 640, 3)
    source.close()


@pytest.mark.parametrize('scene,message', [
    ('', 'needs a scene'),
    ('virtual:bag:x', 'shows a recorded scene'),
    ('device:0', 'shows a recorded scene'),
    ('bag:{tmp}/none.mcap', 'bag not found'),
    ('{tmp}/plain', 'not an annotated sequence'),
    ('{tmp}/plain/a.txt', 'is a file'),
    ('{tmp}/missing/seq', 'scene not found'),
    ('nosuch', "no sequence 'nosuch' in the data root"),
    ('{tmp}/broken', 'bad sequence'),
])
def test_bad_scenes_say_why(tmp_path, monkeypatch, scene, message):
    (tmp_path / 'plain').mkdir()
    (tmp_path / 'plain' / 'a.txt').write_text('x')
    (write_sequence(tmp_path, 'broken') / 'gt_xywh.txt').write_text('1,2,3\n')
    monkeypatch.setenv('ACTIVELOC_DATA', str(tmp_path))
    with pytest.raises(SourceError, match=message):
        open_scene(scene.format(tmp=tmp_path))


def test_a_name_without_a_data_root(tmp_path, monkeypatch):
    monkeypatch.setenv('ACTIVELOC_DATA', str(tmp_path / 'absent'))
    with pytest.raises(SourceError, match='cannot look up the sequence'):
        open_scene('otb_crossing')


def test_the_camera_node_is_no_virtual_camera():
    with pytest.raises(SourceError, match="the sim node's"):
        open_source(f'virtual:bag:{default_bag()}', clock=None)


# -- the lockstep state machine ----------------------------------------------------------


def test_lockstep_steps_one_frame_after_every_answer():
    step = Lockstep(timeout=5.0, command_timeout=1.0)
    assert [time_ns(i, 10.0) for i in range(3)] == [0, 100_000_000, 200_000_000]
    assert [time_ns(i, 30.0) for i in (1, 3)] == [33_333_333, 100_000_000]
    assert step.poll(0.0) == 'next'                   # nothing in progress: begin
    step.begin(0, 0.0)
    with pytest.raises(ConfigError, match='not finished'):
        step.begin(0, 0.0)
    assert step.poll(0.01) == 'wait'                  # the arm state is not back yet
    step.on_state(0)
    assert step.poll(0.02) == 'render'
    step.rendered(0.02)
    step.on_command(0)                                # no location yet, but an answer
    assert step.poll(0.03) == 'next'
    step.begin(100_000_000, 0.2)
    step.on_state(0)                                  # an old stamp is not the frame's
    assert step.poll(0.3) == 'wait'
    step.on_state(100_000_000)
    assert step.poll(0.31) == 'render'
    step.rendered(0.31)
    step.on_location(100_000_000, 0.4)
    step.on_command(0)                                # a late command is counted
    step.on_ignored(0)                                # and an old answer is not this one
    assert step.poll(0.5) == 'wait'
    step.on_ignored(100_000_000)                      # the controller ignored it
    assert step.poll(0.51) == 'next'
    assert dict(step.missed) == {LATE_COMMAND: 1}


@pytest.mark.parametrize('events,missed', [
    ([], [NO_POSE, NO_LOCATION]),
    (['state'], [NO_LOCATION]),
    (['state', 'location'], [NO_COMMAND]),
    (['state', 'location', 'command'], []),
])
def test_lockstep_never_hangs(events, missed):
    step = Lockstep(timeout=5.0, command_timeout=1.0)
    step.begin(0, 0.0)
    if 'state' in events:
        step.on_state(0)
    now, actions = 0.0, []
    while now < 30.0:
        now += 0.25
        action = step.poll(now)
        actions.append(action)
        if action == 'next':
            break
        if action == 'render':
            step.rendered(now)
            if 'location' in events:
                step.on_location(0, now)
            if 'command' in events:
                step.on_command(0)
    assert actions[-1] == 'next' and now < 12.0
    assert sorted(step.missed) == sorted(missed)


@pytest.mark.parametrize('kwargs', [{'timeout': math.inf}, {'command_timeout': -1.0},
                                    {'timeout': 0.0}])
def test_lockstep_settings_are_checked(kwargs):
    with pytest.raises(ConfigError, match='lockstep'):
        Lockstep(**kwargs)


# -- the nodes ---------------------------------------------------------------------------


SIM = 'use_sim_time:=true'


@pytest.mark.parametrize('extra,message', [
    (['lockstep:=true'], 'use_sim_time'),
    ([SIM], 'set lockstep:=true'),
    (['view_fraction:=2.0'], 'view_fraction'),
    (['scene:=nosuch/scene'], 'scene not found'),
])
def test_bad_sim_settings(context, extra, message):
    from activeloc_ros.nodes.sim_node import SimNode
    with pytest.raises((ConfigError, SourceError), match=message):
        SimNode(context=context, cli_args=params_args(*extra))


def test_rate_is_refused_at_run_time_in_lockstep_and_applied_in_real_time(context):
    """
    In lockstep the graph sets the pace, so a new rate would be reported as set and
    never used: it is refused with the reason; in real time it is applied.
    """
    from rclpy.parameter import Parameter
    from activeloc_ros.nodes.sim_node import SimNode
    for extra, accepted in ((['lockstep:=true', SIM], False), ([], True)):
        node = SimNode(context=context, cli_args=params_args(*extra,
                                                             'wait_for_subscriber:=0.0'))
        try:
            [result] = node.set_parameters([Parameter('rate', value=2.0)])
            assert result.successful is accepted, extra
            if accepted:
                assert node.pacer.rate == 2.0
            else:
                assert 'in lockstep' in result.reason and node.get_parameter('rate').value == 1.0
        finally:
            node.destroy_node()


class Probe:
    """
    Records the camera's poses, images' stamps, the arm's states and the controller's
    answers; sends joint commands.
    """

    def __init__(self, context):
        from geometry_msgs.msg import PointStamped
        from rclpy.node import Node
        from rclpy.qos import QoSProfile
        from sensor_msgs.msg import CameraInfo, JointState
        self.node = Node('probe', context=context)
        self.poses, self.infos, self.commands, self.ignored = [], [], [], []
        self.states = []
        deep = QoSProfile(depth=100)
        sub = self.node.create_subscription
        sub(JointState, 'camera/pose', self.poses.append, deep)
        sub(CameraInfo, 'camera/camera_info', self.infos.append, deep)
        sub(JointState, 'joint_commands', self.commands.append, deep)
        sub(JointState, 'joint_states', self.states.append, deep)
        sub(PointStamped, 'action_location/ignored', self.ignored.append, deep)
        self.command = self.node.create_publisher(JointState, 'joint_commands', 10)


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def test_realtime_sim_moves_its_arm_and_the_camera_with_it(context):
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState
    from activeloc_ros.nodes.sim_node import SimNode
    sim = SimNode(context=context,
                  cli_args=params_args('rate:=5.0', 'loop:=true', 'wait_for_subscriber:=0.0'))
    probe = Probe(context)
    executor = SingleThreadedExecutor(context=context)
    for node in (sim, probe.node):
        executor.add_node(node)
    turned = JointState(name=list(JOINT_NAMES),
                        position=[math.radians(q) for q in pose(pan_deg=12.0)])
    bad = JointState(name=list(JOINT_NAMES), position=[math.nan] * 6)
    try:
        assert spin_until(executor, lambda: probe.poses and probe.states, 20)
        assert tuple(probe.poses[0].name) == ('pan', 'tilt')
        assert list(probe.poses[0].position) == [0.0, 0.0]
        assert spin_until(executor, lambda: sim.command_sub.get_publisher_count() > 0, 10)
        probe.command.publish(bad)
        assert spin_until(executor, lambda: sim.rejected == 1, 10), 'a NaN command was taken'

        def turned_seen():
            probe.command.publish(turned)
            return probe.poses[-1].position[0] == pytest.approx(math.radians(12.0))
        assert spin_until(executor, turned_seen, 20), 'the camera did not turn'
        # joint_states come on their own timer: the pose of a frame may be seen first
        assert spin_until(executor, lambda: math.degrees(probe.states[-1].position[0])
                          == pytest.approx(90.0 + 12.0), 10), 'the arm did not report the turn'
    finally:
        executor.shutdown()
        sim.destroy_node()
        probe.node.destroy_node()
    assert list(probe.infos[-1].k) == pytest.approx(VirtualScreen().K.ravel())
    base = [math.degrees(s.position[0]) for s in probe.states]
    assert base[-1] == pytest.approx(90.0 + 12.0) and base == sorted(base)


def test_max_frames_ends_a_realtime_sim_too(context):
    """It was read in lockstep only: in real time it was accepted and did nothing."""
    from rclpy.executors import SingleThreadedExecutor
    from activeloc_ros.nodes.sim_node import SimNode
    sim = SimNode(context=context, cli_args=params_args(
        'rate:=5.0', 'loop:=true', 'wait_for_subscriber:=0.0', 'max_frames:=3'))
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(sim)
    try:
        assert spin_until(executor, lambda: sim.finished, 30)
        assert sim.published == 3
    finally:
        executor.shutdown()
        sim.destroy_node()


def test_lockstep_graph_steps_frame_by_frame_like_closed_loop(context):
    """
    The sim (lockstep), the real perception and controller on simulated time: every
    frame is processed and answered (a command or an ignored location), each image's stamp
    is i / fps, and the pose each frame was rendered with is where closed_loop's arm is
    when every command is applied at its frame's time.
    """
    from rclpy.executors import MultiThreadedExecutor
    from activeloc_ros.nodes.controller_node import ControllerNode
    from activeloc_ros.nodes.perception_node import PerceptionNode
    from activeloc_ros.nodes.sim_node import SimNode
    frames = 8
    nodes = [PerceptionNode(context=context, cli_args=params_args(SIM)),
             ControllerNode(context=context, cli_args=params_args(SIM)),
             SimNode(context=context,
                     cli_args=params_args('lockstep:=true', SIM, f'max_frames:={frames}'))]
    sim = nodes[-1]
    probe = Probe(context)
    executor = MultiThreadedExecutor(num_threads=4, context=context)
    for node in nodes + [probe.node]:
        executor.add_node(node)
    try:
        assert spin_until(executor, lambda: sim.finished, 120), 'lockstep did not finish'
        spin_until(executor, lambda: len(probe.commands) + len(probe.ignored) >= frames, 2.0)
    finally:
        executor.shutdown()
        for node in nodes + [probe.node]:
            node.destroy_node()
    assert not sim.lockstep.missed, sim.lockstep.missed
    times = [time_ns(i, 10.0) for i in range(frames)]
    assert [stamp_ns(p) for p in probe.poses] == times
    assert [stamp_ns(i) for i in probe.infos] == times
    assert [stamp_ns(s) for s in probe.states] == times      # one arm state per frame
    # every frame answered, in step: a command, the location the controller ignored, or
    # both (an ignored location that carries on a move the servos' speed cut short)
    answers = sorted({stamp_ns(c) for c in probe.commands}
                     | {stamp_ns(loc) for loc in probe.ignored})
    assert answers == times
    assert len({stamp_ns(c) for c in probe.commands}) == len(probe.commands)  # one a frame
    commanded = {stamp_ns(c): [math.degrees(q) for q in c.position] for c in probe.commands}
    assert any(np.abs(np.subtract(q, HOME_DEG)).max() >= 1 for q in commanded.values()), \
        'the arm was never told to move: the check below would prove nothing'
    # closed_loop's arm: rendered at t_i after the commands of t_0..t_{i-1}, each at its t
    arm, mapping = SimArm(HOME_DEG, 0.0), ArmMapping()
    for i, p in enumerate(probe.poses):
        expected = mapping.pan_tilt(arm.advance(times[i] / 1e9))
        assert tuple(p.position) == pytest.approx(expected, abs=1e-9), f'frame {i}'
        if times[i] in commanded:
            arm.command(commanded[times[i]], times[i] / 1e9)


# -- bringup ---------------------------------------------------------------------------------


@pytest.mark.parametrize('args,message', [
    (['--camera', 'virtual:nosuch/scene'], 'scene not found'),
    (['--camera', 'virtual:device:0'], 'shows a recorded scene'),
    (['--mode', 'lockstep', '--camera', f'bag:{default_bag()}'], 'needs --camera virtual'),
    (['--arm', 'serial:/dev/null'], "--arm must be 'sim'"),
])
def test_bringup_refuses_bad_virtual_cameras_before_any_node(tmp_path, args, message):
    logs = tmp_path / 'logs'
    result = subprocess.run([sys.executable, '-m', 'activeloc_ros.bringup', *args,
                             '--log-dir', str(logs)], cwd=REPO, capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 2
    assert message in result.stderr
    assert not logs.exists(), 'a node was started'


def test_bringup_aim_limits_are_the_arms_or_on_request_the_screens(tmp_path):
    """
    As in the screen benchmark: by default only the arm limits the aim; with
    --aim-limits screen the controller gets the screen's aim limits, from the sim's
    params files, unless the user's own files set them.
    """
    from activeloc_ros.bringup import parse_args
    from activeloc_ros.graph_plan import node_arguments
    wider = tmp_path / 'wider.yaml'
    wider.write_text('/**:\n  ros__parameters:\n    view_fraction: 0.5\n')
    mine = tmp_path / 'mine.yaml'
    mine.write_text('controller:\n  ros__parameters:\n    pan_limit_deg: 10.0\n')

    def limits(*argv):
        ros_args = node_arguments('controller', parse_args(list(argv)))
        return {a.split(':=')[0]: float(a.split(':=')[1]) for a in ros_args
                if a.startswith(('pan_limit_deg:=', 'tilt_limit_deg:='))}

    assert limits() == {}                   # the faithful rig: only the arm's joints
    pan, tilt = VirtualScreen().aim_limits_deg()
    screen = ('--aim-limits', 'screen')
    assert limits(*screen) == pytest.approx({'pan_limit_deg': pan, 'tilt_limit_deg': tilt})
    narrower = limits(*screen, '--params', str(wider))
    assert narrower['pan_limit_deg'] < pan and narrower['tilt_limit_deg'] < tilt
    assert set(limits(*screen, '--params', str(mine))) == {'tilt_limit_deg'}
    assert limits(*screen, '--camera', f'bag:{default_bag()}') == {}


def test_recorded_poses_read_back_per_frame(tmp_path):
    from activeloc_ros.bag.write import BagWriter
    from activeloc_ros.nodes.lockstep import recorded_poses
    writer = BagWriter(tmp_path / 'run')
    types = writer.store.types

    def joint_state(ns, names, positions):
        header = types['std_msgs/msg/Header'](
            stamp=types['builtin_interfaces/msg/Time'](sec=ns // 10**9, nanosec=ns % 10**9),
            frame_id='')
        return types['sensor_msgs/msg/JointState'](
            header=header, name=names, position=np.array(positions, np.float64),
            velocity=np.zeros(0), effort=np.zeros(0))

    for i, (pan, tilt) in reversed(list(enumerate([(0.0, 0.0), (0.1, -0.05), (0.2, 0.0)]))):
        t = time_ns(i, 30.0)
        writer.write('/camera/pose', 'sensor_msgs/msg/JointState', 10**9 - i,
                     joint_state(t, ['pan', 'tilt'], [pan, tilt]))
        writer.write('/joint_states', 'sensor_msgs/msg/JointState', 10**9 - i,
                     joint_state(t, list(JOINT_NAMES), [1.0] * 6))
    writer.close()
    poses = recorded_poses(tmp_path / 'run')
    assert [round(t * 30.0) for t, _, _ in poses] == [0, 1, 2]
    assert [(pan, tilt) for _, pan, tilt in poses] == [(0.0, 0.0), (0.1, -0.05), (0.2, 0.0)]
