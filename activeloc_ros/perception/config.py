"""
Every choice of the perception model: `PerceptionConfig`, built from ROS parameters or YAML.

The perception node declares one ROS parameter per field, with the field's help string
(`perception.params.model_params`), so the field's default is the parameter's. What each
default was measured against is in docs/decisions.md and docs/history.md, not in the help
strings.
"""
import dataclasses
from dataclasses import dataclass, field
import math
from typing import Any

from activeloc_ros.checks import above, at_least, Check, in_range, one_of
from activeloc_ros.errors import ConfigError

ENCODER_NAMES = ('vgg16', 'vgg19', 'efficientnet_lite0', 'resnet50')
MOTIONS = ('abs_sigmoid', 'sigmoid', 'raw', 'none')
PRECISIONS = ('auto', 'float32', 'bfloat16')
ENCODER_PRECISIONS = PRECISIONS + ('int8',)


def _blur(value: int) -> 'str | None':
    if value == 0 or (value >= 3 and value % 2 == 1):
        return None
    return f'must be 0 (off) or an odd size >= 3, got {value}'


def _param(default: Any, text: str, check: Check | None = None) -> Any:
    return field(default=default, metadata={'help': text, 'check': check})


@dataclass
class PerceptionConfig:
    """Every choice of the perception model; `from_dict` builds it from ROS parameters/YAML."""

    # encoder
    encoder: str = _param(
        'vgg19',
        'CNN encoder to the stride-16 grid. Default vgg19 to pool4: the closest stand-in for the '
        "paper's vgg16 pool4 whose ImageNet weights the registries hold; vgg16 needs "
        '`weights`; efficientnet_lite0 is far cheaper and less accurate (docs/history.md)',
        one_of(*ENCODER_NAMES))
    weights: str = _param('', 'encoder weights file; empty = the package weight cache')
    encoder_precision: str = _param(
        'auto', "arithmetic of the encoder's forward pass: float32; bfloat16 (features "
        'within ~1% of float32; faster where the CPU computes it natively, slower where it is '
        'emulated); int8 (OpenVINO, quantised once by NNCF on the sample bag, see '
        'perception.int8; a frozen encoder only); auto = int8 for a frozen ImageNet '
        'encoder, else bfloat16 where the CPU has AMX or AVX512_BF16, else float32',
        one_of(*ENCODER_PRECISIONS))
    encoder_pad: int = _param(
        0, 'pixels of mirrored picture added round the encoder input, whose extra feature '
        'cells are cut off again: the border cells then see picture, not the zero padding '
        'of the convolutions, which otherwise makes them the most surprising cells when the '
        'camera moves (a multiple of the encoder stride, 16; 0 = off, paper; 32 with '
        'conv_padding zeros: params/mirrored_border.yaml)', at_least(0))
    conv_padding: str = _param(
        'zeros', "what the encoder's convolutions pad their input with: zeros (the "
        "paper's, as in ImageNet training) or reflect (mirrored picture at every layer: like "
        'encoder_pad the border cells see no zeros, but at no extra work)',
        one_of('zeros', 'reflect'))
    input_height: int = _param(
        0, 'height of the encoder input, px: a multiple of the encoder stride (16), one grid '
        "row per 16 px; 0 = the encoder's own, 224 (the paper's, 14 rows). 160 (10 rows) "
        "halves the encoder's work and the predictor's cells, and follows less accurately "
        '(params/fast.yaml; docs/performance.md)', in_range(0, 1024))
    input_aspect: float = _param(
        1.0, "width over height of the encoder input: its height is input_height's (224), "
        'its width the multiple of the encoder stride (16) nearest to height x this, and the '
        "grid has one column per 16 px. 1 = the paper's 224 x 224, which squashes a 4:3 "
        "frame to three quarters of its width; the camera's own aspect keeps its picture "
        'undistorted (4:3, 1.3333: 304 x 224, 14 rows and 19 columns; '
        'docs/history.md)', in_range(0.25, 4.0))
    pretrained: bool = _param(
        True, 'load ImageNet weights; False = random encoder, for unit tests only')
    blur_ksize: int = _param(
        0, 'Gaussian blur of the resized frame before encoding; 0 = off, 5 = lab code', _blur)
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
        'auto', "arithmetic of the predictor's matrix products, forward and backward: "
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
        'full', "full = this paper; predlearn = the ECCV'20 PredLearn baseline of Table 3 "
        '(motion=raw and no L_attn, whatever those fields say)', one_of('full', 'predlearn'))
    motion: str = _param(
        'abs_sigmoid', 'weight of the prediction error by the motion d = f_t - f_{t-1}: '
        'abs_sigmoid = 2*sigmoid(|d|/s)-1 (0 where nothing moves, -> 1 with motion); '
        "sigmoid = sigmoid(d/s), the paper's literal Eq. 2 (0.5 where nothing moves, "
        'below 0.5 where a feature drops); raw = d^2 (lab code, Table 3 "w/o normalized '
        'motion"); none = unweighted', one_of(*MOTIONS))
    motion_scale: float = _param(
        1.0, 'motion scale s of the sigmoid weightings (paper: 1), for frames motion_period '
        'apart', above(0.0))
    motion_period: float = _param(
        0.0, 'seconds between compared frames (their capture stamps) at which motion_scale '
        'and image_motion_scale hold; frames closer together or farther apart scale both '
        'by (gap / motion_period) ** motion_gap_power, within 1/4 to 4 times, because a '
        'picture changes less in less time (0.1 was no better on the synthetic set, '
        'docs/decisions.md); 0 = fixed scales at any frame rate (paper, default)',
        at_least(0.0))
    motion_gap_power: float = _param(
        0.5, 'how the motion scales grow with the time between frames: 1 = in proportion '
        '(a steady motion), 0.5 = as its square root (the spread of a random walk)',
        at_least(0.0))
    motion_source: str = _param(
        'features', 'what the motion d is measured on: features = f_t - f_{t-1} of each '
        'cell, broadcast over nothing (paper Eq. 2); image = the per-cell mean change of '
        'the blurred grey picture against the previous one moved into the new view '
        "(perception.motion: pixel-accurate, so the grid features' misregistration under "
        'camera motion is no motion), in grey levels scaled by image_motion_scale',
        one_of('features', 'image'))
    image_motion_scale: float = _param(
        2.0, 'with motion_source image, the change (grey levels) at which the sigmoid '
        'weights reach ~0.46', above(0.0))
    use_attn_loss: bool = _param(True, 'add L_attn (paper Eq. 3); False = Table 3 "w/o L_attn"')
    attn_weight: float = _param(1.0, 'factor of L_attn in the total loss', at_least(0.0))
    ego_motion: str = _param(
        'none', "the camera's own motion: estimated from the images (ORB + RANSAC) "
        'as a similarity or a homography (exact for a camera turning about its optical '
        'centre), the new frame is compared with the previous one warped into its view, '
        'and the LSTM state and past maps move with it; none = ignored (paper; the '
        'protocol found similarity no better on the static sequences, docs/decisions.md)',
        one_of('none', 'similarity', 'homography'))
    ego_warp: str = _param(
        'features', "with ego_motion, how the previous frame's features reach the new "
        'view: features = they are warped cell by cell (cells the previous view did not '
        "see take the new frame's); image = the previous image is warped and encoded "
        'again, a second encoder pass on every frame the camera moved',
        one_of('features', 'image'))
    map_temperature: float = _param(
        1.0, 'softmax temperature of the surprise map over the cells (paper: 1)', above(0.0))
    location: str = _param(
        'region', "where the action is: peak = the centre of the map's argmax cell (paper); "
        'mass = the centroid of the cells that reach location_share of the peak, which '
        'follows a group rather than the one cell of it that is most surprising this frame; '
        'region = the centre of the box round the blob of cells connected to the peak that '
        "stand location_region_share of the way up the log map's range: the whole moving "
        'person, where the peak and the centroid sit on the head and shoulders',
        one_of('peak', 'mass', 'region'))
    location_share: float = _param(
        0.25, 'with location mass, the share of the peak value a cell needs to count',
        in_range(0.0, 1.0))
    location_floor: str = _param(
        'zero', 'with location mass, what the cells that count are weighted by: zero = their '
        "map value; min = their height above the map's lowest cell, so the even surprise a "
        "flat map spreads over the whole view does not pull the location to the view's "
        'centre (with location_share 0 on the screen benchmark: 1.1 and 2.5 deg closer on '
        'tud_stadtmitte and walking2, farther on kitti_17 and otb_crossing; '
        'docs/history.md)', one_of('zero', 'min'))
    location_region_share: float = _param(
        0.5, "with location region, how far up the map's range, from its lowest cell to its "
        "peak on a log scale (the prediction error's range), a cell must stand to join the "
        "peak's blob (0 = every connected cell, 1 = the peak alone)", in_range(0.0, 1.0))
    location_region_spread: float = _param(
        0.1, "with location region, the location is the mean of the box's centre at three "
        'bars: location_region_share and this much below and above it (each kept within '
        '0..1), so a cell that crosses one bar moves the location by a sixth of a cell, not '
        'by half of one (0 = the one bar)', in_range(0.0, 0.5))
    location_prior: float = _param(
        5.0, "width (cells, a Gaussian's sigma) of a prior on the image centre that weights "
        'the map before the location is read from it: of two equally surprising places the '
        'one nearer where the camera looks wins, so the camera stays on its action instead '
        "of jumping to a passer-by or to the view's border (0 = off, paper; the published "
        'map and its peak are not weighted)', at_least(0.0))
    loss_reduction: str = _param(
        'mean', 'L_global over cells and channels: mean or sum', one_of('mean', 'sum'))
    # online learning
    learn: bool = _param(True, 'one optimiser step per frame; False = predict only')
    skip_late_updates: int = _param(
        0, 'a frame whose map is ready only after the camera has captured its next one (a '
        'camera faster than the model, in real time) gets no optimiser step, so the model '
        'turns to the newer frame sooner; at most this many frames in a row, so at least one '
        "frame in this + 1 is learnt from. 0 = the paper's strict one step per frame "
        '(default: with a 30 frames/s camera 1 makes more maps but follows worse, '
        'docs/performance.md). A camera the model keeps up with, and lockstep, are never late; '
        "the perception node's pipeline: true learns from every frame", at_least(0))
    update_encoder: bool = _param(
        False, 'also train the encoder online (paper: True; it costs 2 encoder backward '
        'passes per frame, each map about 4.75 times dearer, and made no difference on the '
        'real set, docs/decisions.md)')
    encoder_grad: str = _param(
        'both', 'with update_encoder, the encoder gradient flows through both the '
        "predictor's input and the target (exact; re-encodes the previous frame) or through "
        'the target only (half the encoder cost)', one_of('both', 'target'))
    optimizer: str = _param(
        'sgd', 'online optimiser (paper: sgd; adam with lr 1e-3 was no better on the static '
        'sequences, docs/decisions.md)', one_of('adam', 'sgd'))
    lr: float = _param(
        1e-6, 'base learning rate (paper: 1e-6, which moves the predictor little within a '
        'sequence; with adam, 1e-3)', at_least(0.0))
    encoder_lr_scale: float = _param(
        1.0, 'encoder learning rate = lr * this (paper: 1)', at_least(0.0))
    momentum: float = _param(0.0, 'SGD momentum', at_least(0.0))
    grad_clip: float = _param(
        0.0, 'clip the global gradient norm to this; 0 = off', at_least(0.0))
    adaptive_lr: bool = _param(
        True, "adaptive learning (Aakur & Sarkar CVPR'19, paper: on): a loss much above "
        'the recent mean gets a boosted learning rate for that step (turn it off with adam: '
        'its 100x steps undo what was learnt)')
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
        'cheaper)')
    compile: bool = _param(  # noqa: A003 (a parameter's name, which users set)
        False, 'torch.compile the predictor (slow first frames)')

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
    def fields_in(cls, values: dict[str, Any]) -> dict[str, Any]:
        """
        The entries of `values` that are fields of this config (a perception node's
        parameters hold its own too).
        """
        names = _field_names(cls)
        return {k: v for k, v in values.items() if k in names}

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
