"""
Passive benchmark: with the camera fixed, does the map's peak fall on the annotated actor?

Every sequence is streamed once; each frame goes to every method (the perception model
under each requested encoder / ablation, and the baselines). Each is a `closed_loop.Pointer`,
as in the screen benchmark (the model and 'framediff-ego' are the same objects,
`bench.pointers`), and answers with a 14x14 map.
Per frame with ground truth (inside `eval_frames`, from frame `--warmup` on):
- hit: the peak cell's centre lies inside an annotated actor's box grown by one grid cell
  (any actor when several are annotated); the centre baseline uses the image centre itself;
- AUC-Judd (MIT saliency benchmark definition, `metrics.auc_judd`) of the 14x14 map
  against the grid cells holding the actors' box centres.
Baselines: 'random' (a seeded uniform-noise map: the chance level of both scores),
'centre' (a centred Gaussian, sigma = 0.25 of the width/height; AUC only sees its ranking,
which is the distance from the image centre in width/height-normalised units) and
'framediff' (mean absolute difference of consecutive 5x5-blurred grey frames per cell) and
'framediff-ego' (the same with the camera's own motion taken out, `perception.motion`).

`--pan DEG` moves the camera: each frame is shown on the virtual screen (`screen`) and seen
by a camera that pans (and tilts half as far) back and forth within +-DEG, in moves of
`--pan-step` degrees a frame separated by still spells, as the arm moves it; the actors'
boxes are projected into its image. Hits are also split by whether the camera moved since
the previous frame, and the share of peaks on the map's outer ring is reported: with a
still scene behind the actors, a peak that leaves the actors when the camera moves is the
camera's own motion showing through.

    python -m activeloc_ros.bench passive --data DIR [--encoder E ...] [--ablations A ...]
"""
import argparse
from dataclasses import dataclass, field
import json
import math
import sys
import time
from typing import Iterator
import zlib

import numpy as np

from activeloc_ros import data, metrics
from activeloc_ros.bench import (
    add_output_options, add_sequence_options, check_seed, key_values, load_selected, names,
    output_dir)
from activeloc_ros.bench.passive_maps import CentreBias, FrameDiff, GRID, RandomMap
from activeloc_ros.bench.pointers import (
    ABLATIONS as MODEL_ROWS, FrameDiffPointer, ModelPointer)
from activeloc_ros.closed_loop import Pointer, Pointing
from activeloc_ros.errors import ActivelocError, ConfigError, DataError
from activeloc_ros.paths import write_atomic
from activeloc_ros.progress import Progress
from activeloc_ros.world import frame_time, pixel_centre, View

# Paper Table 3 rows of the perception (`bench.pointers.ABLATIONS`); the encoder rows are
# chosen with --encoder here.
ABLATIONS = tuple(name for name, fields in MODEL_ROWS.items() if 'encoder' not in fields)


def model_pointer(encoder: str | None, ablation: str, *, seed: int = 0,
                  extra: dict | None = None) -> ModelPointer:
    """
    The perception model of one row, named model:ENCODER/ABLATION (a paper Table 3 row,
    `bench.pointers.ABLATIONS`), fresh for every sequence as in the screen benchmark.
    """
    if ablation not in ABLATIONS:
        raise ActivelocError(f'unknown ablation {ablation!r}; choose from '
                             f'{", ".join(ABLATIONS)}')
    settings = {'seed': seed, **(extra or {})}
    if encoder:
        settings['encoder'] = encoder
    settings.update(MODEL_ROWS[ablation])
    pointer = ModelPointer('', settings)
    pointer.name = f'model:{pointer.config.encoder}/{ablation}'
    return pointer


class PanningCamera:
    """
    A camera on the virtual screen that moves by itself: pan in moves of `step_deg` a
    frame for `move` frames, then still for `hold` frames, turning back at +-`amplitude_deg`;
    tilt the same at half the size. Deterministic.
    """

    def __init__(self, amplitude_deg: float, *, step_deg: float = 2.0, move: int = 4,
                 hold: int = 4) -> None:
        from activeloc_ros.screen import VirtualScreen
        if not (0 < amplitude_deg < 90 and 0 < step_deg < 90 and move >= 1 and hold >= 0):
            raise ActivelocError('--pan and --pan-step must be > 0 and < 90 degrees')
        self.screen = VirtualScreen()
        self.amplitude, self.step_deg, self.move, self.hold = amplitude_deg, step_deg, move, hold

    def poses(self, n: int) -> list[tuple[float, float]]:
        """(pan, tilt) in degrees of frames 0..n-1."""
        pan, direction, out = 0.0, 1.0, []
        period = self.move + self.hold
        for i in range(n):
            if i > 0 and (i - 1) % period < self.move:
                if abs(pan + direction * self.step_deg) > self.amplitude:
                    direction = -direction
                pan += direction * self.step_deg
            out.append((pan, pan / 2.0))
        return out

    def frames(self, sequence: data.Sequence, *, max_frames: int | None
               ) -> Iterator[tuple[data.Sample, bool, tuple[float, float]]]:
        """
        The sequence as this camera sees it: (sample in camera pixels, moved since the
        previous frame, (pan, tilt) in radians).
        """
        limit = len(sequence) if max_frames is None else min(len(sequence), max_frames)
        poses = self.poses(limit)
        wh = (sequence.width, sequence.height)
        w, h = self.screen.size
        for sample in sequence.frames(max_frames=max_frames):
            pan_deg, tilt_deg = poses[sample.index]
            pan, tilt = math.radians(pan_deg), math.radians(tilt_deg)
            boxes = []
            for b in sample.truth.actors:
                corners = self.screen.project([(b.x, b.y), (b.x + b.w, b.y), (b.x, b.y + b.h),
                                               (b.x + b.w, b.y + b.h)], pan, tilt, wh)
                cx, cy = np.mean(corners, axis=0)
                if np.all(np.isfinite(corners)) and 0 <= cx < w and 0 <= cy < h:
                    x0, y0 = corners.min(axis=0)
                    x1, y1 = corners.max(axis=0)
                    boxes.append(data.Box(x0, y0, x1 - x0, y1 - y0))
            truth = data.FrameTruth(sample.index, boxes[0] if boxes else None, tuple(boxes),
                                    sample.truth.scored)
            moved = sample.index > 0 and poses[sample.index] != poses[sample.index - 1]
            yield data.Sample(sample.index, self.screen.render(sample.image, pan, tilt),
                              truth), moved, (pan, tilt)


@dataclass
class Tally:
    """Per-frame scores of one method on one sequence."""

    hits: list[bool] = field(default_factory=list)
    aucs: list[float] = field(default_factory=list)
    moving: list[bool] = field(default_factory=list)   # the camera moved before the frame
    border: list[bool] = field(default_factory=list)   # the peak is on the map's outer ring
    seconds: float = 0.0
    steps: int = 0

    def summary(self) -> dict:
        hits = np.array(self.hits, bool)
        moving = np.array(self.moving, bool)
        return {'frames': len(self.hits),
                'hit_rate': float(np.mean(self.hits)) if self.hits else float('nan'),
                'hit_rate_moving': float(hits[moving].mean()) if moving.any() else None,
                'hit_rate_still': float(hits[~moving].mean()) if (~moving).any() else None,
                'border_peaks': float(np.mean(self.border)) if self.border else float('nan'),
                'auc_judd': metrics.summarise(self.aucs).mean,
                'ms_per_frame': 1000.0 * self.seconds / self.steps if self.steps else None}


def run_sequence(sequence: data.Sequence, methods: list[Pointer], *, max_frames: int | None,
                 warmup: int, progress: Progress | None = None,
                 frames_out: list | None = None, auc_jitter: bool = False,
                 camera: PanningCamera | None = None) -> tuple[dict[str, Tally], float]:
    """
    Stream one sequence through every method; returns the tallies and the mean chance
    hit rate of its scored frames.

    :param auc_jitter: break AUC ties at random (the MIT code's `jitter`), seeded per
        sequence; off = ties count against the map, as NOTES.md section 5 reads.
    """
    tallies = {m.name: Tally() for m in methods}
    rng = np.random.default_rng(zlib.crc32(sequence.name.encode())) if auc_jitter else None
    for m in methods:
        m.reset(sequence.name)
    chance = []
    image_wh = (sequence.width, sequence.height)
    if camera is None:
        stream = ((s, False, (0.0, 0.0)) for s in sequence.frames(max_frames=max_frames))
    else:
        stream = camera.frames(sequence, max_frames=max_frames)
        image_wh = camera.screen.size
    cell_wh = metrics.cell_size(GRID, image_wh)
    for sample, moved, (pan, tilt) in stream:
        truth = sample.truth
        view = view_of(sample, sequence.fps, pan=pan, tilt=tilt)
        scored = truth.scored and bool(truth.actors) and sample.index >= warmup
        fixations = {}       # per map shape: the model's grid follows its input's aspect
        if scored:
            chance.append(metrics.chance_hit_rate(truth.actors, GRID, image_wh))
        for m in methods:
            start = time.perf_counter()
            pointing = m.locate(view)
            tally = tallies[m.name]
            tally.seconds += time.perf_counter() - start
            tally.steps += 1
            if not scored:
                continue
            heat, point = heat_and_point(pointing, image_wh)
            hit = metrics.is_hit(point, truth.actors, cell_wh=cell_wh)
            if heat.shape not in fixations:
                fixations[heat.shape] = metrics.fixation_map(
                    [b.centre for b in truth.actors], heat.shape, image_wh)
            auc = metrics.auc_judd(heat, fixations[heat.shape], jitter=auc_jitter, rng=rng)
            tally.hits.append(hit)
            tally.aucs.append(auc)
            tally.moving.append(moved)
            row, col = metrics.peak_cell(heat)
            tally.border.append(row in (0, heat.shape[0] - 1) or col in (0, heat.shape[1] - 1))
            if frames_out is not None:
                frames_out.append({'sequence': sequence.name, 'frame': sample.index,
                                   'method': m.name, 'hit': hit, 'auc_judd': auc,
                                   'peak_xy': [round(point[0], 1), round(point[1], 1)]})
        if progress is not None:
            progress.update(note=sequence.name)
    return tallies, float(np.mean(chance)) if chance else float('nan')


def view_of(sample: data.Sample, fps: float, *, pan: float = 0.0, tilt: float = 0.0) -> View:
    """
    What a pointer is shown of a sample: its image, taken at `world.frame_time` by a
    camera at (pan, tilt), radians.
    """
    h, w = sample.image.shape[:2]
    actors = np.array([pixel_centre(b) for b in sample.truth.actors], np.float64)
    return View(sample.image, sample.index, frame_time(sample.index, fps), pan, tilt,
                actors.reshape(-1, 2), None, np.array([w / 2.0, h / 2.0]))


def heat_and_point(pointing: Pointing, image_wh: tuple[int, int]
                   ) -> tuple[np.ndarray, tuple[float, float]]:
    """
    The map and the point a pointer's answer is scored by: a measured map (one with a
    peak) at its peak cell; a prior (the centre's) at the pointer's location; no map at all
    (a first frame) as a uniform map, at its first cell like any flat map.
    """
    heat = pointing.heat
    if heat is None:
        heat = np.full(GRID, 1.0 / (GRID[0] * GRID[1]), np.float32)
    if pointing.peak is None and pointing.location is not None:
        return heat, pointing.location
    return heat, metrics.peak_point(heat, image_wh)


def evaluate(sequences: list[data.Sequence], methods: list[Pointer], *,
             max_frames: int | None = None, warmup: int = 1, quiet: bool = False,
             keep_frames: bool = False, auc_jitter: bool = False,
             camera: PanningCamera | None = None) -> dict:
    """
    Run every method over every sequence; a sequence whose frames turn out bad is
    dropped for all methods and listed under 'skipped'.
    """
    total = sum(len(s) if max_frames is None else min(len(s), max_frames) for s in sequences)
    progress = None if quiet else Progress(total, 'passive')
    per_seq: dict[str, dict[str, Tally]] = {}
    info: dict[str, dict] = {}
    skipped: list[tuple[str, str]] = []
    frames_out: list | None = [] if keep_frames else None
    for seq in sequences:
        mark = len(frames_out) if frames_out is not None else 0
        try:
            tallies, chance = run_sequence(seq, methods, max_frames=max_frames,
                                           warmup=warmup, progress=progress,
                                           auc_jitter=auc_jitter,
                                           frames_out=frames_out, camera=camera)
        except DataError as err:
            skipped.append((seq.name, str(err)))
            if frames_out is not None:
                del frames_out[mark:]
            print(f'skipping {seq.name}: {err}', file=sys.stderr)
            continue
        per_seq[seq.name] = tallies
        info[seq.name] = {'camera': seq.camera_kind, 'chance_hit_rate': chance}
    if progress is not None:
        progress.close()
    results = []
    for m in methods:
        seqs = {}
        hits: list[bool] = []
        aucs: list[float] = []
        moving: list[bool] = []
        border: list[bool] = []
        seconds, steps = 0.0, 0
        for name, tallies in per_seq.items():
            t = tallies[m.name]
            seqs[name] = {**info[name], **t.summary()}
            hits += t.hits
            aucs += t.aucs
            moving += t.moving
            border += t.border
            seconds += t.seconds
            steps += t.steps
        rates = [s['hit_rate'] for s in seqs.values() if s['frames']]
        by_camera = {}
        for kind in data.KIND_ORDER:
            kind_hits = [h for name, tallies in per_seq.items()
                         if info[name]['camera'] == kind for h in tallies[m.name].hits]
            if any(info[name]['camera'] == kind for name in per_seq):
                by_camera[kind] = {'frames': len(kind_hits), 'hit_rate': (
                    float(np.mean(kind_hits)) if kind_hits else float('nan'))}
        row = {'method': m.name, 'frames': len(hits),
               'hit_rate': float(np.mean(hits)) if hits else float('nan'),
               'hit_rate_seq_mean': float(np.mean(rates)) if rates else float('nan'),
               'auc_judd': metrics.summarise(aucs).mean,
               'ms_per_frame': 1000.0 * seconds / steps if steps else None,
               **{k: v for k, v in Tally(hits, aucs, moving, border).summary().items()
                  if k in ('hit_rate_moving', 'hit_rate_still', 'border_peaks')},
               'by_camera': by_camera, 'sequences': seqs}
        if isinstance(m, ModelPointer):
            row.update(encoder=m.config.encoder, ablation=m.name.rpartition('/')[2],
                       config=_plain(m.config))
        results.append(row)
    chance = [i['chance_hit_rate'] for i in info.values()]
    return {'methods': results, 'skipped': skipped,
            'chance_hit_rate_seq_mean': float(np.nanmean(chance)) if chance else float('nan'),
            'frames': frames_out}


def _plain(config: object) -> dict:
    to_dict = getattr(config, 'to_dict', None)
    return dict(to_dict()) if callable(to_dict) else dict(vars(config))


def _pct(value: float) -> str:
    return '-' if value != value else f'{100.0 * value:.1f}'


def markdown(result: dict) -> str:
    """The overall row per method, then hit % / AUC-Judd % per sequence (one row each)."""
    rows = result['methods']
    kinds = [k for k in data.KIND_ORDER if rows and k in rows[0]['by_camera']]
    head = ['method', 'frames', 'hit %', 'hit % (seq mean)', 'AUC-Judd %']
    head += [f'hit % {k}' for k in kinds]
    panned = any(r.get('hit_rate_moving') is not None for r in rows)
    if panned:
        head += ['hit % camera moved', 'hit % camera still']
    head += ['peaks on border %', 'ms/frame']
    lines = ['| ' + ' | '.join(head) + ' |', '|---|' + '---:|' * (len(head) - 1)]
    for r in rows:
        ms = '-' if r['ms_per_frame'] is None else f'{r["ms_per_frame"]:.1f}'
        cells = [r['method'], str(r['frames']), _pct(r['hit_rate']),
                 _pct(r['hit_rate_seq_mean']), _pct(r['auc_judd'])]
        cells += [_pct(r['by_camera'][k]['hit_rate']) for k in kinds]
        if panned:
            cells += [_pct(r['hit_rate_moving'] if r['hit_rate_moving'] is not None
                           else float('nan')),
                      _pct(r['hit_rate_still'] if r['hit_rate_still'] is not None
                           else float('nan'))]
        cells += [_pct(r['border_peaks']), ms]
        lines.append('| ' + ' | '.join(cells) + ' |')
    names = list(rows[0]['sequences']) if rows else []
    if names:
        first = rows[0]['sequences']
        lines += ['', 'Per sequence: hit % / AUC-Judd %; chance = hit % of a uniformly random '
                  'cell', '',
                  '| sequence | camera | frames | chance | '
                  + ' | '.join(r['method'] for r in rows) + ' |',
                  '|---|---|' + '---:|' * (len(rows) + 2)]
        for n in names:
            cells = [n, first[n]['camera'], str(first[n]['frames']),
                     _pct(first[n]['chance_hit_rate'])]
            cells += [f'{_pct(r["sequences"][n]["hit_rate"])} / '
                      f'{_pct(r["sequences"][n]["auc_judd"])}' for r in rows]
            lines.append('| ' + ' | '.join(cells) + ' |')
    for name, reason in result['skipped']:
        lines.append(f'\nskipped {name}: {reason}')
    return '\n'.join(lines)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog='python -m activeloc_ros.bench passive',
        description='Fixed camera: hit rate of the map peak on the annotated actor and '
                    'AUC-Judd of the 14x14 map, for the perception model and the random, '
                    'centre and frame-differencing baselines.')
    add_sequence_options(p)
    p.add_argument('--encoder', nargs='+', metavar='NAME',
                   help='encoder(s) of the model, one row each (default: the config default)')
    p.add_argument('--ablations', nargs='+', metavar='NAME', default=['full'],
                   help=f'model variants, one row each: {", ".join(ABLATIONS)} or all '
                        '(default: full)')
    p.add_argument('--set', nargs='+', action='extend', metavar='KEY=JSON', default=[],
                   help='extra PerceptionConfig fields for every model row, e.g. lr=1e-4')
    p.add_argument('--no-model', action='store_true', help='baselines only')
    p.add_argument('--pan', type=float, default=0.0, metavar='DEG',
                   help='move the camera: the frames on the virtual screen, seen by a camera '
                        'panning within +-DEG (tilting half as far); 0 = the still camera '
                        'of the source (default)')
    p.add_argument('--pan-step', type=float, default=2.0, metavar='DEG',
                   help='with --pan, degrees the camera turns a frame while it moves '
                        '(default 2: 20 deg/s at 10 frames/s)')
    p.add_argument('--warmup', type=int, default=1, metavar='N',
                   help='frames not scored at the start of each sequence (default 1)')
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--auc-jitter', action='store_true',
                   help='break AUC-Judd ties at random (MIT code default); off: ties count '
                        'against the map, so a saturated one-hot map scores 0.5 on a miss')
    add_output_options(p, 'write passive.json (with per-frame scores) and passive.md there')
    return p


def build_methods(args: argparse.Namespace) -> list[Pointer]:
    methods: list[Pointer] = [RandomMap(args.seed), CentreBias(), FrameDiff(),
                              FrameDiffPointer('framediff-ego')]
    if args.no_model:
        return methods
    ablations = names(args.ablations)
    if 'all' in ablations:
        ablations = list(ABLATIONS)
    extra = key_values(args.set, '--set')
    for encoder in names(args.encoder) or [None]:
        for ablation in ablations:
            methods.append(model_pointer(encoder, ablation, seed=args.seed, extra=extra))
    return methods


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    if args.max_frames is not None and args.max_frames < 1:
        print('--max-frames must be >= 1', file=sys.stderr)
        return 2
    try:
        check_seed(args.seed)
        if args.warmup < 0:
            raise ConfigError('--warmup must be >= 0')
        root, sequences, skipped = load_selected(args)
        methods = build_methods(args)
        camera = PanningCamera(args.pan, step_deg=args.pan_step) if args.pan else None
        out = output_dir(args.out) if args.out else None
    except ActivelocError as err:
        print(f'error: {err}', file=sys.stderr)
        return 2
    for name, reason in skipped:
        print(f'skipping {name}: {reason}', file=sys.stderr)
    if not sequences:
        print(f'error: no usable sequence under {root}', file=sys.stderr)
        return 1
    try:
        result = evaluate(sequences, methods, max_frames=args.max_frames,
                          warmup=args.warmup, quiet=args.quiet, keep_frames=bool(args.out),
                          auc_jitter=args.auc_jitter, camera=camera)
    except ActivelocError as err:
        print(f'error: {err}', file=sys.stderr)
        return 2
    result['skipped'] = skipped + result['skipped']
    if result['methods'] and not any(row['frames'] for row in result['methods']):
        print(f'error: no frame was scored: --warmup {args.warmup} leaves none of the '
              'annotated frames', file=sys.stderr)
        return 1
    result['settings'] = {'data': str(root), 'max_frames': args.max_frames,
                          'warmup': args.warmup, 'seed': args.seed, 'grid': list(GRID),
                          'auc_jitter': args.auc_jitter, 'set': args.set,
                          'pan_deg': args.pan, 'pan_step_deg': args.pan_step}
    table = markdown(result)
    if args.json:
        for row in result['methods']:
            print(json.dumps({**row, 'skipped': result['skipped'],
                              'settings': result['settings']}))
    else:
        print(table)
    if out is not None:
        write_atomic(out / 'passive.json', json.dumps(result, indent=1) + '\n')
        write_atomic(out / 'passive.md', table + '\n')
    return 0
