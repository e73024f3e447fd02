"""
Synthetic static-camera sequences, for breadth beside the real ones.

    python -m activeloc_ros.bench scenes --count 48 --out out/synth48 --seed 0

Scene i is rendered by `tracking.clips` from ``numpy.random.default_rng([seed, i])`` on the
tracking world's engine (pybullet's TinyRenderer, CPU only) and assets: one dominant actor
playing a DeepMimic clip (walk, run, dance, kick, punch, jump) seen by a camera that never
moves, zero to six smaller, farther distractors, props and light that vary. It is written to
``DIR/synth_{i:03d}/`` in the annotated-sequence format `data.load_sequence` reads:

- ``video.mp4``: H.264, the frames as rendered;
- ``gt_xywh.txt``: the actor's box per frame from the segmentation mask (``nan`` rows when
  fewer than a handful of its pixels show);
- ``gt_all_xywh.txt``: the same boxes as track 1 (``primary_track``), and only them: the
  benchmark scores against the closest annotated actor, and the distractors are not the
  action to find;
- ``distractors_xywh.txt``: the distractors' boxes (track 2 on), for reference only; the
  loader does not read it;
- ``meta.json``, written last: sizes, ``camera: static``, the scene's parameters.

Each scene is rendered into ``DIR/.partial/<pid>/`` and renamed into place when whole, so an
interrupted run leaves whole scenes only (what a killed run leaves there, the next run
removes). A scene folder that already holds one rendered with the same seed, index,
settings and generator version is skipped (a rerun resumes); any other is replaced.
``--force`` replaces them all. The ground truth depends only on the seed and settings: the
same --seed writes byte-identical gt files.
"""
import argparse
import dataclasses
import json
import os
from pathlib import Path
import shutil
import sys
import tempfile
import time

import numpy as np

from activeloc_ros.bench import add_jobs_option, check_seed, output_dir, run_jobs
from activeloc_ros.errors import ActivelocError, ConfigError
from activeloc_ros.progress import Progress

PREFIX = 'synth_'
VIDEO = 'video.mp4'
STAGING = '.partial'
MAX_COUNT = 1000          # synth_000 .. synth_999
CRF = 18                  # x264 quality: the rendered edges stay sharp
GT_ALL_HEADER = ('# frame0,track_id,x,y,w,h,conf. Only the dominant actor (track 1) is '
                 'annotated: the benchmark scores against the closest annotated actor, and '
                 'the distractors are not the action to find (see distractors_xywh.txt).\n')
DISTRACTOR_HEADER = ('# frame0,track_id,x,y,w,h: the distractors (not annotated in '
                     'gt_all_xywh.txt), frames where they show; reference only.\n')


def scene_name(index: int) -> str:
    return f'{PREFIX}{index:03d}'


def generator(seed: int, index: int, config) -> dict:
    """What decides scene ``index``'s content; recorded in its meta.json."""
    from activeloc_ros.tracking import clips
    return {'command': 'bench scenes', 'version': clips.VERSION, 'seed': seed,
            'index': index, 'width': config.width, 'height': config.height,
            'frames': config.frames, 'fps': config.fps,
            'min_visible_px': config.min_visible_px}


def is_current(folder: Path, settings: dict) -> bool:
    """Does ``folder`` hold a whole scene rendered with ``settings``?"""
    try:
        meta = json.loads((folder / 'meta.json').read_text(encoding='utf-8'))
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and meta.get('generator') == settings and all(
        (folder / name).is_file() for name in (VIDEO, 'gt_xywh.txt', 'gt_all_xywh.txt'))


def _box_text(box) -> str:
    return 'nan,nan,nan,nan' if box is None else ','.join(str(v) for v in box)


def render_scene(folder: Path, seed: int, index: int, config) -> dict:
    """Render scene ``index`` of ``seed`` into the (empty) ``folder``; a summary."""
    from activeloc_ros.bench.video import H264Writer
    from activeloc_ros.tracking.clips import SyntheticClip
    rows, actor_rows, other_rows, heights = [], [], [], []
    with SyntheticClip(seed, index, config) as clip:
        writer = H264Writer(folder / VIDEO, config.fps, (config.width, config.height),
                            crf=CRF)
        try:
            for frame in clip.frames():
                writer.write(np.ascontiguousarray(frame.rgb[..., ::-1]))
                rows.append(_box_text(frame.actor) + '\n')
                if frame.actor is not None:
                    actor_rows.append(f'{frame.index},1,{_box_text(frame.actor)},1\n')
                    heights.append(frame.actor[3])
                for track, box in enumerate(frame.distractors, start=2):
                    if box is not None:
                        other_rows.append(f'{frame.index},{track},{_box_text(box)}\n')
        finally:
            writer.close()
        params = clip.describe()
    distance = params['actor']['distance_m']
    far = (f'{distance[0]:.1f} m' if distance[1] - distance[0] < 0.05
           else f'{distance[0]:.1f}-{distance[1]:.1f} m')
    n = len(params['distractors'])
    actor = (f"{params['action']} ({params['actor']['path']}), {far}, "
             f"{n} distractor{'' if n == 1 else 's'}, {params['scene']} scene")
    settings = generator(seed, index, config)
    meta = {
        'W': config.width, 'H': config.height, 'frames': config.frames,
        'camera': 'static', 'fps': config.fps, 'video': VIDEO, 'actor': actor,
        'primary_track': 1, 'eval_frames': [0, config.frames - 1],
        'targets': f'1 track (the dominant actor); {n} distractors not annotated',
        'source': (f'generated by `python -m activeloc_ros.bench scenes --seed {seed} '
                   f'--frames {config.frames} --width {config.width} --height '
                   f'{config.height} --fps {config.fps:g}` (scene {index}; numpy '
                   f'default_rng([{seed}, {index}]); activeloc_ros.tracking.clips '
                   f'v{settings["version"]}): pybullet TinyRenderer, the DeepMimic humanoid '
                   'and motion clips shipped in pybullet_data'),
        'license': 'generated data; assets from pybullet_data (bullet3, zlib licence)',
        'annotation': ('gt from the segmentation mask, exact; gt_all_xywh.txt holds only the '
                       'dominant actor (track 1): the benchmark scores against the closest '
                       'annotated actor and the distractors are not the action to find; '
                       'their boxes are in distractors_xywh.txt'),
        'visible_frames': len(actor_rows),
        'actor_height_px': ([int(np.min(heights)), int(np.median(heights)),
                             int(np.max(heights))] if heights else None),
        'scene_params': params, 'generator': settings,
    }
    (folder / 'gt_xywh.txt').write_text(''.join(rows), encoding='utf-8')
    (folder / 'gt_all_xywh.txt').write_text(GT_ALL_HEADER + ''.join(actor_rows),
                                            encoding='utf-8')
    (folder / 'distractors_xywh.txt').write_text(DISTRACTOR_HEADER + ''.join(other_rows),
                                                 encoding='utf-8')
    (folder / 'meta.json').write_text(json.dumps(meta, indent=1) + '\n', encoding='utf-8')
    return {'actor': actor, 'visible': len(actor_rows)}


def clear_stale(out: Path) -> None:
    """
    Remove what killed runs (SIGKILL, SIGTERM) left in ``out``'s staging folder: the
    folders of runs whose process is gone.
    """
    for folder in (out / STAGING).glob('*'):
        try:
            os.kill(int(folder.name), 0)
        except ValueError:
            continue                    # not a run's folder
        except ProcessLookupError:
            shutil.rmtree(folder, ignore_errors=True)
        except PermissionError:         # another user's live process
            pass


def install(staged: Path, target: Path) -> None:
    """
    Put a whole scene in place of ``target``: the old one (if any) moves aside first, so
    a reader finds the old scene, the new one, or none, never a mix.
    """
    old = staged.with_name(staged.name + '.old')
    if target.exists():
        os.replace(target, old)
    os.replace(staged, target)
    shutil.rmtree(old, ignore_errors=True)


def run_job(job: dict) -> dict:
    """One scene (in a worker process): rendered into the staging folder, then installed."""
    from activeloc_ros.tracking.clips import ClipConfig
    started = time.monotonic()
    target = Path(job['target'])
    staged = Path(tempfile.mkdtemp(prefix=target.name + '.', dir=job['staging']))
    try:
        summary = render_scene(staged, job['seed'], job['index'], ClipConfig(**job['config']))
        staged.chmod(0o777 & ~job['umask'])     # mkdtemp's folder is private, 0700
        install(staged, target)
    except ActivelocError as err:
        return {'name': target.name, 'error': str(err)}
    finally:
        shutil.rmtree(staged, ignore_errors=True)
    return {**summary, 'name': target.name, 'seconds': time.monotonic() - started}


# -- command line ----------------------------------------------------------------------------

def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog='python -m activeloc_ros.bench scenes',
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description='Generate synthetic static-camera sequences. In each, one dominant '
                    'person plays an action\n(walk, run, dance, kick, punch, jump) in a '
                    'seeded pybullet scene (room, urban, snow,\nparking) with 0-6 smaller, '
                    'farther distractors, rendered on the CPU (TinyRenderer) with\nits exact '
                    'box per frame from the segmentation mask.',
        epilog='Scene i goes to DIR/synth_{i:03d}/ (meta.json, video.mp4, gt_xywh.txt, '
               'gt_all_xywh.txt with the\nactor only, distractors_xywh.txt), the format '
               'activeloc_ros.data reads. It is rendered\nunder DIR/.partial/ and renamed '
               'into place when whole. An existing scene made with the same\nseed, index '
               'and settings is skipped, so a rerun resumes; any other is replaced (all of\n'
               'them with --force). Scenes numbered --count and above are left alone.\n'
               'Cost: about 0.12 s of CPU a frame at 640x360 (shadows, in half the scenes, '
               'take 2.4 times\nas long): 48 default scenes are about 11 minutes of CPU, '
               'under 6 minutes on 2 free cores.')
    p.add_argument('--count', type=int, required=True, metavar='N',
                   help=f'scenes to generate, synth_000 .. synth_N-1 (1-{MAX_COUNT})')
    p.add_argument('--out', required=True, metavar='DIR', help='where the scene folders go')
    p.add_argument('--seed', type=int, default=0,
                   help='scene i is built from numpy default_rng([SEED, i]) (default 0)')
    p.add_argument('--frames', type=int, default=120,
                   help='frames per scene (default 120: 8 s at 15 fps)')
    p.add_argument('--fps', type=float, default=15.0,
                   help='frame rate, how fast people move between frames (default 15)')
    p.add_argument('--width', type=int, default=640,
                   help='image width, even, >= 32 (default 640)')
    p.add_argument('--height', type=int, default=360,
                   help='image height, even, >= 32 (default 360: 16:9 like the projected '
                        'screen)')
    add_jobs_option(p)
    p.add_argument('--force', action='store_true',
                   help='replace existing scenes even when they are up to date')
    p.add_argument('--quiet', action='store_true', help='no progress on stderr')
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    from activeloc_ros.tracking.clips import ClipConfig
    try:
        if not 1 <= args.count <= MAX_COUNT:
            raise ConfigError(f'--count must be in [1, {MAX_COUNT}], got {args.count}')
        if args.jobs < 1:
            raise ConfigError(f'--jobs must be >= 1, got {args.jobs}')
        check_seed(args.seed)
        config = ClipConfig(width=args.width, height=args.height, frames=args.frames,
                            fps=args.fps)
        out = output_dir(args.out)
    except ActivelocError as err:
        print(f'error: {err}', file=sys.stderr)
        return 2
    clear_stale(out)
    work, skipped = [], 0
    for index in range(args.count):
        target = out / scene_name(index)
        if not args.force and is_current(target, generator(args.seed, index, config)):
            skipped += 1
            continue
        work.append({'target': str(target), 'seed': args.seed, 'index': index,
                     'config': dataclasses.asdict(config)})
    if not args.quiet:
        print(f'{len(work)} scenes to render ({skipped} up to date, skipped), '
              f'{config.width}x{config.height}, {config.frames} frames at {config.fps:g} fps, '
              f'seed {args.seed}, {args.jobs} jobs', file=sys.stderr)
    staging = out / STAGING / str(os.getpid())   # this run's own: another run's is not ours
    started = time.monotonic()
    failed = []
    try:
        staging.mkdir(parents=True, exist_ok=True)
        umask = os.umask(0)
        os.umask(umask)
        for job in work:
            job.update(staging=str(staging), umask=umask)
        progress = None if args.quiet or not work else Progress(len(work), 'scenes')
        for result in run_jobs(run_job, work, jobs=min(args.jobs, max(len(work), 1))):
            if 'error' in result:
                failed.append(result)
                print(f'\nfailed: {result["name"]}: {result["error"]}', file=sys.stderr)
            if progress:
                progress.update(note=result['name'])
        if progress:
            progress.close()
    except KeyboardInterrupt:
        print(f'\ninterrupted: the finished scenes in {out} are whole; run again to '
              'resume', file=sys.stderr)
        return 130
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        try:
            (out / STAGING).rmdir()        # unless another run is staging there
        except OSError:
            pass
    seconds = time.monotonic() - started
    print(f'wrote {len(work) - len(failed)} scenes to {out} ({skipped} skipped, '
          f'{len(failed)} failed) in {seconds:.0f} s')
    return 1 if failed else 0


if __name__ == '__main__':
    raise SystemExit(main())
