"""
The selection protocol: is a candidate configuration better than a base, or was it luck?

    python -m activeloc_ros.bench compare --base ours --candidate 'ours --set location=peak'
    python -m activeloc_ros.bench compare --base ours-paper --candidate ours mog2

Each side is a method of the screen benchmark (``bench screen --methods``) with its own
``--set``, ``--control`` and ``--params``, or ``saved:FILE[#K]`` (side K of an earlier
compare's compare.json, or ``saved:GLOB#METHOD`` of ``bench screen`` screen.json files, one
per seed). Both sides run on every chosen sequence (the static ones unless told) with every
seed, in lockstep, exactly as ``bench screen`` runs them; a method without randomness runs
once. It prints the paired difference (candidate minus base, mean AAE) per sequence and
over all, with a 95% interval from a bootstrap over sequences with the seeds nested inside
each (``bench.protocol``). With several candidates it also gives the leave-one-sequence-out
estimate of choosing among them. The rule for a default is in docs/protocol.md.
"""
import argparse
import glob
import hashlib
import json
import os
from pathlib import Path
import shlex
import sys
import time

from activeloc_ros import data
from activeloc_ros.bench import (
    add_jobs_option, add_sequence_options, check_seed, key_values, load_selected, output_dir,
    run_jobs)
from activeloc_ros.bench import protocol, screen
from activeloc_ros.bench.methods import (
    controller_for, METHODS, MODEL_METHODS, params_file)
from activeloc_ros.closed_loop import MODES
from activeloc_ros.errors import ActivelocError, ConfigError
from activeloc_ros.paths import write_atomic
from activeloc_ros.progress import Progress
from activeloc_ros.screen import AIM_LIMITS, ScreenConfig, VirtualScreen

SEEDED = (*MODEL_METHODS, 'random')       # the methods whose runs depend on the seed


def _side_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='side', add_help=False, exit_on_error=False)
    p.add_argument('method')
    p.add_argument('--set', nargs='+', action='extend', default=[])
    p.add_argument('--control', nargs='+', action='extend', default=[])
    p.add_argument('--params')
    return p


def parse_side(spec: str) -> dict:
    """
    A side from its words: ``METHOD [--set K=V ...] [--control K=V ...] [--params F]``
    or ``saved:FILE[#K]``. Raises ConfigError.
    """
    if spec.startswith('saved:'):
        return {'label': spec, 'saved': spec[len('saved:'):]}
    try:
        args = _side_parser().parse_args(shlex.split(spec))
    except (argparse.ArgumentError, ValueError) as exc:
        raise ConfigError(f'side {spec!r}: {exc}') from None
    if args.method not in METHODS:
        raise ConfigError(f'side {spec!r}: unknown method {args.method!r}; known: '
                          f'{", ".join(METHODS)}')
    settings, control = params_file(args.params) if args.params else ({}, {})
    settings.update(key_values(args.set, f'side {spec!r}: --set'))
    control.update(key_values(args.control, f'side {spec!r}: --control'))
    controller_for(args.method, control)               # a bad setting fails now
    if args.method in MODEL_METHODS:
        from activeloc_ros.perception.config import PerceptionConfig
        PerceptionConfig.from_dict(settings)
    return {'label': spec, 'method': args.method, 'settings': settings, 'control': control}


def load_saved(where: str, metric: str) -> protocol.Scores:
    """
    The scores of a saved side: ``FILE#K`` (compare.json, side K; default 0) or
    ``GLOB#METHOD`` (screen.json files of ``bench screen``, one per seed).
    """
    path, _, which = where.partition('#')
    files = sorted(glob.glob(path))
    if not files:
        raise ConfigError(f'saved:{where}: no such file')
    scores: protocol.Scores = {}
    for file in files:
        try:
            content = json.loads(Path(file).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ConfigError(f'saved:{where}: cannot read {file}: {exc}') from None
        if 'sides' in content:                   # a compare.json
            sides = content['sides']
            index = int(which or 0)
            if not 0 <= index < len(sides) or content.get('metric') != metric:
                raise ConfigError(f'saved:{where}: {file} has no side {index} of {metric}')
            for seq, runs in sides[index]['scores'].items():
                scores.setdefault(seq, {}).update({int(s): v for s, v in runs.items()})
            continue
        rows = {r['method']: r for r in content.get('methods', [])}
        if which not in rows:
            raise ConfigError(f'saved:{where}: {file} has no method {which!r}; it has '
                              f'{", ".join(rows) or "none"}')
        seed = int(content['settings']['seed'])
        for seq, summary in rows[which]['sequences'].items():
            scores.setdefault(seq, {})[seed] = summary[metric]
    return scores


def _fingerprint() -> str:
    """A hash of the package's code, so a cached run is reused only by the same code."""
    digest = hashlib.sha256()
    root = Path(__file__).resolve().parents[1]
    for path in sorted(root.rglob('*.py')):
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def _run(job: dict) -> dict:
    """One run (screen.run_job), kept in the run cache so a repeated side is not rerun."""
    cache = Path(job.pop('cache'))
    if cache.is_file():
        return {**json.loads(cache.read_text()), 'cached': True}
    result = screen.run_job(job)
    if 'error' not in result:
        result.pop('frames', None)
        write_atomic(cache, json.dumps(result) + '\n')
    return result


def run_sides(sides: list[dict], sequences: list[data.Sequence], seeds: list[int], *,
              common: dict, metric: str, jobs: int, cache_dir: Path, quiet: bool
              ) -> list[protocol.Scores]:
    """
    Every side's scores (``{sequence: {seed: metric}}``), the runs in ``jobs`` worker
    processes. A failed run stops the comparison: a side missing a sequence is no pair.
    """
    threads = max(1, (os.cpu_count() or 1) // jobs)
    code = _fingerprint()
    work = []
    for index, side in enumerate(sides):
        if 'saved' in side:
            continue
        for seed in seeds if side['method'] in SEEDED else seeds[:1]:
            for seq in sequences:
                job = {'path': str(seq.path), 'method': side['method'],
                       'settings': side['settings'], 'control': side['control'],
                       'seed': seed, **common, 'video': ''}
                key = hashlib.sha256(json.dumps([code, job], sort_keys=True).encode())
                work.append({**job, 'threads': threads, 'side': index,
                             'cache': str(cache_dir / f'{key.hexdigest()[:24]}.json')})
    work.sort(key=lambda j: j['method'] not in MODEL_METHODS)   # slow ones first
    frames = {s.name: len(s) if common['max_frames'] is None
              else min(len(s), common['max_frames']) for s in sequences}
    progress = None if quiet else Progress(
        sum(frames[Path(j['path']).name] for j in work), 'compare frames')
    tags = {(j['side'], j['seed'], Path(j['path']).name): j for j in work}
    scores: list[protocol.Scores] = [
        load_saved(s['saved'], metric) if 'saved' in s else {} for s in sides]
    for run in run_jobs(_tagged, list(tags.values()), jobs=jobs):
        if 'error' in run:
            raise ActivelocError(f'{run["method"]} on {run["sequence"]}: {run["error"]}')
        scores[run['side']].setdefault(run['sequence'], {})[run['seed']] = \
            run['summary'][metric]
        if progress is not None:
            progress.update(frames[run['sequence']],
                            note=f'{run["method"]} seed {run["seed"]} on {run["sequence"]}'
                                 + (' (cached)' if run.get('cached') else ''))
    if progress is not None:
        progress.close()
    return scores


def _tagged(job: dict) -> dict:
    side, seed = job.pop('side'), job['seed']
    return {**_run(job), 'side': side, 'seed': seed}


def report(sides: list[dict], scores: list[protocol.Scores], *, metric: str,
           resamples: int) -> tuple[str, dict]:
    """(Markdown, JSON-able result) of every candidate against the base (side 0)."""
    names = sorted(set.intersection(*(set(s) for s in scores)))
    if not names:
        raise ConfigError('the sides have no sequence in common')
    trimmed = [{n: s[n] for n in names} for s in scores]
    means = [protocol.sequence_means(s) for s in trimmed]
    comparisons = [protocol.compare(trimmed[0], s, resamples=resamples) for s in trimmed[1:]]
    labels = ['base'] + [f'cand {i}' for i in range(1, len(sides))]
    lines = [f'{metric}, lower is better; each cell the mean over its seeds', '',
             '| sequence | ' + ' | '.join(labels) + ' | '
             + ' | '.join(f'{lab} - base' for lab in labels[1:]) + ' |',
             '|---|' + '---:|' * (2 * len(sides) - 1)]
    for n in names:
        lines.append(f'| {n} | ' + ' | '.join(f'{m[n]:.2f}' for m in means) + ' | '
                     + ' | '.join(f'{c.per_sequence[n]:+.2f}' for c in comparisons) + ' |')
    lines.append('| **mean** | ' + ' | '.join(
        f'{sum(m.values()) / len(m):.2f}' for m in means) + ' | '
        + ' | '.join(f'{c.mean:+.2f}' for c in comparisons) + ' |')
    lines += ['', f'sides ({len(names)} sequences; seeds per side: '
              + ', '.join(str(max(len(v) for v in s.values())) for s in trimmed) + '):']
    lines += [f'- {lab}: `{side["label"]}`' for lab, side in zip(labels, sides)]
    lines += ['', '| candidate | mean difference | 95% interval | lower on | verdict |',
              '|---|---:|---|---:|---|']
    for lab, c in zip(labels[1:], comparisons):
        lines.append(f'| {lab} | {c.mean:+.2f} | [{c.low:+.2f}, {c.high:+.2f}] | '
                     f'{c.wins}/{len(names)} | {c.verdict} |')
    result = {'metric': metric, 'sequences': names, 'resamples': resamples,
              'sides': [{'label': s['label'], 'scores': {n: {str(k): v for k, v in r.items()}
                                                         for n, r in sc.items()}}
                        for s, sc in zip(sides, trimmed)],
              'comparisons': [{'candidate': i + 1, 'per_sequence': c.per_sequence,
                               'mean': c.mean, 'low': c.low, 'high': c.high, 'wins': c.wins,
                               'verdict': c.verdict} for i, c in enumerate(comparisons)]}
    if len(sides) > 2 and len(names) >= 3:
        loo = protocol.leave_one_out(trimmed, resamples=resamples)
        c = loo.against_base
        lines += ['', 'leave one sequence out (choose the side with the lowest mean on the '
                  'others, score it on the one left out):', '',
                  '| left out | chosen | its score | base |', '|---|---|---:|---:|']
        lines += [f'| {n} | {labels[loo.chosen[n]]} | {loo.estimate[n]:.2f} | '
                  f'{means[0][n]:.2f} |' for n in names]
        lines += ['', f'estimate {sum(loo.estimate.values()) / len(names):.2f}, against the '
                  f'base {c.mean:+.2f} [{c.low:+.2f}, {c.high:+.2f}]: {c.verdict}']
        result['leave_one_out'] = {'chosen': loo.chosen, 'estimate': loo.estimate,
                                   'mean': c.mean, 'low': c.low, 'high': c.high,
                                   'verdict': c.verdict}
    return '\n'.join(lines) + '\n', result


def provenance(argv: list[str]) -> dict:
    """The command, date, CPU and commit of a result, for docs/decisions.yaml."""
    import subprocess
    from activeloc_ros.bench.perception import cpu_info, describe_cpu
    try:
        commit = subprocess.run(['git', 'describe', '--always', '--dirty'], capture_output=True,
                                text=True, cwd=Path(__file__).parent, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        commit = ''
    return {'command': shlex.join(['python', '-m', 'activeloc_ros.bench', 'compare', *argv]),
            'date': time.strftime('%Y-%m-%d'), 'cpu': describe_cpu(cpu_info()),
            'commit': commit or 'unknown'}


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog='python -m activeloc_ros.bench compare',
        description='The selection protocol: every side on every sequence and seed of the '
                    'screen benchmark; the paired difference from the base per sequence '
                    'and over all, with a 95%% interval (bootstrap over sequences, seeds '
                    'nested), and with several candidates the leave-one-sequence-out '
                    'estimate. A side: "METHOD [--set K=V ...] [--control K=V ...] '
                    '[--params FILE]" (quoted) or saved:FILE[#K].')
    p.add_argument('--base', required=True, metavar='SIDE', help='the side compared with')
    p.add_argument('--candidate', required=True, nargs='+', action='extend', metavar='SIDE',
                   help='one or more sides (several: also leave-one-sequence-out)')
    p.add_argument('--seeds', nargs='+', type=int, default=[0, 1, 2], metavar='S',
                   help='seeds of the seeded methods (default 0 1 2)')
    add_sequence_options(p)
    p.set_defaults(camera=['static'])
    p.add_argument('--metric', default='aae_deg', choices=('aae_deg', 'pointing_deg'),
                   help='lower is better (default aae_deg)')
    p.add_argument('--mode', choices=MODES, default='lockstep', help='default lockstep')
    p.add_argument('--camera-fps', type=float, default=10.0, metavar='HZ',
                   help="the virtual camera's rate (default 10)")
    p.add_argument('--screen', nargs='+', action='extend', metavar='KEY=VALUE', default=[],
                   help='ScreenConfig fields for both sides')
    p.add_argument('--aim-limits', choices=AIM_LIMITS, default='arm')
    p.add_argument('--resamples', type=int, default=10000, metavar='N',
                   help='bootstrap draws (default 10000)')
    add_jobs_option(p)
    p.add_argument('--out', metavar='DIR', default='out/compare',
                   help='compare.md and compare.json go here, runs in DIR/runs (a cache: '
                        'the same run of the same code is not repeated)')
    p.add_argument('--quiet', action='store_true', help='no progress on stderr')
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        if args.jobs < 1 or args.resamples < 100:
            raise ConfigError('--jobs must be >= 1 and --resamples >= 100')
        if args.max_frames is not None and args.max_frames < 1:
            raise ConfigError('--max-frames must be >= 1')
        for s in args.seeds:
            check_seed(s)
        if len(set(args.seeds)) != len(args.seeds):
            raise ConfigError('--seeds repeats a seed')
        sides = [parse_side(args.base), *(parse_side(c) for c in args.candidate)]
        screen_cfg = key_values(args.screen, '--screen')
        VirtualScreen(ScreenConfig.from_dict(screen_cfg))
        _, sequences, skipped = load_selected(args)
        if not sequences:
            raise ConfigError('no usable sequence: ' + '; '.join(
                f'{n}: {r}' for n, r in skipped))
        out = output_dir(args.out)
        common = {'mode': args.mode, 'latency_ms': 0.0, 'camera_fps': args.camera_fps,
                  'screen': screen_cfg, 'aim_limits': args.aim_limits,
                  'max_frames': args.max_frames}
        started = time.monotonic()
        scores = run_sides(sides, sequences, args.seeds, common=common, metric=args.metric,
                           jobs=args.jobs, cache_dir=out / 'runs', quiet=args.quiet)
        table, result = report(sides, scores, metric=args.metric, resamples=args.resamples)
    except ActivelocError as err:
        print(f'error: {err}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print('\ninterrupted: finished runs are kept in the run cache', file=sys.stderr)
        return 130
    result['settings'] = {**common, 'seeds': args.seeds, 'data': str(args.data or ''),
                          'seconds': round(time.monotonic() - started, 1),
                          **provenance(sys.argv[1:] if argv is None else argv)}
    write_atomic(out / 'compare.json', json.dumps(result, indent=1) + '\n')
    write_atomic(out / 'compare.md', table)
    print(table, end='')
    print(f'\nwrote {out}/compare.md, compare.json; {result["settings"]["seconds"]:.0f} s')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
