"""Typed, described and validated ROS parameters, and the Jazzy run idiom for every node.

Validation is a pure function per parameter (value -> error message or None), registered
before the parameters are declared so values from `params/*.yaml` are validated too.
"""
import signal
import sys
import threading
from dataclasses import dataclass
from typing import Any, Callable, Sequence

from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
import rclpy
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException

from activeloc_ros.checks import Check
from activeloc_ros.errors import ActivelocError, ConfigError


@dataclass(frozen=True)
class Param:
    name: str
    default: Any
    description: str
    check: Check | None = None
    read_only: bool = False


def validate(params: Sequence[Param], values: dict[str, Any]) -> list[str]:
    """Return one message per invalid value, naming the parameter."""
    by_name = {p.name: p for p in params}
    errors = []
    for name, value in values.items():
        spec = by_name.get(name)
        if spec is not None and spec.check is not None:
            problem = spec.check(value)
            if problem:
                errors.append(f'parameter {name!r} {problem}')
    return errors


def declare(node, params: Sequence[Param]) -> dict[str, Any]:
    """Declare `params` on `node` with descriptors and validation; return their values.

    Raises ConfigError naming the parameter when a value (default, YAML or command line)
    is invalid.
    """
    def on_set(changes):
        errors = validate(params, {p.name: p.value for p in changes})
        return SetParametersResult(successful=not errors, reason='; '.join(errors))

    node.add_on_set_parameters_callback(on_set)
    for spec in params:
        descriptor = ParameterDescriptor(description=spec.description, read_only=spec.read_only)
        try:
            node.declare_parameter(spec.name, spec.default, descriptor)
        except InvalidParameterValueException as exc:
            reason = exc.args[2] if len(exc.args) == 3 else str(exc)
            raise ConfigError(f'node {node.get_name()!r}: {reason}') from exc
        except InvalidParameterTypeException as exc:  # e.g. kp:=1 for a double
            raise ConfigError(f'node {node.get_name()!r}: {exc}') from exc
    return {p.name: node.get_parameter(p.name).value for p in params}


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def run(node_factory: Callable[..., Any], args=None, *,
        on_stop: Callable[[Any], None] | None = None) -> int:
    """Init, spin and shut down one node the Jazzy way; a project error exits 1 with a message.

    :param on_stop: called with the node after Ctrl-C and before the context ends, so
        the node can act on purpose (the arm holds) while it can still publish.
    """
    from rclpy.signals import SignalHandlerOptions
    handler = SignalHandlerOptions.NO if on_stop else SignalHandlerOptions.ALL
    stop = threading.Event()

    def request_stop(signum, frame):
        # The first Ctrl-C or kill only asks the loop to end: an exception raised in the
        # middle of rclpy's C++ (taking a message) would come out as a RuntimeError and
        # fail the exit. A second one interrupts on_stop at once.
        stop.set()
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, _interrupt)

    if on_stop:
        # Ctrl-C and kill both reach on_stop, even where SIGINT came in ignored (a process
        # started in the background inherits SIG_IGN, and Python then leaves it so).
        signal.signal(signal.SIGINT, request_stop)
        signal.signal(signal.SIGTERM, request_stop)
    rclpy.init(args=args, signal_handler_options=handler)
    node = None
    try:
        node = node_factory()
        # A node that ends by itself (a camera at the end of its bag) sets `finished`.
        while rclpy.ok() and not stop.is_set() and not getattr(node, 'finished', False):
            rclpy.spin_once(node, timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ActivelocError as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1
    finally:
        if node is not None:
            if on_stop is not None and rclpy.ok():
                on_stop(node)
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
