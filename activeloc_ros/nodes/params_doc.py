"""
docs/parameters.md: every node's parameters, made from their declarations.

    python -m activeloc_ros.nodes.params_doc            # write docs/parameters.md
    python -m activeloc_ros.nodes.params_doc --check    # exit 1 if it is stale

The page lists what `ros2 run activeloc_ros NODE --help` prints: each parameter's name,
default, whether it is read-only, and its description. A test fails when it is stale.
"""
import argparse
import importlib
from pathlib import Path
import sys

from activeloc_ros.graph_plan import PARAMS_MODULES
from activeloc_ros.paths import NODE_NAMES, write_atomic

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / 'docs' / 'parameters.md'


def _cell(text: str) -> str:
    return str(text).replace('|', '\\|').replace('\n', ' ')


def render() -> str:
    lines = ['# Parameters', '',
             "<!-- made by `python -m activeloc_ros.nodes.params_doc` from the nodes' "
             'declarations; do not edit -->', '',
             'Every parameter each node declares, with its default. Defaults are the '
             "declarations'; the package's one params file, `params/robot.yaml`, sets what "
             'several nodes must agree on, and a --params file holds what you change (the '
             'YAML wins). Read-only parameters are fixed at '
             'start (`ros2 param set` is refused); the others apply at once. `ros2 run '
             'activeloc_ros NODE --help` prints the same list.', '']
    for node in NODE_NAMES:
        module = importlib.import_module(PARAMS_MODULES[node])
        lines += [f'## {node}_node', '', '| parameter | default | read-only | description |',
                  '|---|---|---|---|']
        for p in module.PARAMS:
            default = repr(p.default).replace(str(ROOT), '<repo>')    # the same on any clone
            lines.append(f'| `{p.name}` | `{_cell(default)}` | '
                         f'{"yes" if p.read_only else ""} | {_cell(p.description)} |')
        lines.append('')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m activeloc_ros.nodes.params_doc',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--check', action='store_true',
                        help='write nothing; exit 1 if the page differs from the declarations')
    parser.add_argument('--page', type=Path, default=PAGE)
    args = parser.parse_args(argv)
    page = render()
    if args.check:
        if not args.page.is_file() or args.page.read_text() != page:
            print(f'{args.page} is stale: run python -m activeloc_ros.nodes.params_doc',
                  file=sys.stderr)
            return 1
        return 0
    write_atomic(args.page, page)
    print(f'wrote {args.page}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
