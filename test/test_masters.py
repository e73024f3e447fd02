"""One master for each actuator: a second publisher of a command topic is noticed."""
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import JointState

from activeloc_ros.nodes.masters import masters_problem, PublisherWatch
from conftest import params_args, spin_until


def test_one_publisher_is_no_problem_and_two_are_named():
    assert masters_problem('/joint_commands', []) is None
    assert masters_problem('/joint_commands', ['/controller']) is None
    text = masters_problem('/joint_commands', ['/controller', '/controller'])
    assert '2 publishers (/controller, /controller)' in text


def test_a_second_controller_is_said_by_the_controller_and_the_arm(context):
    """
    The hostile test: a second controller_node with the same name beside the graph.
    Both controllers, the arm, and a watch like bringup's say so, once; and again when the
    set of publishers changes; /diagnostics carries it.
    """
    from diagnostic_msgs.msg import DiagnosticArray
    from activeloc_ros.nodes.arm_node import ArmNode
    from activeloc_ros.nodes.controller_node import ControllerNode
    first = ControllerNode(context=context, cli_args=params_args())
    arm = ArmNode(context=context, cli_args=params_args())
    heard: list[str] = []
    probe = Node('probe', context=context)
    watch = PublisherWatch(probe, 'joint_commands', say=heard.append, diagnostics=False)
    statuses = []
    probe.create_subscription(DiagnosticArray, '/diagnostics',
                              lambda m: statuses.extend(m.status), 100)
    executor = SingleThreadedExecutor(context=context)
    for node in (first, arm, probe):
        executor.add_node(node)
    second = None
    try:
        assert spin_until(executor, lambda: watch.publishers == ('/controller',), 5.0)
        assert not heard and first.masters.warnings == 0
        second = ControllerNode(context=context, cli_args=params_args('kp:=0.5'))
        executor.add_node(second)
        assert spin_until(executor, lambda: heard and arm.masters.warnings == 1
                          and first.masters.warnings == 1 and second.masters.warnings == 1,
                          10.0)
        assert '2 publishers (/controller, /controller)' in heard[0]
        assert spin_until(executor, lambda: any(
            s.level == s.WARN and 'publishers of /joint_commands' in s.name for s in statuses),
            5.0)
        extra = probe.create_publisher(JointState, 'joint_commands', 1)   # a third one
        assert spin_until(executor, lambda: len(heard) == 2, 10.0)
        assert '3 publishers' in heard[1]
        probe.destroy_publisher(extra)
    finally:
        executor.shutdown()
        for node in (first, arm, probe, second):
            if node is not None:
                node.destroy_node()
