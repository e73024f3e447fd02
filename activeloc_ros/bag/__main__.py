"""
Print a bag's facts, or make a bag cut off by a kill or a full disk readable.

Reading uses the `mcap` library directly, so both a rosbag2 folder (metadata.yaml + .mcap)
and a bare .mcap file work. A bag whose writer died (killed, disk full) has no index and no
metadata.yaml; `reindex` keeps its complete chunks and writes both, as `ros2 bag reindex`
does, and moves the bytes of the chunk the writer left unfinished to `<file>.incomplete`
beside the bag.

    python -m activeloc_ros.bag info PATH
    python -m activeloc_ros.bag reindex PATH
"""
import argparse
from pathlib import Path
import sys

from activeloc_ros.bag.read import bag_facts, format_facts
from activeloc_ros.bag.recover import reindex
from activeloc_ros.errors import SourceError


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m activeloc_ros.bag', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest='command', required=True)
    info = sub.add_parser('info', help='print the facts of a bag (like `ros2 bag info`)')
    info.add_argument('path', type=Path)
    fix = sub.add_parser(
        'reindex', help='make a bag whose recording was cut off (killed, disk full) readable: '
        'keep every complete chunk, write the index and metadata.yaml (in place, like '
        "`ros2 bag reindex`); the unfinished chunk's bytes go to <file>.incomplete")
    fix.add_argument('path', type=Path, help='rosbag2 folder or .mcap file')
    args = parser.parse_args(argv)
    try:
        if args.command == 'info':
            print(format_facts(bag_facts(args.path)))
            return 0
        report = reindex(args.path)
        print('\n'.join(report.lines))
        print(format_facts(bag_facts(args.path)))
        if report.unrecovered:     # a readable bag, but of nothing that was recorded
            print(f'error: nothing could be recovered from {", ".join(report.unrecovered)}:'
                  ' the recording stopped before its first chunk was complete (its bytes '
                  'are kept in the .incomplete file beside it)', file=sys.stderr)
            return 1
        return 0
    except (SourceError, OSError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1


if __name__ == '__main__':
    sys.exit(main())
