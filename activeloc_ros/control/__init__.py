"""
Reactive control and the Braccio arm, free of ROS (paper Sec. 3.3, Eq. 4).

The same objects run in the ROS nodes and in the closed-loop benchmark; every function that
depends on time takes it as an argument. A loop in simulated time::

    ctl = ReactiveController(ControllerConfig(pd=PDConfig.variant('paper')), t0=0.0)
    ctl.set_intrinsics(Intrinsics.from_camera_info(k, width, height))
    arm = SimArm(HOME_DEG, 0.0, step_delay_ms=20)
    for t, (u, v) in frames:                      # action pixel seen at capture time t
        ctl.observe(arm.advance(t), t)     # where the camera was when it looked
        cmd = ctl.on_location(u, v, t, t + latency) or ctl.tick(t + latency)
        if cmd:
            arm.command(cmd.joints_deg, cmd.t)
    pan, tilt = ctl.mapping.pan_tilt(arm.joints)  # radians, for the angular error metric
"""
from activeloc_ros.control.braccio import (
    ArmMapping, check_pose, clamp_to_limits, fixed_moves, HOME_DEG, JOINT_NAMES, JointGuard,
    LIMITS_DEG, pose_problem, SAFETY_DEG, speed_deg_s, STEP_DELAY_MS_RANGE, within_limits)
from activeloc_ros.control.geometry import angular_error, Intrinsics
from activeloc_ros.control.pd import PD_VARIANTS, PDConfig, PDController
from activeloc_ros.control.reactive import (
    Command, ControllerConfig, LatencyStats, PoseHistory, ReactiveController)
from activeloc_ros.control.sim_arm import quantize, SimArm

__all__ = [
    'angular_error', 'ArmMapping', 'check_pose', 'clamp_to_limits', 'Command',
    'ControllerConfig', 'fixed_moves', 'HOME_DEG', 'Intrinsics', 'JOINT_NAMES', 'JointGuard',
    'LatencyStats',
    'LIMITS_DEG', 'PD_VARIANTS', 'PDConfig', 'PDController', 'pose_problem', 'PoseHistory',
    'quantize', 'ReactiveController', 'SAFETY_DEG', 'SimArm', 'speed_deg_s', 'STEP_DELAY_MS_RANGE',
    'within_limits',
]
