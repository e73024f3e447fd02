"""
The Jazzy run idiom for every node process: init, spin, a stop on purpose, shut down,
with Ctrl-C and SIGTERM at any moment of it handled; and the executor the nodes spin in.
"""
import math
import os
import signal
import sys
import threading
import time
from typing import Any, Callable, Sequence

try:
    import rclpy
except ModuleNotFoundError as exc:     # pip install . without the 'ros' extra
    raise ModuleNotFoundError(
        'rclpy is not installed: source a ROS 2 Jazzy (source /opt/ros/jazzy/setup.bash) or '
        "install the PyPI wheels with pip install '.[ros]'", name='rclpy') from exc
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
import yaml

from activeloc_ros.errors import ActivelocError
from activeloc_ros.nodes.params_files import load_params_file, params_files


class ProcessContext(Context):
    """
    The context `run` initialises with the process's arguments, which it keeps: a node
    made in it that uses the global arguments checks their params files too (`declare`).
    """

    def __init__(self, args):
        super().__init__()
        self.args = list(args)


class _StopRequest:
    """
    Set by a signal handler. A plain attribute, because a handler can interrupt anything,
    itself included: threading.Event.set takes a lock, and a signal arriving inside it
    deadlocks the process (seen: a node that the repeated SIGTERMs of its parent's death
    left hanging for good).
    """

    requested = False
    starting = False          # the node is being made, which a stop ends at once
    requested_at = math.inf   # time.monotonic() of the first request while starting


START_STOP_GRACE_S = 3.0      # a stop while starting ends the process within this
STOPPED_STARTING = 'stopped (Ctrl-C or SIGTERM) before the node was ready'


def _end_a_start_that_goes_on(stop: _StopRequest) -> None:
    """
    While the node is being made: once a stop was asked for and the start still goes on
    `START_STOP_GRACE_S` later, end the process. The stop raises KeyboardInterrupt in the
    start, but third-party code can swallow it (OpenVINO's model conversion, tracing the
    encoder for an int8 build, goes on after one), and the build would then take its
    minute. Nothing is lost: the node never became ready, and a build's folder is removed
    by the next build (`int8`).
    """
    while stop.starting:
        if time.monotonic() - stop.requested_at > START_STOP_GRACE_S:
            print(f'{STOPPED_STARTING}: its start went on {START_STOP_GRACE_S:g} s after the '
                  'stop, so the process ends here', file=sys.stderr, flush=True)
            os._exit(0)
        time.sleep(0.1)


def wants_help(args: Sequence[str]) -> bool:
    """-h or --help among the arguments before ``--ros-args``."""
    ours = list(args)[:list(args).index('--ros-args')] if '--ros-args' in args else args
    return any(a in ('-h', '--help') for a in ours)


def frame_due(timer, due: float) -> bool:
    """
    Is a paced frame (a replayed camera's, a world's real-time step) due at ``due``
    (monotonic seconds) now? If not, the node's timer sleeps until then (at most 50 ms)
    instead of polling; if so, it comes back in 1 ms for the frame after.
    """
    wait = due - time.monotonic()
    timer.timer_period_ns = int(min(max(wait, 0.001), 0.05) * 1e9)
    timer.reset()
    return wait <= 0


def frames_stopped(node) -> None:
    """
    on_stop of a node that publishes frames (camera, sim, tracking world): how many it
    published, unless it had ended by itself and said so.
    """
    if not node.finished:
        node.get_logger().info(f'stopped: {node.published} frames published')


def lean_executor(context=None):
    """
    A single-threaded executor with the least work per callback: rclpy's EventsExecutor
    where this rclpy has it (Jazzy's later releases), else its SingleThreadedExecutor, which
    builds a wait set in Python for every callback.
    """
    try:
        from rclpy.experimental import EventsExecutor
    except ImportError:
        return SingleThreadedExecutor(context=context)
    return EventsExecutor(context=context)


def ros_args_problem(args: list[str]) -> str | None:
    """
    Why rcl refuses a command line's ROS arguments (an unknown flag, ``-p`` without a
    rule), or None; rclpy raises it from ``init`` as a bare RuntimeError.
    """
    from rclpy.signals import SignalHandlerOptions
    context = rclpy.Context()
    try:   # (no signal handlers: the caller's, for Ctrl-C, stay as they are)
        rclpy.init(args=args, context=context, signal_handler_options=SignalHandlerOptions.NO)
    except RuntimeError as exc:
        if type(exc).__name__ == 'UnknownROSArgsError':
            return f'unknown ROS arguments {exc}'
        return f'bad ROS arguments: {exc}'
    rclpy.try_shutdown(context=context)
    return None


def ignore_late_stops() -> None:
    """
    Ignore Ctrl-C and SIGTERM from now on: the node is gone and the process only ends.
    A stop that comes then (bringup's, when a node that ended by itself is stopped in the
    same moment) has nothing left to stop, but Python, finalising, puts its handlers back to
    the default first, so it would kill the process (exit -2 or -15) in the middle of its
    exit.
    """
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)


def run(node_factory: Callable[..., Any], args=None, *,
        on_stop: Callable[[Any], None] | None = None,
        help_text: Callable[[], str] | None = None) -> int:
    """
    Init, spin and shut down one node the Jazzy way; a project error exits 1 with a message.

    A node that ends by itself sets ``finished``; one that ends because it cannot go on
    (the arm's serial link is gone) also sets ``failure`` to the reason, and the process
    exits 1 with it.

    :param node_factory: makes the node, called as ``node_factory(context=...)`` with the
        `ProcessContext` rclpy is initialised in (a Node class).
    :param on_stop: called with the node after Ctrl-C and before the context ends, so
        the node can act on purpose (the arm holds) while it can still publish.
    :param help_text: what ``-h`` / ``--help`` prints (`node_help`) instead of starting.
    """
    from rclpy.signals import SignalHandlerOptions
    process_args = sys.argv if args is None else args
    if help_text is not None and wants_help(process_args):
        print(help_text())
        return 0
    for path in params_files(process_args):  # rcl's own parse error names no line
        try:
            load_params_file(path)
        except (OSError, yaml.YAMLError) as exc:
            print(f'error: params file {path} cannot be read: {exc}', file=sys.stderr)
            return 1
    handler = SignalHandlerOptions.NO if on_stop else SignalHandlerOptions.ALL
    stop = _StopRequest()

    def request_stop(signum, frame):
        # The first Ctrl-C or kill only asks the loop to end: an exception raised in the
        # middle of rclpy's C++ (taking a message) would come out as a RuntimeError and
        # fail the exit. A second Ctrl-C interrupts on_stop at once; a repeated SIGTERM
        # (a parent's death can signal more than once) is the same request again. While the
        # node is being made no message is being taken, and the making can take a minute
        # (the first use of an int8 encoder builds it), so a stop then ends it at once.
        if stop.starting:             # (requested too: a start that swallows it ends so)
            stop.requested, stop.requested_at = True, min(stop.requested_at, time.monotonic())
            raise KeyboardInterrupt
        if stop.requested and signum == signal.SIGINT:
            raise KeyboardInterrupt
        stop.requested = True

    if on_stop:
        # Ctrl-C and kill both reach on_stop, even where SIGINT came in ignored (a process
        # started in the background inherits SIG_IGN, and Python then leaves it so).
        signal.signal(signal.SIGINT, request_stop)
        signal.signal(signal.SIGTERM, request_stop)
    problem = ros_args_problem(process_args)
    if problem:
        print(f'error: {problem}', file=sys.stderr)
        return 2
    context = ProcessContext(process_args)
    rclpy.init(args=args, context=context, signal_handler_options=handler)
    node = executor = None
    try:
        stop.starting = True
        threading.Thread(target=_end_a_start_that_goes_on, args=(stop,), daemon=True).start()
        if stop.requested:            # asked before the handler could end the start
            raise KeyboardInterrupt
        node = node_factory(context=context)
        stop.starting = False
        executor = lean_executor(context)
        executor.add_node(node)
        # A node that ends by itself (a camera at the end of its bag) sets `finished`.
        while context.ok() and not stop.requested and not getattr(node, 'finished', False):
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        stop.starting = False
        if node is None:
            print(STOPPED_STARTING, file=sys.stderr, flush=True)
    except ActivelocError as exc:
        stop.starting = False
        print(f'error: {exc}', file=sys.stderr)
        return 1
    finally:
        stop.starting = False
        if executor is not None:              # (only ever made once the node exists)
            executor.remove_node(node)        # on_stop may spin the node on its own
        if node is not None:
            if on_stop is not None and context.ok():
                on_stop(node)
            node.destroy_node()
        rclpy.try_shutdown(context=context)
        ignore_late_stops()
    failure = getattr(node, 'failure', None)
    if failure:
        print(f'error: {failure}', file=sys.stderr)
    code = 1 if failure else 0
    if stop.requested_at < math.inf:
        _end_after_a_stopped_start(code)
    return code


def _end_after_a_stopped_start(code: int) -> None:
    """
    End the process now, with ``code``, after a stop interrupted its start.

    The stop raised KeyboardInterrupt in the start. When that passed through an
    extension's call into Python (C++ running Python code, as pybind11's exec does),
    CPython marks the run to end with SIGINT however it was caught, and a ``python -m``
    process (every node, as bringup starts them) exits -2 after its clean stop. The node is
    gone and the context shut down, so nothing is left to finalise.
    """
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
