"""Reactive control and the Braccio arm, free of ROS (paper Sec. 3.3, Eq. 4).

The same objects run in the ROS nodes and in the closed-loop benchmark; every function that
depends on time takes it as an argument.
"""
from activeloc_ros.control.braccio import (
    ArmMapping, check_pose, clamp_to_limits, HOME_DEG, JOINT_NAMES, JointGuard, LIMITS_DEG,
    SAFETY_DEG, speed_deg_s, STEP_DELAY_MS_RANGE, within_limits)
from activeloc_ros.control.geometry import angular_error, Intrinsics
from activeloc_ros.control.pd import PD_VARIANTS, PDConfig, PDController
from activeloc_ros.control.reactive import (
    Command, ControllerConfig, LatencyStats, PoseHistory, ReactiveController)
from activeloc_ros.control.sim_arm import quantize, SimArm

__all__ = [
    'angular_error', 'ArmMapping', 'check_pose', 'clamp_to_limits', 'Command',
    'ControllerConfig', 'HOME_DEG', 'Intrinsics', 'JOINT_NAMES', 'JointGuard', 'LatencyStats',
    'LIMITS_DEG', 'PD_VARIANTS', 'PDConfig', 'PDController', 'PoseHistory', 'quantize',
    'ReactiveController', 'SAFETY_DEG', 'SimArm', 'speed_deg_s', 'STEP_DELAY_MS_RANGE',
    'within_limits',
]
