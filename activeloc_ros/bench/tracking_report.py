"""
Report `bench tracking`'s episodes: the means, their intervals and the tables.

Table 1 (and Table 3 on the room scene) in the paper's form, each recall with its 95%
interval over episodes; ours' recall against every other method's, paired by episode (the
same episode seed: the same scene, person and paths); and where each method's location
was when it was not on the person, by what the camera saw there (`TrackingWorld.kind_at`).
"""
from collections import Counter
import csv
import io
import math
from pathlib import Path

import numpy as np

from activeloc_ros.bench import protocol, save_png
from activeloc_ros.tracking.reward import LOST_CAUSES
from activeloc_ros.tracking.scenes import PAPER_NAMES

SCORES = ('recall', 'precision', 'precision_relaxed', 'episode_length', 'reward', 'success',
          'aae_deg', 'in_view', 'distance_m', 'on_target', 'distance_error_m')

# Paper Table 1, the Ours row: (recall, precision, relaxed precision) per scene. Its columns
# are SnowVillage, DuelingRoom, UrbanCity, ParkingLot; DuelingRoom's is Table 3's full model.
PAPER_OURS = {'snow': (0.68, 0.16, 0.36), 'room': (0.85, 0.26, 0.41),
              'urban': (0.75, 0.14, 0.40), 'parking': (0.49, 0.23, 0.46)}
RESAMPLES = 10000      # bootstrap draws of an interval, from a seed of its own (0)


def summarise(runs: list[dict], methods: list[str], scenes: list[str]) -> dict:
    """Per method and scene, the means over its episodes (failed runs are listed apart)."""
    failed = [r for r in runs if 'error' in r]
    rows = []
    for method in methods:
        per_scene = {}
        for scene in scenes:
            done = [r for r in runs if r['method'] == method and r['scene'] == scene
                    and 'error' not in r]
            if not done:
                continue
            per_scene[scene] = {k: _mean([r['scores'][k] for r in done]) for k in SCORES}
            per_scene[scene]['episodes'] = len(done)
            per_scene[scene]['compute_ms'] = float(np.mean([r['compute_ms'] for r in done]))
            per_scene[scene]['lost'] = {c: sum(r['lost'] == c for r in done) for c in LOST_CAUSES}
            per_scene[scene]['recall_95'] = interval([r['scores']['recall'] for r in done])
            per_scene[scene]['off_target'] = dict(sum(
                (Counter(r.get('off_target', {})) for r in done), Counter()).most_common())
        rows.append({'method': method, 'scenes': per_scene})
    return {'methods': rows, 'scenes': scenes,
            'failed': [{k: r[k] for k in ('method', 'scene', 'episode', 'error')}
                       for r in failed],
            'episodes': [{k: r.get(k) for k in ('method', 'scene', 'episode', 'scores', 'lost',
                                                'off_target', 'rewards')}
                         for r in runs if 'error' not in r]}


def interval(values: list[float]) -> tuple[float, float]:
    """Return the 95% percentile-bootstrap interval of the mean of ``values``."""
    draws = np.random.default_rng(0).choice(np.asarray(values, float),
                                            size=(RESAMPLES, len(values)))
    low, high = np.percentile(draws.mean(axis=1), [2.5, 97.5])
    return float(low), float(high)


def paired(result: dict, method: str, other: str, scene: str | None, key: str = 'recall'):
    """
    Compare ``method`` with ``other`` on ``scene`` (None: every scene), episode by episode.

    Return the mean of method minus other, its 95% interval (a paired bootstrap over the
    episodes both ran, `protocol.compare`), the episodes where ``method`` scored higher and
    how many there were; None when they share no episode.
    """
    def scores(name: str) -> dict[str, dict[int, float]]:
        return {f'{e["scene"]}/{e["episode"]}': {0: e['scores'][key]}
                for e in result['episodes']
                if e['method'] == name and scene in (None, e['scene'])}
    base, candidate = scores(other), scores(method)
    if not set(base) & set(candidate):
        return None
    c = protocol.compare(base, candidate, resamples=RESAMPLES)
    higher = sum(d > 0 for d in c.per_sequence.values())
    return c.mean, c.low, c.high, higher, len(c.per_sequence)


def _mean(values: list[float]) -> float:
    """
    Average over the episodes that have the score.

    A method without boxes has no distance error; nan when none has.
    """
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def _cell(s: dict | None) -> str:
    if s is None:
        return '-'
    low, high = s['recall_95']
    return (f'{s["recall"]:.2f} [{low:.2f}, {high:.2f}] | {s["precision"]:.2f} '
            f'({s["precision_relaxed"]:.2f})')


def table(result: dict, methods: list[str], scenes: list[str], *, title: str) -> str:
    head = ' | '.join(f'{s} ({PAPER_NAMES[s]}) recall [95%] | precision (relaxed)'
                      for s in scenes)
    lines = [f'## {title}', '', f'| method | {head} |',
             '|---|' + '---:|---:|' * len(scenes)]
    for row in result['methods']:
        if row['method'] in methods and row['scenes']:
            lines.append(f'| {row["method"]} | '
                         + ' | '.join(_cell(row['scenes'].get(s)) for s in scenes) + ' |')
    if title.startswith('Table 1'):
        lines.append('| ours, paper (Unreal) | ' + ' | '.join(
            f'{PAPER_OURS[s][0]:.2f} | {PAPER_OURS[s][1]:.2f} ({PAPER_OURS[s][2]:.2f})'
            for s in scenes) + ' |')
        lines.append('| AD-VAT+, SmartTarget-RL, RandomTarget-RL | '
                     + ' | '.join('reported in Unreal, not comparable | -' for _ in scenes)
                     + ' |')
    lines += ['', 'episode length, accumulated reward, success rate, mean |bearing| (deg), in '
              'view (%), median distance to the person (m; the goal is 2.5), the share of '
              'locations on the person (inside its true box, %), the median error of the '
              "distance the forward rule reads from the method's box (m), ms per step:", '',
              '| method | scene | length | reward | success | bearing | in view | distance '
              '| on target | distance error | ms | lost: pinned, hidden, out of view, other |',
              '|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|']
    for row in result['methods']:
        if row['method'] not in methods:
            continue
        for scene in scenes:
            s = row['scenes'].get(scene)
            if s is not None:
                lines.append(f'| {row["method"]} | {scene} | {s["episode_length"]:.0f} | '
                             f'{s["reward"]:.1f} | {100 * s["success"]:.0f}% | '
                             f'{s["aae_deg"]:.1f} | {100 * s["in_view"]:.0f} | '
                             f'{s["distance_m"]:.1f} | {_number(100 * s["on_target"], 0)} | '
                             f'{_number(s["distance_error_m"], 2)} | {s["compute_ms"]:.0f} | '
                             + ', '.join(str(s['lost'][c]) for c in LOST_CAUSES) + ' |')
    return '\n'.join(lines + _pairs(result, methods, scenes) + _off_target(result, methods,
                                                                           scenes)) + '\n'


def _pairs(result: dict, methods: list[str], scenes: list[str]) -> list[str]:
    """Set the first method's recall against each other's, paired by episode."""
    lines = []
    for other in methods[1:]:
        cells = [paired(result, methods[0], other, s) for s in scenes]
        if any(cells):
            lines.append(f'| {other} | ' + ' | '.join(
                '-' if c is None else f'{c[0]:+.2f} [{c[1]:+.2f}, {c[2]:+.2f}], {c[3]}/{c[4]}'
                for c in cells) + ' |')
    if not lines:
        return []
    return ['', f"{methods[0]}: recall minus each method's, paired by episode [95% "
            'interval], and the episodes where it is higher:', '',
            f'| against | {" | ".join(scenes)} |', '|---|' + '---|' * len(scenes), *lines]


def _off_target(result: dict, methods: list[str], scenes: list[str]) -> list[str]:
    """Show where each method's location was when not on the person: shares of its steps."""
    lines = ['', 'where the location was when it was not on the person, by what the camera '
             'saw there (% of the located steps off the person):', '',
             '| method | scene | off the person | where |', '|---|---|---:|---|']
    for row in result['methods']:
        for scene in scenes:
            s = row['scenes'].get(scene)
            if row['method'] not in methods or s is None or not s.get('off_target'):
                continue
            off = sum(s['off_target'].values())
            lines.append(f'| {row["method"]} | {scene} | {_number(100 * (1 - s["on_target"]), 0)}'
                         ' | ' + ', '.join(f'{kind} {100 * n / off:.0f}'
                                           for kind, n in s['off_target'].items()) + ' |')
    return lines if len(lines) > 5 else []


def _number(value: float, digits: int) -> str:
    return f'{value:.{digits}f}' if math.isfinite(value) else '-'


def to_csv(result: dict) -> str:
    out = io.StringIO()
    w = csv.writer(out)
    w.writerow(['method', 'scene', 'episodes', *SCORES, 'compute_ms'])
    for row in result['methods']:
        for scene, s in row['scenes'].items():
            w.writerow([row['method'], scene, s['episodes'],
                        *(f'{s[k]:.4f}' for k in SCORES), f'{s["compute_ms"]:.2f}'])
    return out.getvalue()


def plots(result: dict, out: Path) -> list[Path]:
    """Per scene: recall, precision and relaxed precision of every method (PNG)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    paths = []
    keys = ('recall', 'precision', 'precision_relaxed')
    for scene in result['scenes']:
        rows = [r for r in result['methods'] if scene in r['scenes']]
        if not rows:
            continue
        fig, ax = plt.subplots(figsize=(max(7, 0.7 * len(rows) + 3), 4))
        width = 0.27
        for i, key in enumerate(keys):
            ax.bar(np.arange(len(rows)) + (i - 1) * width,
                   [r['scenes'][scene][key] for r in rows], width, label=key)
        ax.axhline(0, color='black', linewidth=0.6)
        ax.set_xticks(np.arange(len(rows)), [r['method'] for r in rows], rotation=30,
                      ha='right', fontsize=8)
        ax.set_title(f'{scene} ({PAPER_NAMES[scene]}): higher is better')
        ax.legend(fontsize=8)
        paths.append(save_png(fig, out / f'{scene}.png'))
    return paths
