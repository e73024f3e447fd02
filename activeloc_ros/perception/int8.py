"""
The frozen encoder in int8 (`encoder_precision: int8`): OpenVINO runs it, after NNCF's
post-training quantisation calibrated it once on frames of the bundled sample bag.

The quantised model is built the first time it is asked for (about a minute on 2 cores) and
kept in the weight cache beside the float weights, under a name that digests everything it
depends on: the encoder's weights, its input size, the calibration frames and the OpenVINO
and NNCF versions. `python -m activeloc_ros.perception.weights fetch` builds it for the
default encoder, so the first run of the graph does not wait.

Calibration frames come from `bags/vtest` (OpenCV's pedestrian video, the graph's default
source) and not from the dev sequences: every installation has it, and the tolerance that
matters is on pictures the calibration never saw. `python -m activeloc_ros.bench perception
--feature-gap` measures it on the annotated sequences.
"""
import contextlib
import hashlib
import os
from pathlib import Path
import shutil
import sys
import tempfile
import time
from typing import Callable, Iterator, TextIO

import numpy as np
import torch
from torch import nn

from activeloc_ros.errors import ConfigError, WeightsError
from activeloc_ros.paths import file_sha256, write_atomic

CALIBRATION_FRAMES = 128
NEEDS = 'pip install openvino nncf (setup.py installs both)'
STALE_BUILD_S = 3600.0   # a build's folder this old was left by a killed process


def available() -> bool:
    """Can this installation build and run an int8 encoder?"""
    try:
        import nncf  # noqa: F401
        import openvino  # noqa: F401
    except ImportError:
        return False
    return True


class Int8Encoder(nn.Module):
    """
    A compiled OpenVINO model behind the encoder's interface: (1, 3, S, S) float ->
    (1, C, g, g) float. Frozen: it has no parameters and no gradient.
    """

    def __init__(self, compiled, input_shape: tuple[int, ...]):
        super().__init__()
        self.compiled = compiled
        self.request = compiled.create_infer_request()
        self.input_shape = tuple(input_shape)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if tuple(x.shape) != self.input_shape:
            raise ConfigError(f'the int8 encoder was built for inputs {self.input_shape}, '
                              f'got {tuple(x.shape)}')
        self.request.infer([np.ascontiguousarray(x.detach().float().numpy())])
        return torch.from_numpy(self.request.get_output_tensor(0).data.copy())


def calibration_frames(count: int | None = None) -> Iterator[np.ndarray]:
    """
    `count` (default `CALIBRATION_FRAMES`) RGB frames spread evenly over the bundled
    sample bag.
    """
    from activeloc_ros.sources import BagSource, default_bag
    count = count or CALIBRATION_FRAMES
    source = BagSource(default_bag())
    try:
        step = max(1, source.topic.count // count)
        taken = 0
        while taken < count:
            frame = source.read()
            if frame is None:
                break
            if frame.index % step == 0:
                taken += 1
                yield frame.rgb
    finally:
        source.close()


def cache_key(encoder: nn.Module, input_shape: tuple[int, ...]) -> str:
    """A digest of everything the quantised model depends on."""
    import nncf
    import openvino
    from activeloc_ros.paths import file_sha256
    from activeloc_ros.perception.cache import state_digest
    from activeloc_ros.sources import default_bag
    bag = sorted(default_bag().glob('*.mcap'))
    # the convolutions' padding (not in the state dict); zeros adds nothing, so models
    # built before conv_padding existed keep their key
    padding = {m.padding_mode for m in encoder.modules() if isinstance(m, nn.Conv2d)}
    parts = [state_digest(encoder.state_dict()), str(tuple(input_shape)),
             *sorted(padding - {'zeros'}),
             *(file_sha256(p) for p in bag), str(CALIBRATION_FRAMES),
             openvino.__version__, nncf.__version__]
    return hashlib.sha256('|'.join(parts).encode()).hexdigest()[:16]


REBUILD = 'rebuild it with `python -m activeloc_ros.perception.weights fetch`'


class DamagedError(WeightsError):
    """The cached int8 model is damaged: never a silent fall back to a 4x slower encoder."""


def load(encoder: nn.Module, *, name: str, input_shape: tuple[int, ...],
         prepare: Callable[[np.ndarray], torch.Tensor], threads: int,
         cache: Path, stream: TextIO | None = None) -> Int8Encoder:
    """
    The int8 version of the float32 `encoder`, built and cached on first use.

    :param prepare: turns a calibration RGB frame into the encoder's input, exactly as the
        model prepares its frames (resize, normalise, mirrored border).
    :raises WeightsError: OpenVINO or NNCF is missing, or the build failed.
    """
    if not available():
        raise WeightsError(f'encoder_precision int8 needs OpenVINO and NNCF: {NEEDS}')
    import openvino
    path = Path(cache) / 'int8' / f'{name}-{cache_key(encoder, input_shape)}.xml'
    if not (path.is_file() and _hashes(path).is_file()):   # (none: an unfinished build)
        build(encoder, path, input_shape=input_shape, prepare=prepare, stream=stream)
    damaged = damaged_files(path)
    if damaged:     # OpenVINO reads a .bin of the right size, whatever its bytes
        raise DamagedError(f'the int8 encoder {path} is damaged ({", ".join(damaged)} no '
                           f'longer match the hashes written when it was built): {REBUILD}')
    core = openvino.Core()
    config = {'INFERENCE_NUM_THREADS': max(1, threads), 'PERFORMANCE_HINT': 'LATENCY'}
    try:
        compiled = core.compile_model(core.read_model(path), 'CPU', config)
    except RuntimeError as exc:
        raise DamagedError(f'cannot load the int8 encoder {path} ({exc}): {REBUILD}') from exc
    return Int8Encoder(compiled, input_shape)


def damaged_files(path: Path) -> list[str]:
    """The files of the int8 model at ``path`` (.xml) that no longer match its hashes."""
    return [f for f, digest in _read_hashes(path).items()
            if not (path.parent / f).is_file() or file_sha256(path.parent / f) != digest]


def discard_damaged(cache: Path, stream: TextIO | None = None) -> list[Path]:
    """
    Delete every int8 model in ``cache`` that its hashes or OpenVINO say is damaged, so
    its next use builds it again from the weights; the models deleted.
    """
    out = stream or sys.stderr
    gone = []
    for xml in sorted((Path(cache) / 'int8').glob('*.xml')):
        if not _hashes(xml).is_file():
            continue                   # an unfinished build: its next use builds it anyway
        try:
            bad = damaged_files(xml)
        except WeightsError:
            bad = [_hashes(xml).name]
        if not bad:
            continue
        for file in (xml, xml.with_suffix('.bin'), _hashes(xml)):
            file.unlink(missing_ok=True)
        print(f'deleted the damaged int8 encoder {xml} ({", ".join(bad)} did not match '
              'its hashes); it is built again from the weights', file=out, flush=True)
        gone.append(xml)
    return gone


def build(encoder: nn.Module, path: Path, *, input_shape: tuple[int, ...],
          prepare: Callable[[np.ndarray], torch.Tensor], stream: TextIO | None = None) -> Path:
    """
    Quantise `encoder` on the calibration frames and save it as OpenVINO IR at `path`
    (written into a temporary folder, then moved: never half a model).

    :raises WeightsError: the folder cannot be written (found before the minute of
        calibration), or the build failed (a full disk, OpenVINO or NNCF).
    """
    out = stream or sys.stderr
    try:                      # a folder it cannot write: found now, not after the minute
        path.parent.mkdir(parents=True, exist_ok=True)
        _remove_stale_builds(path.parent)
        tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix='.build-'))
    except OSError as exc:
        raise WeightsError(f'cannot write the int8 encoder into {path.parent} '
                           f'({exc.strerror or exc}): make it writable, or set '
                           'ACTIVELOC_CACHE to a folder that is') from None
    try:
        _build_into(tmp, encoder, path, input_shape=input_shape, prepare=prepare, out=out)
    except (OSError, RuntimeError) as exc:     # a full disk; OpenVINO's and NNCF's failures
        raise WeightsError(f'building the int8 encoder {path.name} failed: '
                           f'{type(exc).__name__}: {exc}') from exc
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f'wrote {path}', file=out, flush=True)
    return path


def _remove_stale_builds(folder: Path) -> None:
    """
    Delete the build folders that killed builds left behind (up to 10 MB each); a build
    still running elsewhere is minutes old, not an hour.
    """
    for stale in folder.glob('.build-*'):
        try:
            if time.time() - stale.stat().st_mtime > STALE_BUILD_S:
                shutil.rmtree(stale, ignore_errors=True)
        except OSError:       # gone meanwhile, removed by another build
            pass


def _build_into(tmp: Path, encoder: nn.Module, path: Path, *, input_shape: tuple[int, ...],
                prepare: Callable[[np.ndarray], torch.Tensor], out: TextIO) -> None:
    """`build`'s work, saved in ``tmp`` and moved to ``path``."""
    import nncf
    import openvino
    print(f'building the int8 encoder {path.name} (once; about a minute) ...', file=out,
          flush=True)
    inputs = [prepare(rgb).contiguous().numpy() for rgb in calibration_frames()]
    if not inputs:
        raise WeightsError('the sample bag gave no calibration frames')
    if any(x.shape != tuple(input_shape) for x in inputs):
        raise ConfigError(f'calibration inputs must have the shape {tuple(input_shape)}')
    with torch.no_grad():
        model = openvino.convert_model(encoder.eval(), example_input=torch.from_numpy(inputs[0]))
    with contextlib.redirect_stdout(out):   # NNCF's progress bars: not in a command's output
        quantised = nncf.quantize(model, nncf.Dataset(inputs), subset_size=len(inputs))
    openvino.save_model(quantised, tmp / path.name)
    os.replace(tmp / path.with_suffix('.bin').name, path.with_suffix('.bin'))
    os.replace(tmp / path.name, path)
    files = (path.with_suffix('.bin'), path)
    write_atomic(_hashes(path), ''.join(f'{file_sha256(f)}  {f.name}\n' for f in files))
    # the hashes last: they mark the build done


def _hashes(path: Path) -> Path:
    """The file of the int8 model's hashes (sha256sum's format) beside its .xml."""
    return path.with_suffix('.sha256')


def _read_hashes(path: Path) -> dict[str, str]:
    try:
        lines = _hashes(path).read_text().splitlines()
    except OSError as exc:
        raise WeightsError(f'cannot read {_hashes(path)}: {exc.strerror}') from None
    pairs = [line.split(None, 1) for line in lines if line.strip()]
    if not pairs or any(len(pair) != 2 for pair in pairs):
        raise DamagedError(f'{_hashes(path)} is damaged (the int8 encoder {path}): '
                           f'{REBUILD}')
    return {name.strip(): digest for digest, name in pairs}
