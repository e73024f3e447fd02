"""
The int8 encoder (`encoder_precision: int8`): built once from the sample bag's frames,
cached, close to float32, and a clear error when it cannot be had. A tiny encoder and a
few calibration frames keep the quantisation fast; nothing here measures time.
"""
import os
import time

import numpy as np
import pytest
import torch
from torch import nn

from activeloc_ros.errors import ConfigError, WeightsError
from activeloc_ros.perception import int8
from activeloc_ros.perception.config import PerceptionConfig
from activeloc_ros.perception.model import SurpriseModel


SMALL = {'encoder': 'efficientnet_lite0', 'predictor_precision': 'float32', 'pretrained': True,
         'hidden': 32, 'layers': 3, 'attn_units': 16, 'encoder_pad': 0, 'num_threads': 0}


class TinyEncoder(nn.Module):
    """
    (B, 3, 64, 64) -> (B, 8, 8, 8), ReLU features as a CNN trunk gives: three 3x3
    convolutions of stride 2, as real trunks are built. (An 8x8 convolution of stride 8 on
    16 channels came out of OpenVINO 2026.4 80% wrong on a Xeon with AMX, even in float32
    IR under its default bfloat16 hint; 3x3 convolutions, VGG's, are right there.)
    """

    input_size = 64
    channels = 8

    def __init__(self):
        super().__init__()
        self.convs = nn.ModuleList(nn.Conv2d(a, b, 3, stride=2, padding=1)
                                   for a, b in ((3, 16), (16, 16), (16, self.channels)))

    def preprocess(self, x: torch.Tensor) -> torch.Tensor:
        return x / 127.5 - 1.0

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for conv in self.convs:
            x = torch.relu(conv(x))
        return x


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv('ACTIVELOC_CACHE', str(tmp_path))
    monkeypatch.setattr(int8, 'CALIBRATION_FRAMES', 16)
    return tmp_path


def make(precision: str, **kw) -> SurpriseModel:
    torch.manual_seed(0)
    cfg = PerceptionConfig(**{**SMALL, 'encoder_precision': precision, **kw})
    return SurpriseModel(cfg, encoder=TinyEncoder())


def frames(n: int) -> list[np.ndarray]:
    return list(int8.calibration_frames(n))


def test_int8_features_stay_close_to_float32_and_the_model_is_built_once(cache, capsys):
    quantised, reference = make('int8'), make('float32')
    built = sorted((cache / 'int8').glob('*.xml'))
    printed = capsys.readouterr()
    assert len(built) == 1 and 'building the int8 encoder' in printed.err
    assert printed.out == ''                # progress never lands in a command's stdout
    gaps = []
    for frame in frames(40)[20:]:          # pictures the calibration did not see
        x = reference.features.preprocess(frame)
        with torch.inference_mode():
            f8 = quantised.features.of(x)
            f32 = reference.features.of(x)
        assert f8.dtype == torch.float32 and f8.shape == f32.shape
        gaps.append(float((f8 - f32).norm() / f32.norm()))
    assert 0 < max(gaps) < 0.1, gaps
    results = [quantised.step(frame) for frame in frames(3)]
    assert results[-1].updated and np.isfinite(results[-1].surprise_map).all()
    mtime = built[0].stat().st_mtime_ns
    make('int8')                           # the cached model: no second build
    assert 'building' not in capsys.readouterr().err
    assert built[0].stat().st_mtime_ns == mtime


def test_int8_needs_a_frozen_encoder(cache):
    with pytest.raises(ConfigError, match='frozen encoder'):
        make('int8', update_encoder=True)


def test_a_damaged_int8_model_is_a_clear_error(cache):
    make('int8')
    xml, = (cache / 'int8').glob('*.xml')
    xml.write_text('<net')
    with pytest.raises(WeightsError, match='weights fetch'):
        make('int8')


def test_an_int8_model_damaged_in_the_cache_is_found_by_its_hashes(cache, capsys):
    """
    OpenVINO loads a .bin of the right size whatever its bytes: garbage features, no
    error. A model without its hashes (a build cut short) is built again.
    """
    make('int8')
    binary, = (cache / 'int8').glob('*.bin')
    binary.write_bytes(bytes(len(binary.read_bytes())))
    for precision in ('int8', 'auto'):      # auto too: never a silent 4x slower run
        with pytest.raises(int8.DamagedError, match=r'is damaged .*weights fetch'):
            make(precision)
    assert int8.discard_damaged(cache) == [binary.with_suffix('.xml')]
    assert 'deleted the damaged int8 encoder' in capsys.readouterr().err
    assert make('auto').precision == 'int8'                # built again from the weights
    hashes, = (cache / 'int8').glob('*.sha256')
    hashes.unlink()
    capsys.readouterr()
    assert make('int8').precision == 'int8'
    assert 'building the int8 encoder' in capsys.readouterr().err


def test_a_build_removes_the_folders_of_killed_builds_but_not_a_running_one(cache):
    """A build killed outright (SIGKILL, power) leaves its temporary folder behind."""
    killed, running = (cache / 'int8' / '.build-killed'), (cache / 'int8' / '.build-running')
    for folder in (killed, running):
        folder.mkdir(parents=True)
    hours_ago = time.time() - 2 * int8.STALE_BUILD_S
    os.utime(killed, (hours_ago, hours_ago))
    make('int8')
    assert sorted(p.name for p in (cache / 'int8').glob('.build-*')) == ['.build-running']


def test_the_cached_model_is_told_apart_by_the_convolutions_padding():
    from activeloc_ros.perception.encoders import set_conv_padding
    encoder = TinyEncoder()
    zeros = int8.cache_key(encoder, (1, 3, 64, 64))
    reflect = int8.cache_key(set_conv_padding(encoder, 'reflect'), (1, 3, 64, 64))
    assert zeros != reflect
    assert int8.cache_key(set_conv_padding(encoder, 'zeros'), (1, 3, 64, 64)) == zeros


def test_int8_without_openvino_says_what_to_install(cache, monkeypatch):
    monkeypatch.setattr(int8, 'available', lambda: False)
    with pytest.raises(WeightsError, match='pip install openvino nncf'):
        make('int8')
    assert make('auto').precision in ('float32', 'bfloat16')   # the slower, correct run


def test_a_cache_it_cannot_write_is_an_error_for_int8_and_float32_for_auto(cache, monkeypatch,
                                                                           capsys):
    """Found before the minute of calibration, not after it as a PermissionError."""
    (cache / 'afile').write_text('')
    monkeypatch.setenv('ACTIVELOC_CACHE', str(cache / 'afile' / 'cache'))
    with pytest.raises(WeightsError, match='cannot write the int8 encoder into'):
        make('int8')
    assert 'building' not in capsys.readouterr().err
    assert make('auto').precision == 'float32'
    assert 'the encoder runs in float32' in capsys.readouterr().err


def test_auto_is_int8_for_a_frozen_imagenet_encoder_only(cache):
    assert make('auto').precision == 'int8'
    assert make('auto', update_encoder=True).precision in ('float32', 'bfloat16')
    assert make('auto', pretrained=False).precision in ('float32', 'bfloat16')
