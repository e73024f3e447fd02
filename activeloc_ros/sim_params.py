"""
The sim node's parameters (the virtual camera on its screen, the simulated arm that aims
it), ROS-free: the node declares them, bringup checks them before any node starts.
"""
from activeloc_ros.checks import in_range, non_negative, one_of, Param, positive
from activeloc_ros.control.braccio import STEP_DELAY_MS_RANGE
from activeloc_ros.settings import MAPPING_PARAMS, SCREEN_PARAMS
from activeloc_ros.sources import default_bag, SCENE_HELP

# Parameters without read_only take effect at once.
PARAMS = [
    Param('scene', f'bag:{default_bag()}', f'what the virtual screen shows: {SCENE_HELP}',
          read_only=True),
    Param('image_topic', '', 'image topic to play from a bag scene (empty: the first one)',
          read_only=True),
    Param('folder_fps', 10.0, 'frame rate of folder:PATH scenes', positive, read_only=True),
    Param('rate', 1.0, 'real time: speed of the scene (1.0 = its own rate)', positive),
    Param('loop', False, 'restart the scene at its end instead of finishing'),
    Param('encoding', 'rgb8', 'encoding of published images', one_of('rgb8', 'bgr8')),
    Param('frame_id', 'camera_color_optical_frame', 'frame_id of published headers'),
    Param('state_rate', 50.0, 'real time: joint_states publishing rate, Hz',
          in_range(1.0, 500.0), read_only=True),
    Param('step_delay_ms', 20, 'servo step delay of the simulated arm, ms per degree',
          in_range(*STEP_DELAY_MS_RANGE), read_only=True),
    Param('max_frames', 0, 'stop after this many frames (0: no limit)', non_negative),
    Param('wait_for_subscriber', 120.0, 'seconds to wait for a subscriber (lockstep: for the '
          'whole graph) before the first frame, so a model still loading misses nothing '
          '(0: do not wait)', non_negative),
    Param('min_subscribers', 1, 'image subscribers to wait for (up to wait_for_subscriber) '
          'before the first frame; bringup --record makes it 2, so the recording holds the '
          'first frame too', in_range(1, 1000)),
    Param('lockstep', False, 'step the graph frame by frame on a simulated /clock this node '
          'publishes, as closed_loop does (needs use_sim_time on every node)', read_only=True),
    Param('lockstep_timeout', 60.0, "lockstep: longest wait for perception's location, s",
          positive, read_only=True),
    Param('lockstep_command_timeout', 5.0, "lockstep: longest wait for the arm state's "
          "echo and for the controller's answer to an action location, s; longer than the "
          'DDS heartbeat period (Fast DDS: 3 s) after which a reliable message lost on the '
          'way is sent again', positive, read_only=True),
    *SCREEN_PARAMS,
    *MAPPING_PARAMS,
]
