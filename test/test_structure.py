"""
The package's structure stays easy to change: no file over 500 lines, a README of at most
300, and the ROS-free side importing no node module. `python test/test_structure.py` prints
every problem.

A node module is one that defines a node (`nodes/*_node.py`, `nodes/recorder.py`): outside
`nodes/` a module should need none of them, only ROS-free parameter lists and configs.
`ALLOWED` lists the one import of that kind kept on purpose; the test fails on a new one,
and on a listed one that is gone.
"""
import ast
from pathlib import Path
import re

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / 'activeloc_ros'
MAX_LINES = 500
MAX_README_LINES = 300
NODE_MODULE = re.compile(r'activeloc_ros\.nodes\.(\w+_node|recorder|\{\w+\}_node)$')

# (importing module, node module): bringup runs the recorder node in its own executor, as
# it runs its monitor, so that a recording holds every message from the first
ALLOWED = {
    ('bringup.py', 'activeloc_ros.nodes.recorder'),
}


def imported_modules(path: Path) -> set[str]:
    """Every module `path` imports, by statement or by a string passed to import_module."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
            names.update(f'{node.module}.{alias.name}' for alias in node.names)
        elif isinstance(node, (ast.Constant, ast.JoinedStr)):
            text = (node.value if isinstance(node, ast.Constant)
                    else ''.join(v.value if isinstance(v, ast.Constant) else
                                 '{' + ast.unparse(v.value) + '}' for v in node.values))
            if isinstance(text, str) and text.startswith('activeloc_ros.nodes.'):
                names.add(text)
    return names


def node_imports() -> set[tuple[str, str]]:
    found = set()
    for path in sorted(PACKAGE.rglob('*.py')):
        where = path.relative_to(PACKAGE).as_posix()
        if where.startswith('nodes/'):
            continue
        found.update((where, name) for name in imported_modules(path)
                     if NODE_MODULE.search(name))
    return found


def problems() -> list[str]:
    out = [f'{path.relative_to(REPO)}: {n} lines (at most {MAX_LINES})'
           for path in sorted(PACKAGE.rglob('*.py'))
           if (n := len(path.read_text().splitlines())) > MAX_LINES]
    readme = len((REPO / 'README.md').read_text().splitlines())
    if readme > MAX_README_LINES:
        out.append(f'README.md: {readme} lines (at most {MAX_README_LINES})')
    found = node_imports()
    out += [f'activeloc_ros/{where} imports the node module {name}'
            for where, name in sorted(found - ALLOWED)]
    out += [f'activeloc_ros/{where} no longer imports {name}: take it off ALLOWED'
            for where, name in sorted(ALLOWED - found)]
    return out


def test_the_structure_has_no_problem():
    assert problems() == []


def test_each_node_declares_the_parameters_of_its_ros_free_module():
    import importlib
    from activeloc_ros.graph_plan import node_params, PARAMS_MODULES
    for node in PARAMS_MODULES:
        module = importlib.import_module(f'activeloc_ros.nodes.{node}_node')
        assert list(module.PARAMS) == node_params(node), node


def test_the_import_check_finds_a_node_module_however_it_is_imported(tmp_path):
    module = tmp_path / 'm.py'
    module.write_text('import importlib\nfrom activeloc_ros.nodes import arm_node\n'
                      "importlib.import_module(f'activeloc_ros.nodes.{n}_node')\n"
                      'from activeloc_ros.nodes.recorder import RecorderNode\n')
    found = {name for name in imported_modules(module) if NODE_MODULE.search(name)}
    assert found == {'activeloc_ros.nodes.arm_node', 'activeloc_ros.nodes.{n}_node',
                     'activeloc_ros.nodes.recorder'}


if __name__ == '__main__':
    found = problems()
    print(*found, f'{len(found)} problems', sep='\n')
