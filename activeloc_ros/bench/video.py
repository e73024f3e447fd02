"""
MP4 videos that browsers play: H.264 (yuv420p, index at the front) through PyAV.

OpenCV's pip wheels write MPEG-4 Part 2 ('mp4v'), which no browser plays, and carry no
H.264 encoder; PyAV's wheels bundle FFmpeg with libx264.
"""
import argparse
from fractions import Fraction
import os
from pathlib import Path
import sys
from typing import Callable

import av
import numpy as np


class H264Writer:
    """
    Writes BGR frames of one size (even width and height) to an H.264 MP4.

    :param path: the file to write (created or truncated).
    :param fps: frames per second.
    :param size: (width, height) of every frame.
    :param crf: x264 quality, 0 (lossless) to 51; 23 is its default.
    """

    def __init__(self, path: Path, fps: float, size: tuple[int, int], *, crf: int = 23):
        width, height = size
        if width % 2 or height % 2:
            raise ValueError(f'H.264 in yuv420p needs an even frame size, got {size}')
        # faststart: the index before the data, so a browser starts playing at once
        self.container = av.open(str(path), mode='w', format='mp4',
                                 options={'movflags': '+faststart'})
        try:
            self.stream = self.container.add_stream(
                'libx264', rate=Fraction(fps).limit_denominator(1001),
                options={'crf': str(crf), 'preset': 'veryfast'})
            self.stream.width, self.stream.height = width, height
            self.stream.pix_fmt = 'yuv420p'   # what browsers decode
        except BaseException:
            self.container.close()
            raise
        self.size = (width, height)
        self.frames = 0

    def write(self, frame: np.ndarray) -> None:
        """Append one (H, W, 3) uint8 BGR frame."""
        if frame.shape != (self.size[1], self.size[0], 3):
            raise ValueError(f'frame of shape {frame.shape}, the video is {self.size}')
        picture = av.VideoFrame.from_ndarray(frame, format='bgr24')
        picture.pts = self.frames
        self.frames += 1
        self.container.mux(self.stream.encode(picture))

    def close(self) -> None:
        """Flush the encoder and finish the file."""
        try:
            self.container.mux(self.stream.encode(None))
        finally:
            self.container.close()


# A benchmark writes each video to a temporary file beside it and puts it in place once its
# tables are written, so an interrupted run leaves the previous run's videos as they were.

def temporary_path(path: Path) -> Path:
    """Where the video for ``path`` is written until it is committed."""
    return path.with_name(f'.{path.stem}.tmp{path.suffix}')


def commit_video(path: Path) -> None:
    """Put a finished video in place (none if its run failed)."""
    if temporary_path(path).exists():
        os.replace(temporary_path(path), path)


class PendingVideo:
    """
    Write a video for ``path`` at ``fps`` to its `temporary_path`.

    It opens at the first frame, whose size it takes; `commit_video` puts it in place once
    the benchmark has its tables, and `abandon` removes it.
    """

    def __init__(self, path: Path, fps: float):
        self.path, self.fps = path, fps
        self.tmp = temporary_path(path)
        self.tmp.unlink(missing_ok=True)     # a killed run's leftover
        self.writer: H264Writer | None = None

    def write(self, frame: np.ndarray) -> None:
        """Append one (H, W, 3) uint8 BGR frame, of the first frame's size."""
        if self.writer is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.writer = H264Writer(self.tmp, self.fps, (frame.shape[1], frame.shape[0]))
        self.writer.write(frame)

    def finish(self) -> None:
        if self.writer is not None:
            self.writer.close()

    def abandon(self) -> None:
        try:
            self.finish()
        finally:
            self.tmp.unlink(missing_ok=True)


def discard_videos(video_dir: Path) -> None:
    """Remove every unfinished or uncommitted video under ``video_dir``."""
    for tmp in video_dir.glob('*/.*.tmp.mp4'):
        tmp.unlink(missing_ok=True)


def run_keeping_results(run: Callable[[argparse.Namespace], int],
                        args: argparse.Namespace) -> int:
    """
    Run a benchmark that writes its results and videos into ``args.out``.

    After a Ctrl-C the unfinished videos are gone, the previous results stay, and the exit
    status is 130.
    """
    try:
        return run(args)
    except KeyboardInterrupt:
        discard_videos(Path(args.out) / 'videos')
        end_of_progress_line = '\n' if sys.stderr.isatty() else ''
        print(f'{end_of_progress_line}interrupted: {args.out} keeps the previous results',
              file=sys.stderr)
        return 130
