"""
Set two saved `bench tracking` runs against each other, episode by episode.

Two runs of the same episodes (the same ``--seed`` and ``--episodes``) under two
configurations, or two methods of one run: the candidate's score minus the base's per
scene and over every episode, each with its 95% interval (`tracking_report.paired`)::

    python -m activeloc_ros.bench tracking-pair out/a/tracking.json 'out/b/tracking.json#csrt'

A side is ``FILE`` or ``FILE#METHOD`` (default ``ours``).
"""
import argparse
import json
from pathlib import Path
import sys

from activeloc_ros.bench.tracking_report import paired
from activeloc_ros.errors import ConfigError
from activeloc_ros.tracking.scenes import SCENES


def load_side(side: str) -> tuple[list[dict], str]:
    """Read the episodes of one method from ``FILE[#METHOD]``."""
    path, _, method = side.partition('#')
    method = method or 'ours'
    try:
        episodes = json.loads(Path(path).read_text())['episodes']
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ConfigError(f'{path}: not a bench tracking result ({err})') from err
    mine = [e for e in episodes if e['method'] == method]
    if not mine:
        raise ConfigError(f'{path}: no episodes of {method!r}')
    return mine, method


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='python -m activeloc_ros.bench tracking-pair',
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('base', help='FILE[#METHOD]: a tracking.json, and its method (ours)')
    p.add_argument('candidate', help='FILE[#METHOD]: the side set against the base')
    p.add_argument('--key', default='recall',
                   help='the episode score to compare (default recall; precision, ...)')
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        (base, base_name), (cand, cand_name) = load_side(args.base), load_side(args.candidate)
        if args.key not in base[0]['scores']:
            raise ConfigError(f'no score {args.key!r}; known: {", ".join(base[0]["scores"])}')
    except ConfigError as err:
        print(f'error: {err}', file=sys.stderr)
        return 2
    result = {'episodes': [{**e, 'method': 'base'} for e in base]
              + [{**e, 'method': 'candidate'} for e in cand]}
    scenes = [s for s in SCENES if any(e['scene'] == s for e in base)]
    print(f'{cand_name} ({args.candidate}) minus {base_name} ({args.base}), {args.key}, '
          'paired by episode [95% interval], and the episodes where it is higher:')
    for scene in (*scenes, None):
        c = paired(result, 'candidate', 'base', scene, args.key)
        name = scene or 'all'
        print(f'  {name:<8} ' + ('no episode in common' if c is None else
                                 f'{c[0]:+.3f} [{c[1]:+.3f}, {c[2]:+.3f}], {c[3]}/{c[4]}'))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
