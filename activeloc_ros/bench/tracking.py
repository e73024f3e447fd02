"""
Simulated active tracking (paper Sec. 4.1, Table 1; its ablations, Table 3).

    python -m activeloc_ros.bench tracking --episodes 10 --out out/tracking

Every method drives the same base controller (`control.base`) in the same seeded episodes of
the pybullet world (`tracking.world`): a person walks ahead of a mobile base carrying a
camera. Episode e of a scene is built from seed ``1000 * seed + e``, whatever the method.
Scores per scene, means over the episodes (AD-VAT's, `tracking.reward`): recall (episode
length / 500), precision (summed reward / 500), precision with the distance term relaxed,
episode length, accumulated reward and success rate (the whole 500 steps); also the mean
bearing error, the share of steps with the target in view, the median distance to the
person, and two checks of each method's answers against the truth of their step: the share
of locations inside the target's true box, and the median error of the distance the forward
rule reads from the method's box (what decides how close the base drives).

Methods: ours (the perception model turning toward its surprise peak), the Table 3 rows
(model ablations and PD variants, on the room scene only), the trackers TLD / MIL / MOSSE /
KCF / CSRT started on the target's true box in the first frame (the tracking standard) and
steering to their box centre, random, and the oracle (the true box's centre). The paper's RL
rows (AD-VAT+, SmartTarget-RL, RandomTarget-RL) were measured in Unreal and are not
comparable; they are quoted in the table as such.

Writes table1.md / table1.csv (methods x scenes), table3.md (the room scene's ablations),
tracking.json, one plot per scene and an overlay video per run (by default the first episode
of each scene and method): the camera view with the true box (green), the surprise map and
the method's choice (red), beside a top-down map with both paths. All atomically.
"""
import argparse
from collections import Counter
import json
import math
from pathlib import Path
import sys
import time
import traceback

import numpy as np

from activeloc_ros.bench import (
    add_jobs_option, add_output_options, check_seed, in_threads, key_values, names, output_dir,
    run_jobs)
from activeloc_ros.bench import methods
from activeloc_ros.bench.methods import (
    method_pd, PD_PARAMS, table3_methods, TRACKER_METHODS)
from activeloc_ros.bench.tracking_report import plots, summarise, table, to_csv
from activeloc_ros.bench.tracking_video import TrackingVideo
from activeloc_ros.bench.video import commit_video, run_keeping_results
from activeloc_ros.closed_loop import MODES, Pointing, run_episode
from activeloc_ros.control.base import BASE_PD, BaseConfig, BaseController, FORWARD_RULES
from activeloc_ros.control.params import BASE_PD_SETTINGS
from activeloc_ros.data import Box
from activeloc_ros.errors import ActivelocError, ConfigError
from activeloc_ros.paths import write_atomic
from activeloc_ros.progress import Progress
from activeloc_ros.tracking.scenes import SCENES

MODEL_METHODS = table3_methods(BASE_PD)       # on the base, whose PD law is its own
METHODS = (*MODEL_METHODS, 'random', 'oracle', *TRACKER_METHODS)
MAIN_METHODS = ('ours', *TRACKER_METHODS, 'random', 'oracle')
ABLATION_METHODS = tuple(m for m in MODEL_METHODS if m != 'ours')
ABLATION_SCENE = 'room'
DISTANCE_RULES = ('ground', 'size')      # the forward rules that read a distance off a box


def base_config(method: str, control: dict) -> BaseConfig:
    """The base controller of a method: its PD variant plus the --control settings."""
    known = set(BaseConfig.__dataclass_fields__) - {'pd'}
    unknown = sorted(set(control) - known - set(PD_PARAMS))
    if unknown:
        raise ConfigError(f'unknown --control settings {unknown}; known: '
                          f'{", ".join(sorted(known | set(PD_PARAMS)))}')
    pd = method_pd(method, {**BASE_PD_SETTINGS, **control})
    return BaseConfig(pd=pd, **{k: v for k, v in control.items() if k in known})


def make_pointer(method: str, settings: dict, seed: int):
    """The screen benchmark's pointer of a method, its tracker started on the true box."""
    if method not in METHODS:
        raise ConfigError(f'unknown method {method!r}; known: {", ".join(METHODS)}')
    return methods.make_pointer(method, settings, seed, tracker_start='truth')


class Remembering:
    """
    A pointer that keeps its newest answer, for the overlay video, and checks each answer
    against the truth of the step it was made on: whether the location lies on the target
    (inside its true box), what the camera saw there when it does not (``off_target``, by
    `TrackingWorld.kind_at`), and how far the distance that the base controller's forward
    rule reads from the answer's box (``witness.distance_to``) is from the true distance.

    :param world: the world the pointer looks at; its state is the view's when the pointer
        answers (None: nothing is checked).
    :param witness: a controller configured as the method's, used only for its readings.
    """

    def __init__(self, pointer, world=None, witness: BaseController | None = None):
        self.pointer, self.name = pointer, pointer.name
        self.world, self.witness = world, witness
        self.last: Pointing | None = None
        self.located = 0                       # steps with a location
        self.on_target = 0                     # ... inside the target's true box
        self.off_target: Counter = Counter()   # ... elsewhere, by what is there
        self.distance_errors: list[float] = []  # |forward rule's distance - true|, m

    def reset(self, sequence: str) -> None:
        self.pointer.reset(sequence)
        self.last = None

    def locate(self, view) -> Pointing:
        self.last = self.pointer.locate(view)
        if self.world is not None and self.last.location is not None:
            self.located += 1
            if view.truth_box is not None and Box(*view.truth_box).contains(*self.last.location):
                self.on_target += 1
            else:
                self.off_target[self.world.kind_at(*self.last.location)] += 1
            reads = self.witness is not None and self.witness.config.forward in DISTANCE_RULES
            reading = self.witness.distance_to(self.last.box) if reads else None
            if reading is not None:
                self.distance_errors.append(abs(reading - self.world.relative()[0]))
        return self.last

    def scores(self) -> dict[str, float]:
        """
        The share of located steps on the target, and the forward rule's median distance
        error (nan where there was nothing to count).
        """
        return {'on_target': self.on_target / self.located if self.located else math.nan,
                'distance_error_m': (float(np.median(self.distance_errors))
                                     if self.distance_errors else math.nan)}


# -- one run (method x scene x episode), in a worker process ---------------------------------

_POINTERS: dict = {}   # per worker process: one pointer per method, its encoder reused


def run_job(job: dict) -> dict:
    """Run one method on one episode; its scores, or the reason it failed."""
    return in_threads(_run_job, job)


def _run_job(job: dict) -> dict:
    from activeloc_ros.tracking.world import TrackingConfig, TrackingWorld
    started = time.perf_counter()
    where = {'method': job['method'], 'scene': job['scene'], 'episode': job['episode']}
    try:
        key = (job['method'], json.dumps(job['settings'], sort_keys=True), job['seed'])
        if key not in _POINTERS:
            _POINTERS[key] = make_pointer(job['method'], job['settings'], job['seed'])
        config = TrackingConfig(**job['world'])
        control = base_config(job['method'], job['control'])
        with TrackingWorld(job['scene'], job['episode_seed'], config) as world:
            pointer = Remembering(_POINTERS[key], world, world.controller(control))
            video = (TrackingVideo(Path(job['video']), world, pointer, job['method'])
                     if job['video'] else None)
            try:
                episode = run_episode(world, pointer, controller=control, mode=job['mode'],
                                      name=f'{job["scene"]}-{job["episode"]}',
                                      on_frame=video.add if video else None)
            except BaseException:
                if video:
                    video.abandon()
                raise
            if video:
                video.finish()
            scores = {**world.episode_score().as_dict(), **pointer.scores()}
            lost = world.lost_cause(episode.records)
            off_target = dict(pointer.off_target)
    except ActivelocError as err:
        return {**where, 'error': str(err)}
    except Exception:  # noqa: B902 - one broken run must not cost the others
        return {**where, 'error': f'{job["method"]} failed: {traceback.format_exc()}'}
    rows = episode.records
    scores['aae_deg'] = float(np.mean([r.aae_deg for r in rows])) if rows else math.nan
    scores['in_view'] = float(np.mean([r.in_view for r in rows])) if rows else math.nan
    # how far the base keeps the person (AD-VAT's goal: 2.5 m); a mean bearing and an in-view
    # rate can look good while the base drives into the person and loses it beside itself
    gaps = [math.dist(r.base_xy, r.target_xy) for r in rows if r.base_xy and r.target_xy]
    scores['distance_m'] = float(np.median(gaps)) if gaps else math.nan
    return {**where, 'scores': scores, 'lost': lost, 'off_target': off_target,
            'seconds': time.perf_counter() - started,
            'compute_ms': float(np.mean(episode.compute_s) * 1e3) if episode.compute_s else 0.0,
            'rewards': [round(r.reward, 4) for r in rows]}


# -- the whole benchmark ---------------------------------------------------------------------

def plan_jobs(scenes: list[str], methods: list[str], *, episodes: int, seed: int,
              video_dir: Path | None, videos: str, common: dict) -> list[dict]:
    """Every (scene, method, episode) to run: the ablation rows on the room scene only."""
    work = []
    for scene in scenes:
        for method in methods:
            if method in ABLATION_METHODS and scene != ABLATION_SCENE:
                continue
            for episode in range(episodes):
                film = video_dir is not None and (videos == 'all' or episode == 0)
                video = str(video_dir / scene / f'{method}-{episode}.mp4') if film else ''
                work.append({'scene': scene, 'method': method, 'episode': episode,
                             'episode_seed': 1000 * seed + episode, 'seed': seed,
                             'video': video, **common})
    # the slow model methods first, so the fast ones fill the gaps at the end
    work.sort(key=lambda j: (j['method'] not in MODEL_METHODS, j['scene'], j['method']))
    return work


def evaluate(work: list[dict], *, jobs: int, quiet: bool) -> list[dict]:
    progress = None if quiet else Progress(len(work), 'tracking episodes')
    runs = []
    for run in run_jobs(run_job, work, jobs=jobs):
        runs.append(run)
        if progress is not None:
            progress.update(1, note=f'{run["method"]} {run["scene"]} #{run["episode"]}')
    if progress is not None:
        progress.close()
    return runs


# -- command line ----------------------------------------------------------------------------

def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog='python -m activeloc_ros.bench tracking',
        description='Simulated active tracking (paper Table 1 and, on the room scene, Table '
                    '3): each method turns and drives a mobile base to keep a walking person '
                    "in view; AD-VAT's recall and precision per scene.")
    p.add_argument('--scenes', nargs='+', metavar='NAME',
                   help=f'scenes (default all): {", ".join(SCENES)}')
    p.add_argument('--methods', nargs='+', metavar='NAME',
                   help=f'methods (default {", ".join(MAIN_METHODS)}; add the Table 3 rows, '
                        f'run on the room scene only, with --ablations); known: '
                        f'{", ".join(METHODS)}')
    p.add_argument('--ablations', action='store_true',
                   help='also the Table 3 rows: ' + ', '.join(ABLATION_METHODS))
    p.add_argument('--episodes', type=int, default=10, metavar='N',
                   help='episodes per scene and method (default 10)')
    p.add_argument('--seed', type=int, default=0,
                   help='episode e is built from seed 1000 * SEED + e (default 0)')
    p.add_argument('--mode', choices=MODES, default='lockstep',
                   help='lockstep: every step processed, deterministic (default); realtime: '
                        'the world goes on while a method computes')
    p.add_argument('--target', choices=('nav', 'ram'), default='nav',
                   help="the target's behaviour, gym-unrealcv's Nav (default) or Ram")
    p.add_argument('--forward', choices=FORWARD_RULES, default=None,
                   help='how the base drives forward, for every method (default the '
                        "controller's, ground)")
    p.add_argument('--world', nargs='+', action='extend', metavar='KEY=VALUE', default=[],
                   help='TrackingConfig fields, e.g. max_steps=200 lost_steps=20')
    p.add_argument('--control', nargs='+', action='extend', metavar='KEY=VALUE', default=[],
                   help='base controller settings for every method (BaseConfig fields and '
                        + ', '.join(PD_PARAMS) + '), e.g. pace=0.8')
    p.add_argument('--set', nargs='+', action='extend', metavar='KEY=VALUE', default=[],
                   help='PerceptionConfig fields for every model method, e.g. lr=1e-4')
    add_jobs_option(p)
    p.add_argument('--videos', choices=('first', 'all', 'none'), default='first',
                   help='overlay videos of the first episode of each scene and method '
                        '(default), of every episode, or none')
    add_output_options(p, 'results, plots and videos go here (default %(default)s)',
                       'out/tracking')
    return p


def main(argv: list[str] | None = None) -> int:
    return run_keeping_results(run, parser().parse_args(argv))


def run(args: argparse.Namespace) -> int:
    from activeloc_ros.tracking.world import TrackingConfig
    try:
        scenes = names(args.scenes) or list(SCENES)
        for s in scenes:
            if s not in SCENES:
                raise ConfigError(f'unknown scene {s!r}; known: {", ".join(SCENES)}')
        methods = names(args.methods) or list(MAIN_METHODS)
        if args.ablations:
            methods += [m for m in ABLATION_METHODS if m not in methods]
        for m in methods:
            if m not in METHODS:
                raise ConfigError(f'unknown method {m!r}; known: {", ".join(METHODS)}')
        if args.episodes < 1 or args.jobs < 1:
            raise ConfigError('--episodes and --jobs must be >= 1')
        check_seed(args.seed)
        check_seed(1000 * args.seed + args.episodes - 1)   # the last episode's own seed
        world = key_values(args.world, '--world')
        if 'target_speed' in world:
            world['target_speed'] = tuple(world['target_speed'])
        world.setdefault('target', args.target)
        TrackingConfig(**world)
        control = key_values(args.control, '--control')
        if args.forward:
            control['forward'] = args.forward
        base_config('ours', control)
        settings = key_values(args.set, '--set')
        if any(m in MODEL_METHODS for m in methods):
            make_pointer('ours', settings, args.seed)    # weights, settings: now
        out = output_dir(args.out)
    except (ActivelocError, TypeError) as err:
        print(f'error: {err}', file=sys.stderr)
        return 2
    # one thread per episode, whatever --jobs: the base's closed loop turns a different
    # rounding (two threads sum in another order) into another path after a few hundred steps
    threads = 1
    work = plan_jobs(scenes, methods, episodes=args.episodes, seed=args.seed,
                     video_dir=None if args.videos == 'none' else out / 'videos',
                     videos=args.videos,
                     common={'settings': settings, 'control': control, 'world': world,
                             'mode': args.mode, 'threads': threads})
    if not args.quiet:
        print(f'{len(work)} episodes: {len(methods)} methods x {len(scenes)} scenes x '
              f'{args.episodes}, {args.mode}, target {world["target"]}', file=sys.stderr)
    started = time.monotonic()
    result = summarise(evaluate(work, jobs=args.jobs, quiet=args.quiet), methods, scenes)
    for fail in result['failed']:
        print(f'failed: {fail["method"]} on {fail["scene"]} #{fail["episode"]}: '
              f'{fail["error"]}', file=sys.stderr)
    result['settings'] = {'scenes': scenes, 'methods': methods, 'episodes': args.episodes,
                          'seed': args.seed, 'mode': args.mode, 'world': world,
                          'control': control, 'set': settings, 'jobs': args.jobs,
                          'seconds': round(time.monotonic() - started, 1)}
    main_rows = [m for m in methods if m not in ABLATION_METHODS]
    text = table(result, main_rows, scenes, title='Table 1: active tracking')
    write_atomic(out / 'table1.md', text)
    if ABLATION_SCENE in scenes and any(m in ABLATION_METHODS for m in methods):
        rows = [m for m in methods if m in MODEL_METHODS]
        ablation = table(result, rows, [ABLATION_SCENE], title='Table 3: ablations (room)')
        write_atomic(out / 'table3.md', ablation)
        text += '\n' + ablation
    write_atomic(out / 'table1.csv', to_csv(result))
    write_atomic(out / 'tracking.json', json.dumps(result) + '\n')
    pictures = plots(result, out)
    for job in work:
        if job['video']:
            commit_video(Path(job['video']))
    if args.json:
        for row in result['methods']:
            print(json.dumps({'method': row['method'], 'scenes': {
                s: {k: v[k] for k in ('recall', 'precision', 'precision_relaxed',
                                      'episode_length', 'reward')}
                for s, v in row['scenes'].items()}}))
    else:
        print(text, end='')
        print(f'\nwrote {out}/table1.md, table1.csv, tracking.json, '
              + ', '.join(p.name for p in pictures)
              + ('' if args.videos == 'none' else ', videos/<scene>/<method>-<episode>.mp4'))
        print(f'{result["settings"]["seconds"]:.0f} s')
    return 0 if not result['failed'] else 1


if __name__ == '__main__':
    raise SystemExit(main())
