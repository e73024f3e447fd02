"""
The encoder's side of the model: frames in, the rows x cols grid of C-d features out.

`Features` owns the CNN encoder (`perception.encoders`), the arithmetic it runs in
(float32, bfloat16 or OpenVINO int8, `perception.int8`), the mirrored border round its input
(`encoder_pad`) and the per-frame scaling of its output (`feature_norm`). It keeps no memory
of earlier frames: that is `perception.model.SurpriseModel`'s.
"""
import copy
import sys
from typing import Any

import cv2
import numpy as np
import torch
from torch import nn
import torch.nn.functional as F

from activeloc_ros.errors import ConfigError, FrameError, WeightsError
from activeloc_ros.perception.config import PerceptionConfig
from activeloc_ros.perception.encoder_weights import build_encoder
from activeloc_ros.perception.encoders import fold_batchnorm, set_conv_padding


# torch's probes of the instruction sets that decide the encoder's speed (private in 2.13)
CPU_FEATURES = (('AVX2', '_is_avx2_supported'), ('AVX512', '_is_avx512_supported'),
                ('VNNI', '_is_vnni_supported'), ('AVX512_BF16', '_is_avx512_bf16_supported'),
                ('AMX', '_is_amx_tile_supported'))


ASPECT_TOLERANCE = 0.1    # a frame's aspect this far from the input's is worth a warning


def cpu_flags() -> list[str]:
    """Which of `CPU_FEATURES` this CPU has."""
    return [name for name, probe in CPU_FEATURES
            if bool(getattr(torch.cpu, probe, lambda: False)())]


def fast_bfloat16() -> bool:
    """
    Does this CPU compute in bfloat16 natively: AMX tiles (Intel Sapphire Rapids on) or
    AVX512_BF16 dot products (AMD Zen 4 on, Intel Cooper Lake)? There bfloat16 convolutions
    run faster than float32; elsewhere they are emulated and slower.
    """
    return bool({'AMX', 'AVX512_BF16'} & set(cpu_flags()))


def resolve_precision(precision: str) -> str:
    """The precision 'auto' stands for on this CPU (int8 is `Features`' own choice)."""
    if precision == 'auto':
        return 'bfloat16' if fast_bfloat16() else 'float32'
    return precision


class Features:
    """
    The encoder of a configuration, ready to run.

    :param cfg: the configuration.
    :param encoder: an already built encoder to use instead of `build_encoder(cfg...)`.
    :param train: the encoder learns online (its weights are then not folded or cast).
    """

    def __init__(self, cfg: PerceptionConfig, *, encoder: nn.Module | None = None,
                 train: bool = False):
        self.cfg = cfg
        self.train = train
        if encoder is None:
            encoder = build_encoder(cfg.encoder, weights=cfg.weights or None,
                                    pretrained=cfg.pretrained, classifier=False)
        set_conv_padding(encoder, cfg.conv_padding)
        # eval mode always: BatchNorm statistics of one frame are meaningless; the weights
        # still learn when `train`
        self.encoder = encoder.eval()
        if cfg.channels_last:
            self.encoder = self.encoder.to(memory_format=torch.channels_last)
        self.encoder.requires_grad_(train)
        # a frozen encoder runs with BatchNorm folded into its convs (same maps, cheaper);
        # `encoder` keeps the unfolded weights for checkpoints
        self.frozen_encoder = self.encoder
        if cfg.fold_bn and not train and _has_batchnorm(self.encoder):
            self.frozen_encoder = fold_batchnorm(self.encoder)
        precision = resolve_precision(cfg.encoder_precision)
        if cfg.encoder_precision == 'auto' and not train and cfg.pretrained:
            from activeloc_ros.perception import int8   # (random weights: not worth a build)
            if int8.available():
                precision = 'int8'
        if precision == 'int8' and train:
            raise ConfigError("perception parameter 'encoder_precision' int8 needs a frozen "
                              'encoder (update_encoder false)')
        self.precision = precision                              # in use
        if precision == 'bfloat16' and not train:
            # cast the weights once: autocast would cast them again on every frame
            if self.frozen_encoder is self.encoder:
                self.frozen_encoder = copy.deepcopy(self.encoder)
            self.frozen_encoder = self.frozen_encoder.to(torch.bfloat16)
        native = int(encoder.input_size)                        # 224
        self.channels = int(encoder.channels)
        with torch.inference_mode():                            # the grid the encoder makes
            zeros = torch.zeros(1, 3, native, native)
            rows = self._run(self.frozen_encoder, self.encoder.preprocess(zeros)).shape[-2]
        self.stride = native // rows                            # input px per cell: 16
        height = cfg.input_height or native
        if height % self.stride:
            raise ConfigError(f"perception parameter 'input_height' must be a multiple of the "
                              f"encoder stride {self.stride} (0: the encoder's own "
                              f'{native}), got {height}')
        width = max(1, round(height * cfg.input_aspect / self.stride)) * self.stride
        self.input_wh = (width, height)                         # (304, 224) at 4:3
        self.grid = (height // self.stride, width // self.stride)   # (rows, cols): (14, 19)
        self.cells = self.grid[0] * self.grid[1]
        if cfg.encoder_pad % self.stride or cfg.encoder_pad >= height:
            raise ConfigError(f"perception parameter 'encoder_pad' must be a multiple of the "
                              f'encoder stride {self.stride} below {height}, got '
                              f'{cfg.encoder_pad}')
        if precision == 'int8':
            from activeloc_ros.perception import cache, int8
            pad = 2 * cfg.encoder_pad
            try:
                self.frozen_encoder = int8.load(
                    self.frozen_encoder, name=cfg.encoder,
                    input_shape=(1, 3, height + pad, width + pad),
                    prepare=lambda rgb: self.padded(self.tensor(self.resize(rgb))),
                    threads=torch.get_num_threads(), cache=cache.cache_dir())
            except WeightsError as exc:
                if cfg.encoder_precision != 'auto' or isinstance(exc, int8.DamagedError):
                    raise        # a damaged model is never a silent 4x slower run
                # auto: the int8 encoder is a speed-up; without it, the correct slower run
                print(f'warning: {exc}; the encoder runs in float32', file=sys.stderr,
                      flush=True)
                self.precision = 'float32'

    def aspect_note(self, frame_wh: tuple[int, int]) -> str | None:
        """
        Why frames of `frame_wh` (width, height) reach the encoder out of the shape
        `input_aspect` was set for, or None: their aspect differs from the input's by more
        than `ASPECT_TOLERANCE`. The paper's square input (1) squashes every frame on
        purpose: no note.
        """
        if self.cfg.input_aspect == 1.0:
            return None
        width, height = frame_wh
        aspect = width / height
        ours = self.input_wh[0] / self.input_wh[1]
        if abs(aspect / ours - 1.0) <= ASPECT_TOLERANCE:
            return None
        return (f'frames of {width}x{height} (aspect {aspect:.2f}) are resized to the '
                f'{self.input_wh[0]}x{self.input_wh[1]} encoder input (aspect {ours:.2f}), '
                f'out of shape: set the perception parameter input_aspect to {aspect:.4f}')

    def preprocess(self, frame: np.ndarray) -> torch.Tensor | None:
        """
        (H, W, 3) RGB 0..255 -> (1, 3, h, w) normalised encoder input (`input_wh`); None
        if not finite.
        """
        img = self.resize(frame)
        return None if img is None else self.tensor(img)

    def resize(self, frame: np.ndarray) -> np.ndarray | None:
        """(H, W, 3) RGB 0..255 -> (h, w, 3) encoder-sized image; None if not finite."""
        _check_frame(frame)
        img = frame
        if frame.dtype != np.uint8:
            if not np.isfinite(frame).all():
                return None
            img = frame.astype(np.float32, copy=False)
        h, w = img.shape[:2]
        width, height = self.input_wh
        shrink = h >= height and w >= width
        img = cv2.resize(img, self.input_wh,
                         interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
        if self.cfg.blur_ksize:
            img = cv2.GaussianBlur(img, (self.cfg.blur_ksize,) * 2, 0)
        return img

    def tensor(self, img: np.ndarray) -> torch.Tensor:
        """(h, w, 3) encoder-sized image -> (1, 3, h, w) normalised encoder input."""
        x = torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None].float()
        x = self.encoder.preprocess(x)                          # (1, 3, h, w)
        if self.cfg.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        return x

    def of(self, x: torch.Tensor, *, learning: bool = False) -> torch.Tensor:
        """
        (B, 3, h, w) -> (B, N, C) float32 features, computed at `precision` by the frozen
        encoder, or with `learning` by the encoder whose weights learn (under autograd).
        """
        encoder = self.encoder if learning else self.frozen_encoder
        return self.to_cells(self._forward(encoder, x))

    def _forward(self, encoder: nn.Module, x: torch.Tensor) -> torch.Tensor:
        crop = self.cfg.encoder_pad // self.stride              # cells the padding adds
        f = self._run(encoder, self.padded(x))
        return f[..., crop:f.shape[-2] - crop, crop:f.shape[-1] - crop]

    def padded(self, x: torch.Tensor) -> torch.Tensor:
        pad = self.cfg.encoder_pad
        return F.pad(x, (pad,) * 4, mode='reflect') if pad else x

    def _run(self, encoder: nn.Module, x: torch.Tensor) -> torch.Tensor:
        if self.precision in ('float32', 'int8'):
            return encoder(x)
        if encoder is self.frozen_encoder and not self.train:  # bfloat16 weights
            return encoder(x.to(torch.bfloat16)).float()
        with torch.autocast('cpu', dtype=torch.bfloat16):
            return encoder(x).float()

    def to_cells(self, f: torch.Tensor) -> torch.Tensor:
        """(B, C, rows, cols) encoder output -> (B, N, C), scaled as `feature_norm` says."""
        f = f.flatten(2).transpose(1, 2)
        if self.cfg.feature_norm == 'frame_rms':
            f = f / (f.square().mean(dim=(1, 2), keepdim=True).sqrt() + 1e-6)
        return f


def _has_batchnorm(module: nn.Module) -> bool:
    return any(isinstance(m, nn.modules.batchnorm._BatchNorm) for m in module.modules())


def _check_frame(frame: Any) -> None:
    if not isinstance(frame, np.ndarray):
        raise FrameError(f'frame must be a numpy array, got {type(frame).__name__}')
    if frame.ndim != 3 or frame.shape[2] != 3 or frame.shape[0] < 1 or frame.shape[1] < 1:
        raise FrameError(f'frame must be (H, W, 3) RGB, got shape {frame.shape}')
    if frame.dtype != np.uint8 and frame.dtype not in (np.float32, np.float64):
        raise FrameError(f'frame must be uint8 (or float 0..255) RGB, got {frame.dtype}')
