"""
Make the bundled sample bag `bags/vtest`, or a bag of your own video.

    python bags/make_sample.py                       # vtest.avi from Debian's opencv-doc
    python bags/make_sample.py --video FILE --out DIR [--frames N] [--width W]

Each frame becomes a JPEG `sensor_msgs/CompressedImage` on /camera/image_raw/compressed, in
a rosbag2 MCAP bag. Without --video it downloads opencv-doc with `apt-get download` and
checks the video's sha256. A repository tool, not part of the installed package.
"""
import argparse
from pathlib import Path
import shutil
import subprocess
import sys
import tempfile

import numpy as np

from activeloc_ros.bag.read import bag_facts, BagFacts, format_facts
from activeloc_ros.bag.write import BagWriter, RecordingError
from activeloc_ros.errors import SourceError
from activeloc_ros.paths import file_sha256

# The sample bag: OpenCV's vtest.avi (pedestrians, 768x576, 10 fps), shipped by Debian's
# opencv-doc package under Apache-2.0 AND BSD-3-Clause.
SAMPLE_DEB = 'opencv-doc'
SAMPLE_MEMBER = './usr/share/doc/opencv-doc/examples/data/vtest.avi'
SAMPLE_SHA256 = '45cddc9490be69345cbdab64ca583be65987e864ca408038e648db99e10516cf'
SAMPLE_TOPIC = '/camera/image_raw/compressed'
SAMPLE_FRAME_ID = 'camera_color_optical_frame'
SAMPLE_START_NS = 1_700_000_000 * 10**9


def fetch_sample_video(workdir: Path) -> Path:
    """Download Debian's opencv-doc and extract vtest.avi (needs apt-get and dpkg-deb)."""
    subprocess.run(['apt-get', 'download', SAMPLE_DEB], cwd=workdir, check=True)
    deb = next(workdir.glob(f'{SAMPLE_DEB}_*.deb'))
    tar = subprocess.run(['dpkg-deb', '--fsys-tarfile', str(deb)], check=True,
                         capture_output=True).stdout
    subprocess.run(['tar', '-x', '-C', str(workdir), SAMPLE_MEMBER], input=tar, check=True)
    video = workdir / SAMPLE_MEMBER
    if file_sha256(video) != SAMPLE_SHA256:
        raise SourceError(f'{video.name} from {deb.name} does not have the expected sha256')
    return video


def replaceable(out: Path) -> bool:
    """
    May `make_sample` replace ``out``? Only when it is absent or a rosbag2 folder: its
    metadata.yaml and MCAP files, nothing else.
    """
    if not out.exists():
        return True
    return out.is_dir() and (out / 'metadata.yaml').is_file() and all(
        f.name == 'metadata.yaml' or f.suffix in ('.mcap', '.incomplete') for f in out.iterdir())


def make_sample(video: Path, out: Path, *, frames: int, width: int, quality: int) -> BagFacts:
    """
    Write `frames` frames of `video`, resized to `width`, as JPEG CompressedImage messages.
    ``out`` is replaced only if it is a bag (`replaceable`); anything else is refused.
    """
    import cv2
    if frames < 1 or not 16 <= width <= 8192 or not 0 <= quality <= 100:
        raise SourceError(f'need frames >= 1, width in 16..8192 and quality in 0..100, got '
                          f'{frames}, {width} and {quality}')
    if not replaceable(out):
        raise SourceError(f'{out} exists and is not a bag: not replacing it')
    capture = cv2.VideoCapture(str(video))
    if not capture.isOpened():
        raise SourceError(f'cannot open video {video}')
    fps = capture.get(cv2.CAP_PROP_FPS) or 10.0
    tmp = out.with_name(out.name + '.partial')
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        written = _write_sample(capture, BagWriter(tmp), frames=frames, width=width,
                                quality=quality, fps=fps)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)    # no half-made bag left beside ``out``
        raise
    if written == 0:
        shutil.rmtree(tmp, ignore_errors=True)
        raise SourceError(f'no frame could be read from {video}')
    shutil.rmtree(out, ignore_errors=True)
    # rosbags names the storage file after the folder; keep that true after the rename.
    for file in tmp.iterdir():
        if file.name.startswith(tmp.name):
            file.rename(tmp / file.name.replace(tmp.name, out.name, 1))
    metadata = tmp / 'metadata.yaml'
    metadata.write_text(metadata.read_text().replace(tmp.name, out.name))
    tmp.rename(out)
    return bag_facts(out)


def _write_sample(capture, writer: BagWriter, *, frames: int, width: int, quality: int,
                  fps: float) -> int:
    """`make_sample`'s frames into ``writer``, which it closes; how many were written."""
    import cv2
    store = writer.store
    Header = store.types['std_msgs/msg/Header']
    Time = store.types['builtin_interfaces/msg/Time']
    Compressed = store.types['sensor_msgs/msg/CompressedImage']
    written = 0
    while written < frames:
        ok, bgr = capture.read()
        if not ok:
            break
        height = round(bgr.shape[0] * width / bgr.shape[1])
        bgr = cv2.resize(bgr, (width, height), interpolation=cv2.INTER_AREA)
        ok, jpeg = cv2.imencode('.jpg', bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
        stamp = SAMPLE_START_NS + round(written * 1e9 / fps)
        header = Header(stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9),
                        frame_id=SAMPLE_FRAME_ID)
        msg = Compressed(header=header, format='jpeg', data=np.frombuffer(jpeg, np.uint8))
        writer.write(SAMPLE_TOPIC, 'sensor_msgs/msg/CompressedImage', stamp, msg)
        written += 1
    writer.close()
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python bags/make_sample.py', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--video', type=Path,
                        help='source video (default: vtest.avi from Debian opencv-doc)')
    parser.add_argument('--out', type=Path, default=Path(__file__).parent / 'vtest')
    parser.add_argument('--frames', type=int, default=300)
    parser.add_argument('--width', type=int, default=640)
    parser.add_argument('--quality', type=int, default=75)
    args = parser.parse_args(argv)
    try:
        with tempfile.TemporaryDirectory() as workdir:
            video = args.video if args.video is not None else fetch_sample_video(Path(workdir))
            facts = make_sample(video, args.out, frames=args.frames, width=args.width,
                                quality=args.quality)
        print(format_facts(facts))
        return 0
    except (SourceError, RecordingError, OSError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1


if __name__ == '__main__':
    sys.exit(main())
