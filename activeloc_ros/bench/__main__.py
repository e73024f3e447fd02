"""Entry point of the benchmarks: one sub-command per benchmark, each in its own module."""
import importlib
import sys

COMMANDS = {
    'perception': ('activeloc_ros.bench.perception', 'per-frame cost of the perception model'),
    'passive': ('activeloc_ros.bench.passive',
                'does the map peak fall on the actor (fixed camera)'),
    'screen': ('activeloc_ros.bench.screen',
               'projected-screen experiment, closed loop (paper Table 2)'),
    'tracking': ('activeloc_ros.bench.tracking',
                 'simulated active tracking, mobile base (paper Tables 1 and 3)'),
    'tracking-pair': ('activeloc_ros.bench.tracking_pair',
                      'two saved tracking runs, episode by episode: better, or luck'),
    'compare': ('activeloc_ros.bench.compare',
                'selection protocol: is a configuration better than another, or luck'),
    'decisions': ('activeloc_ros.bench.decisions',
                  'the verdicts on the defaults: append one from a compare, render the page'),
    'scenes': ('activeloc_ros.bench.scenes', 'generate synthetic static-camera sequences'),
    'graph-check': ('activeloc_ros.bench.graph_check',
                    'does the ROS graph in lockstep move the camera as the benchmark does'),
}


def usage() -> str:
    lines = ['usage: python -m activeloc_ros.bench COMMAND [options]', '', 'commands:']
    lines += [f'  {name:<12} {text}' for name, (_, text) in COMMANDS.items()]
    lines += ['', 'Each command has its own --help.']
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ('-h', '--help'):
        print(usage())
        return 0
    if argv[0] not in COMMANDS:
        print(f'unknown command {argv[0]!r}\n\n{usage()}', file=sys.stderr)
        return 2
    module = importlib.import_module(COMMANDS[argv[0]][0])
    return module.main(argv[1:])


if __name__ == '__main__':
    sys.exit(main())
