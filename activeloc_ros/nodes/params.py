"""
Typed, described and validated ROS parameters.

Validation is a pure function per parameter (value -> error message or None), registered
before the parameters are declared so values from `params/*.yaml` are validated too. A
``checks.Range`` goes into the descriptor (``floating_point_range`` / ``integer_range``), so
``ros2 param describe`` shows it and rclpy enforces it. The params files a node is given are
checked first (`params_files`).

At run time a parameter either applies at once (the node passes ``on_change``; a whole-set
check ``check_all`` may refuse a combination) or is declared read-only, so that
``ros2 param set`` is refused rather than reported as set and never used.
"""
import math
import sys
import textwrap
from typing import Any, Callable, Sequence

from rcl_interfaces.msg import (
    FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult)
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException

from activeloc_ros.checks import Param, Range, validate
from activeloc_ros.errors import ConfigError
from activeloc_ros.nodes.params_files import (check_params_files, params_files,
                                              unknown_cli_params)

_INT64 = (-2**63, 2**63 - 1)


def descriptor(spec: Param) -> ParameterDescriptor:
    """
    The descriptor of `spec`: description, read-only flag and, for a numeric scalar with
    a ``Range`` check, its range.
    """
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


def declare(node, params: Sequence[Param], *, cli_args: Sequence[str] | None = None,
            use_global_arguments: bool = True,
            check_all: Callable[[dict, set], 'str | None'] | None = None,
            on_change: Callable[[dict, set], None] | None = None) -> dict[str, Any]:
    """
    Declare `params` on `node` with descriptors and validation; return their values.

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

    # the process's arguments, where `process.run` made the node (a node in another
    # context, as bringup --in-process makes them, has none)
    process_args = getattr(node.context, 'args', []) if use_global_arguments else []
    files = params_files(process_args) + params_files(cli_args)
    check_params_files(node, params, files)
    unknown = unknown_cli_params([*process_args, *(cli_args or [])], [p.name for p in params])
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


def node_help(executable: str, doc: str, params: Sequence[Param]) -> str:
    """
    What ``EXECUTABLE --help`` prints: usage, the module's description and every
    parameter with its default.
    """
    lines = [f'usage: ros2 run activeloc_ros {executable} [--ros-args [-p NAME:=VALUE]... '
             '[--params-file FILE]...]', '', doc.strip(), '',
             'parameters (default; * read-only: set at start-up):']
    for spec in params:
        flag = '*' if spec.read_only else ' '
        lines.append(f'  {spec.name} {flag} ({spec.default!r})')
        lines.append(textwrap.fill(spec.description, 96, initial_indent=' ' * 6,
                                   subsequent_indent=' ' * 6))
    return '\n'.join(lines)
