"""
The online surprise model: shapes, learning, determinism, non-finite handling, checkpoints.

A small predictor and either the real encoders with random weights (`pretrained=False`) or a
tiny stand-in encoder (64 px, 8 x 8 cells, features of order 1, so learning is visible
whatever scale random ImageNet trunks give) keep the file fast. Nothing here measures time.
"""
import dataclasses
import math

import cv2
import numpy as np
import pytest
import torch
from torch import nn

from activeloc_ros.errors import ConfigError, FrameError, WeightsError
from activeloc_ros.perception import checkpoint, model as M, predictor as P
from activeloc_ros.perception.config import PerceptionConfig
from activeloc_ros.perception.features import fast_bfloat16
from activeloc_ros.perception.model import SurpriseModel

SMALL = {'encoder': 'efficientnet_lite0', 'encoder_precision': 'float32',
         'predictor_precision': 'float32', 'pretrained': False, 'hidden': 32, 'layers': 3,
         'attn_units': 16, 'lr': 1e-3, 'num_threads': 0}


class TinyEncoder(nn.Module):
    """The encoder interface in miniature: (B, 3, 64, 64) -> (B, 6, 8, 8)."""

    input_size = 64
    channels = 6

    def __init__(self):
        super().__init__()
        self.conv = nn.Conv2d(3, self.channels, 8, stride=8)

    def preprocess(self, x: torch.Tensor) -> torch.Tensor:
        return x / 127.5 - 1.0

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.conv(x)) * 2.0


def make(*, real: bool = False, **kw) -> SurpriseModel:
    """A model on the random efficientnet_lite0 trunk (`real`) or on the tiny encoder."""
    cfg = PerceptionConfig(**{**SMALL, **kw})
    if real:
        return SurpriseModel(cfg)
    torch.manual_seed(cfg.seed)
    return SurpriseModel(cfg, encoder=TinyEncoder())


def clip(n: int, *, h: int = 48, w: int = 64, seed: int = 0) -> list[np.ndarray]:
    """A textured background with a bright square moving right: n (h, w, 3) uint8 frames."""
    rng = np.random.default_rng(seed)
    bg = (rng.random((h, w, 3)) * 200).astype(np.uint8)
    frames = []
    for i in range(n):
        f = bg.copy()
        x = (4 + 5 * i) % (w - 12)
        f[h // 3:h // 3 + 12, x:x + 12] = (255, 255, 40)
        frames.append(f)
    return frames


def weights(model: SurpriseModel) -> dict[str, torch.Tensor]:
    named = {f'p.{k}': v for k, v in model.predictor.state_dict().items()}
    named.update({f'e.{k}': v for k, v in model.encoder.state_dict().items()})
    return {k: v.detach().clone() for k, v in named.items()}


def same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return all(torch.equal(a[k], b[k]) for k in a)


# -- configuration ---------------------------------------------------------------------------
def test_every_field_has_a_default_and_help_and_round_trips():
    cfg = PerceptionConfig()
    for f in dataclasses.fields(PerceptionConfig):
        assert f.metadata['help'], f.name
        assert PerceptionConfig.check(f.name, getattr(cfg, f.name)) is None, f.name
    assert PerceptionConfig.from_dict(cfg.to_dict()) == cfg


@pytest.mark.parametrize('key, value', [
    ('no_such_field', 1),
    ('encoder', 'alexnet'),
    ('lr', -1.0),
    ('lr', 'fast'),
    ('lr', float('nan')),
    ('hidden', 0),
    ('hidden', 2.5),
    ('update_encoder', 1),
    ('motion', 'cubic'),
    ('blur_ksize', 4),
    ('input_aspect', 0.0),
    ('input_aspect', 5.0),
    ('input_aspect', float('inf')),
    ('input_height', -16),
    ('input_height', 2048),
    ('map_temperature', 0.0),
    ('optimizer', 'lbfgs'),
])
def test_invalid_values_raise_config_error_naming_the_key(key, value):
    with pytest.raises(ConfigError, match=key):
        PerceptionConfig.from_dict({key: value})
    assert PerceptionConfig.check(key, value)


def test_from_dict_takes_ints_for_floats_and_modes_resolve():
    cfg = PerceptionConfig.from_dict({'lr': 1, 'mode': 'predlearn', 'motion': 'sigmoid'})
    assert cfg.lr == 1.0 and isinstance(cfg.lr, float)
    assert cfg.motion_weighting == 'raw' and not cfg.attn_loss_on
    full = PerceptionConfig(motion='sigmoid', use_attn_loss=False)
    assert full.motion_weighting == 'sigmoid' and not full.attn_loss_on


def test_head_none_needs_matching_width():
    with pytest.raises(ConfigError, match='head'):
        make(head='none')


@pytest.mark.parametrize('pad', [8, 224])
def test_encoder_pad_must_be_whole_cells_smaller_than_the_frame(pad):
    with pytest.raises(ConfigError, match='encoder_pad'):
        make(real=True, encoder_pad=pad)


@pytest.mark.parametrize('pad', [0, 32])
@pytest.mark.parametrize('aspect, wh, grid', [(1.0, (224, 224), (14, 14)),
                                              (4 / 3, (304, 224), (14, 19)),
                                              (16 / 9, (400, 224), (14, 25))])
def test_the_grid_follows_the_input_aspect_and_the_mirrored_border_keeps_it(pad, aspect, wh,
                                                                            grid):
    model = make(real=True, encoder_pad=pad, input_aspect=aspect)
    result = [model.step(f) for f in clip(2)][-1]
    assert model.input_wh == wh and model.grid == grid and model.cells == grid[0] * grid[1]
    assert result.surprise_map.shape == grid


@pytest.mark.parametrize('height, aspect, wh, grid', [(160, 1.0, (160, 160), (10, 10)),
                                                      (160, 4 / 3, (208, 160), (10, 13)),
                                                      (256, 1.0, (256, 256), (16, 16))])
def test_the_grid_follows_the_input_height(height, aspect, wh, grid):
    model = make(real=True, input_height=height, input_aspect=aspect)
    result = [model.step(f) for f in clip(2)][-1]
    assert model.input_wh == wh and model.grid == grid
    assert result.surprise_map.shape == grid


@pytest.mark.parametrize('height', [8, 150])
def test_input_height_must_be_whole_cells(height):
    with pytest.raises(ConfigError, match=r"'input_height' must be a multiple of the encoder "
                                          r'stride 16 .*got ' + str(height)):
        make(real=True, input_height=height)


@pytest.mark.parametrize('encoder', ['efficientnet_lite0', 'vgg19'])
def test_reflect_conv_padding_gives_a_uniform_picture_the_same_features_in_every_cell(encoder):
    """
    The border cells see mirrored picture, not zeros: with conv_padding reflect a grey
    frame's cells are all alike; with the convolutions' zero padding the border differs.
    """
    from activeloc_ros.perception.features import Features

    def spread(padding: str) -> float:
        torch.manual_seed(0)
        features = Features(PerceptionConfig(**{**SMALL, 'encoder': encoder, 'encoder_pad': 0,
                                                'conv_padding': padding}))
        cells = features.of(features.preprocess(np.full((224, 224, 3), 120, np.uint8)))[0]
        return float((cells - cells.mean(dim=0)).abs().max() / cells.abs().max())

    assert spread('reflect') < 1e-4 < 0.01 < spread('zeros')


# -- maps and locations ----------------------------------------------------------------------
@pytest.mark.parametrize('real', [True, False])
def test_first_map_is_uniform_then_a_distribution_with_its_argmax(real):
    model = make(real=real, location='peak', location_prior=0.0)   # the paper's
    assert model.grid == ((14, 14) if real else (8, 8))
    frames = clip(4, h=37, w=53)
    first = model.step(frames[0])
    assert first.surprise_map.shape == model.grid
    np.testing.assert_allclose(first.surprise_map, 1 / model.cells, rtol=1e-6)
    assert not first.updated and first.lr == 0.0 and first.losses['total'] == 0.0
    for frame in frames[1:]:
        res = model.step(frame)
        m = res.surprise_map
        assert m.dtype == np.float32 and (m >= 0).all()
        assert m.sum() == pytest.approx(1.0, abs=1e-5)
        row, col = res.cell
        assert m[row, col] == m.max() == pytest.approx(res.peak)
        rows, cols = model.grid
        assert res.location_px == pytest.approx(((col + .5) * 53 / cols,
                                                 (row + .5) * 37 / rows))
        assert res.updated and res.lr > 0
        assert set(res.losses) == {'global', 'attn', 'total'}
        assert set(res.timings) == {'preprocess', 'encode', 'predict', 'update', 'total'}
    assert res.frame_index == 3


def test_the_mass_location_is_the_centroid_of_the_cells_near_the_peak():
    grid = torch.full((4, 6), 0.01)
    grid[1, 1], grid[1, 2], grid[3, 5] = 0.4, 0.2, 0.05      # a group, and a weak stray cell
    assert P.action_location(grid, 'peak', 0.25) == (1.5, 1.5)
    x, y = P.action_location(grid, 'mass', 0.25)              # the stray cell is under 0.1
    assert (x, y) == pytest.approx(((0.4 * 1.5 + 0.2 * 2.5) / 0.6, 1.5))
    assert P.action_location(grid, 'mass', 1.0) == (1.5, 1.5)
    everything = P.action_location(torch.ones(4, 6), 'mass', 0.0)
    assert everything == pytest.approx((3.0, 2.0))            # the map's middle


def test_the_floor_keeps_a_flat_maps_even_surprise_from_pulling_the_location_to_the_middle():
    grid = torch.full((14, 14), 0.004)          # an even pedestal over the whole view
    grid[2, 10] = grid[3, 10] = 0.02            # and the action on it
    x, y = P.action_location(grid, 'mass', 0.0)
    assert abs(x - 7.0) < 1.0 and abs(y - 7.0) < 1.5           # the pedestal's middle wins
    assert P.action_location(grid, 'mass', 0.0, floor='min') == pytest.approx((10.5, 3.0))
    assert P.action_location(grid, 'mass', 0.25, floor='min') == pytest.approx((10.5, 3.0))
    assert P.action_location(grid, 'peak', 0.0, floor='min') == (10.5, 2.5)   # no effect
    flat = torch.full((14, 14), 1 / 196)        # nothing above the floor: the middle
    assert P.action_location(flat, 'mass', 0.0, 5.0, 'min') == (7.0, 7.0)


def test_the_location_prior_prefers_the_surprise_nearer_where_the_camera_looks():
    grid = torch.full((14, 14), 0.001)
    grid[6, 7] = grid[0, 0] = 0.3              # equally surprising: the middle and a corner
    assert P.action_location(grid, 'mass', 0.25) == pytest.approx((4.0, 3.5))  # between
    assert P.action_location(grid, 'mass', 0.25, 5.0) == pytest.approx((7.5, 6.5))
    assert P.action_location(grid, 'peak', 0.25, 5.0) == (7.5, 6.5)
    grid[0, 0] = 3.0                            # a far stronger surprise still wins
    assert P.action_location(grid, 'peak', 0.25, 5.0) == (0.5, 0.5)


def test_the_region_location_is_the_centre_of_the_blob_round_the_peak():
    grid = torch.full((14, 14), 0.001)
    grid[2, 10] = 0.05                          # the head, most surprising
    grid[3:9, 10] = 0.01                        # the body below it, 0.59 up the log range
    grid[12, 2] = 0.02                          # a stray surprise, not connected to them
    assert P.action_location(grid, 'peak', 0.25) == (10.5, 2.5)
    assert P.action_location(grid, 'region', 0.25) == pytest.approx((10.5, 5.5))
    head = P.action_location(grid, 'region', 0.25, region_share=0.7)   # the body is below
    assert head == pytest.approx((10.5, 2.5))
    # three bars, 0.5 and 0.1 either side: the body stands above 0.4 and 0.5, not 0.6
    spread = P.action_location(grid, 'region', 0.25, region_share=0.5, region_spread=0.1)
    assert spread == pytest.approx((10.5, (5.5 + 5.5 + 2.5) / 3))
    # bars beyond the range are kept within it: 0 (every connected cell) and 1 (the peak)
    wide = P.action_location(grid, 'region', 0.25, region_share=0.5, region_spread=0.5)
    assert wide == pytest.approx(((7.0 + 10.5 + 10.5) / 3, (7.0 + 5.5 + 2.5) / 3))
    flat = torch.full((14, 14), 1 / 196)        # no information: the middle
    assert P.action_location(flat, 'region', 0.25) == (7.0, 7.0)        # all one blob
    assert P.action_location(flat, 'region', 0.25, 5.0) == (7.0, 7.0)   # the prior's disc
    assert P.action_location(flat, 'region', 0.25, 5.0, region_spread=0.1) == (7.0, 7.0)


@pytest.mark.parametrize('settings', [
    {'location': 'mass', 'location_share': 0.0, 'location_floor': 'min'},
    {'location': 'region', 'location_region_share': 0.4},
    {'location': 'region', 'location_region_share': 0.4, 'location_region_spread': 0.2},
])
def test_the_model_reports_its_location_in_frame_pixels(settings):
    model = make(input_aspect=1.5, **settings)          # the tiny encoder's 96 x 64: 8 x 12
    assert model.grid == (8, 12)
    frames = clip(3, h=37, w=53)
    for frame in frames:
        res = model.step(frame)
    m = torch.from_numpy(res.surprise_map)
    x, y = P.action_location(m, settings['location'], model.cfg.location_share,
                             model.cfg.location_prior, model.cfg.location_floor,
                             region_share=model.cfg.location_region_share,
                             region_spread=model.cfg.location_region_spread)
    assert res.location_px == pytest.approx((x * 53 / 12, y * 37 / 8))


@pytest.mark.parametrize('frame', [
    np.zeros((32, 32), np.uint8),
    np.zeros((32, 32, 4), np.uint8),
    np.zeros((0, 32, 3), np.uint8),
    np.zeros((32, 32, 3), np.int16),
    np.zeros((32, 32, 3), bool),
    [[[0, 0, 0]]],
])
def test_bad_frames_raise_frame_error(frame):
    model = make()
    with pytest.raises(FrameError):
        model.step(frame)
    assert model.frame_index == 0


# -- learning --------------------------------------------------------------------------------
@pytest.mark.parametrize('update_encoder, encoder_grad, real', [
    (False, 'both', False), (True, 'both', True), (True, 'target', False)])
def test_gradients_reach_the_predictor_and_the_encoder_only_when_asked(update_encoder,
                                                                       encoder_grad, real):
    model = make(real=real, update_encoder=update_encoder, encoder_grad=encoder_grad)
    before = weights(model)
    for frame in clip(3):
        res = model.step(frame)
    assert res.updated
    for name, p in model.predictor.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    enc_grads = [p.grad for p in model.encoder.parameters()]
    after = weights(model)
    enc_changed = any(not torch.equal(before[k], after[k]) for k in before if k[0] == 'e')
    assert enc_changed == update_encoder
    assert any(g is not None and g.abs().sum() > 0 for g in enc_grads) == update_encoder


@pytest.mark.parametrize('kw', [
    {}, {'optimizer': 'sgd', 'lr': 1e-2, 'motion': 'none'}, {'update_encoder': True},
    {'mode': 'predlearn'}])
def test_one_online_step_lowers_the_error_on_a_repeated_pair(kw):
    model = make(adaptive_lr=False, **kw)
    a, b = clip(2)
    model.step(a)
    first = model.step(b).losses
    model.reset()
    model.step(a)
    second = model.step(b).losses
    assert second['global'] < first['global']
    assert second['total'] < first['total']


def test_no_learning_leaves_weights_alone():
    model = make(learn=False)
    before = weights(model)
    for frame in clip(4):
        res = model.step(frame)
    assert not res.updated and res.lr == 0.0
    assert same(before, weights(model))
    assert res.surprise_map.sum() == pytest.approx(1.0, abs=1e-5)


@pytest.mark.parametrize('limit', [0, 1, 2])
def test_late_frames_skip_their_update_but_never_more_than_the_limit_in_a_row(limit):
    model = make(skip_late_updates=limit)
    asked = []

    def always_late():
        asked.append(model.frame_index)
        return True
    learnt = []
    for frame in clip(9):
        before = weights(model)
        res = model.step(frame, late=always_late)
        learnt.append(res.updated)
        assert same(before, weights(model)) != res.updated     # a skip changes nothing
        assert res.surprise_map.sum() == pytest.approx(1.0, abs=1e-5)
    # the first frame has nothing to learn from; then `limit` skips, one update, and again
    assert learnt == [False] + (([False] * limit + [True]) * 8)[:8]
    assert len(asked) == (0 if limit == 0 else 8 - learnt.count(True))


def test_a_frame_in_time_learns_and_the_late_skips_go_on_from_the_same_state():
    lag, strict = make(skip_late_updates=1), make()
    for i, frame in enumerate(clip(6)):
        a = lag.step(frame, late=lambda: i == 3)
        b = strict.step(frame)
        assert b.updated == (i > 0)
        assert a.updated == (i > 0 and i != 3)
        if i < 3:                      # the same until the skipped update
            np.testing.assert_array_equal(a.surprise_map, b.surprise_map)
    assert lag.updates == strict.updates - 1


def test_predlearn_has_no_attention_loss():
    model = make(mode='predlearn')
    for frame in clip(4):
        res = model.step(frame)
    assert res.losses['attn'] == 0.0 and res.losses['global'] > 0


def test_adaptive_rule_boosts_the_rate_after_a_surprise():
    model = make(adaptive_lr=True, adaptive_window=3, adaptive_ratio=1.5, adaptive_boost=100.0,
                 lr=1e-5)
    still = clip(1)[0]
    rates = [model.step(still).lr for _ in range(5)]
    assert rates[1:] == [1e-5] * 4
    surprise = np.full_like(still, 255)
    surprise[::2, ::3] = 0
    assert model.step(surprise).lr == pytest.approx(1e-3)


@pytest.mark.parametrize('bfloat16, state_grad', [
    (False, False), (True, False), (False, True), (True, True)])
def test_the_gate_product_gives_the_linear_layers_values_and_gradients(bfloat16, state_grad):
    torch.manual_seed(0)
    cell = nn.Linear(24, 32)
    x0, h0 = torch.randn(5, 16), torch.randn(5, 8)
    got = []
    for split in (False, True):
        cell.zero_grad()
        x, h = x0.clone().requires_grad_(), h0.clone().requires_grad_(state_grad)
        with torch.autocast('cpu', dtype=torch.bfloat16, enabled=bfloat16):
            gates = (P.GateProduct.apply(x, h, cell.weight, cell.bias) if split
                     else cell(torch.cat([x, h], dim=1)))          # (5, 32)
        (gates.float().sigmoid() * torch.arange(32.0)).square().mean().backward()
        got.append([gates, x.grad, h.grad, cell.weight.grad, cell.bias.grad])
    for linear, split in zip(*got):
        if linear is None:
            assert split is None and not state_grad
        else:
            assert split.dtype == linear.dtype and torch.equal(split, linear)


@pytest.mark.parametrize('kind, at_rest', [
    ('abs_sigmoid', 0.0), ('sigmoid', 0.5), ('raw', 0.0), ('none', 1.0)])
def test_motion_weights(kind, at_rest):
    d = torch.tensor([0.0, -3.0, 3.0])
    w = P.motion_weight(d, kind, 1.0)
    assert float(w[0]) == pytest.approx(at_rest)
    assert (w >= 0).all()
    if kind != 'sigmoid':
        assert float(w[1]) == pytest.approx(float(w[2]))   # symmetric in the sign
        assert float(w[2]) > float(w[0]) or kind == 'none'


@pytest.mark.parametrize('power', [1.0, 0.5])
def test_the_motion_scale_grows_with_the_time_between_frames(power):
    assert P.gap_factor(0.1, 0.1, power) == 1.0
    assert P.gap_factor(0.3 - 0.2, 0.1, power) == 1.0    # stamp jitter below a millisecond
    assert P.gap_factor(1 / 30, 0.1, power) == pytest.approx(0.33 ** power)
    assert P.gap_factor(0.2, 0.1, power) == pytest.approx(2.0 ** power)
    assert P.gap_factor(1e-3, 0.1, power) == 0.25 and P.gap_factor(60.0, 0.1, power) == 4.0
    for gap in (None, 0.0, -0.1, math.nan):
        assert P.gap_factor(gap, 0.1, power) == 1.0
    assert P.gap_factor(1 / 30, 0.0, power) == 1.0        # motion_period 0: the paper's
    assert P.gap_factor(1 / 30, 0.1, 0.0) == 1.0


def test_frames_a_motion_period_apart_give_the_maps_of_frames_without_times():
    frames = clip(5)
    untimed, at_period, faster = (make(motion_period=0.1) for _ in range(3))
    fixed = make()                                    # the default's 0: the paper's one scale
    for i, frame in enumerate(frames):
        a = untimed.step(frame)
        b = at_period.step(frame, t=100.0 + 0.1 * i)
        c = faster.step(frame, t=100.0 + i / 30)
        d = fixed.step(frame, t=100.0 + i / 30)
        np.testing.assert_array_equal(a.surprise_map, b.surprise_map)
        np.testing.assert_array_equal(a.surprise_map, d.surprise_map)
    # three times the frame rate: the square's smaller change weighs more than it would
    assert not np.allclose(a.surprise_map, c.surprise_map)


# -- determinism and checkpoints -------------------------------------------------------------
def test_same_seed_same_maps_other_seed_other_maps():
    frames = clip(5)
    runs = []
    for seed in (3, 3, 4):
        model = make(seed=seed)
        runs.append([model.step(f) for f in frames])
    for a, b in zip(runs[0], runs[1]):
        np.testing.assert_array_equal(a.surprise_map, b.surprise_map)
        assert a.losses == b.losses
    assert any(not np.array_equal(a.surprise_map, c.surprise_map)
               for a, c in zip(runs[0], runs[2]))


@pytest.mark.parametrize('kw', [{}, {'update_encoder': True, 'optimizer': 'sgd',
                                     'momentum': 0.9}])
def test_checkpoint_resumes_learning_exactly(tmp_path, kw):
    frames = clip(9)
    model = make(real=True, adaptive_window=2, **kw)
    times = [i / 30 for i in range(len(frames))]    # the motion scale follows their gaps
    for f, t in zip(frames[:5], times):
        model.step(f, t=t)
    path = str(tmp_path / 'perception.pt')
    checkpoint.save(model, path)
    expected = [model.step(f, t=t) for f, t in zip(frames[5:], times[5:])]
    loaded = checkpoint.load(path)
    assert loaded.cfg == model.cfg
    got = [loaded.step(f, t=t) for f, t in zip(frames[5:], times[5:])]
    for a, b in zip(expected, got):
        np.testing.assert_array_equal(a.surprise_map, b.surprise_map)
        assert a.losses == b.losses and a.lr == b.lr and a.frame_index == b.frame_index
    assert same(weights(model), weights(loaded))


def test_a_checkpoint_from_before_encoder_pad_and_motion_period_loads_as_it_learned(tmp_path):
    path = tmp_path / 'old.pt'
    checkpoint.save(make(real=True), str(path))
    ckpt = torch.load(path, weights_only=True)
    del ckpt['config']['encoder_pad'], ckpt['config']['motion_period']
    del ckpt['running']['t_prev']
    torch.save(ckpt, path)
    cfg = checkpoint.load(str(path)).cfg
    assert cfg.encoder_pad == 0 and cfg.motion_period == 0.0   # no border, one scale


@pytest.mark.parametrize('content', [None, b'', b'random bytes', 'a folder'])
def test_a_missing_or_corrupt_checkpoint_is_a_weights_error_naming_it(tmp_path, content):
    path = tmp_path / 'model.pt'
    if content == 'a folder':
        path.mkdir()
    elif content is not None:
        path.write_bytes(content)
    with pytest.raises(WeightsError, match='cannot load the checkpoint .*model.pt'):
        checkpoint.load(str(path))


# -- non-finite values -----------------------------------------------------------------------
def test_nan_frame_skips_the_update_and_restarts_the_sequence():
    model = make()
    frames = clip(5)
    for f in frames[:3]:
        model.step(f)
    before = weights(model)
    bad = frames[3].astype(np.float32)
    bad[5, 5, 1] = np.nan
    res = model.step(bad)
    assert res.nan_events == 1 and not res.updated
    np.testing.assert_allclose(res.surprise_map, 1 / model.cells, rtol=1e-6)
    assert model.state is None and model.x_prev is None
    assert same(before, weights(model))
    first_again = model.step(frames[4])                 # a new first frame, then learning
    assert not first_again.updated
    assert model.step(frames[0]).updated


def test_nan_weights_are_restored_and_counted():
    model = make(snapshot_every=1)
    frames = clip(6)
    for f in frames[:3]:
        model.step(f)
    good = weights(model)
    with torch.no_grad():
        model.predictor.head.weight[0, 0] = float('nan')
    res = model.step(frames[3])
    assert res.nan_events == 1 and not res.updated and res.lr == 0.0
    assert np.isfinite(res.surprise_map).all()
    assert res.surprise_map.sum() == pytest.approx(1.0, abs=1e-5)
    assert same(good, weights(model))
    assert model.state is None
    model.step(frames[4])
    assert model.step(frames[5]).updated


def test_nan_loss_skips_the_update_but_keeps_the_map(monkeypatch):
    model, twin = make(), make()
    frames = clip(4)
    for f in frames[:2]:
        model.step(f)
        twin.step(f)
    before = weights(model)
    real = P.global_error

    def poisoned(*args, **kw):
        loss, e = real(*args, **kw)
        return loss * float('nan'), e
    monkeypatch.setattr(M, 'global_error', poisoned)
    res = model.step(frames[2])
    assert res.nan_events == 1 and not res.updated
    assert same(before, weights(model))
    assert model.state is None
    # the map of the prediction, as an unpoisoned twin makes it
    np.testing.assert_array_equal(res.surprise_map, twin.step(frames[2]).surprise_map)
    monkeypatch.setattr(M, 'global_error', real)
    model.step(frames[3])
    assert model.step(frames[0]).updated


def test_nan_gradients_skip_the_update(monkeypatch):
    model = make()
    frames = clip(4)
    for f in frames[:2]:
        model.step(f)
    before = weights(model)
    real = P.attention_loss

    def sharp(alpha, target, f):                         # finite value, infinite slope
        return real(alpha, target, f) + torch.sqrt((alpha - alpha.detach()).sum())
    monkeypatch.setattr(M, 'attention_loss', sharp)
    res = model.step(frames[2])
    assert res.nan_events == 1 and not res.updated
    assert same(before, weights(model))


# -- the map's formula -----------------------------------------------------------------------
@pytest.mark.parametrize('motion', ['abs_sigmoid', 'sigmoid', 'raw', 'none'])
def test_an_untrained_residual_predictor_gives_the_motion_weighted_difference_map(motion):
    # residual with a zero head predicts fhat_t = f_{t-1}: e = mean_c w(d) d^2, d = f_t - f_{t-1}
    model = make(residual=True, learn=False, motion=motion, map_temperature=0.5)
    a, b = clip(2)
    model.step(a)
    got = model.step(b).surprise_map
    with torch.no_grad():
        feats = model.features
        fa, fb = (feats.to_cells(model.encoder(feats.preprocess(x)))[0] for x in (a, b))
    d = fb - fa
    e = (P.motion_weight(d, motion, 1.0) * d.square()).mean(1)
    want = torch.softmax(e / 0.5, 0).reshape(model.grid).numpy()
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize('update_encoder', [False, True])
def test_bfloat16_encoder_gives_float32_features_close_to_float32(update_encoder):
    """
    encoder_precision only changes the encoder's arithmetic: the same features within
    bfloat16's rounding, handed on in float32; the checkpointed weights stay float32.
    """
    frames = clip(2, h=224, w=224)
    features = {}
    for precision in ('float32', 'bfloat16'):
        model = make(real=True, encoder_precision=precision, update_encoder=update_encoder)
        x = model.features.preprocess(frames[0])
        with torch.no_grad():
            features[precision] = model.features.of(x)[0]
        assert all(p.dtype == torch.float32 for p in model.encoder.parameters())
        result = model.step(frames[0])
        result = model.step(frames[1])
        assert result.surprise_map.dtype == np.float32
        assert np.isfinite(result.surprise_map).all() and result.updated
    f32, bf16 = features['float32'], features['bfloat16']
    assert bf16.dtype == torch.float32 and bf16.shape == f32.shape
    if update_encoder:          # a frozen encoder's auto is int8: test_int8.py
        auto = make(real=True, encoder_precision='auto', update_encoder=update_encoder)
        assert auto.precision == ('bfloat16' if fast_bfloat16() else 'float32')
    gap = float((bf16 - f32).norm() / f32.norm())
    assert 0 < gap < 0.1, gap


@pytest.mark.parametrize('amx, avx512_bf16, native', [
    (False, False, False), (True, False, True), (False, True, True), (True, True, True)])
def test_auto_precision_takes_bfloat16_where_the_cpu_computes_it_natively(
        monkeypatch, amx, avx512_bf16, native):
    monkeypatch.setattr(torch.cpu, '_is_amx_tile_supported', lambda: amx)
    monkeypatch.setattr(torch.cpu, '_is_avx512_bf16_supported', lambda: avx512_bf16)
    assert fast_bfloat16() is native
    learning = make(encoder_precision='auto', update_encoder=True)   # not int8: it learns
    assert learning.precision == ('bfloat16' if native else 'float32')


def test_bfloat16_predictor_changes_only_the_arithmetic():
    """
    predictor_precision bfloat16 runs the predictor's products under autocast: the maps
    and losses stay float32 and close to float32's, the weights and their updates too.
    """
    frames = clip(4)
    runs = {}
    for precision in ('float32', 'bfloat16'):
        model = make(predictor_precision=precision, hidden=64)
        results = [model.step(f) for f in frames]
        assert all(p.dtype == torch.float32 for p in model.predictor.parameters())
        assert all(s.dtype == torch.float32 for s in model.state)
        assert results[-1].updated and results[-1].surprise_map.dtype == np.float32
        runs[precision] = (results, model)
    (r32, m32), (r16, m16) = runs['float32'], runs['bfloat16']
    for a, b in zip(r32[1:], r16[1:]):
        assert b.losses['total'] == pytest.approx(a.losses['total'], rel=0.05)
        np.testing.assert_allclose(b.surprise_map, a.surprise_map, rtol=0.05)
    w32 = torch.cat([p.detach().flatten() for p in m32.predictor.parameters()])
    w16 = torch.cat([p.detach().flatten() for p in m16.predictor.parameters()])
    assert 0 < float((w16 - w32).norm() / w32.norm()) < 0.01
    assert make(predictor_precision='auto').predictor_precision == (
        'bfloat16' if fast_bfloat16() else 'float32')


def test_frame_rms_normalises_every_frame():
    model = make(feature_norm='frame_rms')
    with torch.no_grad():
        x = torch.cat([model.features.preprocess(f) for f in clip(2)])
        f = model.features.to_cells(model.encoder(x) * torch.tensor([3.0, 0.1]).view(2, 1, 1, 1))
    np.testing.assert_allclose(f.square().mean(dim=(1, 2)).sqrt().numpy(), 1.0, rtol=1e-4)


# -- the camera's own motion (ego_motion) -------------------------------------------------------

def panning(n: int, *, step: int = 8, square: bool = False) -> list[np.ndarray]:
    """
    A camera panning right over a still, textured scene: n (224, 224, 3) crops; with
    `square`, a bright square also moves down the scene.
    """
    rng = np.random.default_rng(3)
    scene = cv2.GaussianBlur((rng.random((240, 224 + step * n, 3)) * 255).astype(np.uint8),
                             (5, 5), 0)
    frames = []
    for i in range(n):
        f = scene.copy()
        if square:
            f[40 + 12 * i:72 + 12 * i, 120 + step * i:152 + step * i] = (255, 255, 40)
        frames.append(np.ascontiguousarray(f[8:232, step * i:step * i + 224]))
    return frames


def test_ego_motion_is_estimated_from_the_images():
    from activeloc_ros.perception.egomotion import EgoMotion
    a, b = (cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in panning(2))
    ego = EgoMotion()
    warp = ego.estimate(ego.keypoints(a), ego.keypoints(b), (224, 224))
    assert warp[:2, :2] == pytest.approx(np.eye(2), abs=0.01)
    assert warp[:2, 2] == pytest.approx([-8.0, 0.0], abs=0.5)    # content moves left
    assert ego.estimate(ego.keypoints(a), ego.keypoints(a), (224, 224)) is None  # no motion


@pytest.mark.parametrize('dx, dy', [(16.0, 0.0), (0.0, 16.0)])    # one cell right / down
def test_warp_cells_moves_state_with_the_view(dx, dy):
    from activeloc_ros.perception.egomotion import warp_cells
    values = torch.arange(12.0).reshape(1, 12, 1)       # a 3 x 4 grid over a 64 x 48 image
    shift = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])
    moved = warp_cells(values, shift, (64, 48), (3, 4))[0, :, 0].reshape(3, 4)
    grid = values[0, :, 0].reshape(3, 4)
    if dx:
        assert moved[:, 0].abs().max() < 1e-4                       # nothing seen there
        assert moved[:, 1:] == pytest.approx(grid[:, :3], abs=1e-4)
    else:
        assert moved[0].abs().max() < 1e-4
        assert moved[1:] == pytest.approx(grid[:2], abs=1e-4)


def test_ego_motion_takes_the_pan_out_of_the_surprise():
    """
    Panning over a still scene: compared in the new view, almost nothing changed; a
    square moving in the scene is then where the map peaks.
    """
    error = {}
    for mode in ('none', 'similarity'):
        model = make(real=True, ego_motion=mode, ego_warp='image')
        error[mode] = [model.step(f) for f in panning(3)][-1].losses['global']
    assert 0 < error['similarity'] < 0.3 * error['none']
    model = make(real=True, ego_motion='similarity', ego_warp='image')
    last = [model.step(f) for f in panning(3, square=True)][-1]
    # the square covers rows 56..88 and columns 120..152 of the last crop (16 px cells)
    row, col = last.cell
    assert 2 <= row <= 5 and 7 <= col <= 9, last.cell


def test_ego_warp_of_the_features_takes_a_whole_cell_pan_out():
    """
    Without a second encoder pass: the previous features move cell by cell, exact for a
    pan of one cell (16 px) but for the edge the previous view did not see.
    """
    error = {}
    for mode in ('none', 'similarity'):
        model = make(real=True, ego_motion=mode, ego_warp='features')
        error[mode] = [model.step(f) for f in panning(3, step=16)][-1].losses['global']
    assert 0 < error['similarity'] < 0.5 * error['none']
    model = make(real=True, ego_motion='similarity', ego_warp='features')
    last = [model.step(f) for f in panning(3, step=16, square=True)][-1]
    # the square covers rows 56..88 and columns 120..152 of the last crop
    row, col = last.cell
    assert 2 <= row <= 5 and 7 <= col <= 9, last.cell


def test_ego_warp_of_the_features_fills_the_unseen_edge_with_the_new_frame():
    model = make(real=True, ego_motion='similarity', ego_warp='features')
    (rows, cols), n, c = model.grid, model.cells, 3
    f_prev = torch.arange(float(n * c)).reshape(n, c)
    f_cur = torch.full((n, c), -1.0)
    shift = np.array([[1.0, 0.0, -model.input_wh[0] / cols], [0.0, 1.0, 0.0],
                      [0.0, 0.0, 1.0]])
    moved = model._warp_features(f_prev, f_cur, shift).reshape(rows, cols, c)
    assert moved[:, -1] == pytest.approx(f_cur.reshape(rows, cols, c)[:, -1], abs=1e-4)
    assert moved[:, :-1] == pytest.approx(f_prev.reshape(rows, cols, c)[:, 1:], abs=1e-4)


@pytest.mark.parametrize('aspect, frame_wh, warned', [
    (1.0, (640, 480), False),         # the paper's square squashes any frame on purpose
    (4 / 3, (640, 480), False),
    (4 / 3, (600, 480), False),       # within 10%
    (4 / 3, (480, 480), True),
    (4 / 3, (1280, 720), True),
    (16 / 9, (1280, 720), False),
])
def test_a_frame_out_of_the_inputs_shape_is_named_with_the_aspect_to_set(aspect, frame_wh,
                                                                         warned):
    note = make(real=True, input_aspect=aspect).features.aspect_note(frame_wh)
    assert (note is not None) == warned
    if warned:
        assert 'input_aspect' in note and f'{frame_wh[0] / frame_wh[1]:.4f}' in note
