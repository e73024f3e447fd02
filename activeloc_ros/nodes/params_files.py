"""
The params files and ``-p`` rules a node is given, read as rcl reads them.

rcl passes over some mistakes in silence: a value of the wrong type in a later file
(``kp: 'fast'``) leaves the earlier value in place, keys no node declares and sections
naming no node are never looked at. Each of these is found here, naming the file, the
section and the key. (rclpy's ``parameter_dict_from_yaml_file`` reads ``1e-6`` as a string
where rcl reads a double, hence `_RclLoader`.)
"""
import difflib
import functools
from pathlib import Path
import re
from typing import Any, Iterable, Mapping, Sequence

from rclpy.parameter import Parameter
import yaml

from activeloc_ros.checks import Param
from activeloc_ros.errors import ConfigError
from activeloc_ros.paths import NODE_NAMES   # a params file section names one, or /**


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
    """
    (name, value text) of the command-line pair ``-p name:=value`` (or ``--param``), else
    None. rcl applies a rule without a node prefix (``node:name:=``) to every node of the
    process.
    """
    if flag in ('-p', '--param') and item is not None and ':=' in item:
        return item.partition(':=')[::2]
    return None


def cli_param_rules(args: Iterable[str] | None) -> list[tuple[str, str]]:
    """The ``-p name:=value`` rules of a command line, as (name, value text)."""
    args = list(args or [])
    return [rule for rule in map(cli_param_rule, args, args[1:]) if rule]


def undeclared(name: str, declared: Iterable[str]) -> bool:
    """
    Whether a ``-p`` rule for ``name`` sets a parameter that a node declaring ``declared``
    (and rclpy's own) does not have; a node-prefixed rule is rcl's to route.
    """
    return ':' not in name and name not in {*declared, *BUILTIN_PARAMS}


def unknown_cli_params(args: Iterable[str] | None, declared: Iterable[str], *,
                       unknown: str = 'no such parameter') -> list[str]:
    """
    Each ``-p`` rule naming a parameter that is not in ``declared`` (nor rclpy's), with
    the nearest declared name: the node would ignore it, silently.
    """
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
    """
    Why a params file's `content` (parsed YAML) is wrong for `node`; empty when fine.

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
def _declared_keys() -> frozenset[str]:
    """
    Every parameter some node of the package declares: the keys a shared /** section
    may hold for other nodes.
    """
    from activeloc_ros.graph_plan import node_params
    from activeloc_ros.paths import NODE_NAMES
    return frozenset(p.name for node in NODE_NAMES for p in node_params(node))


# rclpy's own parameters of every node, which a params file may set too
BUILTIN_PARAMS = {'use_sim_time': Parameter.Type.BOOL,
                  'start_type_description_service': Parameter.Type.BOOL}


def files_problems(node_name: str, params: Sequence[Param], files: Iterable[str]) -> list[str]:
    """
    Every problem of the params `files` for the node `node_name` declaring `params`
    (see ``params_file_problems``), each naming its file.
    """
    declared = {**BUILTIN_PARAMS, **{p.name: _declared_type(p.default) for p in params}}
    problems = []
    for path in files:
        try:
            content = load_params_file(path)
        except (OSError, yaml.YAMLError) as exc:
            problems.append(f'{path}: cannot be read: {exc}')
            continue
        problems += [f'{path}: {p}' for p in params_file_problems(
            content, node_name, declared, _declared_keys())]
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
