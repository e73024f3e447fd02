"""
The tracking node's parameters, ROS-free: the node declares them, bringup checks them
before any node starts.
"""
from activeloc_ros.checks import in_range, non_negative, one_of, Param, positive
from activeloc_ros.tracking.scenes import SCENES
from activeloc_ros.tracking.world import TARGETS

PARAMS = [
    Param('scene', 'room', f'the scene: {", ".join(SCENES)}', one_of(*SCENES),
          read_only=True),
    Param('seed', 0, 'the episode seed (the benchmark runs episode e of seed S as '
          '1000 * S + e)', non_negative, read_only=True),
    Param('target', 'nav', "the target's behaviour, gym-unrealcv's Nav or Ram",
          one_of(*TARGETS), read_only=True),
    Param('max_steps', 500, 'the longest episode, control steps', in_range(1, 1000000),
          read_only=True),
    Param('lost_steps', 10, 'steps in a row with the target lost that end the episode '
          '(paper 10; gym-unrealcv 20)', in_range(1, 1000000), read_only=True),
    Param('rate', 1.0, 'real time: speed of the world (1.0 = its own)', positive),
    Param('encoding', 'rgb8', 'encoding of published images', one_of('rgb8', 'bgr8')),
    Param('frame_id', 'camera_color_optical_frame', 'frame_id of published images'),
    Param('world_frame', 'world', 'frame of odom and target/position'),
    Param('wait_for_subscriber', 120.0, 'seconds to wait for a subscriber (lockstep: for the '
          'whole graph) before the first step (0: do not wait)', non_negative),
    Param('min_subscribers', 1, 'image subscribers to wait for before the first step '
          '(bringup --record: 2)', in_range(1, 1000)),
    Param('lockstep', False, 'step the graph on a simulated /clock this node publishes, as '
          'closed_loop does (needs use_sim_time on every node)', read_only=True),
    Param('lockstep_timeout', 60.0, "lockstep: longest wait for perception's location, s",
          positive, read_only=True),
    Param('lockstep_command_timeout', 5.0, "lockstep: longest wait for the odometry's echo "
          "and for the controller's answer to an action location, s (longer than the DDS "
          'heartbeat period, Fast DDS 3 s)', positive, read_only=True),
]
