"""The virtual screen, the closed loop in simulated time and the screen benchmark's CLI."""
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from activeloc_ros import closed_loop, data
from activeloc_ros.bench import screen as bench
from activeloc_ros.bench.pointers import CentrePointer, OraclePointer, RandomPointer
from activeloc_ros.closed_loop import gaze_map, Pointing, run_episode, screen_world
from activeloc_ros.control import angular_error, ControllerConfig
from activeloc_ros.errors import ConfigError
from activeloc_ros.screen import ScreenConfig, VirtualScreen

SCENE = (320, 180)


def polygon_area(points: np.ndarray) -> float:
    x, y = points[:, 0], points[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1))))


def test_home_view_is_centred_and_covers_the_view_fraction():
    screen = VirtualScreen(ScreenConfig(view_fraction=0.3))
    centre = ((SCENE[0] - 1) / 2, (SCENE[1] - 1) / 2)
    u, v = screen.project([centre], 0.0, 0.0, SCENE)[0]
    assert (u, v) == pytest.approx(((640 - 1) / 2, (480 - 1) / 2))
    outline = screen.view_outline(0.0, 0.0, SCENE, samples=1)
    assert polygon_area(outline) / (SCENE[0] * SCENE[1]) == pytest.approx(0.3, rel=1e-6)
    assert screen.home_fraction == pytest.approx(0.3)


def test_explicit_distance_sets_the_fraction():
    near = VirtualScreen(ScreenConfig(distance_m=0.5))
    far = VirtualScreen(ScreenConfig(distance_m=1.0))
    assert far.home_fraction == pytest.approx(4 * near.home_fraction)
    assert near.distance == 0.5


@pytest.mark.parametrize('pan,tilt', [(0.2, 0.0), (-0.3, 0.1), (0.1, -0.25), (0.4, 0.3)])
def test_controller_error_centres_the_point(pan, tilt):
    """The controller's angular error, applied to the pose, puts the point on the axis."""
    screen = VirtualScreen()
    point = (250.0, 40.0)
    u, v = screen.project([point], pan, tilt, SCENE)[0]
    d_pan, d_tilt = angular_error(u, v, screen.intrinsics, camera_tilt=tilt)
    assert screen.angles_deg([point], pan, tilt, SCENE)[0] > 5.0
    assert screen.angles_deg([point], pan + d_pan, tilt + d_tilt, SCENE)[0] < 1e-6
    back = screen.to_scene([(u, v)], pan, tilt, SCENE)[0]
    assert back == pytest.approx(point)


def test_render_shows_a_marker_where_it_projects_and_pan_left_moves_it_right():
    screen = VirtualScreen(ScreenConfig(width=320, height=240))
    scene = np.zeros((SCENE[1], SCENE[0], 3), np.uint8)
    scene[85:95, 150:160] = 255
    first_x = 0.0
    for pan in (0.0, 0.2):
        image = screen.render(scene, pan, 0.0)
        ys, xs = np.nonzero(image[..., 0] > 128)
        expected = screen.project([(154.5, 89.5)], pan, 0.0, SCENE)[0]
        assert (xs.mean(), ys.mean()) == pytest.approx(tuple(expected), abs=1.0)
        if pan:
            assert xs.mean() > first_x + 20     # turning left moves the scene right
        first_x = xs.mean()


@pytest.mark.parametrize('wall', [0, 40])
def test_rays_that_miss_the_screen_see_the_plain_wall(wall):
    screen = VirtualScreen(ScreenConfig(width=160, height=120, wall_grey=wall))
    scene = np.full((SCENE[1], SCENE[0], 3), 200, np.uint8)
    image = screen.render(scene, math.radians(89.0), 0.0)   # looking along the screen
    assert image[:, :40].min() == image[:, :40].max() == wall and image.max() == 200
    past_edge = screen.render(scene, math.radians(40.0), 0.0)
    assert (past_edge == wall).all(axis=2).any() and (past_edge == 200).all(axis=2).any()


@pytest.mark.parametrize('config', [ScreenConfig(), ScreenConfig(view_fraction=0.1)])
def test_within_the_aim_limits_the_view_lies_on_the_screen(config):
    screen = VirtualScreen(config)
    pan, tilt = (math.radians(a) for a in screen.aim_limits_deg())
    assert pan > 0 and tilt > 0
    scene = np.full((SCENE[1], SCENE[0], 3), 200, np.uint8)
    for sp, st in ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, 1), (1, -1), (-1, -1)):
        image = screen.render(scene, sp * pan, st * tilt)
        assert image.min() > config.wall_grey          # no ray misses the screen (edges blend)
    wider = screen.render(scene, pan * 1.05, tilt * 1.05)
    assert wider.min() == config.wall_grey                   # a little farther, one does


def test_place_map_puts_the_peak_where_the_camera_looked():
    screen = VirtualScreen()
    heat = np.zeros((14, 14), np.float32)
    heat[3, 10] = 1.0
    for pan, tilt in [(0.0, 0.0), (0.3, -0.1)]:
        placed = screen.place_map(heat, pan, tilt, (96, 54))
        cell_px = ((10 + 0.5) * 640 / 14 - 0.5, (3 + 0.5) * 480 / 14 - 0.5)
        x, y = screen.to_scene([cell_px], pan, tilt, (96, 54))[0]
        row, col = np.unravel_index(np.argmax(placed), placed.shape)
        assert abs(col - x) <= 1.5 and abs(row - y) <= 1.5
        assert placed.min() == -1.0 and 0.2 < np.mean(placed > -1) < 0.4


def test_bad_screen_settings():
    with pytest.raises(ConfigError, match='view_fraction'):
        ScreenConfig(view_fraction=0.0)
    with pytest.raises(ConfigError, match='unknown screen settings'):
        ScreenConfig.from_dict({'size': 3})


def test_gaze_map_peaks_at_the_point():
    heat = gaze_map((600.0, 20.0), (640, 480))
    assert np.unravel_index(np.argmax(heat), heat.shape) == (0, 13)
    assert np.all(gaze_map(None, (640, 480)) == 1.0)


# -- synthetic scenes ------------------------------------------------------------------------

def make_walker(root: Path, name: str = 'walker', n: int = 40, *, fps: float = 10.0) -> Path:
    """A bright square walking left to right across a textured scene, the GT its box."""
    path = root / name
    (path / 'img').mkdir(parents=True)
    w, h = SCENE
    rng = np.random.default_rng(0)
    background = cv2.GaussianBlur(rng.integers(0, 120, (h, w, 3), dtype=np.uint8), (5, 5), 0)
    rows = []
    for i in range(n):
        img = background.copy()
        x, y = 20 + int(6.5 * i), 80
        img[y:y + 16, x:x + 16] = 255
        cv2.imwrite(str(path / 'img' / f'{i:03d}.png'), img)
        rows.append(f'{x},{y},16,16')
    meta = {'W': w, 'H': h, 'frames': n, 'camera': 'STATIC', 'frames_glob': 'img/*.png',
            'fps': f'{fps} (synthetic)'}
    (path / 'meta.json').write_text(json.dumps(meta))
    (path / 'gt_xywh.txt').write_text('\n'.join(rows) + '\n')
    return path


def episode(seq: data.Sequence, pointer, mode: str = 'lockstep', **options):
    controller = ControllerConfig(settle_time=0.0)
    camera_fps = options.pop('camera_fps', None)
    world = screen_world(((s.index, s.image, s.truth) for s in seq.frames()), fps=seq.fps,
                         screen=VirtualScreen(ScreenConfig(width=320, height=240)),
                         controller=controller, camera_fps=camera_fps)
    return run_episode(world, pointer, controller=controller, mode=mode, name=seq.name,
                       **options)


def test_oracle_follows_the_walker_and_centre_loses_it(tmp_path):
    seq = data.load_sequence(make_walker(tmp_path))
    assert seq.fps == 10.0
    oracle = episode(seq, OraclePointer()).summary()
    centre = episode(seq, CentrePointer()).summary()
    assert oracle['scored'] == 40 and oracle['processed'] == 40
    # it starts 40 deg away; the paper's PD (kd 0.1 on the error) lags it by about 10 deg
    assert oracle['aae_deg'] < 12.0 < 20.0 < centre['aae_deg']
    assert oracle['in_view'] >= 0.9 > 0.6 > centre['in_view']
    assert oracle['auc_judd'] > 0.9 > centre['auc_judd']


def test_pointing_error_scores_the_location_not_the_camera(tmp_path):
    seq = data.load_sequence(make_walker(tmp_path))
    oracle = episode(seq, OraclePointer())
    seen = [r for r in oracle.records if r.in_view]
    assert seen and max(r.pointing_deg for r in seen) < 0.1      # it points at the walker
    summary = oracle.summary()
    assert summary['aae_deg'] > summary['pointing_deg']      # the arm lags behind it
    assert math.isnan(episode(seq, CentrePointer()).summary()['pointing_deg'])  # no location


def test_lockstep_is_deterministic(tmp_path):
    seq = data.load_sequence(make_walker(tmp_path))
    runs = [[(r.pan, r.tilt, r.auc) for r in episode(seq, RandomPointer(seed=3)).records]
            for _ in range(2)]
    assert runs[0] == runs[1]
    assert len({p for p, _, _ in runs[0]}) > 5      # the random target does move the camera


class ComputeClock:
    """
    The realtime benchmark's clock, moved on only by the pointers below, so each
    frame costs exactly their delay however busy the machine is (a loaded machine made
    a real sleep overrun and dropped one frame more in one run than in the other).
    """

    def __init__(self):
        self.now = 0.0

    def perf_counter(self) -> float:
        return self.now

    def spend(self, seconds: float) -> None:
        self.now += seconds


@pytest.fixture
def clock(monkeypatch) -> ComputeClock:
    clock = ComputeClock()
    monkeypatch.setattr(closed_loop, 'time', clock)
    return clock


class SlowOracle(OraclePointer):
    """The oracle, taking `delay` seconds of `clock` per frame."""

    def __init__(self, delay: float, clock: ComputeClock):
        self.delay, self.clock = delay, clock

    def locate(self, view) -> Pointing:
        self.clock.spend(self.delay)
        return super().locate(view)


def test_realtime_drops_frames_a_slow_pointer_cannot_take(tmp_path, clock):
    seq = data.load_sequence(make_walker(tmp_path, fps=20.0))
    lock = episode(seq, SlowOracle(0.12, clock))
    real = episode(seq, SlowOracle(0.12, clock), mode='realtime')
    assert lock.summary()['processed'] == 40
    # a frame every 50 ms, 120+ ms each: at most every second frame goes through
    assert real.summary()['processed'] <= 21
    assert real.summary()['aae_deg'] > lock.summary()['aae_deg']


class EarlyOracle(SlowOracle):
    """
    The slow oracle, with its answer ready at once (as the model's map is before its
    optimiser step).
    """

    def locate(self, view) -> Pointing:
        answer = super().locate(view)
        answer.ready_s = 0.0
        return answer


def test_realtime_commands_leave_when_the_answer_is_ready_not_when_the_pointer_is_done(
        tmp_path, clock):
    seq = data.load_sequence(make_walker(tmp_path, fps=20.0))
    late = episode(seq, SlowOracle(0.12, clock), mode='realtime').summary()
    early = episode(seq, EarlyOracle(0.12, clock), mode='realtime').summary()
    assert early['processed'] == late['processed']        # busy just as long
    assert early['aae_deg'] < late['aae_deg']              # but it steers sooner


class AskingOracle(OraclePointer):
    """
    The oracle, taking ``delay`` s and then asking whether its frame is late (as the
    model asks before its optimiser step).
    """

    def __init__(self, delay: float, clock: ComputeClock):
        super().__init__()
        self.delay, self.clock, self.answers = delay, clock, []

    def locate(self, view) -> Pointing:
        self.clock.spend(self.delay)
        self.answers.append(None if view.late is None else view.late())
        return super().locate(view)


@pytest.mark.parametrize('delay, late', [(0.0, False), (0.15, True)])
def test_realtime_tells_a_pointer_its_frame_is_late_once_the_next_is_captured(
        tmp_path, clock, delay, late):
    seq = data.load_sequence(make_walker(tmp_path, n=8))
    real = AskingOracle(delay, clock)
    episode(seq, real, mode='realtime')
    assert real.answers and set(real.answers) == {late}    # a frame every 100 ms
    lock = AskingOracle(delay, clock)
    episode(seq, lock)
    assert set(lock.answers) == {None}                      # lockstep: never late


def test_realtime_scores_the_pointing_of_frames_taken_from_the_queue_too(tmp_path, clock):
    seq = data.load_sequence(make_walker(tmp_path, fps=20.0))
    run = episode(seq, SlowOracle(0.12, clock), mode='realtime')
    pointed = [r for r in run.records if math.isfinite(r.pointing_deg)]
    # every frame it processed, the ones taken from the queue too, is scored and counted
    assert len(pointed) == len(run.compute_s) == sum(r.processed for r in run.records)


def test_a_slower_camera_takes_fewer_pictures_but_every_frame_is_scored(tmp_path):
    seq = data.load_sequence(make_walker(tmp_path, fps=30.0, n=30))
    images = []
    run = episode(seq, OraclePointer(), camera_fps=10.0,
                  on_frame=lambda scene, record, camera: images.append(camera is not None))
    assert images == [True, False, False] * 10
    assert run.summary()['processed'] == 10 and run.summary()['scored'] == 30


def test_bad_mode_is_refused(tmp_path):
    seq = data.load_sequence(make_walker(tmp_path, n=3))
    with pytest.raises(ConfigError, match='mode'):
        episode(seq, CentrePointer(), mode='fast')


def test_a_fixed_latency_delays_the_arm_deterministically_and_keeps_every_frame(tmp_path):
    seq = data.load_sequence(make_walker(tmp_path, fps=20.0))
    prompt = episode(seq, OraclePointer())
    late = [episode(seq, OraclePointer(), latency_s=0.12) for _ in range(2)]
    assert [r.pan for r in late[0].records] == [r.pan for r in late[1].records]
    first_move = [next(r.t for r in run.records if r.pan != 0.0) for run in (prompt, late[0])]
    assert first_move[0] < first_move[1] <= first_move[0] + 0.12 + 0.05   # + a scene frame
    assert late[0].summary()['processed'] == prompt.summary()['processed']   # every frame
    assert late[0].summary()['aae_deg'] > prompt.summary()['aae_deg']


@pytest.mark.parametrize('latency,mode', [(-0.01, 'lockstep'), (math.nan, 'lockstep'),
                                          (0.03, 'realtime')])
def test_bad_latency_is_refused(tmp_path, latency, mode):
    seq = data.load_sequence(make_walker(tmp_path, n=3))
    with pytest.raises(ConfigError, match='latency'):
        episode(seq, CentrePointer(), mode=mode, latency_s=latency)


# -- the command ---------------------------------------------------------------------------

def test_cli_table_csv_plots_videos_and_bad_sequences(tmp_path, capsys):
    root = tmp_path / 'data'
    make_walker(root, 'a_walker', n=12)
    make_walker(root, 'b_walker', n=12)
    broken = make_walker(root, 'c_broken', n=12)
    (broken / 'img' / '006.png').write_bytes(b'not an image')
    bad_gt = make_walker(root, 'd_bad_gt', n=12)
    (bad_gt / 'gt_xywh.txt').write_text('1,2,3,4\n' * 11 + 'x,2,3,4\n')
    out = tmp_path / 'out'
    args = ['--data', str(root), '--methods', 'oracle', 'centre', '--jobs', '1', '--out',
            str(out), '--screen', 'width=320', 'height=240', '--quiet']
    assert bench.main(args) == 0
    captured = capsys.readouterr()
    assert '| oracle |' in captured.out and '| centre |' in captured.out
    assert 'c_broken' in captured.err and '006.png' in captured.err
    assert 'd_bad_gt' in captured.err and 'gt_xywh.txt:12' in captured.err
    result = json.loads((out / 'screen.json').read_text())
    assert result['sequences'] == ['a_walker', 'b_walker']
    assert [r['method'] for r in result['methods']] == ['oracle', 'centre']
    rows = (out / 'screen.csv').read_text().splitlines()
    assert rows[0].startswith('method,sequence,aae_deg') and len(rows) == 1 + 2 * 3
    for name in ('aae_deg', 'auc_judd', 'in_view'):
        assert (out / f'{name}.png').read_bytes()[:4] == b'\x89PNG'
    video = cv2.VideoCapture(str(out / 'videos' / 'a_walker' / 'oracle.mp4'))
    assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == 12
    assert not list(out.rglob('.*tmp*'))          # no temporary file left behind

    assert bench.main(args + ['--json', '--no-video']) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [d['method'] for d in lines] == ['oracle', 'centre']
    assert set(lines[0]['sequences']) == {'a_walker', 'b_walker'}
    assert lines[0]['aae_deg'] < lines[1]['aae_deg']


@pytest.mark.parametrize('args,message', [
    (['--methods', 'magic'], 'unknown method'),
    (['--screen', 'view_fraction=2'], 'view_fraction'),
    (['--control', 'gain=3'], 'unknown --control'),
    (['--max-frames', '0'], '--max-frames'),
    (['--latency', '-5'], '--latency'),
    (['--latency', '30', '--mode', 'realtime'], '--latency is for --mode lockstep'),
    (['--seed', '-1'], '--seed must be in [0, 4294967295], got -1'),
    (['--control', 'kp=nan'], 'kp must be finite'),       # nan: a number, not the string
    (['--control', 'kp=fast'], "kp must be a number, got 'fast'"),
    (['--screen', 'width=100.5'], 'width must be a whole number'),
    (['--sequences', 'walker', 'walkr'], "no sequence 'walkr' under"),
])
def test_cli_refuses_bad_options(tmp_path, capsys, args, message):
    make_walker(tmp_path, n=3)
    assert bench.main(['--data', str(tmp_path), '--quiet', '--no-video', '--out',
                       str(tmp_path / 'out'), '--methods', 'centre', *args]) == 2
    assert message in capsys.readouterr().err


def test_an_out_folder_that_cannot_be_made_fails_before_the_run(tmp_path, capsys):
    make_walker(tmp_path, n=3)
    (tmp_path / 'afile').write_text('kept')
    assert bench.main(['--data', str(tmp_path), '--quiet', '--no-video', '--methods', 'centre',
                       '--out', str(tmp_path / 'afile')]) == 2
    assert '--out' in capsys.readouterr().err and (tmp_path / 'afile').read_text() == 'kept'


def test_control_kp_and_kd_set_the_gains_of_every_method_but_a_pd_variant():
    assert bench.controller_for('ours', {'kp': 0.5, 'kd': 0.2}).pd.kp == 0.5
    assert bench.controller_for('oracle', {'kd': 0.2}).pd.kd == 0.2
    high_d = bench.controller_for('ours-pd-high_d', {'kp': 0.5, 'dead_band_deg': 1.0}).pd
    assert (high_d.kp, high_d.kd, high_d.dead_band) == (1.0, 1.0,
                                                        pytest.approx(math.radians(1.0)))
    with pytest.raises(ConfigError, match='kp'):
        bench.controller_for('ours', {'kp': -1.0})


def test_help(capsys):
    with pytest.raises(SystemExit) as exc:
        bench.main(['--help'])
    assert exc.value.code == 0
    assert '--mode' in capsys.readouterr().out


def test_tracker_methods_run_in_the_loop(tmp_path, capsys):
    make_walker(tmp_path, n=8)
    assert bench.main(['--data', str(tmp_path), '--methods', 'kcf', 'mosse', '--jobs', '1',
                       '--no-video', '--quiet', '--json', '--out', str(tmp_path / 'out'),
                       '--screen', 'width=320', 'height=240']) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r['method'] for r in rows] == ['kcf', 'mosse']
    assert all(math.isfinite(r['aae_deg']) for r in rows)


def test_ours_does_not_follow_a_passing_car_off_the_screen(data_root, tmp_path, capsys):
    """
    Regression on real frames, the faithful rig: on otb_crossing the argmax cell of the
    map followed a passing car and then the screen's edge, out to the wall (in view 53%,
    AAE 42.6 deg; a camera that never moves: 23.4 deg). The centroid of the cells near
    the peak stays with the scene (in view 100%, 13.4-15.8 deg over 3 seeds). The PD law is
    pinned to kd 0 on the action's direction, the law this guard was set with: the paper's
    kd 0.1 on the error, the default since, loses the crossing by itself (docs/decisions.md,
    38.7 deg on seed 0).
    """
    assert bench.main(['--data', str(data_root), '--sequences', 'otb_crossing', '--methods',
                       'ours', '--control', 'kd=0', 'derivative=target', '--jobs', '1',
                       '--json', '--no-video', '--quiet', '--out', str(tmp_path)]) == 0
    row = json.loads(capsys.readouterr().out.splitlines()[0])
    result = row['sequences']['otb_crossing']
    assert result['in_view'] >= 0.9 and result['aae_deg'] < 23.0, result


def test_the_model_pointer_shares_only_a_frozen_encoder():
    """
    An encoder that learns online starts every sequence from the same weights; a frozen
    one is the same object, so it is not built again.
    """
    from activeloc_ros.bench.pointers import ModelPointer
    import torch
    tiny = {'encoder': 'efficientnet_lite0', 'pretrained': False, 'hidden': 8,
            'attn_units': 8, 'ego_motion': 'none'}
    frames = np.random.default_rng(0).integers(0, 255, (4, 64, 64, 3), np.uint8)

    learning = ModelPointer('ours', {**tiny, 'update_encoder': True})
    learning.reset('a')
    start = [p.detach().clone() for p in learning.model.encoder.parameters()]
    for frame in frames:
        learning.model.step(frame)
    assert any(not torch.equal(a, b) for a, b in zip(start, learning.model.encoder.parameters()))
    learning.reset('b')                                # the next sequence
    assert all(torch.equal(a, b) for a, b in zip(start, learning.model.encoder.parameters()))

    frozen = ModelPointer('ours', tiny)
    frozen.reset('a')
    encoder = frozen.model.encoder
    frozen.model.step(frames[0])
    frozen.reset('b')
    assert frozen.model.encoder is encoder
