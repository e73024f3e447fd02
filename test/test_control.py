"""The reactive control maths without ROS: geometry, the PD law (Eq. 4), the watchdog."""
import math

import numpy as np
import pytest

from activeloc_ros.control import (
    angular_error, ArmMapping, ControllerConfig, HOME_DEG, Intrinsics, JOINT_NAMES, LatencyStats,
    PD_VARIANTS, PDConfig, PDController, PoseHistory, ReactiveController)
from activeloc_ros.errors import ConfigError

D435 = Intrinsics(fx=615.0, fy=615.0, cx=319.5, cy=239.5, width=640, height=480)
DEG = math.radians(1.0)


def test_core_imports_without_ros():
    import subprocess
    import sys
    code = ('import sys, activeloc_ros.control, activeloc_ros.control.serial_link, '
            'activeloc_ros.control.emulator; '
            'sys.exit(any(m.startswith("rclpy") for m in sys.modules))')
    assert subprocess.run([sys.executable, '-c', code]).returncode == 0


@pytest.mark.parametrize('u, v, pan_deg, tilt_deg', [
    (319.5, 239.5, 0.0, 0.0),                                  # the principal point
    (319.5 + 615.0, 239.5, -45.0, 0.0),                        # right: turn right (pan < 0)
    (319.5 - 615.0, 239.5, 45.0, 0.0),
    (319.5, 239.5 - 615.0, 0.0, 45.0),                         # above: raise (tilt > 0)
    (319.5 + 615.0, 239.5 + 615.0, -45.0, -math.degrees(math.atan(1 / math.sqrt(2)))),
])
def test_angular_error_from_intrinsics(u, v, pan_deg, tilt_deg):
    wide = Intrinsics(615.0, 615.0, 319.5, 239.5, 2000, 2000)  # room for far pixels
    pan, tilt = angular_error(u, v, wide)
    assert math.degrees(pan) == pytest.approx(pan_deg, abs=1e-9)
    assert math.degrees(tilt) == pytest.approx(tilt_deg, abs=1e-9)


def test_field_of_view_comes_from_the_intrinsics_not_a_constant():
    # The D435 colour camera: 69.4 deg horizontal FOV at 1920 px -> fx = 960 / tan(34.7 deg).
    fx = 960 / math.tan(math.radians(34.7))
    intr = Intrinsics(fx, fx, 959.5, 539.5, 1920, 1080)
    pan, _ = angular_error(-0.5, 539.5, intr)
    assert math.degrees(pan) == pytest.approx(34.7, abs=1e-6)
    narrow = Intrinsics(2 * fx, 2 * fx, 959.5, 539.5, 1920, 1080)
    assert angular_error(-0.5, 539.5, narrow)[0] < pan / 1.5


@pytest.mark.parametrize('camera_tilt_deg', [-40.0, -10.0, 0.0, 25.0, 60.0])
@pytest.mark.parametrize('u, v', [(10.0, 20.0), (600.0, 470.0), (319.5, 50.0), (100, 239.5)])
def test_turning_by_the_error_centres_the_ray(camera_tilt_deg, u, v):
    """Pan then tilt by the error: the ray's world direction is then the optical axis."""
    tilt0 = math.radians(camera_tilt_deg)
    d_pan, d_tilt = angular_error(u, v, D435, camera_tilt=tilt0)
    x, y = D435.normalized(u, v)

    def world(fwd, left, up, pan, tilt):  # camera body -> world, pan about the vertical
        c, s = math.cos(tilt), math.sin(tilt)
        fwd, up = fwd * c - up * s, fwd * s + up * c
        c, s = math.cos(pan), math.sin(pan)
        return (fwd * c - left * s, fwd * s + left * c, up)

    ray = world(1.0, -x, -y, 0.0, tilt0)
    axis = world(1.0, 0.0, 0.0, d_pan, tilt0 + d_tilt)
    norm = math.sqrt(sum(r * r for r in ray))
    assert [r / norm for r in ray] == pytest.approx(list(axis), abs=1e-9)


def test_distortion_is_undone():
    k1, k2, p1, p2, k3 = -0.1, 0.02, 0.001, -0.002, 0.0
    intr = Intrinsics(600.0, 600.0, 320.0, 240.0, 640, 480, dist=(k1, k2, p1, p2, k3))
    x, y = 0.3, -0.2                                   # an ideal ray, distorted forwards:
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    assert intr.normalized(320.0 + 600.0 * xd, 240.0 + 600.0 * yd) == pytest.approx((x, y))


def test_where_the_lens_model_does_not_invert_the_pixel_stays_as_measured():
    """
    Strong barrel distortion folds the image's corners: the fixed-point inverse does not
    converge there and its last step was 85 (normalised units), or infinite.
    """
    intr = Intrinsics(400.0, 400.0, 319.5, 239.5, 640, 480, dist=(-0.4, 0.2, 0.001, 0.001, -0.05))
    x, y = intr.normalized(592.0, 456.0)
    assert (x, y) == pytest.approx(((592.0 - 319.5) / 400, (456.0 - 239.5) / 400))
    rng = np.random.default_rng(0)
    for _ in range(300):
        dist = tuple(rng.uniform(-1.0, 1.0, 5) * (1.0, 1.0, 0.05, 0.05, 1.0))
        intr = Intrinsics(400.0, 400.0, 319.5, 239.5, 640, 480, dist=dist)
        u, v = rng.uniform(0, 639), rng.uniform(0, 479)
        assert all(math.isfinite(e) for e in angular_error(u, v, intr)), (dist, u, v)


def test_a_location_the_geometry_cannot_aim_at_never_reaches_the_pd(monkeypatch):
    """
    A NaN error in the PD's memory made every later command NaN, which the guard
    turned into 'stay': the arm froze for good, tracking by every count.
    """
    from activeloc_ros.control import reactive
    ctl = make_controller()
    with monkeypatch.context() as patch:
        patch.setattr(reactive, 'angular_error', lambda *a, **k: (math.nan, 0.0))
        assert ctl.on_location(pixel_for(5.0), D435.cy, 0.0, 0.1) is None
    assert ctl.ignored == {'bad geometry': 1}
    turn = ctl.on_location(pixel_for(5.0), D435.cy, 0.2, 0.3)
    assert all(math.isfinite(q) for q in turn.joints_deg)
    assert turn.joints_deg[0] == pytest.approx(HOME_DEG[0] + 5.0)


def test_binning_and_roi_map_back_to_full_resolution():
    full = Intrinsics.from_camera_info([600, 0, 320, 0, 600, 240, 0, 0, 1], 640, 480)
    binned = Intrinsics.from_camera_info([600, 0, 320, 0, 600, 240, 0, 0, 1], 640, 480,
                                         binning_x=2, binning_y=2, roi=(100, 50, 400, 300))
    assert binned.image_size == (200, 150)
    assert binned.normalized(50.0, 40.0) == pytest.approx(full.normalized(200.0, 130.0))
    assert binned.contains(199.0, 149.0) and not binned.contains(250.0, 10.0)


@pytest.mark.parametrize('k, width, height', [
    ([0] * 9, 640, 480), ([600, 0, 320, 0, 600, 240, 0, 0, 1], 0, 480),
    ([math.nan, 0, 320, 0, 600, 240, 0, 0, 1], 640, 480), ([600, 0, 320], 640, 480)])
def test_bad_intrinsics_are_refused(k, width, height):
    with pytest.raises(ConfigError):
        Intrinsics.from_camera_info(k, width, height)


# -- the PD law (Eq. 4) -----------------------------------------------------------------------

def test_step_response_matches_the_closed_form():
    """Error 0 until t1, E after: u(t1) = kp E + kd E / (t1 - t0), then kp E."""
    kp, kd, E = 1.0, 0.1, math.radians(10.0)
    pd = PDController(PDConfig(kp=kp, kd=kd, dead_band=0.0))
    times = [0.0, 0.040, 0.071, 0.130, 0.166]  # real, uneven frame stamps
    out = [pd.update((0.0, 0.0), times[0])]
    out += [pd.update((E, -E), t) for t in times[1:]]
    assert out[0] == (0.0, 0.0)
    expected = kp * E + kd * E / (times[1] - times[0])
    assert out[1] == pytest.approx((expected, -expected))
    for o in out[2:]:
        assert o == pytest.approx((kp * E, -kp * E))


def test_filtered_derivative_decays_geometrically():
    """With a low-pass of time constant tau: d_n = d_1 * prod(tau / (tau + dt_k))."""
    kp, kd, tau, E = 1.0, 0.1, 0.05, 0.2
    pd = PDController(PDConfig(kp=kp, kd=kd, dead_band=0.0, derivative_tau=tau))
    times = [0.0, 0.03, 0.07, 0.10, 0.16]
    pd.update((0.0, 0.0), times[0])
    d = (times[1] - times[0]) / (tau + times[1] - times[0]) * E / (times[1] - times[0])
    assert pd.update((E, 0.0), times[1])[0] == pytest.approx(kp * E + kd * d)
    for t_prev, t in zip(times[1:], times[2:]):
        d *= tau / (tau + t - t_prev)
        assert pd.update((E, 0.0), t)[0] == pytest.approx(kp * E + kd * d)


def test_dead_band_gates_small_errors():
    pd = PDController(PDConfig(kp=1.0, kd=0.1, dead_band=math.radians(2.0)))
    assert pd.within_dead_band((math.radians(1.9), -math.radians(1.9)))
    assert not pd.within_dead_band((math.radians(0.5), math.radians(2.5)))


def test_target_derivative_sees_the_action_move_not_the_camera():
    pd = PDController(PDConfig(kp=1.0, kd=0.5, dead_band=0.0, derivative='target'))
    pd.update((0.2, 0.0), 0.0, camera=(0.0, 0.0))
    # The camera turned by 0.2 and now sees the action centred: the action did not move.
    assert pd.update((0.0, 0.0), 0.1, camera=(0.2, 0.0)) == pytest.approx((0.0, 0.0))
    # The action moves at 1 rad/s: feed-forward kd * 1.
    assert pd.update((0.1, 0.0), 0.2, camera=(0.2, 0.0)) == pytest.approx((0.1 + 0.5, 0.0))


@pytest.mark.parametrize('name, gains', [
    ('paper', (1.0, 0.1)), ('low_p', (0.5, 0.1)), ('no_d', (1.0, 0.0)), ('high_d', (1.0, 1.0))])
def test_paper_variants(name, gains):
    assert PD_VARIANTS[name] == gains
    config = PDConfig.variant(name, dead_band=0.0)
    assert (config.kp, config.kd) == gains


@pytest.mark.parametrize('options', [
    {'kp': -1.0}, {'kd': math.nan}, {'dead_band': -0.1}, {'derivative': 'both'}])
def test_bad_pd_config_is_refused(options):
    with pytest.raises(ConfigError):
        PDConfig(**options)


def test_unknown_variant_is_refused():
    with pytest.raises(ConfigError, match='unknown PD variant'):
        PDConfig.variant('pid')


# -- the controller ---------------------------------------------------------------------------

def make_controller(**options) -> ReactiveController:
    pd = options.pop('pd', PDConfig(kp=1.0, kd=0.0, dead_band=0.0))
    ctl = ReactiveController(ControllerConfig(pd=pd, **options), t0=0.0)
    ctl.set_intrinsics(D435)
    return ctl


def pixel_for(pan_deg: float, intr: Intrinsics = D435) -> float:
    """The column where an action at pan_deg (left > 0) of the optical axis appears."""
    return intr.cx - intr.fx * math.tan(math.radians(pan_deg))


def test_one_step_turns_by_the_error_within_the_speed_limit():
    ctl = make_controller()
    cmd = ctl.on_location(pixel_for(10.0), D435.cy, 0.9, 1.0)
    assert cmd.reason == 'track' and cmd.stamp == 0.9 and cmd.t == 1.0
    assert cmd.joints_deg[0] == pytest.approx(HOME_DEG[0] + 10.0)
    assert cmd.joints_deg[1:] == pytest.approx(HOME_DEG[1:])
    # 10 degrees in 20 ms is faster than the servos (50 deg/s): the guard spreads it.
    ctl = make_controller()
    cmd = ctl.on_location(pixel_for(10.0), D435.cy, 0.0, 0.02)
    assert cmd.joints_deg[0] == pytest.approx(HOME_DEG[0] + 1.0)


def test_a_move_cut_short_by_the_speed_limit_is_finished_without_new_targets():
    """
    The rest of a cut-short move comes with the locations it ignores (a moving
    camera's frames), until it is done.
    """
    ctl = make_controller(settle_time=0.3)
    ctl.observe(HOME_DEG, 0.0)
    cmd = ctl.on_location(pixel_for(10.0), D435.cy, 0.0, 0.02)
    assert cmd.joints_deg[0] == pytest.approx(HOME_DEG[0] + 1.0)
    ctl.observe([HOME_DEG[0] + 1.0] + list(HOME_DEG[1:]), 0.1)
    more = ctl.on_location(pixel_for(0.0), D435.cy, 0.1, 0.1)        # the camera moved
    assert ctl.ignored == {'camera moving': 1}
    assert more.reason == 'continue' and more.stamp is None
    assert more.joints_deg[0] == pytest.approx(HOME_DEG[0] + 5.0)
    assert ctl.tick(0.15) is None                 # the watchdog's timer does not move it
    ctl.observe([HOME_DEG[0] + 5.0] + list(HOME_DEG[1:]), 0.2)
    last = ctl.on_location(pixel_for(0.0), D435.cy, 0.3, 0.3)
    assert last.reason == 'continue' and last.joints_deg[0] == pytest.approx(HOME_DEG[0] + 10.0)
    assert ctl.on_location(pixel_for(0.0), D435.cy, 0.4, 0.4) is None   # done: silence


def test_pose_at_capture_time_is_used_not_the_latest():
    """A frame captured before the arm turned asks for the turn once, not twice."""
    ctl = make_controller()
    home = list(HOME_DEG)
    ctl.observe(home, 0.0)
    ctl.observe([home[0] + 10.0] + home[1:], 1.0)
    cmd = ctl.on_location(pixel_for(10.0), D435.cy, 0.0, 1.5)  # captured at home
    assert cmd.joints_deg[0] == pytest.approx(HOME_DEG[0] + 10.0)


def test_tilt_goes_to_the_tilt_joints_with_their_gains():
    mapping = ArmMapping(tilt_joints=('elbow', 'wrist_ver'), tilt_gains=(-0.5, 0.5))
    ctl = make_controller(mapping=mapping)
    cmd = ctl.on_location(D435.cx, D435.cy - D435.fy * math.tan(math.radians(8.0)), 0.0, 1.0)
    assert cmd.joints_deg[2] == pytest.approx(HOME_DEG[2] - 4.0)
    assert cmd.joints_deg[3] == pytest.approx(HOME_DEG[3] + 4.0)
    assert mapping.pan_tilt(cmd.joints_deg)[1] == pytest.approx(math.radians(8.0))


@pytest.mark.parametrize('u, v, peak', [
    (math.nan, 100.0, 1.0), (100.0, math.inf, 1.0), (1e9, 100.0, 1.0), (-50.0, 100.0, 1.0),
    (100.0, 480.0, 1.0), (100.0, 100.0, math.nan), (100.0, 100.0, -1.0)])
def test_nan_and_absurd_locations_are_ignored(u, v, peak):
    ctl = make_controller(min_peak=0.0)
    assert ctl.on_location(u, v, 0.5, 1.0, peak=peak) is None
    assert sum(ctl.ignored.values()) == 1 and ctl.commands == 0


def test_locations_need_intrinsics_and_increasing_stamps():
    ctl = ReactiveController(ControllerConfig(), t0=0.0)
    assert ctl.on_location(100.0, 100.0, 0.5, 1.0) is None and ctl.state == 'waiting'
    ctl.set_intrinsics(D435)
    assert ctl.on_location(100.0, 100.0, 0.5, 1.0) is not None
    assert ctl.on_location(100.0, 100.0, 0.5, 1.1) is None        # the same frame again
    assert ctl.on_location(100.0, 100.0, 0.4, 1.2) is None        # an older frame
    assert ctl.ignored == {'no camera info': 1, 'out of order': 2}


def test_a_stamp_from_the_future_is_ignored_and_does_not_block_later_locations():
    """
    A frame stamped far ahead of the controller's clock (a wrong clock on the camera's
    host) is turned away; accepted, every later, truthful stamp would look out of order.
    """
    ctl = make_controller(settle_time=0.0)
    assert ctl.on_location(600.0, 240.0, 1e9, 1.1) is None
    assert ctl.ignored == {'stamp in the future': 1}
    cmd = ctl.on_location(600.0, 240.0, 1.2, 1.3)
    assert cmd is not None and cmd.reason == 'track'
    assert ctl.on_location(320.0, 240.0, 1.9, 1.6) is not None   # within the clock skew


def test_aim_limits_bound_the_camera_not_the_joints_beyond():
    """A far action turns the camera only as far as the workspace allows, either way."""
    ctl = make_controller(pan_limit_deg=12.0, tilt_limit_deg=5.0)
    up_left = ctl.on_location(0.0, 0.0, 0.0, 10.0)                  # the image's corner
    pan, tilt = ArmMapping().pan_tilt(up_left.joints_deg)
    assert math.degrees(pan) == pytest.approx(12.0) and math.degrees(tilt) == pytest.approx(5.0)
    ctl = make_controller(pan_limit_deg=12.0, tilt_limit_deg=5.0)
    down_right = ctl.on_location(D435.width - 1, D435.height - 1, 0.0, 10.0)
    pan, tilt = ArmMapping().pan_tilt(down_right.joints_deg)
    assert math.degrees(pan) == pytest.approx(-12.0)
    assert math.degrees(tilt) == pytest.approx(-5.0)
    with pytest.raises(ConfigError, match='pan_limit_deg'):
        ControllerConfig(pan_limit_deg=-1.0)


def test_dead_band_keeps_the_last_command():
    ctl = make_controller(pd=PDConfig(kp=1.0, kd=0.1, dead_band=math.radians(2.0)))
    first = ctl.on_location(pixel_for(5.0), D435.cy, 0.0, 0.5)
    second = ctl.on_location(pixel_for(1.0), D435.cy, 0.1, 0.6)
    assert second.joints_deg == first.joints_deg


def test_watchdog_holds_once_then_stays_silent():
    ctl = make_controller(watchdog_timeout=0.5)
    ctl.observe(HOME_DEG, 0.0)
    assert ctl.on_location(pixel_for(20.0), D435.cy, 0.0, 0.0) is not None
    ctl.observe([HOME_DEG[0] + 7] + list(HOME_DEG[1:]), 0.3)  # the arm on its way
    assert ctl.tick(0.4) is None and ctl.state == 'tracking'
    hold = ctl.tick(0.51)
    assert hold is not None and hold.reason == 'hold' and ctl.state == 'holding'
    assert hold.joints_deg[0] == pytest.approx(HOME_DEG[0] + 7)   # where the arm is
    assert all(ctl.tick(t) is None for t in (0.6, 1.0, 5.0, 50.0))  # no drift afterwards


@pytest.mark.parametrize('before', ['hold', 'dead band', 'track'])
def test_a_foreign_pose_never_reaches_the_joints_that_do_not_aim(before):
    """
    The hostile test's foreign command, reported back as the arm's state: the controller
    still commands the gripper and the other fixed joints at home, whatever it sends.
    """
    ctl = make_controller(watchdog_timeout=0.5,
                          pd=PDConfig(kp=1.0, kd=0.0, dead_band=math.radians(2.0)))
    foreign = (171.0, 15.0, 0.0, 151.0, 180.0, 10.0)
    for i in range(5):
        ctl.observe(foreign, 0.1 * i)
    if before == 'hold':
        ctl.on_location(pixel_for(0.0), D435.cy, 0.4, 0.4)
        cmd = ctl.tick(1.0)
    else:
        pan = 1.0 if before == 'dead band' else 10.0
        cmd = ctl.on_location(pixel_for(pan), D435.cy, 0.4, 5.0)
    assert cmd is not None
    fixed = [i for i, n in enumerate(JOINT_NAMES) if n not in ('base', 'wrist_ver')]
    assert [cmd.joints_deg[i] for i in fixed] == pytest.approx([HOME_DEG[i] for i in fixed])
    assert cmd.joints_deg[5] == HOME_DEG[5]            # the gripper holding the camera
    assert cmd.joints_deg[0] > 165                     # the aiming joints it does take


def test_after_the_clock_runs_back_a_restart_tracks_again_from_the_last_command():
    """
    A bag replayed in a loop sends the clock back to its start. Without `restart` every
    later location is out of order and the guard allows no motion until the clock is back.
    """
    ctl = make_controller(settle_time=0.3)
    ctl.observe(HOME_DEG, 100.0)
    first = ctl.on_location(pixel_for(10.0), D435.cy, 100.0, 100.2)
    assert first.joints_deg[0] == pytest.approx(HOME_DEG[0] + 10.0)
    stale = ctl.on_location(pixel_for(5.0), D435.cy, 1.0, 1.0)
    assert stale is None and ctl.ignored == {'out of order': 1}
    ctl.restart(1.0)
    assert ctl.state == 'idle'
    ctl.observe(first.joints_deg, 1.0)
    turn = ctl.on_location(pixel_for(5.0), D435.cy, 1.0, 1.1)
    assert turn.reason == 'track' and turn.joints_deg[0] > first.joints_deg[0]
    assert turn.joints_deg[0] - first.joints_deg[0] <= 50.0 * 0.1 + 1e-6  # servo speed kept


def test_ignored_locations_run_the_watchdog_as_silence_does():
    """
    A stream of locations it ignores (weak maps) is no location: after the timeout the
    answer to one is the hold, once, in every driver (the benchmark has no timer).
    """
    ctl = make_controller(watchdog_timeout=0.5, min_peak=0.01)
    assert ctl.on_location(pixel_for(20.0), D435.cy, 0.0, 0.0, peak=0.2) is not None
    rest = ctl.on_location(pixel_for(5.0), D435.cy, 0.4, 0.4, peak=0.005)
    assert rest.reason == 'continue'      # the first move's rest, not a move to this one
    assert ctl.on_location(pixel_for(5.0), D435.cy, 0.5, 0.5, peak=0.005) is None
    hold = ctl.on_location(pixel_for(5.0), D435.cy, 0.6, 0.6, peak=0.005)
    assert hold is not None and hold.reason == 'hold' and ctl.state == 'holding'
    assert ctl.on_location(pixel_for(5.0), D435.cy, 0.7, 0.7, peak=0.005) is None
    assert ctl.ignored == {'weak or bad peak': 4}


def test_after_a_hold_tracking_restarts_without_a_derivative_kick():
    ctl = make_controller(pd=PDConfig(kp=1.0, kd=1.0, dead_band=0.0), watchdog_timeout=0.5)
    ctl.on_location(pixel_for(0.0), D435.cy, 0.0, 0.0)
    assert ctl.tick(1.0) is not None
    cmd = ctl.on_location(pixel_for(5.0), D435.cy, 10.0, 10.0)
    assert cmd.joints_deg[0] == pytest.approx(HOME_DEG[0] + 5.0)  # kp * e only


def test_closed_loop_step_response_on_the_servo_model():
    """
    A still action 20 deg to the left, 10 fps, servos at 50 deg/s (5 deg a frame): the
    camera ramps there at the servos' speed and settles inside the dead band (the paper's
    loop: acting on frames seen while moving).
    """
    from activeloc_ros.control import SimArm
    ctl = make_controller(pd=PDConfig(kp=1.0, kd=0.1, dead_band=math.radians(1.0)),
                          settle_time=0.0)
    arm = SimArm(HOME_DEG, 0.0)
    action = 20.0
    pans = []
    for k in range(60):
        t = k * 0.1
        here = arm.advance(t)
        ctl.observe(here, t)
        pan = here[0] - HOME_DEG[0]
        pans.append(pan)
        cmd = ctl.on_location(pixel_for(action - pan), D435.cy, t, t + 0.01)
        arm.command(cmd.joints_deg, t + 0.01)
    assert pans[:3] == [0, 0, 5]  # no motion at t0, then the servos' speed
    assert all(b - a <= 5 for a, b in zip(pans, pans[1:]))
    assert all(abs(p - action) < 2.0 for p in pans[-30:])  # settled, no limit cycle
    assert max(pans) <= action + 1


def test_pose_history_interpolates_and_falls_back_to_the_newest():
    h = PoseHistory()
    assert h.at(1.0, 0.5) is None
    h.add(1.0, [0.0] * 6)
    h.add(2.0, [10.0] * 6)
    assert not h.add(1.5, [5.0] * 6)  # out of order
    assert h.at(1.25, 0.5) == pytest.approx([2.5] * 6)
    assert h.at(0.8, 0.5) == (0.0,) * 6
    assert h.at(-100.0, 0.5) == (10.0,) * 6  # e.g. a replayed bag's old stamps


def test_latency_percentiles():
    stats = LatencyStats()
    assert math.isnan(stats.percentile(50))
    for ms in range(1, 101):
        stats.add(ms / 1000)
    stats.add(math.nan)
    assert stats.summary() == {'n': 100, 'p50': 0.05, 'p95': 0.095}


def test_confirm_deg_moves_only_on_two_agreeing_locations():
    """
    With confirm_deg, a location that calls for a move acts only when the previous still
    frame's location pointed within confirm_deg of it (in the world); a moving camera's
    frame in between breaks the chain; within the dead band nothing needs confirming.
    """
    ctl = make_controller(pd=PDConfig(dead_band=math.radians(2.0)), settle_time=0.3,
                          confirm_deg=5.0)
    for k in range(5):
        ctl.observe(HOME_DEG, k * 0.1)
    assert ctl.on_location(pixel_for(10.0), D435.cy, 0.4, 0.4) is None     # alone
    assert ctl.on_location(pixel_for(-20.0), D435.cy, 0.5, 0.5) is None    # 30 deg away
    assert ctl.ignored == {'unconfirmed': 2}
    assert ctl.on_location(pixel_for(1.0), D435.cy, 0.6, 0.6).reason == 'track'  # dead band
    assert ctl.commands == 1 and ctl.guard.last_deg == tuple(HOME_DEG)
    assert ctl.on_location(pixel_for(12.0), D435.cy, 0.7, 0.7) is None     # 11 deg from 1
    command = ctl.on_location(pixel_for(8.0), D435.cy, 0.8, 0.8)           # 4 deg from 12
    assert command.reason == 'track' and command.joints_deg[0] != HOME_DEG[0]
    moved = [command.joints_deg[0], *HOME_DEG[1:]]
    for k in range(9, 14):                          # the camera turned, then stood still
        ctl.observe(moved, k * 0.1)
    ctl.on_location(pixel_for(8.0), D435.cy, 0.9, 0.9)                     # moving: ignored
    assert ctl.ignored['camera moving'] == 1
    for k in range(14, 20):
        ctl.observe(moved, k * 0.1)
    assert ctl.on_location(pixel_for(8.0), D435.cy, 1.8, 1.8) is None      # chain broken
    assert ctl.ignored['unconfirmed'] == 4
    assert ctl.on_location(pixel_for(8.0), D435.cy, 1.9, 1.9).reason == 'track'
    with pytest.raises(ConfigError, match='confirm_deg'):
        ControllerConfig(confirm_deg=-1.0)


def test_confirm_deg_lets_a_decided_saccade_run_to_its_end():
    """
    A command at the instant of the last joint state moves nothing yet (the servos'
    speed); with confirm_deg the next location does not replace that move: it goes on.
    """
    ctl = make_controller(settle_time=0.3, confirm_deg=5.0)
    for k in range(5):
        ctl.observe(HOME_DEG, k * 0.1)
    assert ctl.on_location(pixel_for(10.0), D435.cy, 0.3, 0.4) is None     # unconfirmed
    first = ctl.on_location(pixel_for(10.0), D435.cy, 0.4, 0.4)
    assert first.reason == 'track' and first.joints_deg == tuple(HOME_DEG)  # dt = 0
    ctl.observe(HOME_DEG, 0.5)                       # the camera has not moved yet
    rest = ctl.on_location(pixel_for(-20.0), D435.cy, 0.5, 0.5)
    assert rest.reason == 'continue' and rest.joints_deg[0] > HOME_DEG[0]   # still to +10
    assert ctl.ignored == {'unconfirmed': 1, 'saccade running': 1}


def test_settle_time_ignores_frames_seen_by_a_moving_camera():
    """
    With settle_time, a location counts only if the camera stood still for that long
    before the frame was captured.
    """
    ctl = make_controller(pd=PDConfig(dead_band=0.0), settle_time=0.3)
    still = list(HOME_DEG)
    moved = [HOME_DEG[0] + 5, *HOME_DEG[1:]]
    for k in range(5):                      # still from 0.0 to 0.4 s
        ctl.observe(still, k * 0.1)
    assert ctl.on_location(pixel_for(10.0), D435.cy, 0.4, 0.4) is not None
    ctl.observe(moved, 0.5)          # a move between 0.4 and 0.5 s
    for k in range(6, 9):
        ctl.observe(moved, k * 0.1)
    rest = ctl.on_location(pixel_for(10.0), D435.cy, 0.7, 0.7)   # ignored: no new target
    assert rest.reason == 'continue' and rest.stamp is None   # the first move's rest
    assert ctl.ignored == {'camera moving': 1}
    ctl.observe(moved, 0.9)
    assert ctl.on_location(pixel_for(10.0), D435.cy, 0.9, 0.9) is not None  # 0.4 s still
