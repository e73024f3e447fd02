"""
One master for each actuator: notice a second publisher on a command topic, and say so.

Two controllers that both publish ``joint_commands`` (or ``cmd_vel``) make the arm follow
whichever spoke last; nothing in DDS forbids it. The controller, the arm and the sim each
run a `PublisherWatch` on the command topic they publish or obey: it checks the topic's
publishers once a second and warns on the console and on ``/diagnostics`` at the start and
whenever the set of publishers changes while there is more than one. bringup's monitor
runs one too, so its console shows it.
"""
from typing import Callable, Sequence

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType


def masters_problem(topic: str, publishers: Sequence[str]) -> str | None:
    """Why ``publishers`` (node names) of command ``topic`` are a problem, or None."""
    if len(publishers) <= 1:
        return None
    return (f'{topic} has {len(publishers)} publishers ({", ".join(publishers)}): the '
            'actuator follows whichever spoke last; run one controller per actuator')


class PublisherWatch:
    """
    Checks the publishers of a command topic on ``node`` once a second.

    :param say: where the warning goes (default: the node's logger, as a warning).
    """

    def __init__(self, node, topic: str, *, say: Callable[[str], None] | None = None,
                 diagnostics: bool = True):
        self.node = node
        self.topic = node.resolve_topic_name(topic)
        self.say = say or (lambda text: node.get_logger().warning(text))
        self.publishers: tuple[str, ...] = ()
        self.problem: str | None = None
        self.warnings = 0
        self.diagnostics = (node.create_publisher(DiagnosticArray, '/diagnostics', 10)
                            if diagnostics else None)
        self.timer = node.create_timer(1.0, self.check,
                                       clock=Clock(clock_type=ClockType.STEADY_TIME))

    def check(self) -> None:
        infos = self.node.get_publishers_info_by_topic(self.topic)
        names = tuple(sorted(
            f'{i.node_namespace.rstrip("/")}/{i.node_name}' for i in infos))
        problem = masters_problem(self.topic, names)
        if problem and names != self.publishers:
            self.warnings += 1
            self.say(problem)
        elif not problem and self.problem:
            self.node.get_logger().info(f'{self.topic} has one publisher again')
        self.publishers, self.problem = names, problem
        if self.diagnostics is not None:
            status = DiagnosticStatus(
                name=f'{self.node.get_name()}: publishers of {self.topic}',
                level=DiagnosticStatus.WARN if problem else DiagnosticStatus.OK,
                message=problem or 'one publisher',
                values=[KeyValue(key='publishers', value=', '.join(names) or '-')])
            msg = DiagnosticArray(status=[status])
            msg.header.stamp = self.node.get_clock().now().to_msg()
            self.diagnostics.publish(msg)
