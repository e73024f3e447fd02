"""The online predictive-learning surprise model (Trehan & Aakur, WACV 2022, Sec. 3.2 and 4).

A CNN encoder turns each frame into a g x g grid of C-d features (g = 14 at 224 x 224). Each
grid cell is one batch element of a shared predictor: Bahdanau attention over the cells
weights the features, a stack of LSTMs carries the scene's dynamics from frame to frame and
predicts every cell's feature of the next frame. The motion-weighted prediction error of the
frame that then arrives, softmaxed over the cells, is the surprise map; its argmax is the
action's location. One optimiser step per frame on L_global + L_attn keeps the model adapting.

Which computation happens when (one frame per `step`, t the new frame):
    the prediction of f_t is made from f_{t-1} with the state after t-2 and the current
    weights W, i.e. exactly what was known before frame t arrived. It is computed at step t
    (not at t-1) with the graph that the update at t needs, so every frame costs one
    predictor forward and one backward, and no graph outlives the optimiser step that
    changes the weights it saved. With a frozen encoder each frame is encoded once (under
    inference mode) and its features are cached; with `update_encoder` and
    `encoder_grad='both'` the previous frame is re-encoded with the current weights in the
    same batch as the new one, so the gradient flows through both the predictor's input
    and the target, as in the paper's end-to-end loss.

Losses (`loss_reduction='mean'`, the default; N cells, C channels; f are the encoder's
features, each frame divided by its RMS under the default `feature_norm='frame_rms'`):
    w        = motion weight of (f_t - f_{t-1}), detached (a weight, not a target)
    E        = w * (f_t - fhat_t)^2                                  # (N, C)
    L_global = mean over N*C of E            ('sum': sum over N*C)
    e        = mean over C of E; map = softmax over the N cells of e / map_temperature
    L_attn   = ||a_{t-1} - ahat_{t-2}||_2 + ||(a_{t-1} - ahat_{t-2}) * f_{t-1}||_2
               (paper Eq. 3: the attention a_{t-1} applied to f_{t-1} is pulled toward the
               surprise map of the frame before; L2 norms over all cells and channels,
               the same under both reductions)
    total    = L_global + attn_weight * L_attn
Defaults that differ from the paper, each measured (see the field helps): feature_norm,
attn_rescale, Adam at 1e-3 instead of 1e-6, adaptive boost off, encoder frozen, the
motion weight 2*sigmoid(|d|)-1 (the literal sigmoid(d) is 0.5 where nothing moves),
ego_motion (bench screen, dev set, mean AAE 19.1 deg with it vs 20.8 without; its
ego_warp 'features' against 'image' with vgg19: 19.02 vs 19.24 deg at seed 0, 19.18 vs 19.40
at seed 1, at 422 vs 678 ms a frame), encoder_pad (below) and vgg19 for the paper's vgg16
(whose weights no registry here holds), run in int8 (`encoder_precision`), with the
predictor's products in bfloat16 where the CPU computes it natively.

`step` is `learn(observe(frame))`: `observe` encodes (and measures the camera's motion) with
its own memory of the previous frame, `learn` does the rest with the sequence's, so the two
may run on consecutive frames at once (`perception.pipeline`). `learn` hands the map out
before the optimiser step, which the map does not need.

encoder_pad: under camera motion the map's peak went to the grid's outer ring, the cells
whose receptive fields reach into the convolutions' zero padding. Measured with `bench
passive --camera static --max-frames 100 --pan 10` (a camera panning over still scenes; any
peak off the actors is wrong), over the 5 static dev sequences, encoder_pad 0 / 16 / 32:
peaks on the outer ring 47.1 / 38.1 / 25.8% (a random cell: 26.5%), hits on frames after a
camera move 46.6 / 54.9 / 62.1%, all frames 55.8 / 63.9 / 70.4%. The ring share falls on
every sequence (kitti 65 -> 32%, tud 52 -> 35, crossing 31 -> 18, walking2 75 -> 35, ball1
13 -> 8). Closed loop (`bench screen --camera static`, seeds 0-2): 11.12 / 10.06 / 10.25 deg
mean AAE. 32 px costs the encoder 1.65x the work of none (288 px input instead of 224).
"""
import collections
import copy
import dataclasses
from dataclasses import dataclass, field
import math
import random
import time
from typing import Any, Callable

import cv2
import numpy as np
import torch
from torch import nn
import torch.nn.functional as F

from activeloc_ros.checks import above, at_least, Check, in_range, one_of
from activeloc_ros.errors import ConfigError, FrameError
from activeloc_ros.perception import egomotion, motion

ENCODER_NAMES = ('vgg16', 'vgg19', 'efficientnet_lite0', 'resnet50')
MOTIONS = ('abs_sigmoid', 'sigmoid', 'raw', 'none')
PRECISIONS = ('auto', 'float32', 'bfloat16')
ENCODER_PRECISIONS = PRECISIONS + ('int8',)
_NO_LOSSES = {'global': 0.0, 'attn': 0.0, 'total': 0.0}


# torch's probes of the instruction sets that decide the encoder's speed (private in 2.13)
CPU_FEATURES = (('AVX2', '_is_avx2_supported'), ('AVX512', '_is_avx512_supported'),
                ('VNNI', '_is_vnni_supported'), ('AVX512_BF16', '_is_avx512_bf16_supported'),
                ('AMX', '_is_amx_tile_supported'))


def cpu_flags() -> list[str]:
    """Which of `CPU_FEATURES` this CPU has."""
    return [name for name, probe in CPU_FEATURES
            if bool(getattr(torch.cpu, probe, lambda: False)())]


def fast_bfloat16() -> bool:
    """Does this CPU compute in bfloat16 natively: AMX tiles (Intel Sapphire Rapids on) or
    AVX512_BF16 dot products (AMD Zen 4 on, Intel Cooper Lake)? There bfloat16 convolutions
    run faster than float32; elsewhere they are emulated and slower."""
    return bool({'AMX', 'AVX512_BF16'} & set(cpu_flags()))


def _resolve(precision: str) -> str:
    """The precision 'auto' stands for on this CPU."""
    if precision == 'auto':
        return 'bfloat16' if fast_bfloat16() else 'float32'
    return precision


def _blur(value: int) -> 'str | None':
    if value == 0 or (value >= 3 and value % 2 == 1):
        return None
    return f'must be 0 (off) or an odd size >= 3, got {value}'


def _param(default: Any, help: str, check: Check | None = None) -> Any:
    return field(default=default, metadata={'help': help, 'check': check})


@dataclass
class PerceptionConfig:
    """Every choice of the perception model; `from_dict` builds it from ROS parameters/YAML."""
    # encoder
    encoder: str = _param(
        'vgg19',
        'CNN encoder to the 14x14 grid. Default vgg19 to pool4: the closest stand-in for the '
        'paper\'s vgg16 pool4 whose ImageNet weights the registries hold; vgg16 needs '
        '`weights`; efficientnet_lite0 is ~17x cheaper in float32, 3.5x in bfloat16 '
        '(bench screen, static sequences: AAE 16.0 deg vs vgg19\'s 13.3)', one_of(*ENCODER_NAMES))
    weights: str = _param('', 'encoder weights file; empty = the package weight cache')
    encoder_precision: str = _param(
        'auto', 'arithmetic of the encoder\'s forward pass: float32; bfloat16 (features '
        'within ~1% of float32; faster where the CPU computes it natively, slower where it is '
        'emulated); int8 (OpenVINO, quantised once by NNCF on the sample bag, see '
        'perception.int8; a frozen encoder only); auto = int8 for a frozen ImageNet '
        'encoder, else bfloat16 where the CPU has AMX or AVX512_BF16, else float32 (bench '
        'screen, 5 static dev sequences, seeds 0-2: mean AAE 10.23 deg in int8, 10.64 in '
        'bfloat16, 10.25 in float32)', one_of(*ENCODER_PRECISIONS))
    encoder_pad: int = _param(
        32, 'pixels of mirrored picture added round the encoder input, whose extra feature '
        'cells are cut off again: the border cells then see picture, not the zero padding '
        'of the convolutions, which otherwise makes them the most surprising cells when the '
        'camera moves (a multiple of the encoder stride, 16; 0 = off, paper)', at_least(0))
    pretrained: bool = _param(
        True, 'load ImageNet weights; False = random encoder, for unit tests only')
    blur_ksize: int = _param(
        0, 'Gaussian blur of the 224x224 frame before encoding; 0 = off, 5 = lab code', _blur)
    feature_norm: str = _param(
        'frame_rms', 'scale of the features the predictor and the losses see: frame_rms '
        '(each frame divided by its RMS over cells and channels, so targets are O(1) whatever '
        'the encoder; without it the predictor does not learn online) or none (raw encoder '
        'units, paper)', one_of('none', 'frame_rms'))
    # predictor
    hidden: int = _param(512, 'units of each LSTM (paper 512)', at_least(1))
    layers: int = _param(3, 'stacked LSTMs (paper 3)', at_least(1))
    attn_units: int = _param(512, 'width of the Bahdanau attention score', at_least(1))
    predictor_precision: str = _param(
        'auto', 'arithmetic of the predictor\'s matrix products, forward and backward: '
        'float32, or bfloat16 under autocast (weights, optimiser and losses stay float32); '
        'auto = bfloat16 where the CPU computes it natively (AMX or AVX512_BF16), else '
        'float32', one_of(*PRECISIONS))
    attn_rescale: bool = _param(
        True, 'feed N * alpha * f to the LSTM (N cells), so uniform attention passes the '
        'features unchanged; False = alpha * f as the lab code (inputs ~f/196)')
    residual: bool = _param(
        False, 'predict the change: fhat = f_t + head(h) with the head starting at zero, '
        'i.e. a copy-last-frame predictor that learns corrections; False = the top LSTM '
        'predicts the feature itself (paper)')
    head: str = _param(
        'linear', 'top LSTM -> predicted feature: linear (to C channels, unbounded) or none '
        '(the LSTM output itself, lab code; needs hidden == C)', one_of('linear', 'none'))
    # losses
    mode: str = _param(
        'full', 'full = this paper; predlearn = the ECCV\'20 PredLearn baseline of Table 3 '
        '(motion=raw and no L_attn, whatever those fields say)', one_of('full', 'predlearn'))
    motion: str = _param(
        'abs_sigmoid', 'weight of the prediction error by the motion d = f_t - f_{t-1}: '
        'abs_sigmoid = 2*sigmoid(|d|/s)-1 (0 where nothing moves, -> 1 with motion); '
        'sigmoid = sigmoid(d/s), the paper\'s literal Eq. 2 (0.5 where nothing moves, '
        'below 0.5 where a feature drops); raw = d^2 (lab code, Table 3 "w/o normalized '
        'motion"); none = unweighted', one_of(*MOTIONS))
    motion_scale: float = _param(
        1.0, 'motion scale s of the sigmoid weightings (paper: 1)', above(0.0))
    motion_source: str = _param(
        'features', 'what the motion d is measured on: features = f_t - f_{t-1} of each '
        'cell, broadcast over nothing (paper Eq. 2); image = the per-cell mean change of '
        'the blurred grey picture against the previous one moved into the new view '
        '(perception.motion: pixel-accurate, so the 14x14 features\' misregistration under '
        'camera motion is no motion), in grey levels scaled by image_motion_scale',
        one_of('features', 'image'))
    image_motion_scale: float = _param(
        2.0, 'with motion_source image, the change (grey levels) at which the sigmoid '
        'weights reach ~0.46', above(0.0))
    use_attn_loss: bool = _param(True, 'add L_attn (paper Eq. 3); False = Table 3 "w/o L_attn"')
    attn_weight: float = _param(1.0, 'factor of L_attn in the total loss', at_least(0.0))
    ego_motion: str = _param(
        'similarity', 'the camera\'s own motion: estimated from the images (ORB + RANSAC) '
        'as a similarity or a homography (exact for a camera turning about its optical '
        'centre), the new frame is compared with the previous one warped into its view, '
        'and the LSTM state and past maps move with it; none = ignored (paper; a turning '
        'camera makes the whole view surprising)', one_of('none', 'similarity', 'homography'))
    ego_warp: str = _param(
        'features', 'with ego_motion, how the previous frame\'s features reach the new '
        'view: features = they are warped cell by cell (cells the previous view did not '
        'see take the new frame\'s); image = the previous image is warped and encoded '
        'again, a second encoder pass on every frame the camera moved',
        one_of('features', 'image'))
    map_temperature: float = _param(
        1.0, 'softmax temperature of the surprise map over the cells (paper: 1)', above(0.0))
    location: str = _param(
        'mass', 'where the action is: peak = the centre of the map\'s argmax cell (paper); '
        'mass = the centroid of the cells that reach location_share of the peak, which '
        'follows a group rather than the one cell of it that is most surprising this frame '
        '(bench screen, 5 static dev sequences, faithful rig: mean AAE 18.34 deg with peak, '
        '11.12 +- 0.25 over 3 seeds with mass 0.25: lower on 4 of the 5, higher on vot_ball1, '
        '10.35 -> 12.5)',
        one_of('peak', 'mass'))
    location_share: float = _param(
        0.25, 'with location mass, the share of the peak value a cell needs to count (same '
        'benchmark, seed 0: 0 -> 13.45 deg, 0.1 -> 12.21, 0.25 -> 10.87, 0.5 -> 15.29, '
        '0.75 -> 17.93)', in_range(0.0, 1.0))
    loss_reduction: str = _param(
        'mean', 'L_global over cells and channels: mean or sum', one_of('mean', 'sum'))
    # online learning
    learn: bool = _param(True, 'one optimiser step per frame; False = predict only')
    update_encoder: bool = _param(
        False, 'also train the encoder online (paper: True; it costs 2 encoder backward '
        'passes per frame, ~5x the frozen step with efficientnet_lite0 on 2 CPU cores)')
    encoder_grad: str = _param(
        'both', 'with update_encoder, the encoder gradient flows through both the '
        'predictor\'s input and the target (exact; re-encodes the previous frame) or through '
        'the target only (half the encoder cost)', one_of('both', 'target'))
    optimizer: str = _param('adam', 'online optimiser', one_of('adam', 'sgd'))
    lr: float = _param(
        1e-3, 'base learning rate (paper 1e-6, which moves nothing within thousands of '
        'frames here)', at_least(0.0))
    encoder_lr_scale: float = _param(
        1.0, 'encoder learning rate = lr * this (paper: 1)', at_least(0.0))
    momentum: float = _param(0.0, 'SGD momentum', at_least(0.0))
    grad_clip: float = _param(
        0.0, 'clip the global gradient norm to this; 0 = off', at_least(0.0))
    adaptive_lr: bool = _param(
        False, 'adaptive learning (Aakur & Sarkar CVPR\'19, paper: on): a loss much above '
        'the recent mean gets a boosted learning rate for that step; off by default: with '
        'Adam the 100x steps undo what was learnt')
    adaptive_window: int = _param(30, 'losses in the running mean', at_least(1))
    adaptive_ratio: float = _param(
        1.5, 'boost when loss / mean of the window exceeds this', above(0.0))
    adaptive_boost: float = _param(100.0, 'learning-rate factor of a boosted step', above(0.0))
    snapshot_every: int = _param(
        25, 'copy the weights and optimiser state every N finite updates; non-finite '
        'weights are restored from the copy', at_least(1))
    # runtime
    seed: int = _param(0, 'seed of random, numpy and torch', at_least(0))
    num_threads: int = _param(0, 'torch CPU threads (process-wide); 0 = leave as is',
                              at_least(0))
    channels_last: bool = _param(True, 'channels-last memory format for the encoder')
    fold_bn: bool = _param(
        True, 'run a frozen encoder with BatchNorm folded into its convs (same features, '
        'about 30% cheaper for efficientnet_lite0)')
    compile: bool = _param(False, 'torch.compile the predictor (slow first frames)')

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            problem = self.check(f.name, getattr(self, f.name))
            if problem:
                raise ConfigError(f'perception parameter {f.name!r} {problem}')

    @classmethod
    def check(cls, name: str, value: Any) -> 'str | None':
        """Why `value` is invalid for field `name`, or None if it is valid (a pure function)."""
        spec = {f.name: f for f in dataclasses.fields(cls)}.get(name)
        if spec is None:
            return f'is unknown (known: {", ".join(sorted(_field_names(cls)))})'
        kind = spec.type
        if kind is bool and not isinstance(value, bool):
            return f'must be a bool, got {value!r}'
        if kind is int and (isinstance(value, bool) or not isinstance(value, int)):
            return f'must be an int, got {value!r}'
        if kind is float:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                return f'must be a number, got {value!r}'
            if not math.isfinite(value):
                return f'must be finite, got {value!r}'
        if kind is str and not isinstance(value, str):
            return f'must be a string, got {value!r}'
        rule = spec.metadata.get('check')
        return rule(value) if rule else None

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> 'PerceptionConfig':
        """Build from a plain dict; an unknown key or invalid value raises ConfigError."""
        names = _field_names(cls)
        unknown = sorted(k for k in d if k not in names)
        if unknown:
            raise ConfigError(f'unknown perception parameter {unknown[0]!r} '
                              f'(known: {", ".join(sorted(names))})')
        types = {f.name: f.type for f in dataclasses.fields(cls)}
        # YAML and ROS give 1 for 1.0: accept ints where a float is expected
        values = {k: float(v) if types[k] is float and type(v) is int else v
                  for k, v in d.items()}
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def descriptions(cls) -> dict[str, str]:
        return {f.name: f.metadata['help'] for f in dataclasses.fields(cls)}

    @property
    def motion_weighting(self) -> str:
        return 'raw' if self.mode == 'predlearn' else self.motion

    @property
    def attn_loss_on(self) -> bool:
        return self.mode == 'full' and self.use_attn_loss


def _field_names(cls) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


@dataclass
class Observation:
    """What `SurpriseModel.observe` made of one frame, for `learn`."""
    frame: np.ndarray                  # (H, W, 3) as given
    index: int
    t0: float                          # perf_counter at the start of `observe`
    timings: dict[str, float]
    f_cur: torch.Tensor | None = None  # (N, C) features; None: the frame was not finite
    warp: np.ndarray | None = None     # the camera's motion since the previous frame
    f_prev: torch.Tensor | None = None  # (N, C) the previous view encoded again, if it was
    change: torch.Tensor | None = None  # (N,) picture change (motion_source: image)


@dataclass
class PerceptionResult:
    """What one `SurpriseModel.step` returns."""
    surprise_map: np.ndarray           # (g, g) float32, >= 0, sums to 1
    cell: tuple[int, int]              # (row, col) of the argmax
    location_px: tuple[float, float]   # (x, y) centre of that cell in input-frame pixels
    peak: float
    losses: dict[str, float]           # global, attn, total; 0.0 without an update
    lr: float                          # learning rate of this step's update, 0.0 if none
    updated: bool
    timings: dict[str, float]          # seconds: preprocess, encode, predict, update, total
    nan_events: int
    frame_index: int


class Predictor(nn.Module):
    """Per-cell Bahdanau attention and stacked LSTMs; all cells share the weights."""

    def __init__(self, cfg: PerceptionConfig, channels: int):
        super().__init__()
        if cfg.head == 'none' and cfg.hidden != channels:
            raise ConfigError(f"perception parameter 'head' none needs hidden == encoder "
                              f'channels ({channels}), got hidden={cfg.hidden}')
        self.hidden = cfg.hidden
        self.layers = cfg.layers
        self.rescale = cfg.attn_rescale
        self.w1 = nn.Linear(channels, cfg.attn_units)
        self.w2 = nn.Linear(cfg.hidden, cfg.attn_units, bias=False)
        self.v = nn.Linear(cfg.attn_units, 1, bias=False)
        # one matmul per LSTM: gates (i, f, g, o) of [input, h_prev], as torch.nn.LSTM
        sizes = [channels] + [cfg.hidden] * (cfg.layers - 1)
        self.cells = nn.ModuleList(nn.Linear(n + cfg.hidden, 4 * cfg.hidden) for n in sizes)
        self.head = nn.Linear(cfg.hidden, channels) if cfg.head == 'linear' else nn.Identity()
        self.residual = cfg.residual
        if cfg.residual and cfg.head == 'linear':
            nn.init.zeros_(self.head.weight)
            nn.init.zeros_(self.head.bias)

    def initial_state(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        zeros = torch.zeros(self.layers, n, self.hidden)
        return zeros, zeros.clone()                             # (L, N, H) each

    def forward(self, f: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor]
                ) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """Predict each cell's next feature from its current one.

        :param f: (N, C) features of the N cells.
        :param state: (h, c), each (L, N, H), after the previous frame.
        :return: fhat (N, C), attention (N,) summing to 1, the new (h, c).
        """
        h_prev, c_prev = state
        score = torch.tanh(self.w1(f) + self.w2(h_prev[-1]))   # (N, A)
        alpha = torch.softmax(self.v(score).squeeze(1), dim=0)  # (N,) over the cells
        x = alpha[:, None] * f                                  # (N, C)
        if self.rescale:
            x = x * f.shape[0]
        hs, cs = [], []
        for i, cell in enumerate(self.cells):
            gates = cell(torch.cat([x, h_prev[i]], dim=1))      # (N, 4H)
            ig, fg, gg, og = gates.chunk(4, dim=1)
            c = torch.sigmoid(fg) * c_prev[i] + torch.sigmoid(ig) * torch.tanh(gg)
            x = torch.sigmoid(og) * torch.tanh(c)               # (N, H)
            hs.append(x)
            cs.append(c)
        fhat = self.head(x)                                     # (N, C)
        if self.residual:
            fhat = fhat + f
        return fhat, alpha, (torch.stack(hs), torch.stack(cs))


def motion_weight(diff: torch.Tensor, kind: str, scale: float) -> torch.Tensor:
    """Weight of each feature's prediction error by its motion `diff` = f_t - f_{t-1}."""
    if kind == 'abs_sigmoid':
        return 2.0 * torch.sigmoid(diff.abs() / scale) - 1.0
    if kind == 'sigmoid':
        return torch.sigmoid(diff / scale)
    if kind == 'raw':
        return diff.square()
    return torch.ones_like(diff)


def global_error(f_next: torch.Tensor, fhat: torch.Tensor, weight: torch.Tensor, *,
                 reduction: str) -> tuple[torch.Tensor, torch.Tensor]:
    """L_global and the per-cell error e (channel mean), from (N, C) tensors."""
    err = weight * (f_next - fhat).square()                     # (N, C)
    loss = err.mean() if reduction == 'mean' else err.sum()
    return loss, err.mean(dim=1)                                # (), (N,)


def attention_loss(alpha: torch.Tensor, target: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    """Paper Eq. 3: attention (N,) against the previous surprise map (N,), on features (N, C)."""
    gap = alpha - target                                        # (N,)
    return torch.linalg.vector_norm(gap) + torch.linalg.vector_norm(gap[:, None] * f)


def surprise_map(e: torch.Tensor, temperature: float) -> torch.Tensor:
    return torch.softmax(e / temperature, dim=0)                # (N,)


def action_location(grid: torch.Tensor, kind: str, share: float) -> tuple[float, float]:
    """(x, y) of the action on a (rows, cols) map, in cells (0.5 = the first cell's centre):
    'peak' the argmax cell's centre; 'mass' the map-weighted centroid of the cells that
    reach `share` of the peak."""
    rows, cols = grid.shape
    if kind == 'peak':
        row, col = divmod(int(torch.argmax(grid)), cols)
        return col + 0.5, row + 0.5
    weight = torch.where(grid >= share * grid.max(), grid, torch.zeros(()))
    ys, xs = torch.meshgrid(torch.arange(rows) + 0.5, torch.arange(cols) + 0.5, indexing='ij')
    total = weight.sum()
    return float((weight * xs).sum() / total), float((weight * ys).sum() / total)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _finite(tensors) -> bool:
    tensors = [t for t in tensors if t is not None and t.is_floating_point()]
    if not tensors:
        return True
    return bool(torch.isfinite(torch.nn.utils.get_total_norm(tensors)))


class SurpriseModel:
    """Encoder + predictor + online learner: `step(frame)` -> PerceptionResult.

    :param cfg: the configuration (the only argument that shapes the model).
    :param encoder: an already built encoder to use instead of `build_encoder(cfg...)`;
        `load` passes a randomly initialised one that the checkpoint then overwrites.
    """

    def __init__(self, cfg: PerceptionConfig, *, encoder: nn.Module | None = None):
        self.cfg = cfg
        if cfg.num_threads:
            torch.set_num_threads(cfg.num_threads)
        seed_everything(cfg.seed)
        if encoder is None:
            from activeloc_ros.perception.encoders import build_encoder
            encoder = build_encoder(cfg.encoder, weights=cfg.weights or None,
                                    pretrained=cfg.pretrained, classifier=False)
        # eval mode always: BatchNorm statistics of one frame are meaningless; the weights
        # still learn when update_encoder
        self.encoder = encoder.eval()
        if cfg.channels_last:
            self.encoder = self.encoder.to(memory_format=torch.channels_last)
        self.train_encoder = cfg.learn and cfg.update_encoder
        self.encoder.requires_grad_(self.train_encoder)
        # a frozen encoder runs with BatchNorm folded into its convs (same maps, cheaper);
        # `encoder` keeps the unfolded weights for checkpoints
        self.frozen_encoder = self.encoder
        if cfg.fold_bn and not self.train_encoder and _has_batchnorm(self.encoder):
            from activeloc_ros.perception.encoders import fold_batchnorm
            self.frozen_encoder = fold_batchnorm(self.encoder)
        precision = _resolve(cfg.encoder_precision)
        if cfg.encoder_precision == 'auto' and not self.train_encoder and cfg.pretrained:
            from activeloc_ros.perception import int8   # (random weights: not worth a build)
            if int8.available():
                precision = 'int8'
        if precision == 'int8' and self.train_encoder:
            raise ConfigError("perception parameter 'encoder_precision' int8 needs a frozen "
                              'encoder (update_encoder false)')
        self.precision = precision                              # the encoder's, in use
        self.predictor_precision = _resolve(cfg.predictor_precision)
        if precision == 'bfloat16' and not self.train_encoder:
            # cast the weights once: autocast would cast them again on every frame
            if self.frozen_encoder is self.encoder:
                self.frozen_encoder = copy.deepcopy(self.encoder)
            self.frozen_encoder = self.frozen_encoder.to(torch.bfloat16)
        self.size = int(encoder.input_size)
        self.channels = int(encoder.channels)
        with torch.inference_mode():                            # the grid the encoder makes
            zeros = torch.zeros(1, 3, self.size, self.size)
            probe = self._run(self.frozen_encoder, self.encoder.preprocess(zeros))
        self.grid = int(probe.shape[-1])                        # 14 at 224
        self.cells = self.grid * probe.shape[-2]
        stride = self.size // self.grid                         # 16 for the 14x14 grid
        if cfg.encoder_pad % stride or cfg.encoder_pad >= self.size:
            raise ConfigError(f"perception parameter 'encoder_pad' must be a multiple of the "
                              f'encoder stride {stride} below {self.size}, got '
                              f'{cfg.encoder_pad}')
        if precision == 'int8':
            from activeloc_ros.perception import int8, weights
            side = self.size + 2 * cfg.encoder_pad
            self.frozen_encoder = int8.load(
                self.frozen_encoder, name=cfg.encoder, input_shape=(1, 3, side, side),
                prepare=lambda rgb: self._padded(self._tensor(self._resize(rgb))),
                threads=torch.get_num_threads(), cache=weights.cache_dir())
        self.predictor = Predictor(cfg, self.channels)
        self._predict = torch.compile(self.predictor) if cfg.compile else self.predictor
        groups = [{'params': list(self.predictor.parameters()), 'scale': 1.0}]
        if self.train_encoder:
            groups.append({'params': list(self.encoder.parameters()),
                           'scale': cfg.encoder_lr_scale})
        self.optimizer = _make_optimizer(cfg, groups)
        self.loss_window = collections.deque(maxlen=cfg.adaptive_window)
        self.ego = (egomotion.EgoMotion(model=cfg.ego_motion) if cfg.ego_motion != 'none'
                    else None)
        self.nan_events = 0
        self.frame_index = 0
        self.updates = 0
        self.reset()
        self._snapshot = None
        self._take_snapshot()

    # -- state -------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the recurrent state, the previous frame and the previous maps."""
        self._forget_view()
        self._forget_sequence()

    def _forget_view(self) -> None:
        """`observe`'s memory of the previous frame."""
        self.x_prev = None         # (1, 3, S, S) normalised previous frame
        self.img_prev = None       # (S, S, 3) previous resized image (ego_motion)
        self.keys_prev = None      # its ORB keypoints and descriptors (ego_motion)
        self.grey_prev = None      # (S, S) its blurred grey picture (motion_source image)

    def _forget_sequence(self) -> None:
        """`learn`'s memory: the predictor's state, the previous features and maps."""
        self.state = None          # (h, c) after the last frame fed to the predictor
        self.f_prev = None         # (N, C) the previous frame's features
        self.map_prev = None       # (N,) surprise map of frame t-1
        self.map_prev2 = None      # (N,) and of frame t-2

    def _params(self) -> list[torch.Tensor]:
        return [p for g in self.optimizer.param_groups for p in g['params']]

    def _take_snapshot(self) -> None:
        """Copy what an update changes (a frozen encoder never changes: not copied)."""
        self._snapshot = {
            'predictor': _clone_tree(self.predictor.state_dict()),
            'optimizer': _clone_tree(self.optimizer.state_dict()),
        }
        if self.train_encoder:
            self._snapshot['encoder'] = _clone_tree(self.encoder.state_dict())

    def _nonfinite(self) -> None:
        """Skip the update, restore the weights if they are corrupt, restart the sequence."""
        self.nan_events += 1
        self.optimizer.zero_grad(set_to_none=True)
        trained = [self.predictor] + ([self.encoder] if self.train_encoder else [])
        if not all(_finite(list(m.state_dict().values())) for m in trained):
            self.predictor.load_state_dict(self._snapshot['predictor'])
            self.optimizer.load_state_dict(_clone_tree(self._snapshot['optimizer']))
            if self.train_encoder:
                self.encoder.load_state_dict(self._snapshot['encoder'])
        self._forget_sequence()

    # -- one frame ---------------------------------------------------------------------------
    def preprocess(self, frame: np.ndarray) -> torch.Tensor | None:
        """(H, W, 3) RGB 0..255 -> (1, 3, S, S) normalised encoder input; None if not finite."""
        img = self._resize(frame)
        return None if img is None else self._tensor(img)

    def _resize(self, frame: np.ndarray) -> np.ndarray | None:
        """(H, W, 3) RGB 0..255 -> (S, S, 3) encoder-sized image; None if not finite."""
        _check_frame(frame)
        img = frame
        if frame.dtype != np.uint8:
            if not np.isfinite(frame).all():
                return None
            img = frame.astype(np.float32, copy=False)
        h, w = img.shape[:2]
        shrink = h >= self.size and w >= self.size
        img = cv2.resize(img, (self.size, self.size),
                         interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
        if self.cfg.blur_ksize:
            img = cv2.GaussianBlur(img, (self.cfg.blur_ksize,) * 2, 0)
        return img

    def _tensor(self, img: np.ndarray) -> torch.Tensor:
        x = torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None].float()
        x = self.encoder.preprocess(x)                          # (1, 3, S, S)
        if self.cfg.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        return x

    def _features(self, encoder: nn.Module, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, S, S) -> (B, N, C) float32 features, computed at `self.precision`."""
        return self._to_cells(self._forward(encoder, x))

    def _forward(self, encoder: nn.Module, x: torch.Tensor) -> torch.Tensor:
        crop = self.cfg.encoder_pad * self.grid // self.size   # cells the padding adds
        f = self._run(encoder, self._padded(x))
        return f[..., crop:f.shape[-2] - crop, crop:f.shape[-1] - crop]

    def _padded(self, x: torch.Tensor) -> torch.Tensor:
        pad = self.cfg.encoder_pad
        return F.pad(x, (pad,) * 4, mode='reflect') if pad else x

    def _run(self, encoder: nn.Module, x: torch.Tensor) -> torch.Tensor:
        if self.precision in ('float32', 'int8'):
            return encoder(x)
        if encoder is self.frozen_encoder and not self.train_encoder:  # bfloat16 weights
            return encoder(x.to(torch.bfloat16)).float()
        with torch.autocast('cpu', dtype=torch.bfloat16):
            return encoder(x).float()

    def _to_cells(self, f: torch.Tensor) -> torch.Tensor:
        f = f.flatten(2).transpose(1, 2)                        # (B, C, g, g) -> (B, N, C)
        if self.cfg.feature_norm == 'frame_rms':
            f = f / (f.square().mean(dim=(1, 2), keepdim=True).sqrt() + 1e-6)
        return f

    def _encode(self, x: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor]:
        """Features (N, C) of the current frame and, where the encoder learns through both
        (`encoder_grad: both`), of the previous one again with the current weights."""
        if not (self.train_encoder and self.x_prev is not None):
            with torch.inference_mode():
                f_cur = self._features(self.frozen_encoder, x)[0]
            return None, f_cur.clone()                          # a normal tensor again
        with torch.enable_grad():
            if self.cfg.encoder_grad == 'both':                 # re-encode with current weights
                feats = self._features(self.encoder, torch.cat([self.x_prev, x]))  # (2, N, C)
                return feats[0], feats[1]
            return None, self._features(self.encoder, x)[0]

    def step(self, frame: np.ndarray) -> PerceptionResult:
        """Encode a frame, score the prediction made for it, update online, predict on."""
        return self.learn(self.observe(frame))

    def observe(self, frame: np.ndarray) -> Observation:
        """The first half of `step`: the frame's encoder input, its features and the
        camera's motion since the frame before. It reads and writes only its own memory of
        the previous frame, so it may run on the next frame while `learn` runs on this one:
        `learn(observe(f))` for each frame in turn gives the same results in either order."""
        cfg = self.cfg
        t0 = time.perf_counter()
        timings = dict.fromkeys(('preprocess', 'encode', 'predict', 'update'), 0.0)
        img = self._resize(frame)                   # a malformed frame raises: not counted
        obs = Observation(frame, self.frame_index, t0, timings)
        self.frame_index += 1
        if img is None:                            # not finite: the next frame starts anew
            self._forget_view()
            timings['preprocess'] = time.perf_counter() - t0
            return obs
        x = self._tensor(img)
        if self.ego is not None:      # timed as preprocessing, re-encoding included
            obs.warp, obs.f_prev = self._follow_camera(img)
        if cfg.motion_source == 'image':
            obs.change = self._image_change(img, obs.warp)
        t1 = time.perf_counter()
        timings['preprocess'] = t1 - t0
        f_again, obs.f_cur = self._encode(x)
        if f_again is not None:
            obs.f_prev = f_again
        self.x_prev = x
        timings['encode'] = time.perf_counter() - t1
        return obs

    def learn(self, obs: Observation, *,
              on_map: Callable[[PerceptionResult], None] | None = None) -> PerceptionResult:
        """The second half of `step`: score the prediction made for the observed frame,
        update online, and remember what the next prediction needs.

        :param on_map: called once with the frame's result as soon as its map exists:
            before the optimiser step (which the map does not need), so a caller can publish
            it early. The result returned at the end also carries the step's outcome.
        """
        def handed(result: PerceptionResult) -> PerceptionResult:
            if on_map is not None:
                on_map(result)
            return result

        cfg = self.cfg
        timings = obs.timings
        done = dict(frame=obs.frame, index=obs.index, timings=timings, t0=obs.t0)
        if obs.f_cur is None or not _finite([obs.f_cur]):
            self._nonfinite()
            return handed(self._result(None, **done))
        t2 = time.perf_counter()
        f_cur, f_prev = obs.f_cur, self.f_prev
        if f_prev is None:                                      # first frame: nothing to score
            self._remember(f_cur, None)
            return handed(self._result(None, **done))
        if obs.f_prev is not None:                              # the previous view encoded again
            f_prev = obs.f_prev
        if obs.warp is not None:
            self._move_memory(obs.warp)
            if cfg.ego_warp == 'features':
                f_prev = self._warp_features(f_prev, f_cur.detach(), obs.warp)
        train = cfg.learn
        state = self.state or self.predictor.initial_state(self.cells)
        uniform = torch.full((self.cells,), 1.0 / self.cells)
        target = self.map_prev2 if self.map_prev2 is not None else uniform
        with torch.set_grad_enabled(train):
            with torch.autocast('cpu', dtype=torch.bfloat16,
                                enabled=self.predictor_precision == 'bfloat16'):
                fhat, alpha, new_state = self._predict(f_prev, state)  # (N, C), (N,)
            fhat, alpha = fhat.float(), alpha.float()
            new_state = (new_state[0].float(), new_state[1].float())
            if obs.change is not None:                               # (N,) grey levels
                weight = motion_weight(obs.change, cfg.motion_weighting,
                                       cfg.image_motion_scale)[:, None].expand_as(f_cur)
            else:
                weight = motion_weight((f_cur - f_prev).detach(), cfg.motion_weighting,
                                       cfg.motion_scale)               # (N, C)
            l_global, e = global_error(f_cur, fhat, weight, reduction=cfg.loss_reduction)
            l_attn = (attention_loss(alpha, target, f_prev) if cfg.attn_loss_on
                      else torch.zeros(()))
            total = l_global + cfg.attn_weight * l_attn
        e = e.detach()                                          # (N,)
        t3 = time.perf_counter()
        timings['predict'] = t3 - t2
        if not _finite([total, e]):
            self._nonfinite()
            return handed(self._result(e if _finite([e]) else None, **done))
        losses = None
        if train:
            losses = {k: float(v.detach()) for k, v in
                      (('global', l_global), ('attn', l_attn), ('total', total))}
        result = handed(self._result(e, losses=losses, **done))
        lr = self._update(total) if train else 0.0
        timings['update'] = time.perf_counter() - t3
        timings['total'] = time.perf_counter() - obs.t0
        if lr is None:                                          # the step was not finite
            probs = self.map_prev
            self._nonfinite()
            self.map_prev = probs                               # this frame's map stays
            return dataclasses.replace(result, losses=dict(_NO_LOSSES), updated=False,
                                       nan_events=self.nan_events)
        self._remember(f_cur, (new_state[0].detach(), new_state[1].detach()))
        return dataclasses.replace(result, lr=lr)

    def _follow_camera(self, img: np.ndarray) -> tuple[np.ndarray | None, torch.Tensor | None]:
        """The camera's warp from the previous frame to this one (None if it did not move),
        and with `ego_warp: image` the previous view warped into this one and encoded again
        (None otherwise: `learn` warps the previous features cell by cell)."""
        gray = img if img.dtype == np.uint8 else np.clip(img, 0, 255).astype(np.uint8)
        keys = self.ego.keypoints(cv2.cvtColor(gray, cv2.COLOR_RGB2GRAY))
        prev_keys, self.keys_prev = self.keys_prev, keys
        img_prev, self.img_prev = self.img_prev, img
        if prev_keys is None or img_prev is None:
            return None, None
        warp = self.ego.estimate(prev_keys, keys, self.size)
        if warp is None or self.cfg.ego_warp != 'image':
            return warp, None
        self.x_prev = self._tensor(egomotion.warp_image(img_prev, warp, img))
        if self.train_encoder and self.cfg.encoder_grad == 'both':   # `_encode` does it
            return warp, None
        with torch.no_grad():
            return warp, self._features(self.frozen_encoder, self.x_prev)[0]

    def _move_memory(self, warp: np.ndarray) -> None:
        """Move the predictor's state and the past maps into the new view."""
        g = self.grid
        if self.state is not None:
            self.state = tuple(egomotion.warp_cells(s, warp, self.size, g) for s in self.state)
        for name in ('map_prev', 'map_prev2'):
            m = getattr(self, name)
            if m is not None:
                m = egomotion.warp_cells(m[None], warp, self.size, g)[0]
                total = float(m.sum())
                setattr(self, name, m / total if total > 0 else None)

    def _image_change(self, img: np.ndarray, warp: np.ndarray | None) -> torch.Tensor | None:
        """(N,) per-cell change of the picture since the previous frame, the camera's own
        motion taken out (`motion_source: image`); None on a first frame."""
        current = motion.grey(np.clip(img, 0, 255))
        previous, self.grey_prev = self.grey_prev, current
        if previous is None:
            return None
        change = motion.residual(previous, current, warp)
        return torch.from_numpy(motion.cell_means(change, (self.grid, self.grid)).reshape(-1))

    def _warp_features(self, f_prev: torch.Tensor, f_cur: torch.Tensor,
                       warp: np.ndarray) -> torch.Tensor:
        """(N, C) previous features moved into the current view (`ego_warp: features`);
        where the previous view saw nothing, the current features: no change there."""
        ones = torch.ones(self.cells, 1)                        # how much of a cell was seen
        moved = egomotion.warp_cells(torch.cat([f_prev, ones], 1)[None], warp, self.size,
                                     self.grid)[0]
        return moved[:, :-1] + (1.0 - moved[:, -1:]) * f_cur

    def _update(self, total: torch.Tensor) -> float | None:
        """One optimiser step; the learning rate used, or None if anything was not finite."""
        cfg = self.cfg
        loss = float(total.detach())
        factor = 1.0
        window = self.loss_window
        if (cfg.adaptive_lr and len(window) == cfg.adaptive_window
                and loss > cfg.adaptive_ratio * (sum(window) / len(window))):
            factor = cfg.adaptive_boost
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        params = self._params()
        if not _finite([p.grad for p in params]):
            return None
        if cfg.grad_clip:
            nn.utils.clip_grad_norm_(params, cfg.grad_clip)
        lr = cfg.lr * factor
        for group in self.optimizer.param_groups:
            group['lr'] = lr * group['scale']
        self.optimizer.step()
        if not _finite(params):
            return None
        window.append(loss)
        self.updates += 1
        if self.updates % cfg.snapshot_every == 0:
            self._take_snapshot()
        return lr

    def _remember(self, f_cur: torch.Tensor,
                  state: tuple[torch.Tensor, torch.Tensor] | None) -> None:
        self.f_prev = f_cur.detach()
        self.state = state

    def _result(self, e: torch.Tensor | None, *, frame: np.ndarray, index: int,
                timings: dict[str, float], t0: float, losses: dict[str, float] | None = None,
                lr: float = 0.0) -> PerceptionResult:
        g, n = self.grid, self.cells
        probs = surprise_map(e, self.cfg.map_temperature) if e is not None else None
        if probs is None or not _finite([probs]):
            probs = torch.full((n,), 1.0 / n)
        self.map_prev2, self.map_prev = self.map_prev, probs
        flat = int(torch.argmax(probs))
        row, col = divmod(flat, g)
        h, w = frame.shape[:2]
        rows = n // g
        x, y = action_location(probs.reshape(rows, g), self.cfg.location,
                               self.cfg.location_share)
        timings['total'] = time.perf_counter() - t0
        return PerceptionResult(
            surprise_map=probs.reshape(rows, g).numpy().astype(np.float32),
            cell=(row, col), location_px=(x * w / g, y * h / rows),
            peak=float(probs[flat]),
            losses=losses or dict(_NO_LOSSES),
            lr=lr, updated=losses is not None, timings=timings,
            nan_events=self.nan_events, frame_index=index)

    # -- checkpoints -------------------------------------------------------------------------
    def save(self, path: str) -> None:
        """Config, weights, optimiser and the running state, so `load` resumes learning."""
        torch.save({
            'config': self.cfg.to_dict(),
            'encoder': self.encoder.state_dict(),
            'predictor': self.predictor.state_dict(),
            'optimizer': self.optimizer.state_dict(),
            'running': {
                'state': self.state, 'x_prev': self.x_prev, 'f_prev': self.f_prev,
                'map_prev': self.map_prev, 'map_prev2': self.map_prev2,
                'loss_window': list(self.loss_window), 'nan_events': self.nan_events,
                'frame_index': self.frame_index, 'updates': self.updates,
                'grey_prev': (None if self.grey_prev is None
                              else torch.from_numpy(self.grey_prev)),
            },
        }, path)

    @classmethod
    def load(cls, path: str) -> 'SurpriseModel':
        """Rebuild a saved model; it continues learning where `save` left it."""
        from activeloc_ros.perception.encoders import build_encoder
        ckpt = torch.load(path, map_location='cpu', weights_only=True)
        # a checkpoint saved before encoder_pad existed was learned without the border
        cfg = PerceptionConfig.from_dict({'encoder_pad': 0, **ckpt['config']})
        # the checkpoint holds the encoder weights: no weight cache needed
        encoder = build_encoder(cfg.encoder, pretrained=False, classifier=False)
        encoder.load_state_dict(ckpt['encoder'])
        model = cls(cfg, encoder=encoder)
        model.predictor.load_state_dict(ckpt['predictor'])
        model.optimizer.load_state_dict(ckpt['optimizer'])
        run = ckpt['running']
        model.state = tuple(run['state']) if run['state'] is not None else None
        model.x_prev, model.f_prev = run['x_prev'], run['f_prev']
        if model.x_prev is not None and cfg.channels_last:
            model.x_prev = model.x_prev.contiguous(memory_format=torch.channels_last)
        model.map_prev, model.map_prev2 = run['map_prev'], run['map_prev2']
        model.loss_window.extend(run['loss_window'])
        model.nan_events, model.frame_index = run['nan_events'], run['frame_index']
        model.updates = run['updates']
        grey_prev = run.get('grey_prev')
        model.grey_prev = None if grey_prev is None else grey_prev.numpy()
        model._take_snapshot()
        return model


def _make_optimizer(cfg: PerceptionConfig, groups: list[dict]) -> torch.optim.Optimizer:
    for g in groups:
        g['lr'] = cfg.lr * g['scale']
    # fused kernels: one pass over all parameters instead of ~10 per tensor (2x on 2 cores)
    if cfg.optimizer == 'adam':
        return torch.optim.Adam(groups, lr=cfg.lr, fused=True)
    return torch.optim.SGD(groups, lr=cfg.lr, momentum=cfg.momentum, fused=True)


def _clone_tree(obj: Any) -> Any:
    if isinstance(obj, torch.Tensor):
        return obj.detach().clone()
    if isinstance(obj, dict):
        return {k: _clone_tree(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_clone_tree(v) for v in obj]
    return obj


def _has_batchnorm(module: nn.Module) -> bool:
    return any(isinstance(m, nn.modules.batchnorm._BatchNorm) for m in module.modules())


def _check_frame(frame: Any) -> None:
    if not isinstance(frame, np.ndarray):
        raise FrameError(f'frame must be a numpy array, got {type(frame).__name__}')
    if frame.ndim != 3 or frame.shape[2] != 3 or frame.shape[0] < 1 or frame.shape[1] < 1:
        raise FrameError(f'frame must be (H, W, 3) RGB, got shape {frame.shape}')
    if frame.dtype != np.uint8 and frame.dtype not in (np.float32, np.float64):
        raise FrameError(f'frame must be uint8 (or float 0..255) RGB, got {frame.dtype}')
