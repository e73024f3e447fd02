"""
Is the ROS graph what the screen benchmark measures? Run both on one scene and compare.

    python -m activeloc_ros.bench graph-check --scene otb_crossing --frames 40

Runs ``bringup --mode lockstep --camera virtual:SCENE --record DIR`` (every node in its own
process, the packaged params), reads the pan and tilt each frame was rendered with (the sim
node's ``camera/pose``), runs ``closed_loop.run_episode`` in lockstep on the same frames
with the same perception and controller settings, and prints the largest per-frame
difference of the camera angles. Exit 0 when every frame agrees within the tolerance.
"""
import argparse
import math
from pathlib import Path
import subprocess
import sys
import tempfile

import yaml

from activeloc_ros.bench import output_dir
from activeloc_ros.bench.pointers import ModelPointer
from activeloc_ros.closed_loop import run_episode, screen_world
from activeloc_ros.data import FrameTruth
from activeloc_ros.errors import ActivelocError
from activeloc_ros.graph_plan import camera_screen, node_values
from activeloc_ros.sources import default_bag, open_scene


def bench_poses(scene: str, frames: int) -> list[tuple[float, float, float]]:
    """(t, pan, tilt) per frame of the benchmark's closed loop on the scene."""
    from activeloc_ros.control.params import config_from
    from activeloc_ros.perception.config import PerceptionConfig
    source = open_scene(scene)
    fps = source.fps

    def scene_frames():
        for i in range(frames):
            frame = source.read()
            if frame is None:
                return
            yield i, frame.rgb, FrameTruth(i, None, (), False)

    control = node_values('controller')       # bringup's default: the arm's aim limits only
    perception = node_values('perception')
    pointer = ModelPointer('ours', PerceptionConfig.fields_in(perception))
    controller = config_from(control)
    # the screen the graph's sim node renders (its packaged params), not a default one
    world = screen_world(scene_frames(), fps=fps, screen=camera_screen(), controller=controller)
    episode = run_episode(world, pointer, controller=controller, mode='lockstep')
    source.close()
    return [(r.t, r.pan, r.tilt) for r in episode.records]


def graph_poses(scene: str, frames: int, record: Path) -> list[tuple[float, float, float]]:
    """(t, pan, tilt) per frame of a lockstep bringup run recorded to `record`."""
    from activeloc_ros.nodes.lockstep import recorded_poses
    params = record.parent / f'{record.name}-sim.yaml'
    params.write_text(yaml.safe_dump(
        {'sim': {'ros__parameters': {'max_frames': frames}}}))
    command = [sys.executable, '-m', 'activeloc_ros.bringup', '--mode', 'lockstep',
               '--camera', f'virtual:{scene}', '--params', str(params),
               '--record', str(record), '--log-dir', str(record.parent / 'logs')]
    print('$ ' + ' '.join(command), file=sys.stderr)
    done = subprocess.run(command, check=False)
    if done.returncode != 0:     # the logs go with the temporary folder: show their ends
        ends = ''.join(f'\n--- {log.name}, last lines:\n'
                       + '\n'.join(log.read_text(errors='replace').splitlines()[-15:])
                       for log in sorted((record.parent / 'logs').glob('*.log')))
        raise ActivelocError(f'bringup exited {done.returncode}{ends}')
    return recorded_poses(record)


def compare(graph: list, bench: list, tolerance_deg: float) -> tuple[bool, str]:
    lines = []
    worst = 0.0
    for (tg, pg, gg), (tb, pb, gb) in zip(graph, bench):
        if abs(tg - tb) > 1e-6:
            return False, f'frame times differ: graph {tg:.6f} s, bench {tb:.6f} s'
        worst = max(worst, abs(math.degrees(pg - pb)), abs(math.degrees(gg - gb)))
    same_length = len(graph) == len(bench)
    ok = same_length and worst <= tolerance_deg and len(graph) > 0
    lines.append(f'frames: graph {len(graph)}, bench {len(bench)}')
    lines.append(f'largest per-frame difference of pan or tilt: {worst:.4f} deg '
                 f'(tolerance {tolerance_deg:g} deg)')
    if graph:
        t, pan, tilt = graph[-1]
        lines.append(f'last frame t={t:.2f} s: pan {math.degrees(pan):.1f} deg, '
                     f'tilt {math.degrees(tilt):.1f} deg')
    lines.append('SAME' if ok else 'DIFFERENT')
    return ok, '\n'.join(lines)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog='python -m activeloc_ros.bench graph-check',
        description="Run the ROS graph in lockstep and the screen benchmark's closed loop on "
                    'one scene and compare the camera angles frame by frame.')
    p.add_argument('--scene', default=f'bag:{default_bag()}',
                   help='what the virtual screen shows: bag:PATH, video:PATH, a sequence '
                        'folder or name (default: the bundled bag)')
    p.add_argument('--frames', type=int, default=40, help='frames to run (default 40)')
    p.add_argument('--tolerance-deg', type=float, default=0.5,
                   help='largest allowed per-frame difference (default 0.5 deg: half a '
                        'servo step)')
    p.add_argument('--keep', type=Path, help='keep the recorded bag and logs here')
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    if args.frames < 1:
        print('error: --frames must be >= 1', file=sys.stderr)
        return 2
    if not (math.isfinite(args.tolerance_deg) and args.tolerance_deg >= 0):
        print('error: --tolerance-deg must be a finite number >= 0', file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix='graph-check-') as tmp:
        try:
            work = output_dir(args.keep, '--keep') if args.keep else Path(tmp)
            graph = graph_poses(args.scene, args.frames, work / 'run')
            bench = bench_poses(args.scene, args.frames)
        except ActivelocError as err:
            print(f'error: {err}', file=sys.stderr)
            return 2
    ok, report = compare(graph, bench, args.tolerance_deg)
    print(report)
    return 0 if ok else 1


if __name__ == '__main__':
    raise SystemExit(main())
