"""
ImageNet encoders: a frame in, a stride-16 feature map out (B, C, 14, 14 for 224 px).

The paper encodes each frame with VGG-16 up to pool4 (Sec. 3.2). No registry this project
can reach ships VGG-16 weights, so four encoders share one interface (see `weights.py` for
where the offline weights come from and their licences):

==================  =======  ================================  ===========================
name                C        tap (last stride-16 layer)        preprocessing
==================  =======  ================================  ===========================
vgg16               512      pool4, torchvision features[:24]  RGB, /255, ImageNet mean/std
vgg19               512      pool4, torchvision features[:28]  caffe: BGR, 0..255 - mean px
efficientnet_lite0  112      end of block 10 (stage 5)         RGB, (x - 127) / 128
resnet50            1024     end of layer3                     caffe: BGR, 0..255 - mean px
==================  =======  ================================  ===========================

Every tap is the output of the last layer that still runs at stride 16, like pool4 ends
VGG's stride-16 stage. For EfficientNet-Lite0 that is the linear bottleneck after block 10
(112 ch), the stage output timm and detection necks take as C4; the 672-ch expansion of
block 11 would be 6x wider for the predictor's input and add no information a 1x1 conv
of the bottleneck does not already have.

BatchNorm stays a module with frozen statistics: `train()` leaves every BatchNorm layer in
eval mode. The online learner fine-tunes on one frame per step, whose batch statistics
would wreck the running ones; the affine weights still learn. Folding BN into the convs
would change what an SGD step on the encoder does, so `build_encoder`
(`encoder_weights`) never does it;
`fold_batchnorm` makes a frozen, folded copy for runs that do not train the encoder.

Modules are plain `nn.Module`s keyed like their sources (torchvision for VGG and ResNet,
EfficientNet-Lite-PyTorch for Lite0), so no model-zoo package is needed at run time. They
work with `torch.channels_last` and `torch.inference_mode`.
"""
from collections.abc import Iterator
import copy
import itertools
import math

import torch
from torch import nn
import torch.nn.functional as F
from torch.nn.utils.fusion import fuse_conv_bn_eval

from activeloc_ros.errors import ConfigError, FrameError

ENCODERS = ('vgg16', 'vgg19', 'efficientnet_lite0', 'resnet50')
INPUT_SIZE = 224
TAP_STRIDE = 16

# torchvision's VGG configurations: conv widths, 'M' for a 2x2 max pool.
VGG_CFGS = {
    'vgg16': (64, 64, 'M', 128, 128, 'M', 256, 256, 256, 'M', 512, 512, 512, 'M',
              512, 512, 512, 'M'),
    'vgg19': (64, 64, 'M', 128, 128, 'M', 256, 256, 256, 256, 'M', 512, 512, 512, 512, 'M',
              512, 512, 512, 512, 'M'),
}
VGG_TAP_POOL = 4  # pool4: stride 16

# EfficientNet-Lite0 stages (TF efficientnet_lite_builder): repeats, kernel, stride,
# expansion, in and out channels. Lite drops squeeze-excitation and uses ReLU6.
LITE0_STAGES = (
    (1, 3, 1, 1, 32, 16),
    (2, 3, 2, 6, 16, 24),
    (2, 5, 2, 6, 24, 40),
    (3, 3, 2, 6, 40, 80),
    (3, 5, 1, 6, 80, 112),
    (4, 5, 2, 6, 112, 192),
    (1, 3, 1, 6, 192, 320),
)
LITE0_STEM = 32
LITE0_HEAD = 1280
TF_BN_EPS = 1e-3  # Keras / TF BatchNormalization default; torch's is 1e-5

# ResNet-50: bottleneck width, blocks, stride of each stage (layer1..layer4).
RESNET50_STAGES = ((64, 3, 1), (128, 4, 2), (256, 6, 2), (512, 3, 2))
RESNET_EXPANSION = 4

CAFFE_MEAN_BGR = (103.939, 116.779, 123.68)
IMAGENET_MEAN_RGB = (0.485, 0.456, 0.406)
IMAGENET_STD_RGB = (0.229, 0.224, 0.225)
NUM_CLASSES = 1000

# Whether the weights' source carries an ImageNet classifier. vgg19 means the Keras (caffe)
# no-top weights; a torchvision VGG-19 file would need other preprocessing, so its head
# keys are refused as unexpected.
HAS_HEAD = {'vgg16': True, 'vgg19': False, 'efficientnet_lite0': True, 'resnet50': True}


class Encoder(nn.Module):
    """
    Base of the encoders: preprocessing, the trunk to the stride-16 tap, an optional head.

    :param name: one of `ENCODERS`.
    :param channels: C of the tapped feature map.
    :param bgr: the weights expect BGR channel order (caffe / Keras).
    :param mean: per-channel mean subtracted from 0..255 pixels, in the weights' order.
    :param std: per-channel divisor after the mean.
    """

    input_size = INPUT_SIZE
    stride = TAP_STRIDE

    def __init__(self, name: str, channels: int, *, bgr: bool,
                 mean: tuple[float, float, float], std: tuple[float, float, float]):
        super().__init__()
        self.name = name
        self.channels = channels
        self._bgr = bgr
        # Plain tuples, not buffers: nothing to keep in the state dict or move by hand.
        self._mean = mean
        self._std = std

    @property
    def has_classifier(self) -> bool:
        return False

    def preprocess(self, x: torch.Tensor) -> torch.Tensor:
        """Normalise RGB pixels in 0..255, (B, 3, H, W), the way this encoder's weights expect."""
        if x.ndim != 4 or x.shape[1] != 3:
            raise FrameError(f'{self.name}: expected a (B, 3, H, W) RGB batch, '
                             f'got shape {tuple(x.shape)}')
        if not x.is_floating_point():
            x = x.float()
        if self._bgr:
            x = x.flip(1)
        mean = torch.tensor(self._mean, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
        inv_std = 1.0 / torch.tensor(self._std, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
        return (x - mean) * inv_std

    def classify(self, x: torch.Tensor) -> torch.Tensor:
        """ImageNet logits (B, 1000) of a normalised batch; only where the source has a head."""
        if not self.has_classifier:
            raise NotImplementedError(f'{self.name} was built without an ImageNet classifier')
        return self.head(self(x))

    def head(self, f: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError(f'{self.name} has no classifier head')

    def train(self, mode: bool = True) -> 'Encoder':
        super().train(mode)
        for m in self.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.eval()  # frozen statistics, see the module docstring
        return self


# ---------------------------------------------------------------------------------------
# VGG
# ---------------------------------------------------------------------------------------

def vgg_pool_index(cfg: tuple, n: int) -> int:
    """Index in torchvision's `features` of the n-th max pool (1-based) of a VGG cfg."""
    index = -1
    pools = 0
    for item in cfg:
        index += 1 if item == 'M' else 2  # a conv is followed by its ReLU
        if item == 'M':
            pools += 1
            if pools == n:
                return index
    raise ConfigError(f'the VGG configuration has only {pools} pools, not {n}')


def vgg_conv_indices(cfg: tuple, end: int) -> list[int]:
    """Indices of the convs in torchvision's `features[:end]` of a VGG cfg."""
    indices = []
    index = 0
    for item in cfg:
        if index >= end:
            break
        if item == 'M':
            index += 1
        else:
            indices.append(index)
            index += 2
    return indices


def vgg_tap_channels(cfg: tuple) -> int:
    """Width of the last conv before pool `VGG_TAP_POOL` of a VGG cfg."""
    pools = 0
    width = 0
    for item in cfg:
        if item == 'M':
            pools += 1
            if pools == VGG_TAP_POOL:
                return width
        else:
            width = item
    raise ConfigError(f'the VGG configuration has fewer than {VGG_TAP_POOL} pools')


def make_vgg_features(cfg: tuple, end: int) -> nn.Sequential:
    """torchvision's `make_layers(cfg)[:end]`, same indices and keys."""
    layers: list[nn.Module] = []
    cin = 3
    for item in cfg:
        if item == 'M':
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
        else:
            layers += [nn.Conv2d(cin, item, kernel_size=3, padding=1), nn.ReLU(inplace=True)]
            cin = item
    return nn.Sequential(*layers[:end])


class VGGEncoder(Encoder):
    """VGG to pool4 in torchvision's layout; with `head`, also pool5 and the classifier."""

    def __init__(self, name: str, *, head: bool = False, caffe: bool = False):
        cfg = VGG_CFGS[name]
        if caffe:
            norm = {'bgr': True, 'mean': CAFFE_MEAN_BGR, 'std': (1.0, 1.0, 1.0)}
        else:
            norm = {'bgr': False, 'mean': tuple(255.0 * m for m in IMAGENET_MEAN_RGB),
                    'std': tuple(255.0 * s for s in IMAGENET_STD_RGB)}
        self.tap = vgg_pool_index(cfg, VGG_TAP_POOL) + 1
        super().__init__(name, vgg_tap_channels(cfg), **norm)
        end = vgg_pool_index(cfg, 5) + 1 if head else self.tap
        self.features = make_vgg_features(cfg, end)
        self._has_head = head
        if head:
            self.avgpool = nn.AdaptiveAvgPool2d((7, 7))
            self.classifier = nn.Sequential(
                nn.Linear(512 * 7 * 7, 4096), nn.ReLU(True), nn.Dropout(),
                nn.Linear(4096, 4096), nn.ReLU(True), nn.Dropout(),
                nn.Linear(4096, NUM_CLASSES))

    @property
    def has_classifier(self) -> bool:
        return self._has_head

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for layer in itertools.islice(self.features, self.tap):
            x = layer(x)
        return x  # (B, 512, H/16, W/16)

    def head(self, f: torch.Tensor) -> torch.Tensor:
        for layer in itertools.islice(self.features, self.tap, None):
            f = layer(f)
        return self.classifier(torch.flatten(self.avgpool(f), 1))


# ---------------------------------------------------------------------------------------
# EfficientNet-Lite0
# ---------------------------------------------------------------------------------------

class Conv2dSame(nn.Conv2d):
    """A strided Conv2d with TensorFlow's 'SAME' padding, which puts the odd pixel last."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pads = []
        for size, k, s in zip(x.shape[-1:-3:-1], self.kernel_size[::-1], self.stride[::-1]):
            total = max((math.ceil(size / s) - 1) * s + k - size, 0)
            pads += [total // 2, total - total // 2]
        mode = 'constant' if self.padding_mode == 'zeros' else self.padding_mode
        return super().forward(F.pad(x, pads, mode=mode))


def tf_conv(cin: int, cout: int, k: int, stride: int, *, groups: int = 1) -> nn.Conv2d:
    """A bias-free conv padded like TF 'SAME' (symmetric, hence plain, at stride 1)."""
    if stride == 1:
        return nn.Conv2d(cin, cout, k, padding=k // 2, groups=groups, bias=False)
    return Conv2dSame(cin, cout, k, stride=stride, groups=groups, bias=False)


def tf_bn(c: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(c, eps=TF_BN_EPS, momentum=0.01)  # TF decay 0.99


class MBConvBlock(nn.Module):
    """Inverted residual of EfficientNet-Lite (no SE, ReLU6), keys as EfficientNet-PyTorch."""

    CONV_BN = (('_expand_conv', '_bn0'), ('_depthwise_conv', '_bn1'), ('_project_conv', '_bn2'))

    def __init__(self, cin: int, cout: int, kernel: int, stride: int, expand: int):
        super().__init__()
        mid = cin * expand
        self.expands = expand != 1
        if self.expands:
            self._expand_conv = nn.Conv2d(cin, mid, 1, bias=False)
            self._bn0 = tf_bn(mid)
        self._depthwise_conv = tf_conv(mid, mid, kernel, stride, groups=mid)
        self._bn1 = tf_bn(mid)
        self._project_conv = nn.Conv2d(mid, cout, 1, bias=False)
        self._bn2 = tf_bn(cout)
        self.skip = stride == 1 and cin == cout
        # No drop-connect: an online learner wants the same features for the same frame.

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu6(self._bn0(self._expand_conv(x))) if self.expands else x
        y = F.relu6(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        return y + x if self.skip else y


def lite0_blocks() -> list[tuple[int, int, int, int, int]]:
    """(cin, cout, kernel, stride, expansion) of each block, and the stride after it."""
    blocks = []
    for repeats, k, s, e, cin, cout in LITE0_STAGES:
        for i in range(repeats):
            blocks.append((cin if i == 0 else cout, cout, k, s if i == 0 else 1, e))
    return blocks


def lite0_tap() -> int:
    """Index of the last block that still runs at `TAP_STRIDE` (10 for Lite0)."""
    stride = 2  # the stem
    tap = None
    for i, (_, _, _, s, _) in enumerate(lite0_blocks()):
        stride *= s
        if stride == TAP_STRIDE:
            tap = i
    if tap is None:
        raise ConfigError(f'EfficientNet-Lite0 has no block at stride {TAP_STRIDE}')
    return tap


class EfficientNetLite0Encoder(Encoder):
    """EfficientNet-Lite0 to block 10 (112 x 14 x 14); with `head`, the rest and the fc."""

    CONV_BN = (('_conv_stem', '_bn0'), ('_conv_head', '_bn1'))

    def __init__(self, *, head: bool = False):
        blocks = lite0_blocks()
        self.tap = lite0_tap()
        super().__init__('efficientnet_lite0', blocks[self.tap][1], bgr=False,
                         mean=(127.0, 127.0, 127.0), std=(128.0, 128.0, 128.0))
        self._conv_stem = tf_conv(3, LITE0_STEM, 3, 2)
        self._bn0 = tf_bn(LITE0_STEM)
        end = len(blocks) if head else self.tap + 1
        self._blocks = nn.ModuleList(MBConvBlock(*b) for b in blocks[:end])
        self._has_head = head
        if head:
            self._conv_head = nn.Conv2d(blocks[-1][1], LITE0_HEAD, 1, bias=False)
            self._bn1 = tf_bn(LITE0_HEAD)
            self._fc = nn.Linear(LITE0_HEAD, NUM_CLASSES)

    @property
    def has_classifier(self) -> bool:
        return self._has_head

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.relu6(self._bn0(self._conv_stem(x)))
        for block in itertools.islice(self._blocks, self.tap + 1):
            x = block(x)
        return x  # (B, 112, H/16, W/16)

    def head(self, f: torch.Tensor) -> torch.Tensor:
        for block in itertools.islice(self._blocks, self.tap + 1, None):
            f = block(f)
        f = F.relu6(self._bn1(self._conv_head(f)))
        return self._fc(f.mean((2, 3)))


# ---------------------------------------------------------------------------------------
# ResNet-50 v1 (Keras)
# ---------------------------------------------------------------------------------------

class Bottleneck(nn.Module):
    """ResNet v1 bottleneck: stride on the first 1x1 (v1.5's on the 3x3); torchvision's keys."""

    CONV_BN = (('conv1', 'bn1'), ('conv2', 'bn2'), ('conv3', 'bn3'),
               ('downsample.0', 'downsample.1'))

    def __init__(self, cin: int, width: int, stride: int):
        super().__init__()
        cout = width * RESNET_EXPANSION
        self.conv1 = nn.Conv2d(cin, width, 1, stride=stride, bias=False)
        self.bn1 = tf_bn(width)
        self.conv2 = nn.Conv2d(width, width, 3, padding=1, bias=False)
        self.bn2 = tf_bn(width)
        self.conv3 = nn.Conv2d(width, cout, 1, bias=False)
        self.bn3 = tf_bn(cout)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = None
        if stride != 1 or cin != cout:
            self.downsample = nn.Sequential(nn.Conv2d(cin, cout, 1, stride=stride, bias=False),
                                            tf_bn(cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.relu(self.bn1(self.conv1(x)))
        y = self.relu(self.bn2(self.conv2(y)))
        y = self.bn3(self.conv3(y))
        shortcut = x if self.downsample is None else self.downsample(x)
        return self.relu(y + shortcut)


def resnet50_tap() -> int:
    """Number of stages (layer1..) up to the last one at `TAP_STRIDE` (3: layer3)."""
    stride = 4  # conv1 and the max pool
    tap = 0
    for i, (_, _, s) in enumerate(RESNET50_STAGES, start=1):
        stride *= s
        if stride == TAP_STRIDE:
            tap = i
    if not tap:
        raise ConfigError(f'ResNet-50 has no stage at stride {TAP_STRIDE}')
    return tap


class ResNet50Encoder(Encoder):
    """Keras ResNet-50 v1 in torchvision's keys, to layer3; with `head`, layer4 and the fc."""

    CONV_BN = (('conv1', 'bn1'),)

    def __init__(self, *, head: bool = False):
        self.tap = resnet50_tap()
        width = RESNET50_STAGES[self.tap - 1][0]
        super().__init__('resnet50', width * RESNET_EXPANSION, bgr=True, mean=CAFFE_MEAN_BGR,
                         std=(1.0, 1.0, 1.0))
        self.conv1 = nn.Conv2d(3, 64, 7, stride=2, padding=3, bias=False)
        self.bn1 = tf_bn(64)
        self.relu = nn.ReLU(inplace=True)
        # Zero padding as in Keras; the same as torch's -inf padding after a ReLU.
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        cin = 64
        stages = RESNET50_STAGES if head else RESNET50_STAGES[:self.tap]
        for i, (w, n, s) in enumerate(stages, start=1):
            blocks = []
            for j in range(n):
                blocks.append(Bottleneck(cin, w, s if j == 0 else 1))
                cin = w * RESNET_EXPANSION
            setattr(self, f'layer{i}', nn.Sequential(*blocks))
        self._has_head = head
        if head:
            self.fc = nn.Linear(cin, NUM_CLASSES)

    @property
    def has_classifier(self) -> bool:
        return self._has_head

    def _stages(self, first: int, last: int) -> Iterator[nn.Module]:
        return (getattr(self, f'layer{i}') for i in range(first, last + 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        for stage in self._stages(1, self.tap):
            x = stage(x)
        return x  # (B, 1024, H/16, W/16)

    def head(self, f: torch.Tensor) -> torch.Tensor:
        for stage in self._stages(self.tap + 1, len(RESNET50_STAGES)):
            f = stage(f)
        return self.fc(f.mean((2, 3)))


def _replace(module: nn.Module, path: str, new: nn.Module) -> None:
    parent, _, name = path.rpartition('.')
    setattr(module.get_submodule(parent) if parent else module, name, new)


def set_conv_padding(encoder: nn.Module, mode: str) -> nn.Module:
    """
    Make every convolution wider than 1x1 pad its input with `mode`: 'zeros' (as the
    ImageNet weights were trained) or 'reflect'. ResNet-50's max pool keeps its padding.
    """
    for m in encoder.modules():
        if isinstance(m, nn.Conv2d) and max(m.kernel_size) > 1:
            m.padding_mode = mode
    return encoder


def fold_batchnorm(enc: Encoder) -> Encoder:
    """
    A frozen copy with every BatchNorm folded into the conv before it, for inference.

    Cheaper per frame (measured here: EfficientNet-Lite0 about 30 % less, ResNet-50 about
    7 %; VGG has no BatchNorm), but an SGD step on the folded weights is not the same step
    on the original ones, so the copy carries no gradients: use it only where the encoder
    is frozen. Its state dict has conv biases instead of BatchNorm keys.
    """
    folded = copy.deepcopy(enc).eval()
    for module in list(folded.modules()):
        for conv_path, bn_path in getattr(module, 'CONV_BN', ()):
            try:
                conv = module.get_submodule(conv_path)
                bn = module.get_submodule(bn_path)
            except AttributeError:  # a block without expansion, a head not built
                continue
            if isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d):
                _replace(module, conv_path, fuse_conv_bn_eval(conv, bn))
                _replace(module, bn_path, nn.Identity())
    return folded.requires_grad_(False)


# ---------------------------------------------------------------------------------------
# Building and loading
# ---------------------------------------------------------------------------------------

def make_encoder(name: str, *, head: bool) -> Encoder:
    """Build a random encoder on the default device; `head` where `HAS_HEAD` (a classifier)."""
    head = head and HAS_HEAD.get(name, False)
    if name in VGG_CFGS:
        return VGGEncoder(name, head=head, caffe=name == 'vgg19')
    if name == 'efficientnet_lite0':
        return EfficientNetLite0Encoder(head=head)
    if name == 'resnet50':
        return ResNet50Encoder(head=head)
    raise ConfigError(f'unknown encoder {name!r}; choose one of {", ".join(ENCODERS)}')
