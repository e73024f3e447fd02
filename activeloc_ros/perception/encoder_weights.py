"""
An ImageNet encoder with its weights: the state dict's layout checked against the
architecture (`encoders`), loaded without a random initialisation first, or fetched from
the weights cache (`build_encoder`).
"""
from collections.abc import Mapping
from pathlib import Path

import torch

from activeloc_ros.errors import ConfigError, WeightsError
from activeloc_ros.perception.cache import read_state_dict, weights_path
from activeloc_ros.perception.encoders import Encoder, ENCODERS, make_encoder


def layout(name: str, *, head: bool) -> dict[str, tuple[int, ...]]:
    """Key -> shape of an encoder's state dict, without allocating any weights."""
    with torch.device('meta'):
        return {k: tuple(v.shape) for k, v in make_encoder(name, head=head).state_dict().items()}


def _is_bn_counter(key: str) -> bool:
    return key.endswith('num_batches_tracked')


def _listing(keys: set[str], limit: int = 8) -> str:
    shown = sorted(keys)[:limit]
    more = f' (+{len(keys) - limit} more)' if len(keys) > limit else ''
    return ', '.join(shown) + more


def check_layout(name: str, state: Mapping[str, torch.Tensor], *,
                 source: str) -> bool:
    """
    Raise WeightsError unless `state` fits the encoder; return whether it has the head.

    The head keys are all-or-nothing; BatchNorm's `num_batches_tracked` may be absent.
    """
    trunk = layout(name, head=False)
    full = layout(name, head=True)
    head_keys = {k for k in full if k not in trunk and not _is_bn_counter(k)}
    got = set(state)
    unexpected = got - set(full)
    missing = {k for k in trunk if k not in got and not _is_bn_counter(k)}
    has_head = bool(head_keys) and bool(head_keys & got)
    if has_head:
        missing |= head_keys - got
    if unexpected or missing:
        parts = [f'{source} is not a {name} state dict']
        if missing:
            parts.append(f'missing keys: {_listing(missing)}')
        if unexpected:
            parts.append(f'unexpected keys: {_listing(unexpected)}')
        raise WeightsError('; '.join(parts))
    wrong = [f'{k} {tuple(state[k].shape)} (expected {full[k]})'
             for k in sorted(got) if tuple(state[k].shape) != full[k]]
    if wrong:
        raise WeightsError(f'{source}: tensors of the wrong shape for {name}: '
                           + _listing(set(wrong), 4))
    return has_head


def load_encoder(name: str, state: Mapping[str, torch.Tensor], *, source: str,
                 classifier: bool = True) -> Encoder:
    """An encoder holding `state`'s tensors (float32), in eval mode."""
    has_head = check_layout(name, state, source=source)
    head = classifier and has_head
    with torch.device('meta'):  # no random init of weights about to be replaced
        enc = make_encoder(name, head=head)
    wanted = enc.state_dict()
    tensors = {}
    for key, meta in wanted.items():
        if key in state:
            t = state[key]
            tensors[key] = t.to(meta.dtype).contiguous() if t.is_floating_point() else t.clone()
        else:  # an absent BN counter; it is never read with frozen statistics
            tensors[key] = torch.zeros((), dtype=meta.dtype)
    enc.load_state_dict(tensors, strict=True, assign=True)
    return enc.eval()


def build_encoder(name: str, *, weights: str | Path | None = None, pretrained: bool = True,
                  classifier: bool = True) -> Encoder:
    """
    An ImageNet encoder in eval mode (BatchNorm frozen also under `train()`).

    :param name: one of `ENCODERS`.
    :param weights: a state dict file; default: the converted file in the weights cache. For
        vgg16 it is required: a torchvision VGG-16 file such as `vgg16-397923af.pth`.
    :param pretrained: False gives random weights, for unit tests only.
    :param classifier: keep the ImageNet head where the weights have one (`classify`);
        False saves its memory (about 0.5 GB for VGG-16).
    :raises WeightsError: weights missing, unreadable or of the wrong layout.
    :raises ConfigError: an unknown name, or weights given with `pretrained=False`.
    """
    if name not in ENCODERS:
        raise ConfigError(f'unknown encoder {name!r}; choose one of {", ".join(ENCODERS)}')
    if not pretrained:
        if weights is not None:
            raise ConfigError('weights were given but pretrained=False asks for random ones')
        return make_encoder(name, head=classifier).eval()
    if weights is None:
        path = weights_path(name)
    else:
        path = Path(weights).expanduser()
        if not path.is_file():
            hint = (' (a torchvision VGG-16 state dict such as vgg16-397923af.pth)'
                    if name == 'vgg16' else '')
            raise WeightsError(f'{name} weights file {path} does not exist{hint}')
    return load_encoder(name, read_state_dict(path), source=str(path), classifier=classifier)
