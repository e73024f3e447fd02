"""
The Braccio model: limits, home, mapping, and the guard every command passes through.

The property tests drive the guard and the whole reactive controller with arbitrary, wild
input sequences: every command must be inside the joint limits and within the servos'
speed since the previous command.
"""
import math

from hypothesis import event as note_event, given, settings, strategies as st
import pytest

from activeloc_ros.control import (
    ArmMapping, clamp_to_limits, ControllerConfig, HOME_DEG, Intrinsics, JOINT_NAMES,
    JointGuard, LIMITS_DEG, PD_VARIANTS, PDConfig, ReactiveController, SAFETY_DEG, SimArm,
    speed_deg_s, within_limits)
from activeloc_ros.errors import ConfigError

EPS = 1e-9


def test_joint_names_limits_and_poses():
    assert JOINT_NAMES == ('base', 'shoulder', 'elbow', 'wrist_ver', 'wrist_rot', 'gripper')
    assert dict(LIMITS_DEG) == {'base': (0, 180), 'shoulder': (15, 165), 'elbow': (0, 180),
                                'wrist_ver': (0, 180), 'wrist_rot': (0, 180),
                                'gripper': (10, 73)}
    assert within_limits(HOME_DEG) and within_limits(SAFETY_DEG)


def test_home_points_the_camera_straight_ahead():
    """Shoulder upright, elbow and wrist bending 45 degrees each: the last link is level."""
    mapping = ArmMapping()
    assert mapping.pan_tilt(HOME_DEG) == (0.0, 0.0)
    base, shoulder, elbow, wrist_ver = HOME_DEG[:4]
    assert base == 90 and shoulder == 90
    assert (shoulder - 90) + (elbow - 90) + (wrist_ver - 90) == -90


@pytest.mark.parametrize('step_delay_ms, speed', [(10, 100.0), (20, 50.0), (30, 1000 / 30)])
def test_speed_from_the_step_delay(step_delay_ms, speed):
    assert speed_deg_s(step_delay_ms) == pytest.approx(speed)


@pytest.mark.parametrize('step_delay_ms', [9, 31, 0, -5])
def test_step_delay_outside_the_library_range_is_refused(step_delay_ms):
    with pytest.raises(ConfigError):
        speed_deg_s(step_delay_ms)


@pytest.mark.parametrize('options', [
    {'pan_joint': 'neck'}, {'tilt_joints': ('base',)}, {'tilt_gains': (1.0, 1.0)},
    {'pan_gain': 0.0}, {'home_deg': (90, 10, 45, 45, 90, 73)}, {'tilt_joints': ()},
    {'home_deg': (90, 90, 45)}])
def test_bad_mappings_are_refused(options):
    with pytest.raises(ConfigError):
        ArmMapping(**options)


def test_clamp_refuses_nan_and_wrong_lengths():
    assert clamp_to_limits([-10, 0, 200, 90, 90, 100]) == (0, 15, 180, 90, 90, 73)
    with pytest.raises(ConfigError):
        clamp_to_limits([math.nan] * 6)
    with pytest.raises(ConfigError):
        clamp_to_limits([90] * 5)


angles = st.floats(min_value=-1.5, max_value=1.5)


@given(pan=angles, tilt=angles, gains=st.sampled_from([
    (('wrist_ver',), (1.0,)), (('elbow', 'wrist_ver'), (-0.5, 0.5)),
    (('shoulder', 'elbow', 'wrist_ver'), (0.2, 0.3, -0.5))]), pan_gain=st.sampled_from([1, -1]))
def test_pan_tilt_round_trip(pan, tilt, gains, pan_gain):
    mapping = ArmMapping(tilt_joints=gains[0], tilt_gains=gains[1], pan_gain=pan_gain)
    assert mapping.pan_tilt(mapping.joints_deg(pan, tilt)) == pytest.approx((pan, tilt))


# -- properties: whatever comes in, what goes out is safe ------------------------------------

wild = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                 st.floats(min_value=-400, max_value=400))
wild_time = st.one_of(st.floats(min_value=-1.0, max_value=5.0),
                      st.sampled_from([0.0, 1e-9, math.nan, math.inf, -math.inf, 1e6]))


def assert_safe(commands, start, t0, speed):
    prev, prev_t = start, t0
    for joints, t in commands:
        assert within_limits(joints, tol=EPS), joints
        dt = max(0.0, t - prev_t) if math.isfinite(t) else 0.0
        for q, p in zip(joints, prev):
            assert abs(q - p) <= speed * dt + EPS, (q, p, dt)
        if dt > 0:
            prev_t = t
        prev = joints


@settings(max_examples=300, deadline=None)
@given(start=st.lists(st.floats(min_value=-50, max_value=250), min_size=6, max_size=6),
       step=st.integers(min_value=10, max_value=30),
       moves=st.lists(st.tuples(st.lists(wild, min_size=6, max_size=6), wild_time),
                      max_size=40))
def test_guard_keeps_commands_inside_limits_and_speed(start, step, moves):
    guard = JointGuard(start, 0.0, step_delay_ms=step)
    t, commands = 0.0, []
    for target, dt in moves:
        t = t + dt
        commands.append((guard.limit(target, t), t))
    assert_safe(commands, clamp_to_limits(start), 0.0, speed_deg_s(step))


plausible = st.tuples(st.just('pixel'), st.floats(0, 639), st.floats(0, 479), st.floats(0, 1),
                      st.floats(0.0, 0.3), st.floats(0.0, 0.5))
event = st.one_of(plausible, st.one_of(  # half of the events are plausible locations
    st.tuples(st.just('location'), wild, wild, wild, wild_time, wild_time),
    st.tuples(st.just('tick'), wild_time),
    st.tuples(st.just('joints'), st.lists(wild, min_size=6, max_size=6), wild_time),
    st.tuples(st.just('camera'), st.floats(10, 5000), st.floats(-1000, 2000),
              st.integers(1, 4000)),
    st.tuples(st.just('hold'), wild_time),
))


@settings(max_examples=300, deadline=None)
@given(events=st.lists(event, min_size=10, max_size=60),
       variant=st.sampled_from(sorted(PD_VARIANTS)),
       derivative=st.sampled_from(['error', 'target']), step=st.integers(10, 30),
       tau=st.sampled_from([0.0, 0.05]),
       mapping=st.sampled_from([ArmMapping(), ArmMapping(pan_gain=-3.0, tilt_gains=(-2.0,)),
                                ArmMapping(tilt_joints=('shoulder', 'elbow'),
                                           tilt_gains=(5.0, -5.0))]))
def test_controller_commands_stay_inside_limits_and_speed(events, variant, derivative, step,
                                                          tau, mapping):
    pd = PDConfig.variant(variant, dead_band=math.radians(1.0), derivative=derivative,
                          derivative_tau=tau)
    config = ControllerConfig(pd=pd, mapping=mapping, step_delay_ms=step, watchdog_timeout=0.3)
    ctl = ReactiveController(config, t0=0.0)
    ctl.set_intrinsics(Intrinsics(600.0, 600.0, 319.5, 239.5, 640, 480))
    now, commands = 0.0, []
    for kind, *args in events:
        if not commands:  # measured joints before the first command move the start
            start, t0 = ctl.guard.last_deg, ctl.guard.last_t
        if kind == 'location':
            u, v, peak, capture_dt, dt = args
            now += dt if math.isfinite(dt) else 0.0
            cmd = ctl.on_location(u, v, now - capture_dt, now, peak=peak)
        elif kind == 'pixel':
            u, v, peak, capture_dt, dt = args
            now += dt
            cmd = ctl.on_location(u, v, now - capture_dt, now, peak=peak)
        elif kind == 'tick':
            now += args[0] if math.isfinite(args[0]) else 0.0
            cmd = ctl.tick(now)
        elif kind == 'joints':
            ctl.observe(args[0], now + (args[1] if math.isfinite(args[1]) else 0.0))
            cmd = None
        elif kind == 'camera':
            fx, cx, width = args
            ctl.set_intrinsics(Intrinsics(fx, fx, cx, cx, width, width))
            cmd = None
        else:
            now += args[0] if math.isfinite(args[0]) else 0.0
            cmd = ctl.hold(now)
        if cmd is not None:
            assert all(math.isfinite(q) for q in cmd.joints_deg)
            commands.append((cmd.joints_deg, cmd.t))
    tracking = ctl.latency.count  # commands made from action locations
    note_event(f'tracking commands: {min(tracking, 5)}{"+" if tracking >= 5 else ""}')
    if commands:
        assert within_limits(start)
        assert_safe(commands, start, t0, speed_deg_s(step))


@settings(max_examples=200, deadline=None)
@given(start=st.lists(st.integers(-20, 200), min_size=6, max_size=6),
       step=st.integers(10, 30),
       moves=st.lists(st.tuples(st.lists(st.floats(-100, 300), min_size=6, max_size=6),
                                st.floats(0.0, 0.5)), max_size=30))
def test_sim_arm_moves_whole_degrees_at_the_servos_speed(start, step, moves):
    arm = SimArm(start, 0.0, step_delay_ms=step)
    t, prev, prev_t = 0.0, arm.joints, 0.0
    for target, dt in moves:
        t += dt
        arm.command(target, t)
        joints = arm.advance(t)
        assert all(isinstance(q, int) for q in joints) and within_limits(joints)
        steps = math.floor((t - prev_t) / (step / 1000.0)) + 1  # step ticks in (prev_t, t]
        assert all(abs(q - p) <= steps for q, p in zip(joints, prev))
        prev, prev_t = joints, t


def test_sim_arm_follows_one_degree_per_step_delay():
    arm = SimArm(HOME_DEG, 0.0, step_delay_ms=20)
    arm.command([HOME_DEG[0] + 10.4] + list(HOME_DEG[1:]), 0.0)
    assert arm.target[0] == HOME_DEG[0] + 10  # servos take whole degrees
    assert arm.advance(0.019)[0] == HOME_DEG[0]
    assert arm.advance(0.1)[0] == HOME_DEG[0] + 5
    assert arm.advance(0.05)[0] == HOME_DEG[0] + 5  # time never runs backwards
    assert arm.advance(0.5)[0] == HOME_DEG[0] + 10 and not arm.moving


def test_sim_arm_restarted_at_an_earlier_time_goes_on_moving():
    arm = SimArm(HOME_DEG, 100.0, step_delay_ms=20)
    arm.command([HOME_DEG[0] + 10] + list(HOME_DEG[1:]), 100.0)
    assert arm.advance(100.1)[0] == HOME_DEG[0] + 5
    assert arm.advance(1.1)[0] == HOME_DEG[0] + 5       # the clock ran back: frozen
    arm.restart(1.0)
    assert arm.advance(1.1)[0] == HOME_DEG[0] + 10 and not arm.moving
    with pytest.raises(ConfigError, match='finite'):
        arm.restart(math.nan)
