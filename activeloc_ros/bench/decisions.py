"""
The verdicts on the defaults, kept as data (docs/decisions.yaml) and rendered to a page.

    python -m activeloc_ros.bench decisions add out/cmp/x/compare.json --candidate 1 \\
        --setting motion --value abs_sigmoid --against sigmoid --set synthetic --decision kept
    python -m activeloc_ros.bench decisions render          # docs/decisions.md from the data
    python -m activeloc_ros.bench decisions render --check  # exit 1 if the page is stale

`add` takes its figures from a `bench compare` result (compare.json): the mean paired
difference, its 95% interval, on how many sequences the candidate was lower, the verdict,
the command, the CPU and the date, so a row is never typed by hand. A trial appends a row;
nothing is rewritten.
"""
import argparse
import json
from pathlib import Path
import sys

import yaml

from activeloc_ros.errors import ActivelocError, ConfigError
from activeloc_ros.paths import write_atomic

DOCS = Path(__file__).resolve().parents[2] / 'docs'
DATA = DOCS / 'decisions.yaml'
PAGE = DOCS / 'decisions.md'
SETS = ('real', 'synthetic')
FIELDS = ('setting', 'default', 'candidate', 'set', 'difference', 'interval', 'lower_on',
          'verdict', 'decision', 'command', 'date', 'cpu', 'commit', 'note')
VERDICTS = ('better', 'worse', 'no difference')     # the candidate's, as compare says it


def load(path: Path = DATA) -> dict:
    """The data: a preamble and the rows, each checked (ConfigError names the row)."""
    try:
        content = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f'{path}: cannot be read: {exc}') from exc
    rows = content.get('rows') if isinstance(content, dict) else None
    if not isinstance(rows, list):
        raise ConfigError(f'{path}: needs a mapping with a list of rows')
    for i, row in enumerate(rows, 1):
        problem = row_problem(row)
        if problem:
            raise ConfigError(f'{path}, row {i}: {problem}')
    return content


def dump(content: dict, old_text: str = '') -> str:
    """The data file's text: `old_text`'s leading comment lines, then `content`."""
    head = ''.join(line + '\n' for line in old_text.splitlines() if line.startswith('#'))
    return head + yaml.safe_dump(content, sort_keys=False, allow_unicode=True, width=100)


def row_problem(row) -> str | None:
    if not isinstance(row, dict):
        return 'not a mapping'
    missing = [f for f in FIELDS if f not in row and f != 'note']
    unknown = [f for f in row if f not in FIELDS]
    if missing or unknown:
        return f'missing {missing}, unknown {unknown}'
    if row['set'] not in SETS or row['verdict'] not in VERDICTS:
        return f'set must be one of {SETS} and verdict one of {VERDICTS}'
    low, high = row['interval']
    if not low <= row['difference'] <= high:
        return 'the difference lies outside its interval'
    if (row['verdict'] == 'no difference') != (low <= 0 <= high):
        return 'the verdict does not match the interval'
    return None


def row_from_compare(result: dict, side: int, **fields) -> dict:
    """
    A row from a compare.json `result`: its comparison of candidate side `side` (1 = the
    first) with the base; `fields` the row's other fields.
    """
    try:
        comparison = next(c for c in result['comparisons'] if c['candidate'] == side)
    except (KeyError, StopIteration):
        raise ConfigError(f'the result has no candidate {side}') from None
    settings = result.get('settings', {})
    for key in ('command', 'date', 'cpu'):
        if key not in settings and fields.get(key) is None:
            raise ConfigError(f'the result does not say its {key} (made before compare '
                              f'recorded it): give --{key}')
    row = {'setting': fields['setting'], 'default': fields['default'],
           'candidate': fields['candidate'], 'set': fields['set'],
           'difference': round(comparison['mean'], 2),
           'interval': [round(comparison['low'], 2), round(comparison['high'], 2)],
           'lower_on': f'{comparison["wins"]}/{len(result["sequences"])}',
           'verdict': comparison['verdict'], 'decision': fields['decision'],
           'command': fields.get('command') or settings['command'],
           'date': fields.get('date') or settings['date'],
           'cpu': fields.get('cpu') or settings['cpu'],
           'commit': fields.get('commit') or settings.get('commit', 'unknown')}
    if fields.get('note'):
        row['note'] = fields['note']
    return row


def render(content: dict) -> str:
    """
    The page: the preamble, then one table of every row (the candidate's difference
    from the default), then each row's command, date, CPU and note.
    """
    rows = content['rows']
    lines = ['# Decisions on the defaults', '',
             '<!-- rendered from decisions.yaml by `python -m activeloc_ros.bench decisions '
             'render`; edit the data, not this page -->', '',
             content.get('preamble', '').strip(), '',
             '| # | setting | default | candidate | set | candidate minus default, deg '
             '[95%] | lower on | verdict | decision |', '|---:|---|---|---|---|---|---:|---|---|']
    for i, r in enumerate(rows, 1):
        low, high = r['interval']
        lines.append(f'| {i} | `{r["setting"]}` | {r["default"]} | {r["candidate"]} | '
                     f'{r["set"]} | {r["difference"]:+.2f} [{low:+.2f}, {high:+.2f}] | '
                     f'{r["lower_on"]} | {r["verdict"]} | {r["decision"]} |')
    lines += ['', '## How each row was measured', '']
    for i, r in enumerate(rows, 1):
        lines.append(f'{i}. `{r["command"]}`; {r["date"]}, {r["cpu"]}, at {r["commit"]}.'
                     + (f' {r["note"].strip()}' if r.get('note') else ''))
    return '\n'.join(lines) + '\n'


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='python -m activeloc_ros.bench decisions',
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest='action', required=True)
    add = sub.add_parser('add', help='append a verdict from a compare.json')
    add.add_argument('result', type=Path, help='a `bench compare` compare.json')
    add.add_argument('--candidate', type=int, default=1,
                     help='which candidate of the result (1 = the first)')
    add.add_argument('--setting', required=True, help='the setting(s) judged')
    add.add_argument('--value', required=True, dest='default',
                     help='the default value (the base side)')
    add.add_argument('--against', required=True, dest='candidate_value',
                     help='the value the candidate side had')
    add.add_argument('--set', required=True, choices=SETS, dest='scene_set')
    add.add_argument('--decision', required=True, help='what it decided for the default')
    add.add_argument('--note', default='')
    for key in ('command', 'date', 'cpu', 'commit'):
        add.add_argument(f'--{key}', dest=f'given_{key}',
                         help=f'the {key}, where the result does not hold it')
    add.add_argument('--data', type=Path, default=DATA)
    show = sub.add_parser('render', help='write docs/decisions.md from the data')
    show.add_argument('--check', action='store_true',
                      help='write nothing; exit 1 if the page differs from the data')
    show.add_argument('--data', type=Path, default=DATA)
    show.add_argument('--page', type=Path, default=PAGE)
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        content = load(args.data)
        if args.action == 'add':
            try:
                result = json.loads(args.result.read_text())
            except (OSError, ValueError) as exc:
                raise ConfigError(f'{args.result}: cannot be read: {exc}') from exc
            row = row_from_compare(
                result, args.candidate, setting=args.setting, default=args.default,
                candidate=args.candidate_value, set=args.scene_set, decision=args.decision,
                note=args.note, command=args.given_command, date=args.given_date,
                cpu=args.given_cpu, commit=args.given_commit)
            problem = row_problem(row)
            if problem:
                raise ConfigError(f'the new row: {problem}')
            content['rows'].append(row)
            write_atomic(args.data, dump(content, args.data.read_text()))
            print(f'added row {len(content["rows"])} to {args.data}; render the page '
                  'with `python -m activeloc_ros.bench decisions render`')
            return 0
        page = render(content)
        if args.check:
            current = args.page.read_text() if args.page.is_file() else ''
            if current != page:
                print(f'{args.page} is stale: run python -m activeloc_ros.bench decisions '
                      'render', file=sys.stderr)
                return 1
            return 0
        write_atomic(args.page, page)
        print(f'wrote {args.page} ({len(content["rows"])} rows)')
        return 0
    except ActivelocError as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
