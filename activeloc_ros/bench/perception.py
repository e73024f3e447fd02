"""
Per-frame cost of the perception model, online update included.

For each encoder and each encoder-update setting, a fresh process builds a `SurpriseModel` and
steps it through N frames of a video or of a synthetic moving scene, then reports the
per-frame latency (p50/p95 of `step`), frames/s, peak RSS and how RSS grew from the steady
state (after warm-up, the first weight snapshot and a tenth of the run) to the last frame: it
must stay flat over long runs. Frame generation and decoding are outside the timings. Every
report names the CPU, the instruction sets that decide the encoder's arithmetic, and the
precision each row ran in. `--floor` adds each stage's arithmetic floor: its GFLOP (counted
by torch's FlopCounterMode on one frame) over this CPU's peak, measured with a matmul in the
stage's precision, and the ratio of the measured p50 to that floor.

    python -m activeloc_ros.bench perception --encoder efficientnet_lite0 --frames 2000
    python -m activeloc_ros.bench perception --params params/mirrored_border.yaml   # two rows
"""
import argparse
import concurrent.futures
import json
import math
import multiprocessing
import os
from pathlib import Path
import platform
import resource
import sys
import time
from typing import Any, Iterator

import numpy as np

from activeloc_ros.bench import key_values
from activeloc_ros.errors import ActivelocError, ConfigError, SourceError

STAGES = ('preprocess', 'encode', 'predict', 'update')
SHORT = {'preprocess': 'prep', 'encode': 'enc', 'predict': 'pred', 'update': 'upd'}
SHORT_PRECISION = {'float32': 'f32', 'bfloat16': 'bf16', 'int8': 'int8'}


def parse_args(argv: list[str]) -> argparse.Namespace:
    from activeloc_ros.perception.config import ENCODER_NAMES
    p = argparse.ArgumentParser(
        prog='python -m activeloc_ros.bench perception',
        description='Per-frame latency, frames/s and memory of the perception model '
                    '(encode + predict + one online update per frame).')
    p.add_argument('--encoder', action='append', choices=ENCODER_NAMES,
                   help="encoder to measure; repeat for several (default: the model's, vgg19)")
    p.add_argument('--frames', type=int, default=2000, help='frames per run (default 2000)')
    p.add_argument('--warmup', type=int, default=20,
                   help='first frames left out of the latency and RSS-growth figures')
    p.add_argument('--update-encoder', choices=('both', 'yes', 'no'), default='both',
                   help='measure with the encoder trained online, frozen, or both')
    p.add_argument('--video', help='a video file to loop over (default: a synthetic scene)')
    p.add_argument('--size', default='640x480', help='synthetic frame size WxH')
    p.add_argument('--threads', type=int, default=os.cpu_count() or 1,
                   help='torch threads (default: all cores)')
    p.add_argument('--weights', help='encoder weights file (needed for vgg16)')
    p.add_argument('--random-weights', action='store_true',
                   help='random encoder weights: same cost, no weight files needed')
    p.add_argument('--set', nargs='+', action='extend', default=[], metavar='KEY=VALUE',
                   help='any PerceptionConfig field, e.g. --set hidden=256 lr=1e-4')
    p.add_argument('--params', nargs='+', action='extend', default=[], metavar='FILE',
                   help='also the configuration a perception params file sets (e.g. '
                        "params/mirrored_border.yaml): each file's rows beside the default's")
    p.add_argument('--floor', action='store_true',
                   help="also each stage's arithmetic floor (GFLOP over a measured matmul "
                        'peak) and the measured/floor ratio')
    p.add_argument('--feature-gap', action='store_true',
                   help="instead of timing: how far the encoder's features in bfloat16 and "
                        "int8 are from float32's (relative L2 norm) on frames of the "
                        'annotated sequences, none of which calibrated the int8 encoder')
    p.add_argument('--data', help='with --feature-gap: the sequences (default: '
                                  '$ACTIVELOC_DATA or ../shared/data/sequences)')
    p.add_argument('--every', type=int, default=10,
                   help='with --feature-gap: every Nth frame of each sequence (default 10)')
    p.add_argument('--json', action='store_true', help='print the rows as JSON')
    args = p.parse_args(argv)
    if args.every < 1:
        p.error('--every must be at least 1')
    if args.frames <= args.warmup:
        p.error('--frames must exceed --warmup')
    if args.warmup < 0 or args.threads < 1:
        p.error('--warmup must be >= 0 and --threads >= 1')
    return args


def synthetic(width: int, height: int, *, seed: int = 0) -> Iterator[np.ndarray]:
    """A textured background, slow camera drift, sensor noise and three moving objects."""
    import cv2
    rng = np.random.default_rng(seed)
    pad = 64
    bg = cv2.resize((rng.random((height // 8 + 16, width // 8 + 16, 3)) * 255).astype(np.uint8),
                    (width + 2 * pad, height + 2 * pad), interpolation=cv2.INTER_CUBIC)
    t = 0
    while True:
        dx = int(pad + pad * 0.8 * np.sin(t / 90.0))
        dy = int(pad + pad * 0.5 * np.sin(t / 130.0))
        frame = bg[dy:dy + height, dx:dx + width].copy()
        for k, colour in enumerate(((230, 40, 40), (40, 200, 60), (250, 250, 250))):
            cx = int((0.5 + 0.4 * np.sin(t / (25.0 + 10 * k) + k)) * width)
            cy = int((0.5 + 0.35 * np.cos(t / (40.0 + 7 * k) + 2 * k)) * height)
            cv2.circle(frame, (cx, cy), 18 + 8 * k, colour, -1)
        noise = rng.integers(-6, 7, size=frame.shape, dtype=np.int16)
        yield np.clip(frame.astype(np.int16) + noise, 0, 255).astype(np.uint8)
        t += 1


def video(path: str) -> Iterator[np.ndarray]:
    """RGB frames of a video file, looped forever."""
    import cv2
    cap = cv2.VideoCapture(path)
    if not cap.isOpened():
        raise SourceError(f'cannot open video {path}')
    frames = 0
    while True:
        ok, bgr = cap.read()
        if not ok:
            if frames == 0:
                raise SourceError(f'video {path} has no readable frames')
            cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            continue
        frames += 1
        yield cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def cpu_info() -> dict[str, Any]:
    """The CPU's model name and which of `model.CPU_FEATURES` it has."""
    from activeloc_ros.perception.features import cpu_flags
    model = platform.processor() or 'unknown CPU'
    try:
        with open('/proc/cpuinfo') as f:
            fields = dict(line.split(':', 1) for line in f.read().split('\n\n')[0].splitlines()
                          if ':' in line)
    except OSError:
        fields = {}
    fields = {k.strip(): v.strip() for k, v in fields.items()}
    if 'model name' in fields:      # the name alone does not tell a Zen 3 from a Zen 4
        model = fields['model name'] + (f' (family {fields["cpu family"]}, model '
                                        f'{fields["model"]})' if 'cpu family' in fields
                                        and 'model' in fields else '')
    return {'model': model, 'cores': os.cpu_count(), 'flags': cpu_flags()}


def describe_cpu(cpu: dict[str, Any]) -> str:
    from activeloc_ros.perception.features import CPU_FEATURES
    missing = [name for name, _ in CPU_FEATURES if name not in cpu['flags']]
    return (f'{cpu["model"]}, {cpu["cores"]} cores, {", ".join(cpu["flags"]) or "no AVX2"}'
            + (f'; no {", ".join(missing)}' if missing else ''))


def matmul_peak_gflops(dtype_name: str, *, n: int = 2048, seconds: float = 1.0) -> float:
    """
    GFLOP/s (int8: GOP/s) of an n x n matmul in this dtype on torch's current threads
    (the best of repeated timings for about `seconds`).
    """
    import torch
    if dtype_name == 'int8':      # int8 x int8 -> int32, as the int8 encoder's convolutions
        a = torch.randint(-128, 128, (n, n), dtype=torch.int8)
        b = torch.randint(-128, 128, (n, n), dtype=torch.int8)
        product = torch._int_mm
    else:
        dtype = getattr(torch, dtype_name)
        a, b = torch.randn(n, n).to(dtype), torch.randn(n, n).to(dtype)
        product = torch.matmul
    product(a, b)
    best, start = math.inf, time.perf_counter()
    while time.perf_counter() - start < seconds:
        t0 = time.perf_counter()
        product(a, b)
        best = min(best, time.perf_counter() - t0)
    return 2 * n ** 3 / best / 1e9


def params_file_settings(path: str) -> dict[str, Any]:
    """The PerceptionConfig fields a ROS 2 params file sets for the perception node."""
    from activeloc_ros.perception.params import PARAMS
    from activeloc_ros.nodes.params_files import file_values, files_problems
    from activeloc_ros.perception.config import PerceptionConfig
    if not Path(path).is_file():
        raise ConfigError(f'--params: no such file {path}')
    problems = files_problems('perception', PARAMS, [path])   # as the node would find them
    if problems:
        raise ConfigError('--params: ' + '; '.join(problems))
    settings = PerceptionConfig.fields_in(file_values('perception', [path]))
    if not settings:
        raise ConfigError(f'--params: {path} sets no perception model parameter')
    return settings


def is_default(config: dict[str, Any]) -> bool:
    """Is this the shipped configuration, the thread count aside?"""
    from activeloc_ros.perception.config import PerceptionConfig
    mine = PerceptionConfig.from_dict(config).to_dict()
    return all(mine[k] == v for k, v in PerceptionConfig().to_dict().items()
               if k != 'num_threads')


def stage_gflop(model, frame: np.ndarray) -> dict[str, float]:
    """
    GFLOP of one frame's encode, predict (forward) and update (the extra backward) on a
    model that has seen at least two frames.
    """
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    def count(fn) -> float:
        with FlopCounterMode(display=False) as counter:
            fn()
        return counter.get_total_flops() / 1e9

    x = model.features.preprocess(frame)

    def encode():            # the float encoder: the same arithmetic in every precision
        with torch.inference_mode():
            model.encoder(model.features.padded(x))

    def predict():
        with torch.no_grad():
            model.predictor(model.f_prev, model.state)

    def learn():
        fhat, alpha, _ = model.predictor(model.f_prev, model.state)
        (fhat.square().mean() + alpha.square().sum()).backward()
        model.predictor.zero_grad(set_to_none=True)

    forward = count(predict)
    return {'encode': count(encode), 'predict': forward, 'update': count(learn) - forward}


def floors(model, frame: np.ndarray, stage_ms: dict[str, float]) -> dict[str, Any]:
    """Each stage's floor (its GFLOP at the measured matmul peak of its precision)."""
    gflop = stage_gflop(model, frame)
    precisions = {stage: model.precision if stage == 'encode' else model.predictor_precision
                  for stage in gflop}
    peaks = {p: matmul_peak_gflops(p) for p in sorted(set(precisions.values()))}
    out = {'peak_gflops': peaks, 'stages': {}}
    for stage, work in gflop.items():
        precision = precisions[stage]
        floor_ms = work / peaks[precision] * 1e3
        out['stages'][stage] = {'gflop': work, 'precision': precision, 'floor_ms': floor_ms,
                                'measured_ms': stage_ms[stage],
                                'ratio': stage_ms[stage] / floor_ms if floor_ms else math.nan}
    return out


def floor_table(row: dict[str, Any]) -> str:
    f = row['floor']
    peaks = ', '.join(f'{p} {g:.0f}' for p, g in f['peak_gflops'].items())
    lines = [f'{row["encoder"]} ({row["configuration"]}) floors (matmul peak GFLOP/s: {peaks}):',
             f'{"stage":<10}{"precision":>10}{"GFLOP":>8}{"floor ms":>10}{"p50 ms":>8}'
             f'{"ratio":>7}']
    for stage, v in f['stages'].items():
        lines.append(f'{stage:<10}{v["precision"]:>10}{v["gflop"]:>8.2f}{v["floor_ms"]:>10.1f}'
                     f'{v["measured_ms"]:>8.1f}{v["ratio"]:>7.2f}')
    return '\n'.join(lines)


def rss_mb() -> float:
    with open('/proc/self/statm') as f:
        pages = int(f.read().split()[1])
    return pages * os.sysconf('SC_PAGE_SIZE') / 2**20


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB


def run(job: dict[str, Any]) -> dict[str, Any]:
    """One configuration, in its own process so memory figures are its own."""
    import torch

    from activeloc_ros.perception.config import PerceptionConfig
    from activeloc_ros.perception.model import SurpriseModel
    from activeloc_ros.progress import Progress
    torch.set_num_threads(job['threads'])
    cfg = PerceptionConfig.from_dict(job['config'])
    model = SurpriseModel(cfg)
    if job['video']:
        source = video(job['video'])
    else:
        source = synthetic(*job['size'])
    n, warmup = job['frames'], job['warmup']
    total = np.zeros(n)
    stages = np.zeros((n, len(STAGES)))
    rss = np.zeros(n)
    label = f"{cfg.encoder} update_encoder={'yes' if cfg.update_encoder else 'no'}"
    progress = Progress(n, label)
    updates = 0
    for i in range(n):
        frame = next(source)
        t0 = time.perf_counter()
        res = model.step(frame)
        updates += res.updated and i >= warmup
        total[i] = time.perf_counter() - t0
        stages[i] = [res.timings[k] for k in STAGES]
        rss[i] = rss_mb()
        progress.update(note=f'{total[i] * 1e3:.0f} ms')
    progress.close()
    lat = total[warmup:]
    # steady state: after the warm-up, the optimiser's lazily made state and the first weight
    # snapshot (`snapshot_every` updates), and a tenth of the run for the allocator to settle
    base = min(n - 1, max(warmup + cfg.snapshot_every + 1, n // 10))
    tail = rss[base:]
    slope = np.polyfit(np.arange(len(tail)), tail, 1)[0] * 1000 if len(tail) > 1 else 0.0
    stage_ms = {k: float(np.median(stages[warmup:, j]) * 1e3) for j, k in enumerate(STAGES)}
    row = {
        'encoder': cfg.encoder, 'update_encoder': cfg.update_encoder,
        'precision': model.precision, 'predictor_precision': model.predictor_precision,
        'cpu': cpu_info(), 'default': job['default'], 'configuration': job['configuration'],
        'frames': n, 'warmup': warmup, 'threads': job['threads'],
        'p50_ms': float(np.percentile(lat, 50) * 1e3),
        'p95_ms': float(np.percentile(lat, 95) * 1e3),
        'fps': float(len(lat) / lat.sum()),
        'stage_p50_ms': stage_ms,
        'update_share': updates / len(lat),
        'peak_rss_mb': peak_rss_mb(),
        'rss_base_frame': int(base),
        'rss_base_mb': float(rss[base]),
        'rss_growth_mb': float(rss[-1] - rss[base]),
        'rss_slope_mb_per_1000': float(slope),
        'nan_events': res.nan_events,
        'config': cfg.to_dict(),
    }
    if job['floor']:
        row['floor'] = floors(model, frame, stage_ms)
    return row


def table(rows: list[dict[str, Any]]) -> str:
    head = (f'{"configuration":<19}{"encoder":<19}{"upd.enc":>8}{"enc/pred":>10}{"frames":>7}'
            f'{"p50 ms":>8}{"p95 ms":>8}{"fps":>7}{"upd %":>6}{"peakRSS MB":>11}'
            f'{"RSS growth MB":>14}  p50 ms: {" / ".join(SHORT[s] for s in STAGES)}')
    lines = [head, '-' * len(head)]
    for r in rows:
        s = r['stage_p50_ms']
        precision = '/'.join(SHORT_PRECISION[r[k]] for k in ('precision', 'predictor_precision'))
        lines.append(
            f'{r["configuration"]:<19}{r["encoder"]:<19}'
            f'{"yes" if r["update_encoder"] else "no":>8}'
            f'{precision:>10}{r["frames"]:>7}{r["p50_ms"]:>8.1f}{r["p95_ms"]:>8.1f}'
            f'{r["fps"]:>7.1f}{100 * r["update_share"]:>6.0f}{r["peak_rss_mb"]:>11.0f}'
            f'{r["rss_growth_mb"]:>+14.1f}  ' + ' / '.join(f'{s[k]:.1f}' for k in STAGES)
            + ('  (default)' if r['default'] else ''))
    return '\n'.join(lines)


def weight_settings(args: argparse.Namespace) -> dict[str, Any]:
    """The PerceptionConfig fields that --random-weights and --weights set."""
    if args.random_weights:
        return {'pretrained': False}
    return {'weights': args.weights} if args.weights else {}


def feature_gaps(root: str | None, *, encoder: str, every: int, threads: int,
                 extra: dict[str, Any]) -> list[dict[str, Any]]:
    """
    Per precision, the relative L2 distance of its encoder features from float32's on
    every `every`-th frame of the sequences under `root`: mean, max and frames.
    """
    import torch

    from activeloc_ros import data
    from activeloc_ros.perception.config import PerceptionConfig
    from activeloc_ros.perception.model import SurpriseModel
    torch.set_num_threads(threads)
    models = {precision: SurpriseModel(PerceptionConfig.from_dict(
        {**extra, 'encoder': encoder, 'encoder_precision': precision, 'num_threads': threads}))
        for precision in ('float32', 'bfloat16', 'int8')}
    reference = models.pop('float32')
    sequences, _ = data.load_sequences(data.resolve_data_root(root))
    if not sequences:
        raise SourceError('no annotated sequences to compare features on')
    gaps: dict[str, list[float]] = {precision: [] for precision in models}
    for seq in sequences:
        for sample in seq.frames():
            if sample.index % every:
                continue
            x = reference.features.preprocess(sample.image)
            with torch.inference_mode():
                want = reference.features.of(x)
                for precision, model in models.items():
                    got = model.features.of(x)
                    gaps[precision].append(float((got - want).norm() / want.norm()))
    return [{'encoder': encoder, 'precision': precision, 'frames': len(values),
             'sequences': len(sequences), 'mean': float(np.mean(values)),
             'max': float(np.max(values))} for precision, values in gaps.items()]


def main(argv: list[str]) -> int:
    from activeloc_ros.perception.config import PerceptionConfig
    args = parse_args(argv)
    if args.feature_gap:
        try:
            rows = [row for encoder in args.encoder or [PerceptionConfig.encoder]
                    for row in feature_gaps(args.data, encoder=encoder, every=args.every,
                                            threads=args.threads,
                                            extra={**key_values(args.set, '--set'),
                                                   **weight_settings(args)})]
        except (ActivelocError, ValueError) as err:
            print(f'error: {err}', file=sys.stderr)
            return 1
        if args.json:
            print(json.dumps(rows, indent=1))
            return 0
        print(f'encoder features against float32 (relative L2 norm), CPU: '
              f'{describe_cpu(cpu_info())}')
        print(f'{"encoder":<19}{"precision":>10}{"frames":>8}{"mean %":>8}{"max %":>7}')
        for r in rows:
            print(f'{r["encoder"]:<19}{r["precision"]:>10}{r["frames"]:>8}'
                  f'{100 * r["mean"]:>8.2f}{100 * r["max"]:>7.2f}')
        return 0
    try:
        extra = key_values(args.set, '--set')
        size = tuple(int(v) for v in args.size.lower().split('x'))
        if len(size) != 2 or min(size) < 1:
            raise ConfigError(f'--size expects WxH, got {args.size!r}')
    except (ValueError, ConfigError) as err:
        print(f'error: {err}', file=sys.stderr)
        return 2
    updates = {'both': (False, True), 'yes': (True,), 'no': (False,)}[args.update_encoder]
    jobs = []
    try:
        configurations = [('default', {})] + [(Path(f).stem, params_file_settings(f))
                                              for f in args.params]
    except ConfigError as err:
        print(f'error: {err}', file=sys.stderr)
        return 2
    for name, settings in configurations:
        name += ' +set' if extra else ''
        for encoder in args.encoder or [PerceptionConfig.encoder]:
            for update in updates:
                config = {**settings, **extra, **weight_settings(args), 'encoder': encoder,
                          'update_encoder': update, 'num_threads': args.threads}
                try:
                    PerceptionConfig.from_dict(config)      # a bad --set fails here, once
                except ConfigError as err:
                    print(f'error: {name}: {err}', file=sys.stderr)
                    return 2
                jobs.append({'config': config, 'default': is_default(config),
                             'configuration': name, 'frames': args.frames,
                             'warmup': args.warmup, 'video': args.video, 'size': size,
                             'threads': args.threads, 'floor': args.floor})
    rows, failed = [], 0
    spawn = multiprocessing.get_context('spawn')
    for job in jobs:
        with concurrent.futures.ProcessPoolExecutor(1, mp_context=spawn) as pool:
            try:
                rows.append(pool.submit(run, job).result())
            except ActivelocError as err:
                failed += 1
                print(f'{job["configuration"]} {job["config"]["encoder"]}: '
                      f'{type(err).__name__}: {err}', file=sys.stderr)
    if args.json:
        print(json.dumps(rows, indent=1))
    elif rows:
        src = args.video or f'synthetic {size[0]}x{size[1]}'
        print(f'perception bench: {src}, {args.threads} threads; latency and fps over frames '
              f'{args.warmup}..{args.frames}; RSS growth from frame {rows[0]["rss_base_frame"]} '
              f'(steady state) to the last')
        print(f'CPU: {describe_cpu(rows[0]["cpu"])}')
        print(table(rows))
        for row in rows:
            if 'floor' in row:
                print('\n' + floor_table(row))
    return 1 if failed else 0
