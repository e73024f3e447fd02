"""
The projected-screen benchmark (paper Sec. 4.2, Table 2), closed loop in simulated time.

    python -m activeloc_ros.bench screen --data ../shared/data/sequences --out out/screen

Every method drives the same controller and simulated Braccio through the virtual screen
(``closed_loop.run_episode``). Per sequence and overall (the mean over sequences): AAE
(degrees, to the closest annotated actor), AUC-Judd (the method's map laid on the screen
where the camera looked, against the closest actor's centre; a method that gives only a
point gets a Gaussian of one map cell there), the in-view rate and the pointing error (the
angle from the location the method gave to the nearest actor, on the frames it processed:
its perception alone, without the arm's lag). Writes a Markdown table, a CSV, a JSON file,
one plot per metric and an overlay video per run, all atomically.
"""
import argparse
import csv
import io
import json
import math
import os
from pathlib import Path
import sys
import time
import traceback

import cv2
import numpy as np

from activeloc_ros import data
from activeloc_ros.bench import (
    add_jobs_option, add_output_options, add_sequence_options, check_seed, in_threads,
    key_values, load_selected, names, output_dir, run_jobs, save_png)
from activeloc_ros.bench.methods import (
    CONTROL_OPTIONS, controller_for, make_pointer, METHODS, MODEL_METHODS, params_file,
    PD_PARAMS)
from activeloc_ros.bench.pointers import ModelPointer
from activeloc_ros.bench.time_plots import time_plots
from activeloc_ros.bench.video import (
    commit_video, PendingVideo, run_keeping_results)
from activeloc_ros.closed_loop import FrameRecord, MODES, run_episode, screen_world
from activeloc_ros.errors import ActivelocError, ConfigError, DataError
from activeloc_ros.paths import write_atomic
from activeloc_ros.progress import Progress
from activeloc_ros.screen import AIM_LIMITS, ScreenConfig, VirtualScreen

METRICS = (('aae_deg', 'AAE (deg)', 'lower is better'),
           ('auc_judd', 'AUC-Judd (%)', 'higher is better'),
           ('in_view', 'in view (%)', 'higher is better'),
           ('pointing_deg', 'pointing error (deg)', 'lower is better'))


# -- one run (method x sequence), in a worker process ------------------------------------------

_POINTERS: dict = {}   # per worker process: one pointer per method, its encoder reused


def _pointer(name: str, settings: dict, seed: int):
    key = (name, json.dumps(settings, sort_keys=True), seed)
    if key not in _POINTERS:
        _POINTERS[key] = make_pointer(name, settings, seed)
    return _POINTERS[key]


def run_job(job: dict) -> dict:
    """
    Run one method on one sequence; returns its summary and per-frame records, or the
    reason it failed (a bad sequence is a DataError).
    """
    return in_threads(_run_job, job)


def _run_job(job: dict) -> dict:
    started = time.perf_counter()
    seq = data.load_sequence(job['path'])
    screen = VirtualScreen(ScreenConfig(**job['screen']))
    try:
        pointer = _pointer(job['method'], job['settings'], job['seed'])
        frames = ((s.index, s.image, s.truth) for s in seq.frames(max_frames=job['max_frames']))
        video = None
        if job['video']:
            video = OverlayVideo(Path(job['video']), screen, seq.fps, job['method'])
        try:
            limits = screen if job['aim_limits'] == 'screen' else None
            controller = controller_for(job['method'], job['control'], limits)
            world = screen_world(frames, fps=seq.fps, screen=screen, controller=controller,
                                 camera_fps=job['camera_fps'] or None)
            episode = run_episode(world, pointer, controller=controller, mode=job['mode'],
                                  latency_s=job['latency_ms'] / 1e3, name=seq.name,
                                  on_frame=video.add if video else None)
        except BaseException:
            if video:
                video.abandon()
            raise
        if video:
            video.finish()
    except (DataError, OSError) as err:
        return {'method': job['method'], 'sequence': seq.name, 'error': str(err)}
    except Exception:  # noqa: B902 - one broken run must not cost the others
        return {'method': job['method'], 'sequence': seq.name,
                'error': f'{job["method"]} failed: {traceback.format_exc()}'}
    return {'method': job['method'], 'sequence': seq.name, 'camera': seq.camera_kind,
            'summary': episode.summary(), 'seconds': time.perf_counter() - started,
            'frames': [_frame_row(r) for r in episode.records]}


def _frame_row(r: FrameRecord) -> list:
    return [r.index, round(r.t, 4), round(math.degrees(r.pan), 3),
            round(math.degrees(r.tilt), 3), r.processed, r.scored,
            None if math.isnan(r.aae_deg) else round(r.aae_deg, 3), r.in_view,
            None if math.isnan(r.auc) else round(r.auc, 4),
            None if math.isnan(r.pointing_deg) else round(r.pointing_deg, 3)]


FRAME_COLUMNS = ['index', 't', 'pan_deg', 'tilt_deg', 'processed', 'scored', 'aae_deg',
                 'in_view', 'auc_judd', 'pointing_deg']


class OverlayVideo(PendingVideo):
    """
    The whole screen with the camera's view (yellow), the truth (green) and the
    method's newest location (red), the camera image inset, as H.264 that browsers play.
    """

    def __init__(self, path: Path, screen: VirtualScreen, fps: float, label: str, *,
                 max_width: int = 640):
        super().__init__(path, fps)
        self.screen = screen
        self.label = label
        self.max_width = max_width
        self.inset = None

    def add(self, scene: np.ndarray, record: FrameRecord, camera: np.ndarray | None) -> None:
        h, w = scene.shape[:2]
        scale = min(1.0, self.max_width / w)
        size = (int(round(w * scale)) // 2 * 2, int(round(h * scale)) // 2 * 2)
        frame = cv2.resize(cv2.cvtColor(scene, cv2.COLOR_RGB2BGR), size,
                           interpolation=cv2.INTER_AREA)
        sx, sy = size[0] / w, size[1] / h
        outline = self.screen.view_outline(record.pan, record.tilt, (w, h))
        if len(outline):
            pts = np.round((outline + 0.5) * (sx, sy)).astype(np.int32)
            cv2.polylines(frame, [pts], True, (0, 220, 255), 2)
        if record.truth_xy is not None:
            x, y = record.truth_xy
            cv2.circle(frame, (int((x + 0.5) * sx), int((y + 0.5) * sy)), 7, (0, 255, 0), 2)
        if record.predicted_xy is not None:
            x, y = record.predicted_xy
            cv2.drawMarker(frame, (int((x + 0.5) * sx), int((y + 0.5) * sy)), (0, 0, 255),
                           cv2.MARKER_CROSS, 16, 2)
        if camera is not None:   # else the camera took no picture: keep the last one
            inset_w = size[0] // 4
            self.inset = cv2.resize(cv2.cvtColor(camera, cv2.COLOR_RGB2BGR),
                                    (inset_w, inset_w * camera.shape[0] // camera.shape[1]))
        if self.inset is not None:
            frame[-self.inset.shape[0]:, -self.inset.shape[1]:] = self.inset
        aae = '' if math.isnan(record.aae_deg) else f'  AAE {record.aae_deg:5.1f} deg'
        cv2.putText(frame, f'{self.label}  frame {record.index}{aae}', (6, 18),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        self.write(frame)


# -- the whole benchmark ---------------------------------------------------------------------

def evaluate(sequences: list[data.Sequence], methods: list[str], *, mode: str,
             latency_ms: float = 0.0, camera_fps: float, screen: dict, settings: dict,
             control: dict, seed: int, jobs: int, aim_limits: str = 'arm',
             max_frames: int | None, video_dir: Path | None, quiet: bool) -> dict:
    """Run every method on every sequence (in `jobs` worker processes)."""
    threads = max(1, (os.cpu_count() or 1) // jobs)
    work = []
    for seq in sequences:
        for method in methods:
            video = str(video_dir / seq.name / f'{method}.mp4') if video_dir else ''
            work.append({'path': str(seq.path), 'method': method, 'settings': settings,
                         'seed': seed, 'mode': mode, 'latency_ms': latency_ms,
                         'camera_fps': camera_fps,
                         'screen': screen, 'control': control, 'aim_limits': aim_limits,
                         'max_frames': max_frames, 'video': video, 'threads': threads})
    # the slowest first (resnet50, then the other model methods), so the fast ones fill
    # the gaps at the end
    work.sort(key=lambda j: (j['method'] != 'ours-resnet50', j['method'] not in MODEL_METHODS))
    length = {s.name: len(s) if max_frames is None else min(len(s), max_frames)
              for s in sequences}
    progress = None if quiet else Progress(sum(length[Path(j['path']).name] for j in work),
                                           'screen frames')
    runs = []
    for run in run_jobs(run_job, work, jobs=jobs):
        runs.append(run)
        if progress is not None:
            progress.update(length[run['sequence']],
                            note=f'{run["method"]} on {run["sequence"]}')
    if progress is not None:
        progress.close()
    return summarise(runs, methods, sequences)


def summarise(runs: list[dict], methods: list[str], sequences: list[data.Sequence]) -> dict:
    """Per-method means over the sequences every method completed."""
    failed = {}
    for run in runs:
        if 'error' in run:
            failed.setdefault(run['sequence'], run['error'])
    kept = [s.name for s in sequences if s.name not in failed]
    by_key = {(r['method'], r['sequence']): r for r in runs if 'error' not in r}
    rows = []
    for method in methods:
        per_seq = {name: {**by_key[(method, name)]['summary'],
                          'camera': by_key[(method, name)]['camera']} for name in kept}
        row = {'method': method}
        for key, _, _ in METRICS:
            values = [v[key] for v in per_seq.values() if not math.isnan(v[key])]
            row[key] = float(np.mean(values)) if values else math.nan
        row['compute_ms'] = float(np.mean([v['compute_ms'] for v in per_seq.values()])
                                  ) if per_seq else math.nan
        row['sequences'] = per_seq
        rows.append(row)
    frames = {f'{r["method"]}/{r["sequence"]}': r['frames'] for r in runs if 'error' not in r}
    return {'methods': rows, 'sequences': kept, 'skipped': sorted(failed.items()),
            'frames': frames, 'frame_columns': FRAME_COLUMNS}


def _fmt(key: str, value: float) -> str:
    if value != value:
        return '-'
    return f'{value:.2f}' if key.endswith('_deg') else f'{100 * value:.1f}'


def markdown(result: dict) -> str:
    arrows = {'lower is better': '↓', 'higher is better': '↑'}
    lines = ['| method | ' + ' | '.join(f'{title} {arrows[better]}'
                                        for _, title, better in METRICS) + ' | ms/frame |',
             '|---|' + '---:|' * (len(METRICS) + 1)]
    for row in result['methods']:
        lines.append(f'| {row["method"]} | ' + ' | '.join(
            _fmt(k, row[k]) for k, _, _ in METRICS) + f' | {row["compute_ms"]:.1f} |')
    lines.append(f'\nmeans over {len(result["sequences"])} sequences: '
                 + ', '.join(result['sequences']))
    for key, title, _ in METRICS:
        lines += ['', f'{title} per sequence', '',
                  '| method | ' + ' | '.join(result['sequences']) + ' |',
                  '|---|' + '---:|' * len(result['sequences'])]
        for row in result['methods']:
            lines.append(f'| {row["method"]} | ' + ' | '.join(
                _fmt(key, row['sequences'][n][key]) for n in result['sequences']) + ' |')
    for name, reason in result['skipped']:
        lines.append(f'\nskipped {name}: {reason}')
    return '\n'.join(lines) + '\n'


def to_csv(result: dict) -> str:
    out = io.StringIO()
    w = csv.writer(out)
    w.writerow(['method', 'sequence', *(k for k, _, _ in METRICS), 'compute_ms'])
    for row in result['methods']:
        w.writerow([row['method'], 'mean', *(f'{row[k]:.4f}' for k, _, _ in METRICS),
                    f'{row["compute_ms"]:.2f}'])
        for name in result['sequences']:
            s = row['sequences'][name]
            w.writerow([row['method'], name, *(f'{s[k]:.4f}' for k, _, _ in METRICS),
                        f'{s["compute_ms"]:.2f}'])
    return out.getvalue()


def plots(result: dict, out: Path) -> list[Path]:
    """
    One bar chart per metric (methods x sequences) and one plot over time per sequence
    (PNG, written atomically).
    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    names = result['sequences']
    paths = []
    for key, title, better in METRICS:
        fig, ax = plt.subplots(figsize=(max(8, 1.1 * len(names) + 3), 4.5))
        n = len(result['methods'])
        width = 0.8 / max(n, 1)
        colours = plt.get_cmap('tab20')       # 20 distinct colours: a table has 16 methods
        for i, row in enumerate(result['methods']):
            values = [row['sequences'][s][key] for s in names]
            if not key.endswith('_deg'):
                values = [100 * v for v in values]
            ax.bar(np.arange(len(names)) + i * width - 0.4 + width / 2, values, width,
                   label=row['method'], color=colours(i % colours.N))
        ax.set_xticks(np.arange(len(names)), names, rotation=30, ha='right', fontsize=8)
        ax.set_ylabel(title)
        ax.set_title(f'{title} per sequence ({better})')
        ax.legend(fontsize=7, ncol=2, loc='upper left', bbox_to_anchor=(1.0, 1.0))
        paths.append(save_png(fig, out / f'{key}.png'))
    return paths + time_plots(result, out)


# -- command line ----------------------------------------------------------------------------

def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog='python -m activeloc_ros.bench screen',
        description='The projected-screen experiment (paper Table 2) in simulated time: '
                    'each method steers the simulated Braccio through a virtual screen; '
                    'AAE, AUC-Judd, in-view rate and pointing error per sequence and '
                    'overall.')
    add_sequence_options(p)
    p.add_argument('--methods', nargs='+', metavar='NAME',
                   help=f'methods (default all): {", ".join(METHODS)}')
    p.add_argument('--mode', choices=MODES, default='lockstep',
                   help='lockstep: every frame processed, deterministic (default); realtime: '
                        'frames the method is too slow for are dropped')
    p.add_argument('--latency', type=float, default=0.0, metavar='MS',
                   help='lockstep: each command reaches the arm this long after its frame '
                        'was captured, a fixed compute time (default 0); deterministic, '
                        'unlike realtime, so what a delay costs can be compared run to run')
    p.add_argument('--camera-fps', type=float, default=10.0, metavar='HZ',
                   help="frame rate of the virtual camera (default 10, the bundled bag's; "
                        '0: one picture per scene frame); the scene plays at its own rate')
    p.add_argument('--params', metavar='FILE',
                   help='a ROS 2 params file (as bringup --params): its perception section '
                        'for every model method, its controller section for every method; '
                        '--set and --control win over it')
    p.add_argument('--set', nargs='+', action='extend', metavar='KEY=VALUE', default=[],
                   help='PerceptionConfig fields for every model method, e.g. lr=1e-4')
    p.add_argument('--screen', nargs='+', action='extend', metavar='KEY=VALUE', default=[],
                   help='ScreenConfig fields, e.g. view_fraction=0.3 width=640 height=480')
    p.add_argument('--control', nargs='+', action='extend', metavar='KEY=VALUE', default=[],
                   help='controller settings for every method: ' + ', '.join(
                       PD_PARAMS + CONTROL_OPTIONS) + " (the controller node's names and "
                   'units; kp and kd '
                   "leave an ours-pd-* variant's gains; derivative=error is the paper's "
                   'literal PD)')
    p.add_argument('--aim-limits', choices=AIM_LIMITS, default='arm',
                   help="how far the camera may turn: 'arm' (default) only the arm's joints "
                        "limit it, and past the screen's edge it sees the plain wall, as the "
                        "paper's rig; 'screen' keeps its whole view on the screen")
    add_jobs_option(p)
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--no-video', action='store_true', help='no overlay videos')
    add_output_options(p, 'results, plots and videos go here (default %(default)s)',
                       'out/screen')
    return p


def main(argv: list[str] | None = None) -> int:
    return run_keeping_results(run, parser().parse_args(argv))


def run(args: argparse.Namespace) -> int:
    try:
        if args.max_frames is not None and args.max_frames < 1:
            raise ConfigError('--max-frames must be >= 1')
        if not (args.camera_fps >= 0 and math.isfinite(args.camera_fps)):
            raise ConfigError('--camera-fps must be >= 0')
        if args.jobs < 1:
            raise ConfigError('--jobs must be >= 1')
        if not (args.latency >= 0 and math.isfinite(args.latency)):
            raise ConfigError('--latency must be >= 0 ms')
        if args.latency and args.mode != 'lockstep':
            raise ConfigError('--latency is for --mode lockstep: realtime measures its own')
        check_seed(args.seed)
        methods = names(args.methods) or list(METHODS)
        for m in methods:
            if m not in METHODS:
                raise ConfigError(f'unknown method {m!r}; known: {", ".join(METHODS)}')
        screen = key_values(args.screen, '--screen')
        geometry = VirtualScreen(ScreenConfig.from_dict(screen))
        settings, control = params_file(args.params) if args.params else ({}, {})
        settings.update(key_values(args.set, '--set'))
        control.update(key_values(args.control, '--control'))
        controller_for('ours', control)
        if any(m in MODEL_METHODS for m in methods):
            ModelPointer('check', {'seed': args.seed, **settings})  # weights, settings: now
        root, sequences, skipped = load_selected(args)
        if sequences:
            out = output_dir(args.out)
    except ActivelocError as err:
        print(f'error: {err}', file=sys.stderr)
        return 2
    if not sequences:
        for name, reason in skipped:
            print(f'skipped {name}: {reason}', file=sys.stderr)
        print(f'error: no usable sequence under {root}', file=sys.stderr)
        return 1
    if not args.quiet:
        rate = f'camera {args.camera_fps:g} Hz' if args.camera_fps else 'every scene frame'
        mode = f'{args.mode} + {args.latency:g} ms' if args.latency else args.mode
        print(f'{len(methods)} methods x {len(sequences)} sequences, {mode}, {rate}; '
              f'{geometry.describe()}', file=sys.stderr)
    started = time.monotonic()
    result = evaluate(sequences, methods, mode=args.mode, latency_ms=args.latency,
                      camera_fps=args.camera_fps,
                      screen=screen, settings=settings,
                      control=control, seed=args.seed, jobs=args.jobs,
                      aim_limits=args.aim_limits,
                      max_frames=args.max_frames, quiet=args.quiet,
                      video_dir=None if args.no_video else out / 'videos')
    result['skipped'] = skipped + result['skipped']
    for name, reason in result['skipped']:
        print(f'skipped {name}: {reason}', file=sys.stderr)
    result['settings'] = {
        'data': str(root), 'mode': args.mode, 'latency_ms': args.latency,
        'camera_fps': args.camera_fps,
        'screen': geometry.describe(),
        'screen_config': screen, 'params': args.params, 'set': settings, 'seed': args.seed,
        'control': control, 'aim_limits': args.aim_limits,
        'max_frames': args.max_frames, 'jobs': args.jobs,
        'seconds': round(time.monotonic() - started, 1)}
    table = markdown(result)
    write_atomic(out / 'screen.json', json.dumps(result) + '\n')
    write_atomic(out / 'screen.md', table)
    write_atomic(out / 'screen.csv', to_csv(result))
    pictures = plots(result, out) if result['sequences'] else []
    if not args.no_video:
        for seq in sequences:
            for method in methods:
                commit_video(out / 'videos' / seq.name / f'{method}.mp4')
    if args.json:
        for row in result['methods']:
            print(json.dumps({'method': row['method'],
                              **{k: row[k] for k, _, _ in METRICS},
                              'sequences': {n: {k: v[k] for k, _, _ in METRICS}
                                            for n, v in row['sequences'].items()}}))
    else:
        print(table, end='')
        print(f'\nwrote {out}/screen.md, screen.csv, screen.json, '
              + ', '.join(p.name for p in pictures)
              + ('' if args.no_video else ', videos/<sequence>/<method>.mp4'))
        print(f'{result["settings"]["seconds"]:.0f} s')
    return 0 if result['sequences'] else 1


if __name__ == '__main__':
    raise SystemExit(main())
