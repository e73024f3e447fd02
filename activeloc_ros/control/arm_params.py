"""
The arm node's parameters, ROS-free: the node declares them, bringup checks them before
any node starts.
"""
from activeloc_ros.checks import in_range, non_negative, one_of, Param, positive
from activeloc_ros.control import HOME_DEG, pose_problem
from activeloc_ros.control.braccio import STEP_DELAY_MS_RANGE
from activeloc_ros.settings import MAPPING_PARAMS

# Set at run time, a parameter applies at once, except those that fix the hardware or the
# start (read-only).
PARAMS = (
    Param('backend', 'sim', "'sim': simulated servos; 'serial': the Arduino sketch",
          one_of('sim', 'serial'), read_only=True),
    Param('state_rate', 50.0, 'joint_states publishing rate, Hz', in_range(1.0, 500.0)),
    Param('step_delay_ms', 20, 'Servo step delay, ms per degree (sim; must match the sketch)',
          in_range(*STEP_DELAY_MS_RANGE), read_only=True),
    Param('home_deg', list(HOME_DEG), 'Home pose, degrees', pose_problem),
    # the joints that aim the camera (params/robot.yaml): a command that moves any other
    # joint away from home is refused, the gripper holding the camera above all
    *(p for p in MAPPING_PARAMS if p.name in ('pan_joint', 'tilt_joints')),
    Param('sim_start_deg', list(HOME_DEG), 'Pose the simulated arm starts in, degrees',
          pose_problem, read_only=True),
    Param('stop_mode', 'hold', "On shutdown: 'hold' stops where it is, 'home' goes home "
          'slowly', one_of('hold', 'home')),
    Param('home_speed_deg_s', 15.0, 'Joint speed when going home at shutdown, deg/s',
          in_range(1.0, 100.0)),
    Param('stop_timeout', 10.0, 'Longest time the shutdown may take, s', positive),
    Param('port', '/dev/ttyACM0', 'Serial device of the Arduino (prefer '
          '/dev/serial/by-id/...)', read_only=True),
    Param('baud', 115200, 'Serial baud rate', one_of(9600, 19200, 38400, 57600, 115200),
          read_only=True),
    Param('poll_period', 0.02, 'Seconds between serial requests', in_range(0.005, 1.0),
          read_only=True),
    Param('silence_timeout', 1.0, 'No valid frame for this long: the link is lost, s',
          positive),
    Param('reconnect_period', 1.0, 'Seconds between attempts to re-open the port', positive),
    Param('handshake_timeout', 4.0, 'Seconds to wait for <ok> after opening (the Arduino '
          'resets on open)', positive),
    Param('give_up_timeout', 10.0, 'The serial link down this long (never connected, or lost '
          'and not back): the node ends with an error, s (0: retry for ever)', non_negative),
)
