"""
`bench scenes`: synthetic static-camera sequences from the tracking world's engine, read
back by `data.load_sequence`. Tiny scenes (160x90, 8 frames) keep it fast.
"""
import json

import numpy as np
import pytest

from activeloc_ros import data
from activeloc_ros.bench import scenes
from activeloc_ros.tracking.clips import ClipConfig, SyntheticClip

TINY = ['--width', '160', '--height', '90', '--frames', '8', '--jobs', '1', '--quiet']
CONFIG = ClipConfig(width=160, height=90, frames=8)
GT_FILES = ('gt_xywh.txt', 'gt_all_xywh.txt', 'distractors_xywh.txt')


def generate(out, seed: int, *extra: str) -> int:
    return scenes.main(['--count', '2', '--out', str(out), '--seed', str(seed), *TINY, *extra])


@pytest.fixture(scope='module')
def seed3(tmp_path_factory):
    out = tmp_path_factory.mktemp('seed3')
    assert generate(out, 3) == 0
    return out


def gt_bytes(folder) -> dict:
    return {name: (folder / name).read_bytes() for name in GT_FILES}


def test_scenes_load_as_static_sequences_with_the_actor_annotated_alone(seed3):
    sequences, skipped = data.load_sequences(seed3)
    assert skipped == [] and [s.name for s in sequences] == ['synth_000', 'synth_001']
    assert not (seed3 / scenes.STAGING).exists()
    for seq in sequences:
        assert seq.camera_kind == 'static' and len(seq) == 8 and seq.fps == 15.0
        assert seq.meta['primary_track'] == 1
        params = seq.meta['scene_params']
        assert params['action'] in ('walk', 'run', 'dance', 'kick', 'punch', 'jump')
        assert params['distractor_count'] == len(params['distractors']) <= 6
        visible = [t.primary for t in seq.truth if t.primary is not None]
        assert len(visible) >= 6                          # in view on most frames
        for t in seq.truth:                               # gt_all: the actor only
            assert t.actors == ((t.primary,) if t.primary else ())
        for box in visible:
            assert 0 <= box.x and box.x + box.w <= 160 and 0 <= box.y and box.y + box.h <= 90
        images = [s.image for s in seq.frames()]
        assert len(images) == 8 and images[0].shape == (90, 160, 3)


def test_each_box_lies_where_the_camera_sees_the_actor_stand(seed3):
    """
    The mask's box against the planned path through the camera model: the actor's
    mid-body point projects inside its box.
    """
    for index in (0, 1):
        seq = data.load_sequence(seed3 / scenes.scene_name(index))
        with SyntheticClip(3, index, CONFIG) as clip:
            actor = clip.motions[0]
            middle = np.column_stack([actor.xy, np.full(len(actor.xy), 0.9 * actor.scale)])
            uv, _ = clip.camera.project(middle)
        for t, (u, v) in zip(seq.truth, uv):
            if t.primary is not None:
                assert t.primary.grown(3, 3).contains(u, v), (index, t.index, t.primary, u, v)


def test_the_camera_never_moves(seed3):
    """
    Outside the people's boxes the first and the last frame are the same picture (but
    for H.264's noise and the people's shadows).
    """
    for index in (0, 1):
        folder = seed3 / scenes.scene_name(index)
        seq = data.load_sequence(folder)
        images = [s.image.astype(int) for s in seq.frames()]
        still = np.ones((90, 160), bool)
        boxes = [t.primary for t in seq.truth if t.primary]
        for line in (folder / 'distractors_xywh.txt').read_text().splitlines()[1:]:
            boxes.append(data.Box(*map(float, line.split(',')[2:6])))
        for b in boxes:
            b = b.grown(2, 2)
            still[max(0, int(b.y)):int(b.y + b.h) + 1, max(0, int(b.x)):int(b.x + b.w) + 1] = 0
        assert still.mean() > 0.5
        change = np.abs(images[-1] - images[0]).max(axis=2)[still]
        assert np.median(change) <= 2 and np.mean(change > 20) < 0.02


def test_the_same_seed_gives_identical_gt_and_another_seed_others(tmp_path, seed3):
    assert generate(tmp_path / 'again', 3) == 0
    assert generate(tmp_path / 'other', 4) == 0
    for index in (0, 1):
        name = scenes.scene_name(index)
        assert gt_bytes(tmp_path / 'again' / name) == gt_bytes(seed3 / name)
        first = json.loads((seed3 / name / 'meta.json').read_text())
        again = json.loads((tmp_path / 'again' / name / 'meta.json').read_text())
        assert again['scene_params'] == first['scene_params']
        other = tmp_path / 'other' / name
        assert (other / 'gt_xywh.txt').read_bytes() != (seed3 / name / 'gt_xywh.txt').read_bytes()


def test_a_rerun_skips_up_to_date_scenes_and_replaces_the_others(tmp_path, capsys):
    assert generate(tmp_path, 5) == 0
    killed = tmp_path / scenes.STAGING / '99999999' / 'synth_000.x'   # a killed run's
    killed.mkdir(parents=True)
    stamp = (tmp_path / 'synth_000' / 'meta.json').stat().st_mtime_ns
    capsys.readouterr()
    assert generate(tmp_path, 5) == 0
    assert '2 skipped' in capsys.readouterr().out
    assert (tmp_path / 'synth_000' / 'meta.json').stat().st_mtime_ns == stamp
    assert scenes.main(['--count', '1', '--out', str(tmp_path), '--seed', '5', *TINY,
                        '--frames', '6']) == 0
    assert len(data.load_sequence(tmp_path / 'synth_000')) == 6      # other settings: redone
    assert len(data.load_sequence(tmp_path / 'synth_001')) == 8      # beyond --count: kept
    assert sorted(p.name for p in tmp_path.iterdir()) == ['synth_000', 'synth_001']


def test_an_interrupted_run_leaves_only_whole_scenes(tmp_path, monkeypatch):
    real = scenes.render_scene

    def render(folder, seed, index, config):
        if index == 1:                  # Ctrl-C halfway through the second scene
            (folder / 'gt_xywh.txt').write_text('0,0,1,1\n')
            raise KeyboardInterrupt
        return real(folder, seed, index, config)

    monkeypatch.setattr(scenes, 'render_scene', render)
    assert generate(tmp_path, 6) == 130
    assert sorted(p.name for p in tmp_path.iterdir()) == ['synth_000']
    assert len(data.load_sequence(tmp_path / 'synth_000')) == 8


@pytest.mark.parametrize('extra, message', [
    (['--count', '0'], '--count'),
    (['--width', '161'], 'even'),
    (['--seed', '-1'], '--seed'),
    (['--frames', '0'], 'frames'),
    (['--fps', 'nan'], 'fps'),
])
def test_bad_input_is_refused_before_any_scene(tmp_path, capsys, extra, message):
    out = tmp_path / 'out'
    argv = ['--count', '1', '--out', str(out), *TINY, *extra]
    assert scenes.main(argv) == 2
    assert message in capsys.readouterr().err
    assert not out.exists() or not any(out.iterdir())


def test_an_out_path_under_a_file_is_refused(tmp_path, capsys):
    (tmp_path / 'file').write_text('')
    assert scenes.main(['--count', '1', '--out', str(tmp_path / 'file' / 'x'), *TINY]) == 2
    assert '--out' in capsys.readouterr().err
