"""Typed, described and validated ROS parameters, and the Jazzy run idiom for every node.

Validation is a pure function per parameter (value -> error message or None), registered
before the parameters are declared so values from `params/*.yaml` are validated too. A
``checks.Range`` goes into the descriptor (``floating_point_range`` / ``integer_range``), so
``ros2 param describe`` shows it and rclpy enforces it.

The params files a node is given are read here too, because rcl passes over some mistakes
in silence: a value of the wrong type in a later file (``kp: 'fast'``) leaves the earlier
value in place, keys no node declares and sections naming no node are never looked at.
Each of these stops the node with a message naming the file, the section and the key.

At run time a parameter either applies at once (the node passes ``on_change``; a whole-set
check ``check_all`` may refuse a combination) or is declared read-only, so that
``ros2 param set`` is refused rather than reported as set and never used.
"""
from dataclasses import dataclass
import difflib
import functools
import math
import os
from pathlib import Path
import re
import signal
import sys
import textwrap
import threading
import time
from typing import Any, Callable, Iterable, Mapping, Sequence

from rcl_interfaces.msg import (
    FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult)
try:
    import rclpy
except ModuleNotFoundError as exc:     # pip install . without the 'ros' extra
    raise ModuleNotFoundError(
        'rclpy is not installed: source a ROS 2 Jazzy (source /opt/ros/jazzy/setup.bash) or '
        "install the PyPI wheels with pip install '.[ros]'", name='rclpy') from exc
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.parameter import Parameter
import yaml

from activeloc_ros.checks import Check, Range
from activeloc_ros.errors import ActivelocError, ConfigError
from activeloc_ros.paths import NODE_NAMES   # a params file section names one, or /**

_INT64 = (-2**63, 2**63 - 1)


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


def descriptor(spec: Param) -> ParameterDescriptor:
    """The descriptor of `spec`: description, read-only flag and, for a numeric scalar with
    a ``Range`` check, its range."""
    text = spec.description + (' (read-only: set at start-up)' if spec.read_only else '')
    result = ParameterDescriptor(description=text, read_only=spec.read_only)
    check = spec.check
    if isinstance(check, Range) and not isinstance(spec.default, bool):
        if isinstance(spec.default, int):
            lo = _INT64[0] if math.isinf(check.lo) else math.ceil(check.lo)
            hi = _INT64[1] if math.isinf(check.hi) else math.floor(check.hi)
            result.integer_range = [IntegerRange(from_value=lo, to_value=hi, step=1)]
        elif isinstance(spec.default, float):
            lo = -sys.float_info.max if math.isinf(check.lo) else float(check.lo)
            hi = sys.float_info.max if math.isinf(check.hi) else float(check.hi)
            result.floating_point_range = [FloatingPointRange(from_value=lo, to_value=hi)]
    return result


def _in_descriptor(spec: Param) -> bool:
    d = descriptor(spec)
    return bool(d.integer_range or d.floating_point_range)


# -- params files -------------------------------------------------------------------------

class _RclLoader(yaml.SafeLoader):
    """YAML as rcl reads a params file: ``1e-6`` is a number (PyYAML's 1.1 rules want a dot)."""


_RclLoader.add_implicit_resolver(
    'tag:yaml.org,2002:float',
    re.compile(r'^[-+]?([0-9]+(\.[0-9]*)?|\.[0-9]+)[eE][-+]?[0-9]+$'), list('-+0123456789.'))


def load_params_file(path) -> Any:
    return yaml.load(Path(path).read_text(), Loader=_RclLoader)


def parse_value(text: str) -> Any:
    """A ``-p name:=value`` value as rcl types it."""
    return yaml.load(text, Loader=_RclLoader)


def _declared_type(value) -> 'Parameter.Type | None':
    """The ROS type of a default; None for an empty list (any array type fits)."""
    if isinstance(value, (list, tuple)) and not value:
        return None
    return Parameter.Type.from_parameter_value(value)


def cli_param_rule(flag: str, item: str | None) -> tuple[str, str] | None:
    """(name, value text) of the command-line pair ``-p name:=value`` (or ``--param``), else
    None. rcl applies a rule without a node prefix (``node:name:=``) to every node of the
    process."""
    if flag in ('-p', '--param') and item is not None and ':=' in item:
        return item.partition(':=')[::2]
    return None


def cli_param_rules(args: Iterable[str] | None) -> list[tuple[str, str]]:
    """The ``-p name:=value`` rules of a command line, as (name, value text)."""
    args = list(args or [])
    return [rule for rule in map(cli_param_rule, args, args[1:]) if rule]


def undeclared(name: str, declared: Iterable[str]) -> bool:
    """Whether a ``-p`` rule for ``name`` sets a parameter that a node declaring ``declared``
    (and rclpy's own) does not have; a node-prefixed rule is rcl's to route."""
    return ':' not in name and name not in {*declared, *BUILTIN_PARAMS}


def unknown_cli_params(args: Iterable[str] | None, declared: Iterable[str], *,
                       unknown: str = 'no such parameter') -> list[str]:
    """Each ``-p`` rule naming a parameter that is not in ``declared`` (nor rclpy's), with
    the nearest declared name: the node would ignore it, silently."""
    known = {*declared, *BUILTIN_PARAMS}
    problems = []
    for name, _ in cli_param_rules(args):
        if undeclared(name, known):
            close = difflib.get_close_matches(name, known, n=1)
            problems.append(f'-p {name}: {unknown}'
                            + (f' (did you mean {close[0]!r}?)' if close else ''))
    return problems


def params_files(args: Iterable[str] | None) -> list[str]:
    """The ``--params-file`` paths among ROS command-line arguments."""
    args = list(args or [])
    return [args[i + 1] for i, a in enumerate(args[:-1]) if a == '--params-file']


def _flatten(section: Mapping, prefix: str = '') -> dict[str, Any]:
    """rcl's view of nested keys: ``a: {b: 1}`` is the parameter ``a.b``."""
    flat = {}
    for key, value in section.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f'{prefix}{key}.'))
        else:
            flat[f'{prefix}{key}'] = value
    return flat


def _section_node(section) -> str:
    """The node name a params file section addresses, without its namespace."""
    return str(section).strip('/').split('/')[-1]


def _type_name(kind: Parameter.Type) -> str:
    return kind.name.lower().replace('_', ' ')


def _example(kind: Parameter.Type, value) -> str:
    if kind == Parameter.Type.DOUBLE and isinstance(value, int) and not isinstance(value, bool):
        return f' (write {float(value)!r})'
    return ''


def params_file_problems(content, node: str, declared: Mapping[str, Parameter.Type],
                         known_elsewhere: Iterable[str] = ()) -> list[str]:
    """Why a params file's `content` (parsed YAML) is wrong for `node`; empty when fine.

    A section must name one of NODE_NAMES (any namespace) or be a wildcard. In the
    sections that reach `node` (its own name, ``*`` or ``**``), a value must have the type
    the node declared; a key it does not declare is an error, except in a wildcard section
    when another node of the package declares it (`known_elsewhere`).
    """
    if not isinstance(content, dict):
        return ['not in ROS 2 format (<node or /**>: ros__parameters: {...})']
    problems = []
    known_elsewhere = set(known_elsewhere)
    for section, body in content.items():
        target = _section_node(section)
        if target not in NODE_NAMES + ('*', '**'):
            close = difflib.get_close_matches(target, NODE_NAMES, n=1, cutoff=0.5)
            hint = f' (did you mean /{close[0]}?)' if close else ''
            problems.append(f'section {section!r} names no node of activeloc_ros, so nothing '
                            f'in it would be applied{hint}; the nodes are '
                            + ', '.join(f'/{n}' for n in NODE_NAMES) + ', or /** for all')
            continue
        if target not in (node, '*', '**'):
            continue
        if not isinstance(body, dict) or not isinstance(body.get('ros__parameters'), dict):
            problems.append(f'section {section!r} has no ros__parameters mapping')
            continue
        for name, value in _flatten(body['ros__parameters']).items():
            if name not in declared:
                if target != node and name in known_elsewhere:
                    continue  # for another node of the package
                close = difflib.get_close_matches(name, list(declared), n=1)
                hint = f' (did you mean {close[0]!r}?)' if close else ''
                problems.append(f'section {section!r}: {name!r} is not a parameter of node '
                                f'{node!r}{hint}')
                continue
            expected = declared[name]
            if expected is None:
                continue
            try:
                kind = Parameter.Type.from_parameter_value(value)
            except TypeError:
                kind = None
            if kind != expected:
                got = _type_name(kind) if kind is not None else 'a mixed list'
                problems.append(f'section {section!r}: {name!r} must be a '
                                f'{_type_name(expected)}{_example(expected, value)}, got '
                                f'{value!r} ({got})')
    return problems


@functools.lru_cache(maxsize=None)
def _shipped_keys() -> frozenset[str]:
    """Every parameter set in the package's own params files: the keys a shared /**
    section may hold for other nodes."""
    from activeloc_ros.paths import packaged_params_files
    keys = set()
    for path in packaged_params_files():
        if path.is_file():
            for body in (load_params_file(path) or {}).values():
                keys.update(_flatten((body or {}).get('ros__parameters') or {}))
    return frozenset(keys)


# rclpy's own parameters of every node, which a params file may set too
BUILTIN_PARAMS = {'use_sim_time': Parameter.Type.BOOL,
                  'start_type_description_service': Parameter.Type.BOOL}


def files_problems(node_name: str, params: Sequence[Param], files: Iterable[str]) -> list[str]:
    """Every problem of the params `files` for the node `node_name` declaring `params`
    (see ``params_file_problems``), each naming its file."""
    declared = {**BUILTIN_PARAMS, **{p.name: _declared_type(p.default) for p in params}}
    problems = []
    for path in files:
        try:
            content = load_params_file(path)
        except (OSError, yaml.YAMLError) as exc:
            problems.append(f'{path}: cannot be read: {exc}')
            continue
        problems += [f'{path}: {p}' for p in params_file_problems(
            content, node_name, declared, _shipped_keys())]
    return problems


def file_values(node_name: str, files: Iterable[str]) -> dict[str, Any]:
    """The values that params `files` give the node `node_name`, later files winning."""
    values = {}
    for path in files:
        for section, body in (load_params_file(path) or {}).items():
            if _section_node(section) in ('*', '**', node_name):
                values.update(_flatten((body or {}).get('ros__parameters') or {}))
    return values


def check_params_files(node, params: Sequence[Param], files: Iterable[str]) -> None:
    """Raise ConfigError listing every problem of `files` for `node` (``files_problems``)."""
    problems = files_problems(node.get_name(), params, files)
    if problems:
        raise ConfigError(f'node {node.get_name()!r}, params file problems:\n  '
                          + '\n  '.join(problems))


# The arguments `run` initialised rclpy with: a node that uses the global arguments reads
# their params files.
_process_args: list[str] = []


def declare(node, params: Sequence[Param], *, cli_args: Sequence[str] | None = None,
            use_global_arguments: bool = True,
            check_all: Callable[[dict, set], 'str | None'] | None = None,
            on_change: Callable[[dict, set], None] | None = None) -> dict[str, Any]:
    """Declare `params` on `node` with descriptors and validation; return their values.

    Raises ConfigError naming the parameter (and the file) when a value (default, YAML or
    command line) is invalid, or a params file holds a key or section nothing reads.

    :param cli_args: the node's own ``cli_args``, whose params files are checked too.
    :param check_all: at run time, ``(values after the change, changed names) -> error or
        None`` for rules across parameters.
    :param on_change: at run time, called with the same after a change was accepted: the
        node applies it. Without one, declare the parameters read-only.
    """
    ready = False

    def values_after(changes) -> dict[str, Any]:
        values = {p.name: node.get_parameter(p.name).value for p in params}
        values.update({p.name: p.value for p in changes})
        return values

    # ranges in the descriptor are enforced by rclpy before on_set is called
    unenforced = [p for p in params if not _in_descriptor(p)]

    def on_set(changes):
        errors = validate(unenforced, {p.name: p.value for p in changes})
        if not errors and ready and check_all is not None:
            problem = check_all(values_after(changes), {p.name for p in changes})
            if problem:
                errors.append(problem)
        return SetParametersResult(successful=not errors, reason='; '.join(errors))

    def post_set(changes):
        if ready and on_change is not None:
            on_change(values_after([]), {p.name for p in changes})

    files = params_files(cli_args)
    if use_global_arguments:
        files = params_files(_process_args) + files
    check_params_files(node, params, files)
    unknown = unknown_cli_params([*(_process_args if use_global_arguments else []),
                                  *(cli_args or [])], [p.name for p in params])
    if unknown:
        raise ConfigError(f'node {node.get_name()!r}: ' + '; '.join(unknown))
    node.add_on_set_parameters_callback(on_set)
    node.add_post_set_parameters_callback(post_set)
    for spec in params:
        try:
            node.declare_parameter(spec.name, spec.default, descriptor(spec))
        except InvalidParameterValueException as exc:
            reason = exc.args[2] if len(exc.args) == 3 else str(exc)
            raise ConfigError(f'node {node.get_name()!r}: {reason}') from exc
        except InvalidParameterTypeException as exc:  # e.g. kp:=1 for a double
            raise ConfigError(f'node {node.get_name()!r}: {exc}') from exc
    ready = True
    return {p.name: node.get_parameter(p.name).value for p in params}


class _StopRequest:
    """Set by a signal handler. A plain attribute, because a handler can interrupt anything,
    itself included: threading.Event.set takes a lock, and a signal arriving inside it
    deadlocks the process (seen: a node that the repeated SIGTERMs of its parent's death
    left hanging for good)."""
    requested = False
    starting = False          # the node is being made, which a stop ends at once
    requested_at = math.inf   # time.monotonic() of the first request while starting


START_STOP_GRACE_S = 3.0      # a stop while starting ends the process within this
STOPPED_STARTING = 'stopped (Ctrl-C or SIGTERM) before the node was ready'


def _end_a_start_that_goes_on(stop: _StopRequest) -> None:
    """While the node is being made: once a stop was asked for and the start still goes on
    `START_STOP_GRACE_S` later, end the process. The stop raises KeyboardInterrupt in the
    start, but third-party code can swallow it (OpenVINO's model conversion, tracing the
    encoder for an int8 build, goes on after one), and the build would then take its
    minute. Nothing is lost: the node never became ready, and a build's folder is removed
    by the next build (`int8`)."""
    while stop.starting:
        if time.monotonic() - stop.requested_at > START_STOP_GRACE_S:
            print(f'{STOPPED_STARTING}: its start went on {START_STOP_GRACE_S:g} s after the '
                  'stop, so the process ends here', file=sys.stderr, flush=True)
            os._exit(0)
        time.sleep(0.1)


def node_help(executable: str, doc: str, params: Sequence[Param]) -> str:
    """What ``EXECUTABLE --help`` prints: usage, the module's description and every
    parameter with its default."""
    lines = [f'usage: ros2 run activeloc_ros {executable} [--ros-args [-p NAME:=VALUE]... '
             '[--params-file FILE]...]', '', doc.strip(), '',
             'parameters (default; * read-only: set at start-up):']
    for spec in params:
        flag = '*' if spec.read_only else ' '
        lines.append(f'  {spec.name} {flag} ({spec.default!r})')
        lines.append(textwrap.fill(spec.description, 96, initial_indent=' ' * 6,
                                   subsequent_indent=' ' * 6))
    return '\n'.join(lines)


def wants_help(args: Sequence[str]) -> bool:
    """-h or --help among the arguments before ``--ros-args``."""
    ours = list(args)[:list(args).index('--ros-args')] if '--ros-args' in args else args
    return any(a in ('-h', '--help') for a in ours)


def frame_due(timer, due: float) -> bool:
    """Is a paced frame (a replayed camera's, a world's real-time step) due at ``due``
    (monotonic seconds) now? If not, the node's timer sleeps until then (at most 50 ms)
    instead of polling; if so, it comes back in 1 ms for the frame after."""
    wait = due - time.monotonic()
    timer.timer_period_ns = int(min(max(wait, 0.001), 0.05) * 1e9)
    timer.reset()
    return wait <= 0


def lean_executor(context=None):
    """A single-threaded executor with the least work per callback: rclpy's EventsExecutor
    where this rclpy has it (Jazzy's later releases), else its SingleThreadedExecutor, which
    builds a wait set in Python for every callback."""
    try:
        from rclpy.experimental import EventsExecutor
    except ImportError:
        return SingleThreadedExecutor(context=context)
    return EventsExecutor(context=context)


def ros_args_problem(args: list[str]) -> str | None:
    """Why rcl refuses a command line's ROS arguments (an unknown flag, ``-p`` without a
    rule), or None; rclpy raises it from ``init`` as a bare RuntimeError."""
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
    """Ignore Ctrl-C and SIGTERM from now on: the node is gone and the process only ends.
    A stop that comes then (bringup's, when a node that ended by itself is stopped in the
    same moment) has nothing left to stop, but Python, finalising, puts its handlers back to
    the default first, so it would kill the process (exit -2 or -15) in the middle of its
    exit."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)


def run(node_factory: Callable[..., Any], args=None, *,
        on_stop: Callable[[Any], None] | None = None,
        help_text: Callable[[], str] | None = None) -> int:
    """Init, spin and shut down one node the Jazzy way; a project error exits 1 with a message.

    A node that ends by itself sets ``finished``; one that ends because it cannot go on
    (the arm's serial link is gone) also sets ``failure`` to the reason, and the process
    exits 1 with it.

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
    _process_args[:] = process_args
    problem = ros_args_problem(process_args)
    if problem:
        print(f'error: {problem}', file=sys.stderr)
        return 2
    rclpy.init(args=args, signal_handler_options=handler)
    node = executor = None
    try:
        stop.starting = True
        threading.Thread(target=_end_a_start_that_goes_on, args=(stop,), daemon=True).start()
        if stop.requested:            # asked before the handler could end the start
            raise KeyboardInterrupt
        node = node_factory()
        stop.starting = False
        executor = lean_executor()
        executor.add_node(node)
        # A node that ends by itself (a camera at the end of its bag) sets `finished`.
        while rclpy.ok() and not stop.requested and not getattr(node, 'finished', False):
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
            if on_stop is not None and rclpy.ok():
                on_stop(node)
            node.destroy_node()
        rclpy.try_shutdown()
        _process_args.clear()
        ignore_late_stops()
    failure = getattr(node, 'failure', None)
    if failure:
        print(f'error: {failure}', file=sys.stderr)
        return 1
    return 0
