"""
The Braccio arm: follows ``joint_commands`` and publishes ``joint_states`` (radians).

Back ends (parameter ``backend``): ``sim`` moves a simulated Braccio at the servos' speed in
whole degrees (``control.SimArm``), an arm without hardware; ``serial`` drives
``braccio_serial.ino`` over a serial port (``control.serial_link.BraccioLink``) and publishes
the state it echoes, surviving a silent, noisy or vanishing port. On Ctrl-C the arm stops
where it is, or goes home slowly (``stop_mode``), before the node ends. (The arm of the
projected-screen simulation, whose camera it aims, is the sim node's.)

Any command a topic can carry is safe: a malformed one (unknown or repeated names, lengths
that differ, a position that is not a finite angle in degrees, such as 1e308 rad) is logged
(throttled) and ignored, one outside the joint limits is clamped. ``/diagnostics`` tells the
link's health once a second. A serial link down for ``give_up_timeout`` (never connected,
or lost and not back) ends the node with an error and exit code 1.
"""
import math
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from activeloc_ros.control import clamp_to_limits, fixed_moves, JOINT_NAMES, SimArm
from activeloc_ros.control.arm_params import PARAMS
from activeloc_ros.control.braccio import clamp_text, refusal_text, speed_deg_s
from activeloc_ros.control.serial_link import BraccioLink
from activeloc_ros.nodes.clock import Rewinds
from activeloc_ros.nodes.masters import PublisherWatch
from activeloc_ros.nodes.messages import joint_state
from activeloc_ros.nodes.params import declare, node_help
from activeloc_ros.nodes.process import run


LINK_TIMES = ('silence_timeout', 'reconnect_period', 'handshake_timeout')


def parse_command(msg: JointState, current: tuple[float, ...]
                  ) -> tuple[tuple[float, ...] | None, str]:
    """
    Six target angles in degrees from a JointState (radians, any subset of the joints by
    name, or all six in order without names), or None and why it is malformed.
    """
    names = list(msg.name) if msg.name else list(JOINT_NAMES)
    positions = list(msg.position)
    if len(names) != len(positions):
        return None, (f'{len(msg.name)} names for {len(positions)} positions' if msg.name
                      else f'{len(positions)} positions without names (need {len(names)})')
    unknown = [n for n in names if n not in JOINT_NAMES]
    if unknown:
        return None, f'unknown joints {unknown[:3]} (joints are {list(JOINT_NAMES)})'
    if len(set(names)) != len(names):
        return None, f'joints named twice in {names}'
    degrees = {n: math.degrees(r) for n, r in zip(names, positions)}  # 1e308 rad: inf deg
    bad = {n: r for n, r in zip(names, positions) if not math.isfinite(degrees[n])}
    if bad:
        return None, 'not a finite angle: ' + ', '.join(f'{n} {r!r} rad' for n, r in bad.items())
    return tuple(degrees.get(n, q) for n, q in zip(JOINT_NAMES, current)), ''


def ramp(current, goal, max_step: float) -> tuple[float, ...]:
    """Move every joint at most ``max_step`` degrees from ``current`` towards ``goal``."""
    return tuple(g if abs(g - q) <= max_step else q + math.copysign(max_step, g - q)
                 for q, g in zip(current, goal))


class ArmNode(Node):

    def __init__(self, **kwargs):
        super().__init__('arm', **kwargs)
        values = declare(self, PARAMS, cli_args=kwargs.get('cli_args'),
                         use_global_arguments=kwargs.get('use_global_arguments', True),
                         on_change=self.on_parameters)
        self.values = values
        self.backend = values['backend']
        self.home = tuple(float(q) for q in values['home_deg'])
        self.rejected = 0
        self.clamped = 0
        self.refused = 0
        self.aiming = (values['pan_joint'], *values['tilt_joints'])
        self.stopping = False
        self._stop_goal: tuple[float, ...] | None = None
        self._stop_pose: tuple[float, ...] | None = None
        self._stop_t = 0.0
        self._problems_logged = 0
        self.failure: str | None = None   # why the node cannot go on (run() exits 1)
        self.finished = False
        self._down_since = time.monotonic()
        self._last_link_event = ''
        self._lock = threading.RLock()  # stop_on_purpose may come from another thread
        self._stopped = threading.Event()
        self.rewinds = Rewinds(self, self._lock, self._restart, 'the arm goes on from there')
        self._locked = self.rewinds.locked   # the lock, for a callback that moves the arm

        if self.backend == 'sim':
            self.sim = SimArm(values['sim_start_deg'], self._now(),
                              step_delay_ms=values['step_delay_ms'])
            self.link = None
        else:
            self.sim = None
            self.link = BraccioLink(
                values['port'], baud=values['baud'], poll_period=values['poll_period'],
                silence_timeout=values['silence_timeout'],
                reconnect_period=values['reconnect_period'],
                handshake_timeout=values['handshake_timeout'],
                max_speed_deg_s=speed_deg_s(values['step_delay_ms']))
            self.create_timer(values['poll_period'], self.on_poll)

        self.publisher = self.create_publisher(JointState, 'joint_states', 10)
        self.masters = PublisherWatch(self, 'joint_commands')   # the arm obeys one master
        self.create_subscription(JointState, 'joint_commands', self.on_command,
                                 QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE))
        self.state_timer = self.create_timer(1.0 / values['state_rate'], self.on_state_timer)
        self.diagnostics = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.create_timer(1.0, self.publish_diagnostics,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        where = values['port'] if self.link else 'simulation'
        self.get_logger().info(f'Braccio arm ({self.backend}: {where}), stop mode '
                               f'{values["stop_mode"]}')

    def on_parameters(self, values: dict, changed: set) -> None:
        """
        A run-time change (validated): stop settings are read when stopping; the rate
        and the link's timeouts change at once.
        """
        with self._lock:
            self.values = values
            self.home = tuple(float(q) for q in values['home_deg'])
            self.state_timer.timer_period_ns = int(1e9 / values['state_rate'])
            if self.link is not None:
                for name in LINK_TIMES:
                    setattr(self.link, name, values[name])
        self.get_logger().info('set at run time: ' + ', '.join(
            f'{name} {values[name]!r}' for name in sorted(changed)))

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _restart(self, now: float) -> None:
        """
        Go on from ``now`` after the clock ran back (`Rewinds`).

        The simulated servos and the stop's ramp restart; the serial link keeps its own,
        monotonic, time.
        """
        if self.sim is not None:
            self.sim.restart(now)
        self._stop_t = min(self._stop_t, now)

    # -- the arm, whichever back end -------------------------------------------------------

    def joints(self) -> tuple[float, ...] | None:
        """Where the arm is (degrees), or None while the serial link has no fresh state."""
        if self.sim is not None:
            return tuple(float(q) for q in self.sim.advance(self._now()))
        if self.link.fresh(time.monotonic()):
            return tuple(float(q) for q in self.link.joints)
        return None

    def _send(self, target_deg) -> None:
        if self.sim is not None:
            self.sim.command(target_deg, self._now())
        else:
            self.link.command(target_deg)

    def _target(self) -> tuple[float, ...]:
        if self.sim is not None:
            return tuple(float(q) for q in self.sim.target)
        if self.link.target is not None:
            return tuple(float(q) for q in self.link.target)
        return self.joints() or self.home

    # -- callbacks -------------------------------------------------------------------------

    def on_command(self, msg: JointState) -> None:
        with self._locked():
            self._on_command(msg)

    def _on_command(self, msg: JointState) -> None:
        if self.stopping:
            return
        target, why = parse_command(msg, self._target())
        if target is None:
            self.rejected += 1
            self.get_logger().warning(f'ignored a malformed joint command: {why} '
                                      f'({self.rejected} so far)', throttle_duration_sec=5.0)
            return
        moved = fixed_moves(target, self._target(), home_deg=self.home, aiming=self.aiming)
        if moved:
            self.refused += 1
            self.get_logger().warning(refusal_text(moved, self.aiming, self.refused),
                                      throttle_duration_sec=5.0)
            return
        safe = clamp_to_limits(target)
        if safe != target:
            self.clamped += 1
            self.get_logger().warning(clamp_text(target, safe, self.clamped),
                                      throttle_duration_sec=5.0)
        self._send(safe)

    def on_poll(self) -> None:
        with self._lock:
            events = self.link.poll(time.monotonic())
        for event in events:
            self.get_logger().info(event)
            self._last_link_event = event
        self._watch_link(time.monotonic())
        problems = self.link.stats.problems
        if problems != self._problems_logged:
            self._problems_logged = problems
            s = self.link.stats
            self.get_logger().warning(
                f'serial link: ignored {s.noise_bytes} noise bytes, {s.bad_frames} bad '
                f'frames, {s.implausible} implausible states, {s.rejected} refused '
                f'commands (last: {s.last_bad or "-"})',
                throttle_duration_sec=5.0)

    def _watch_link(self, now: float) -> None:
        """End the node with an error once the link has been down for give_up_timeout."""
        if self.link.state == 'connected':
            self._down_since = None
            return
        if self._down_since is None:
            self._down_since = now
        limit = self.values['give_up_timeout']
        if self.failure is None and limit > 0 and now - self._down_since > limit:
            ever = self.link.stats.connects > 0
            self.failure = (f'serial link to the arm on {self.link.path} '
                            + ('lost' if ever else 'never connected')
                            + f' for {limit:g} s (give_up_timeout); last: '
                            f'{self._last_link_event or "-"}')
            self.get_logger().error(self.failure)
            self.finished = True

    def publish_diagnostics(self) -> None:
        """The link's health on /diagnostics (diagnostic_msgs), as drivers do."""
        status = DiagnosticStatus(name=f'{self.get_name()}: ' + (
            'serial link' if self.link else 'simulated servos'))
        counts = {'rejected commands': self.rejected, 'clamped commands': self.clamped,
                  'refused commands (a joint that does not aim the camera)': self.refused}
        if self.link is None:
            status.level, status.message, status.hardware_id = (
                DiagnosticStatus.OK, 'simulated', 'sim')
        else:
            link, s = self.link, self.link.stats
            status.hardware_id = link.path
            status.level = {'connected': DiagnosticStatus.OK,
                            'handshake': DiagnosticStatus.WARN}.get(link.state,
                                                                    DiagnosticStatus.ERROR)
            status.message = {'connected': 'connected',
                              'handshake': 'opened, waiting for <ok>'}.get(
                link.state, 'disconnected: ' + (self._last_link_event or 'not opened yet'))
            age = time.monotonic() - link.joints_time
            counts.update({'state': link.state, 'port': link.path, 'baud': link.baud,
                           'commands sent': s.writes, 'states received': s.states,
                           'last state age (s)': f'{age:.2f}' if math.isfinite(age) else '-',
                           'connects': s.connects, 'losses': s.losses,
                           'noise bytes': s.noise_bytes, 'bad frames': s.bad_frames,
                           'commands refused by the sketch': s.rejected,
                           'implausible states refused': s.implausible})
        status.values = [KeyValue(key=k, value=str(v)) for k, v in counts.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics.publish(msg)

    def on_state_timer(self) -> None:
        with self._locked():
            if self.stopping:
                self._stop_step()
                if self.stop_done():
                    self._stopped.set()
            joints = self.joints()
        if joints is not None:
            self._publish_state(joints, self.get_clock().now().to_msg())

    def _publish_state(self, joints, stamp) -> None:
        self.publisher.publish(joint_state(joints, stamp))

    # -- stopping on purpose ---------------------------------------------------------------

    def begin_stop(self) -> None:
        """Start the on-purpose stop: ignore commands, then hold here or ramp home."""
        self.stopping = True
        here = self.joints()
        if here is None:
            self._stop_goal = None
            self.get_logger().warning('stopping without a fresh arm state: nothing to hold')
            return
        self._stop_pose = here
        self._stop_t = self._now()
        self._stop_goal = self.home if self.values['stop_mode'] == 'home' else here
        self._send(here)

    def _stop_step(self) -> None:
        if self._stop_goal is None or self._stop_pose == self._stop_goal:
            return
        now = self._now()
        step = self.values['home_speed_deg_s'] * max(0.0, now - self._stop_t)
        self._stop_t = now
        self._stop_pose = ramp(self._stop_pose, self._stop_goal, step)
        self._send(self._stop_pose)

    def stop_done(self) -> bool:
        """True once the arm holds its stop goal (or there is nothing to wait for)."""
        if self._stop_goal is None:
            return True
        here = self.joints()
        if here is None:
            return self.link is not None and self.link.state != 'connected'
        goal = tuple(int(round(q)) for q in self._stop_goal)
        if self.sim is not None:
            return self.sim.joints == goal and self.sim.target == goal
        return (self.link.target == goal and not self.link.busy
                and tuple(int(q) for q in here) == goal)

    def stop_on_purpose(self, executor=None) -> bool:
        """
        Stop on purpose while the context is alive: hold here or ramp home, and wait
        (at most ``stop_timeout``) until the arm got there.

        :param executor: spin this one; by default a private one, unless the node belongs
            to an executor that another thread spins (an in-process graph): then its timers
            do the work and this call only waits.
        """
        with self._locked():
            self.begin_stop()
        timeout = self.values['stop_timeout']
        try:
            spun_elsewhere = self.executor is not None and self in self.executor.get_nodes()
            if executor is None and spun_elsewhere:
                self._stopped.wait(timeout)
            else:
                own = executor is None
                if own:
                    executor = SingleThreadedExecutor(context=self.context)
                    executor.add_node(self)
                deadline = time.monotonic() + timeout
                try:
                    while not self._stopped.is_set() and time.monotonic() < deadline:
                        executor.spin_once(timeout_sec=0.02)
                finally:
                    if own:
                        executor.remove_node(self)
        except KeyboardInterrupt:
            self.get_logger().warning('second interrupt: stopping at once')
        with self._lock:
            done = self.stop_done()
            where = self.joints()
            if self.link is not None:
                self.link.close()
        if where is not None:
            self._publish_state(where, self.get_clock().now().to_msg())
        # the last state must reach the subscribers before this process ends
        self.publisher.wait_for_all_acked(Duration(seconds=0.5))
        self.get_logger().info(
            f'stopped ({self.values["stop_mode"]}) at '
            + (', '.join(f'{q:.0f}' for q in where) if where else 'an unknown pose')
            + ('' if done else ' (timed out)'))
        return done


def main(args=None) -> int:
    return run(ArmNode, args, on_stop=lambda node: node.stop_on_purpose(),
               help_text=lambda: node_help('arm_node', __doc__, PARAMS))


if __name__ == '__main__':
    raise SystemExit(main())
