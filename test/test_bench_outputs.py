"""
What `bench screen` leaves on disk: H.264 videos, plots over time, and nothing of an
interrupted run.
"""
import json
import math
import os
from pathlib import Path
import signal
import stat
import subprocess
import sys
import time

import av
import numpy as np
import pytest

from activeloc_ros.bench import screen as bench
from activeloc_ros.bench.time_plots import series, time_plots
from activeloc_ros.bench.video import H264Writer
from test_screen import make_walker

REPO = Path(__file__).resolve().parents[1]


def test_h264_writer_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    frames = [np.full((48, 64, 3), 40 * i, np.uint8) + rng.integers(0, 8, (48, 64, 3),
                                                                    dtype=np.uint8)
              for i in range(6)]
    writer = H264Writer(tmp_path / 'v.mp4', 12.5, (64, 48))
    for frame in frames:
        writer.write(frame)
    writer.close()
    with av.open(str(tmp_path / 'v.mp4')) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == 'h264'
        assert stream.codec_context.pix_fmt == 'yuv420p'     # what browsers decode
        decoded = [f.to_ndarray(format='bgr24') for f in container.decode(stream)]
    assert len(decoded) == 6
    for got, sent in zip(decoded, frames):
        assert np.abs(got.astype(int) - sent).mean() < 6


@pytest.mark.parametrize('size,frame_shape', [((63, 48), None), ((64, 48), (48, 62, 3))])
def test_h264_writer_refuses_odd_or_mismatched_frames(tmp_path, size, frame_shape):
    with pytest.raises(ValueError):
        writer = H264Writer(tmp_path / 'v.mp4', 10.0, size)
        try:
            writer.write(np.zeros(frame_shape, np.uint8))
        finally:
            writer.close()


def test_cli_writes_h264_readable_videos_and_plots_over_time(tmp_path, capsys):
    root = tmp_path / 'data'
    make_walker(root, 'a_walker', n=12)
    out = tmp_path / 'out'
    assert bench.main(['--data', str(root), '--methods', 'oracle', 'centre', '--jobs', '1',
                       '--out', str(out), '--screen', 'width=320', 'height=240',
                       '--quiet']) == 0
    assert 'time_a_walker.png' in capsys.readouterr().out
    video = out / 'videos' / 'a_walker' / 'oracle.mp4'
    assert video.stat().st_mode & stat.S_IROTH
    with av.open(str(video)) as container:
        stream = container.streams.video[0]
        assert (stream.codec_context.name, stream.frames) == ('h264', 12)
    assert (out / 'time_a_walker.png').read_bytes()[:4] == b'\x89PNG'
    result = json.loads((out / 'screen.json').read_text())
    t, pan = series(result, 'oracle', 'a_walker', 'pan_deg')
    assert len(t) == 12 and t == sorted(t)
    assert max(pan) > 0.5                    # the oracle turns after the walker
    assert not any(series(result, 'centre', 'a_walker', 'pan_deg')[1])


def test_time_plots_leave_gaps_for_unscored_frames(tmp_path):
    columns = bench.FRAME_COLUMNS
    row = dict.fromkeys(columns, 0)
    frames = []
    for i, aae in enumerate([5.0, None, 3.0]):
        frames.append([{**row, 'index': i, 't': 0.1 * i, 'aae_deg': aae}[c] for c in columns])
    result = {'sequences': ['s'], 'methods': [{'method': 'm'}], 'frame_columns': columns,
              'frames': {'m/s': frames}}
    t, aae = series(result, 'm', 's', 'aae_deg')
    assert t == [0.0, 0.1, 0.2] and aae[0] == 5.0 and math.isnan(aae[1])
    assert [p.name for p in time_plots(result, tmp_path)] == ['time_s.png']


# `python -m activeloc_ros.bench` with Ctrl-C raising KeyboardInterrupt, as on a terminal, even
# when the suite runs with SIGINT ignored (a background job), which Python would pass on
CTRL_C_AS_ON_A_TERMINAL = (
    'import runpy, signal; signal.signal(signal.SIGINT, signal.default_int_handler); '
    "runpy.run_module('activeloc_ros.bench', run_name='__main__', alter_sys=True)")


@pytest.mark.parametrize('jobs', [1, 2])
def test_ctrl_c_keeps_the_previous_results(tmp_path, jobs):
    root = tmp_path / 'data'
    for i in range(6):
        make_walker(root, f'w{i}', n=40)
    out = tmp_path / 'out'
    previous = {out / 'screen.md': b'previous table\n',
                out / 'videos' / 'w0' / 'oracle.mp4': b'previous video',
                out / 'videos' / 'w5' / 'oracle.mp4': b'previous video'}
    for path, content in previous.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(content)
    proc = subprocess.Popen(
        [sys.executable, '-c', CTRL_C_AS_ON_A_TERMINAL, 'screen', '--data', str(root),
         '--methods', 'oracle', '--jobs', str(jobs), '--out', str(out),
         '--screen', 'width=320', 'height=240', '--camera-fps', '0'],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    try:
        # a video under way: the run is in the middle of its first sequences
        deadline = time.monotonic() + 60
        while not list(out.glob('videos/*/.oracle.tmp.mp4')):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, 'no video was started'
            time.sleep(0.02)
        os.killpg(proc.pid, signal.SIGINT)          # Ctrl-C on a terminal: the whole group
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    err = err.decode()
    assert proc.returncode == 130, err
    assert 'Traceback' not in err and f'interrupted: {out} keeps the previous results' in err
    assert not list(out.rglob('*.tmp*'))
    assert {p: p.read_bytes() for p in previous} == previous
    assert sorted(p.relative_to(out) for p in out.rglob('*') if p.is_file()) == sorted(
        p.relative_to(out) for p in previous)
