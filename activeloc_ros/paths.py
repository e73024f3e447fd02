"""Where the package's data files are (the source tree when run from it, else share/)."""
import hashlib
import os
from pathlib import Path
import sys
import tempfile

SOURCE_ROOT = Path(__file__).resolve().parents[1]
# the graph's nodes, in the order bringup starts and stops
# them (the arm last). A virtual camera's run has the sim node in place of camera and arm,
# the tracking world's the tracking node.
NODE_NAMES = ('camera', 'sim', 'tracking', 'perception', 'controller', 'arm')


def share_path(relative: str) -> Path:
    """
    `relative` (e.g. 'params/camera.yaml') in the source tree, else in the installed
    share: the ament index's (colcon) or, without one, pip's (``<prefix>/share``).
    """
    here = SOURCE_ROOT / relative
    if here.exists():
        return here
    try:
        from ament_index_python.packages import get_package_share_directory
        return Path(get_package_share_directory('activeloc_ros')) / relative
    except (ImportError, LookupError, OSError):   # OSError: AMENT_PREFIX_PATH is not set
        pass
    installed = Path(sys.prefix) / 'share' / 'activeloc_ros' / relative
    return installed if installed.exists() else here


def packaged_params_files() -> list[Path]:
    """
    The params files the package gives every node: params/robot.yaml, what several nodes
    must agree on (the home pose, the servos' speed, the aiming joints). Everything else is
    the nodes' declared defaults (docs/parameters.md); a user's --params file holds what
    differs from them.
    """
    return [share_path('params/robot.yaml')]


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, 'rb') as stream:
        for block in iter(lambda: stream.read(1 << 20), b''):
            digest.update(block)
    return digest.hexdigest()


def write_atomic(path: Path, content: str | bytes) -> None:
    """
    Write through a temporary file in the same folder, then rename over `path`: a reader
    (or an interrupted run) never sees half a file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f'.{path.name}.', suffix='.tmp')
    try:
        with os.fdopen(fd, 'wb') as f:
            f.write(content.encode('utf-8') if isinstance(content, str) else content)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
