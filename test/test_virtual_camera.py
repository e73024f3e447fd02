"""The virtual camera (virtual:SCENE sources) and lockstep: core, nodes and the graph."""
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
from activeloc_ros.errors import ConfigError, SourceError
from activeloc_ros.nodes.lockstep import (
    LATE_COMMAND, Lockstep, NO_COMMAND, NO_LOCATION, NO_POSE, NOT_APPLIED, time_ns)
from activeloc_ros.screen import VirtualScreen
from activeloc_ros.sources import default_bag, open_source, SequenceSource, VirtualSource
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


# -- the source --------------------------------------------------------------------------


def test_virtual_source_renders_the_screen_and_follows_the_arm(tmp_path):
    screen = VirtualScreen()
    source = open_source(f'virtual:folder:{write_folder(tmp_path / "scene")}', clock=None,
                         folder_fps=5.0, screen=screen)
    assert isinstance(source, VirtualSource)
    assert source.fps == 5.0
    np.testing.assert_array_equal(source.camera_matrix(), screen.K)
    home = source.read()
    assert (home.index, home.stamp) == (0, 0.0)
    assert home.rgb.shape == (480, 640, 3)
    np.testing.assert_array_equal(home.rgb, screen.render(scene_image(160, 90), 0.0, 0.0))
    x0, y0 = bright_centroid(home.rgb)
    assert (x0, y0) == pytest.approx((319.5, 239.5), abs=1.0)   # screen centre at home

    source.set_joints(pose(pan_deg=10.0))           # pan > 0 turns the camera left ...
    left = source.read()
    assert (left.index, left.stamp) == (1, 0.2)
    x1, y1 = bright_centroid(left.rgb)
    assert x1 > x0 + 50 and y1 == pytest.approx(y0, abs=2.0)   # ... so the scene moves right
    assert (source.pan, source.tilt) == pytest.approx((math.radians(10.0), 0.0))

    source.set_joints(pose(tilt_deg=8.0))           # tilt > 0 raises it: the scene goes down
    x2, y2 = bright_centroid(source.read().rgb)
    assert y2 > y0 + 40 and x2 == pytest.approx(x0, abs=2.0)
    assert source.read() is None
    source.rewind()
    assert source.read().index == 0


def test_virtual_source_refuses_a_bad_pose(tmp_path):
    source = open_source(f'virtual:folder:{write_folder(tmp_path / "scene", 1)}', clock=None)
    with pytest.raises(SourceError, match='six finite joint angles'):
        source.set_joints([90.0, math.nan, 45, 45, 90, 73])
    with pytest.raises(SourceError, match='six finite joint angles'):
        source.set_joints([90.0] * 5)
    assert source.joints_deg == tuple(float(q) for q in HOME_DEG)


def test_sequence_scenes_by_folder_and_by_name(tmp_path, monkeypatch):
    folder = write_sequence(tmp_path, fps='25 (header)')
    by_path = open_source(f'virtual:{folder}', clock=None)
    assert isinstance(by_path.scene, SequenceSource) and by_path.fps == 25.0
    monkeypatch.setenv('ACTIVELOC_DATA', str(tmp_path))
    by_name = open_source('virtual:tiny', clock=None)
    frames = [by_name.read() for _ in range(4)]
    assert [f.index for f in frames[:3]] == [0, 1, 2] and frames[3] is None
    assert frames[2].stamp == pytest.approx(2 / 25.0)
    np.testing.assert_array_equal(frames[0].rgb, by_path.read().rgb)


def test_the_bundled_bag_as_a_scene():
    source = open_source(f'virtual:bag:{default_bag()}', clock=None)
    assert source.fps == 10.0                  # 300 frames over 29.9 s
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
        open_source('virtual:' + scene.format(tmp=tmp_path), clock=None)


def test_a_name_without_a_data_root(tmp_path, monkeypatch):
    monkeypatch.setenv('ACTIVELOC_DATA', str(tmp_path / 'absent'))
    with pytest.raises(SourceError, match='cannot look up the sequence'):
        open_source('virtual:otb_crossing', clock=None)


# -- the lockstep state machine ----------------------------------------------------------


def test_lockstep_steps_one_frame_after_every_answer():
    step = Lockstep(10.0, timeout=5.0, command_timeout=1.0, retick=0.5)
    assert [time_ns(i, 10.0) for i in range(3)] == [0, 100_000_000, 200_000_000]
    assert [time_ns(i, 30.0) for i in (1, 3)] == [33_333_333, 100_000_000]
    assert step.begin(0.0) == 0
    step.on_state(0, HOME_DEG)
    assert step.poll(0.01) == 'render' and step.pose == HOME_DEG
    step.rendered(0.01)
    assert step.poll(0.02) == 'wait'                  # perception has not answered
    step.on_location(0, 0.1)
    step.on_command(0)
    assert step.poll(0.11) == 'wait'                  # the arm has not confirmed it
    step.on_state(0, HOME_DEG)
    assert step.poll(0.12) == 'next'
    assert step.begin(0.2) == 100_000_000
    with pytest.raises(ConfigError, match='not finished'):
        step.begin(0.2)
    step.on_state(0, HOME_DEG)                        # an old stamp is not the frame's pose
    assert step.poll(0.3) == 'wait'
    assert step.poll(0.71) == 'tick' and step.ticks == 2
    step.on_state(100_000_000, (91.0, 90, 45, 45, 90, 73))
    step.on_state(100_000_000, (91.0, 90, 45, 45, 90, 73))   # the answer to the second tick
    assert step.poll(0.8) == 'render' and step.pose[0] == 91.0
    step.rendered(0.8)
    step.on_command(100_000_000)
    step.on_command(0)                                # a late command counts as well
    step.on_state(100_000_000, (91.0, 90, 45, 45, 90, 73))
    assert step.poll(0.9) == 'wait'
    step.on_state(100_000_000, (91.0, 90, 45, 45, 90, 73))
    assert step.poll(0.91) == 'next'
    assert dict(step.missed) == {LATE_COMMAND: 1}
    step.begin(1.0)                                   # the controller ignores the location:
    step.on_state(200_000_000, HOME_DEG)              # no command to wait for
    assert step.poll(1.0) == 'render'
    step.rendered(1.0)
    step.on_location(200_000_000, 1.1)
    step.on_ignored(100_000_000)                      # not this frame's
    assert step.poll(1.2) == 'wait'
    step.on_ignored(200_000_000)
    assert step.poll(1.21) == 'next'
    assert dict(step.missed) == {LATE_COMMAND: 1}


@pytest.mark.parametrize('events,missed', [
    ([], [NO_POSE, NO_LOCATION]),
    (['state'], [NO_LOCATION]),
    (['state', 'location'], [NO_COMMAND]),
    (['state', 'location', 'command'], [NOT_APPLIED]),
])
def test_lockstep_never_hangs(events, missed):
    step = Lockstep(10.0, timeout=5.0, command_timeout=1.0, retick=100.0)
    step.begin(0.0)
    if 'state' in events:
        step.on_state(0, HOME_DEG)
    now, actions = 0.0, []
    while step.phase != 'idle' and now < 30.0:
        now += 0.25
        action = step.poll(now)
        actions.append(action)
        if action == 'render':
            step.rendered(now)
            if 'location' in events:
                step.on_location(0, now)
            if 'command' in events:
                step.on_command(0)
    assert actions[-1] == 'next' and now < 12.0
    assert sorted(step.missed) == sorted(missed)


@pytest.mark.parametrize('kwargs', [dict(fps=0.0), dict(fps=10.0, timeout=math.inf),
                                    dict(fps=10.0, command_timeout=-1.0)])
def test_lockstep_settings_are_checked(kwargs):
    with pytest.raises(ConfigError, match='lockstep'):
        Lockstep(**kwargs)


# -- the nodes ---------------------------------------------------------------------------


SIM = 'use_sim_time:=true'


@pytest.mark.parametrize('node_name,extra,message', [
    ('camera', ['lockstep:=true', SIM], "'lockstep' needs a virtual"),
    ('camera', ['source:=virtual:bag:' + str(default_bag()), 'lockstep:=true'],
     'use_sim_time'),
    ('camera', ['source:=virtual:bag:' + str(default_bag()), 'view_fraction:=2.0'],
     'view_fraction'),
    ('camera', ['source:=virtual:nosuch/scene'], 'scene not found'),
    ('arm', ['backend:=serial', SIM], 'use_sim_time must be false'),
])
def test_bad_virtual_and_lockstep_settings(context, node_name, extra, message):
    from activeloc_ros.nodes.arm_node import ArmNode
    from activeloc_ros.nodes.camera_node import CameraNode
    cls = {'camera': CameraNode, 'arm': ArmNode}[node_name]
    with pytest.raises((ConfigError, SourceError), match=message):
        cls(context=context, cli_args=params_args(node_name, *extra))


class Probe:
    """Records the camera's poses, images' stamps and the controller's commands."""

    def __init__(self, context):
        from rclpy.node import Node
        from rclpy.qos import QoSProfile
        from sensor_msgs.msg import CameraInfo, JointState
        self.node = Node('probe', context=context)
        from geometry_msgs.msg import PointStamped
        self.poses, self.infos, self.commands, self.ignored = [], [], [], []
        deep = QoSProfile(depth=100)
        sub = self.node.create_subscription
        sub(JointState, 'camera/pose', self.poses.append, deep)
        sub(CameraInfo, 'camera/camera_info', self.infos.append, deep)
        sub(JointState, 'joint_commands', self.commands.append, deep)
        sub(PointStamped, 'action_location/ignored', self.ignored.append, deep)
        self.joints = self.node.create_publisher(JointState, 'joint_states', 10)


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def test_realtime_virtual_camera_follows_joint_states(context):
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState
    from activeloc_ros.nodes.camera_node import CameraNode
    camera = CameraNode(context=context, cli_args=params_args(
        'camera', f'source:=virtual:bag:{default_bag()}', 'rate:=5.0', 'loop:=true',
        'wait_for_subscriber:=0.0'))
    probe = Probe(context)
    executor = SingleThreadedExecutor(context=context)
    for node in (camera, probe.node):
        executor.add_node(node)
    turned = JointState(name=list(JOINT_NAMES),
                        position=[math.radians(q) for q in pose(pan_deg=12.0)])
    try:
        assert spin_until(executor, lambda: probe.poses, 20), 'no camera/pose'
        assert tuple(probe.poses[0].name) == ('pan', 'tilt')
        assert list(probe.poses[0].position) == [0.0, 0.0]
        assert spin_until(executor, lambda: camera.state_sub.get_publisher_count() > 0, 10)

        def turned_seen():
            probe.joints.publish(turned)
            return probe.poses[-1].position[0] == pytest.approx(math.radians(12.0))
        assert spin_until(executor, turned_seen, 20), 'the camera did not turn'
    finally:
        executor.shutdown()
        camera.destroy_node()
        probe.node.destroy_node()
    assert list(probe.infos[-1].k) == pytest.approx(VirtualScreen().K.ravel())


def test_lockstep_graph_steps_frame_by_frame_like_closed_loop(context):
    """Camera (lockstep), the real perception, controller and simulated arm on simulated
    time: every frame is processed and answered (a command or an ignored location), each
    image's stamp is i / fps, and the pose each frame was rendered with is where the
    simulated arm is when every command is applied at its frame's time (closed_loop's
    lockstep)."""
    from rclpy.executors import MultiThreadedExecutor
    from activeloc_ros.nodes.arm_node import ArmNode
    from activeloc_ros.nodes.camera_node import CameraNode
    from activeloc_ros.nodes.controller_node import ControllerNode
    from activeloc_ros.nodes.perception_node import PerceptionNode
    frames = 8
    nodes = [PerceptionNode(context=context, cli_args=params_args('perception', SIM)),
             ControllerNode(context=context, cli_args=params_args('controller', SIM)),
             ArmNode(context=context, cli_args=params_args('arm', 'backend:=sim', SIM)),
             CameraNode(context=context, cli_args=params_args(
                 'camera', f'source:=virtual:bag:{default_bag()}', 'lockstep:=true', SIM,
                 f'max_frames:={frames}'))]
    camera = nodes[-1]
    probe = Probe(context)
    executor = MultiThreadedExecutor(num_threads=4, context=context)
    for node in nodes + [probe.node]:
        executor.add_node(node)
    try:
        assert spin_until(executor, lambda: camera.finished, 120), 'lockstep did not finish'
        spin_until(executor, lambda: len(probe.commands) + len(probe.ignored) >= frames, 2.0)
    finally:
        executor.shutdown()
        for node in nodes + [probe.node]:
            node.destroy_node()
    assert not camera.lockstep.missed, camera.lockstep.missed
    times = [time_ns(i, 10.0) for i in range(frames)]
    assert [stamp_ns(p) for p in probe.poses] == times
    assert [stamp_ns(i) for i in probe.infos] == times
    # one answer per frame, in step: a command, or the location the controller ignored
    answers = sorted([stamp_ns(c) for c in probe.commands]
                     + [stamp_ns(loc) for loc in probe.ignored])
    assert answers == times
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
    """As in the screen benchmark: by default only the arm limits the aim; with
    --aim-limits screen the controller gets the screen's aim limits, from the camera's
    params files, unless the user's own files set them."""
    from activeloc_ros.bringup import node_arguments, parse_args
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
    from activeloc_ros.bag import BagWriter
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
