"""
The sequence loader: good folders stream RGB frames with their ground truth, bad ones
raise DataError naming the file (and line).
"""
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from activeloc_ros import data
from activeloc_ros.errors import DataError

W, H = 32, 24


def make_sequence(root: Path, name: str = 'seq', *, n: int = 4, gt: list[str] | None = None,
                  meta: dict | None = None, video: bool = False, n_images: int | None = None,
                  gt_all: list[str] | None = None) -> Path:
    """A tiny sequence folder: frame i is black with a red 4x4 square at x = 4i, y = 0."""
    path = root / name
    path.mkdir(parents=True)
    images = []
    for i in range(n if n_images is None else n_images):
        bgr = np.zeros((H, W, 3), np.uint8)
        bgr[0:4, 4 * i:4 * i + 4] = (0, 0, 255)
        images.append(bgr)
    m = {'W': W, 'H': H, 'frames': n, 'camera': 'STATIC'}
    if video:
        writer = cv2.VideoWriter(str(path / 'v.avi'), cv2.VideoWriter_fourcc(*'MJPG'), 10,
                                 (W, H))
        for bgr in images:
            writer.write(bgr)
        writer.release()
        m['video'] = 'v.avi'
    else:
        (path / 'img').mkdir()
        for i, bgr in enumerate(images):
            cv2.imwrite(str(path / 'img' / f'{i:04d}.png'), bgr)
        m['frames_glob'] = 'img/*.png'
    m.update(meta or {})
    (path / 'meta.json').write_text(json.dumps(m, indent=1))
    rows = gt if gt is not None else [f'{i}.0,2.0,5.0,6.0' for i in range(n)]
    (path / 'gt_xywh.txt').write_text('\n'.join(rows) + '\n')
    if gt_all is not None:
        (path / 'gt_all_xywh.txt').write_text('\n'.join(gt_all) + '\n')
    return path


def test_image_sequence_streams_rgb_frames_with_truth(tmp_path):
    gt = ['# x,y,w,h', '1,2,5,6', '', 'nan,nan,nan,nan', '3.5, 2, 5, 6', '4,2,5,6']
    seq = data.load_sequence(make_sequence(tmp_path, gt=gt))
    assert (seq.name, len(seq), seq.width, seq.height) == ('seq', 4, W, H)
    samples = list(seq.frames())
    assert [s.index for s in samples] == [0, 1, 2, 3]
    first = samples[0].image
    assert first.shape == (H, W, 3) and first.dtype == np.uint8
    assert tuple(first[1, 0]) == (255, 0, 0)  # red in RGB order
    assert samples[0].truth.primary == data.Box(1, 2, 5, 6)
    assert samples[0].truth.actors == (data.Box(1, 2, 5, 6),)
    assert samples[1].truth.primary is None and samples[1].truth.actors == ()
    assert samples[2].truth.primary.x == 3.5
    assert all(s.truth.scored for s in samples)
    assert len(list(seq.frames(max_frames=2))) == 2


def test_video_sequence_decodes_every_frame(tmp_path):
    seq = data.load_sequence(make_sequence(tmp_path, video=True, n=5))
    frames = [s.image for s in seq.frames()]
    assert len(frames) == 5
    assert frames[3].shape == (H, W, 3)
    # MJPG is lossy: compare the red squares' positions, not pixel values
    redness = frames[3][0:4, :, 0].astype(int) - frames[3][0:4, :, 2]
    assert int(np.argmax(redness.reshape(4, 8, 4).sum(axis=(0, 2)))) == 3


@pytest.mark.parametrize('n_images, message', [(3, 'ends after 3 frames'),
                                               (6, 'more than the 5 frames')])
def test_video_with_the_wrong_frame_count_raises(tmp_path, n_images, message):
    seq = data.load_sequence(make_sequence(tmp_path, video=True, n=5, n_images=n_images))
    with pytest.raises(DataError, match=message):
        list(seq.frames())


def test_missing_frames_are_reported(tmp_path):
    path = make_sequence(tmp_path, n=4, n_images=3)
    with pytest.raises(DataError, match=r'meta\.json.*matches 3 files, frames is 4'):
        data.load_sequence(path)


def test_corrupt_image_is_reported_while_streaming(tmp_path):
    path = make_sequence(tmp_path)
    (path / 'img' / '0002.png').write_bytes(b'not a png')
    seq = data.load_sequence(path)
    with pytest.raises(DataError, match=r'0002\.png: cannot decode'):
        list(seq.frames())


def test_frame_of_the_wrong_size_is_reported(tmp_path):
    path = make_sequence(tmp_path, meta={'W': W + 1})
    with pytest.raises(DataError, match=rf'frame 0 is {W}x{H}'):
        next(data.load_sequence(path).frames())


@pytest.mark.parametrize('rows, message', [
    (['1,2,5,6'] * 3, r'gt_xywh\.txt: 3 ground-truth rows, meta\.json frames is 4'),
    (['1,2,5,6'] * 5, r'gt_xywh\.txt: 5 ground-truth rows'),
    (['1,2,5,6', '1,2,5', '1,2,5,6', '1,2,5,6'], r'gt_xywh\.txt:2: expected x,y,w,h'),
    (['# c', '1,2,5,6', '1,2,abc,6', '1,2,5,6', '1,2,5,6'], r'gt_xywh\.txt:3: not a number'),
    (['1,2,5,6', '1,2,5,6', '1,nan,5,6', '1,2,5,6'], r'gt_xywh\.txt:3: .*all nan'),
    (['1,2,5,6', '1,2,5,6', '1,2,5,6', '1,2,-5,6'], r'gt_xywh\.txt:4: .*positive'),
    (['1,2,5,6', 'inf,2,5,6', '1,2,5,6', '1,2,5,6'], r'gt_xywh\.txt:2: .*finite'),
])
def test_malformed_ground_truth_names_file_and_line(tmp_path, rows, message):
    with pytest.raises(DataError, match=message):
        data.load_sequence(make_sequence(tmp_path, gt=rows))


def test_missing_ground_truth_file(tmp_path):
    path = make_sequence(tmp_path)
    (path / 'gt_xywh.txt').unlink()
    with pytest.raises(DataError, match=r'gt_xywh\.txt: missing'):
        data.load_sequence(path)


@pytest.mark.parametrize('edit, message', [
    (lambda m: m.pop('H'), r'missing key\(s\) H'),
    (lambda m: m.pop('frames_glob'), 'video or frames_glob'),
    (lambda m: m.update(W='32'), 'W must be a positive integer'),
    (lambda m: m.update(frames=0), 'frames must be a positive integer'),
    (lambda m: m.update(video='nope.mp4') or m.pop('frames_glob'), 'nope.mp4.*does not exist'),
    (lambda m: m.update(eval_frames=[2, 9]), 'eval_frames'),
])
def test_bad_meta_is_reported(tmp_path, edit, message):
    path = make_sequence(tmp_path)
    meta = json.loads((path / 'meta.json').read_text())
    edit(meta)
    (path / 'meta.json').write_text(json.dumps(meta))
    with pytest.raises(DataError, match=r'meta\.json: .*' + message):
        data.load_sequence(path)


def test_unparsable_meta_names_the_line(tmp_path):
    path = make_sequence(tmp_path)
    (path / 'meta.json').write_text('{\n "W": 32,\n "H": ,\n}')
    with pytest.raises(DataError, match=r'meta\.json:3: not valid JSON'):
        data.load_sequence(path)


def test_all_actors_and_eval_frames(tmp_path):
    gt_all = ['# frame0,track_id,x,y,w,h,conf',
              '0,7,1,2,5,6,1', '0,8,20,2,5,6,1', '1,8,21,2,5,6,1',
              '2,9,10,10,4,4,0',  # conf 0: a MOT 'ignore' entry
              '3,7,4,2,5,6,1']
    path = make_sequence(tmp_path, gt=['1,2,5,6', 'nan,nan,nan,nan', 'nan,nan,nan,nan',
                                       '4,2,5,6'],
                         meta={'primary_track': 7, 'eval_frames': [0, 2]}, gt_all=gt_all)
    truth = data.load_sequence(path).truth
    assert truth[0].actors == (data.Box(1, 2, 5, 6), data.Box(20, 2, 5, 6))
    assert truth[1].primary is None and truth[1].actors == (data.Box(21, 2, 5, 6),)
    assert truth[2].actors == ()
    assert [t.scored for t in truth] == [True, True, True, False]


@pytest.mark.parametrize('row, message', [
    ('4,7,1,2,5,6,1', r'gt_all_xywh\.txt:1: frame 4 outside 0\.\.3'),
    ('0,7,1,2,5,6', r'gt_all_xywh\.txt:1: expected frame0'),
    ('0,7,1,x,5,6,1', r'gt_all_xywh\.txt:1: not a number'),
])
def test_malformed_all_actors_file(tmp_path, row, message):
    path = make_sequence(tmp_path, gt_all=[row])
    with pytest.raises(DataError, match=message):
        data.load_sequence(path)


def test_find_and_load_skip_bad_sequences(tmp_path):
    make_sequence(tmp_path, 'b_good')
    make_sequence(tmp_path, 'a_moving', meta={'camera': 'MOVING handheld'})
    make_sequence(tmp_path, 'c_bad', gt=['1,2,5,6'])
    (tmp_path / 'not_a_sequence').mkdir()
    assert [p.name for p in data.find_sequences(tmp_path)] == ['a_moving', 'b_good', 'c_bad']
    assert data.find_sequences(tmp_path / 'b_good') == [tmp_path / 'b_good']
    seqs, skipped = data.load_sequences(tmp_path)
    assert [s.name for s in seqs] == ['a_moving', 'b_good']
    assert [name for name, _ in skipped] == ['c_bad']
    assert 'gt_xywh.txt' in skipped[0][1]
    seqs, skipped = data.load_sequences(tmp_path, names=['b_good', 'zzz'],
                                        cameras=['static'])
    assert [s.name for s in seqs] == ['b_good'] and skipped == [('zzz', 'no such sequence')]
    seqs, _ = data.load_sequences(tmp_path, cameras=['static'])
    assert [s.name for s in seqs] == ['b_good']


@pytest.mark.parametrize('text, kind', [
    ('STATIC', 'static'), ('STATIC (street level)', 'static'), ('slow PAN following', 'pan'),
    ('PAN/handheld (elevated)', 'pan'), ('MOVING (pans to follow)', 'moving'),
    ('handheld', 'moving'),
])
def test_camera_kind(text, kind):
    assert data.camera_kind(text) == kind


def test_data_root_resolution(tmp_path, monkeypatch):
    monkeypatch.setenv(data.ENV_VAR, str(tmp_path))
    assert data.resolve_data_root() == tmp_path
    assert data.resolve_data_root(str(tmp_path / '..')) == tmp_path / '..'
    with pytest.raises(DataError, match='not a directory'):
        data.resolve_data_root(tmp_path / 'absent')
    with pytest.raises(DataError, match='not a directory'):
        data.find_sequences(tmp_path / 'absent')


def test_box_geometry():
    box = data.Box(10, 20, 4, 6)
    assert box.centre == (12, 23)
    assert box.grown(1, 2) == data.Box(9, 18, 6, 10)
    assert box.contains(14, 26) and not box.contains(14.1, 26)


REAL_ROOT = data.default_data_root()
needs_real = pytest.mark.skipif(REAL_ROOT is None or not REAL_ROOT.is_dir(),
                                reason='real sequences absent (set ACTIVELOC_DATA)')


@needs_real
def test_real_sequences_load():
    seqs, skipped = data.load_sequences(REAL_ROOT)
    assert seqs and not skipped
    for seq in seqs:
        assert len(seq) == seq.meta['frames']
        assert any(t.primary is not None for t in seq.truth)
    small = min(seqs, key=lambda s: s.width * s.height * len(s))
    sample = next(small.frames())
    assert sample.image.shape == (small.height, small.width, 3)
    for box in sample.truth.actors:
        assert math.isfinite(box.x) and box.w > 0
