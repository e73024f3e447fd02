"""
Encoders and their offline weights: shapes, real ImageNet behaviour, layouts and errors.

The pretrained tests read the weights cache that `python -m activeloc_ros.perception.weights
fetch` fills; they skip where it is empty, except under CI (which fetches first), where an
empty cache fails.
"""
from collections.abc import Callable
import io
import os
from pathlib import Path
import socket
import subprocess

import cv2
import pytest
import torch
import torch.nn.functional as F

from activeloc_ros.errors import ConfigError, FrameError, WeightsError
from activeloc_ros.perception import cache, weights
from activeloc_ros.perception.encoder_weights import build_encoder
from activeloc_ros.perception.encoders import Encoder, ENCODERS, fold_batchnorm

DATA = Path(__file__).parent / 'data'
CHANNELS = {'vgg16': 512, 'vgg19': 512, 'efficientnet_lite0': 112, 'resnet50': 1024}
ESPRESSO = 967
# tabby, tiger cat, Egyptian cat: which one a model picks for this cat is a matter of taste.
CATS = {281, 282, 285}

# torchvision's VGG-16 `features`: conv index -> (out, in) channels, up to pool4 (index 23).
TORCHVISION_VGG16_CONVS = {0: (64, 3), 2: (64, 64), 5: (128, 64), 7: (128, 128),
                           10: (256, 128), 12: (256, 256), 14: (256, 256), 17: (512, 256),
                           19: (512, 512), 21: (512, 512)}
TORCHVISION_VGG16_POOLS = (4, 9, 16, 23)


@pytest.fixture(scope='module', autouse=True)
def one_thread():
    """
    One intra-op thread: on a shared 2-core box every op of a two-thread run waits at a
    barrier for a descheduled thread (EfficientNet measured >10x slower). Restored after.
    """
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def photo(name: str) -> torch.Tensor:
    """A test photo as a (1, 3, 224, 224) RGB float batch in 0..255."""
    bgr = cv2.imread(str(DATA / f'{name}.png'), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FileNotFoundError(DATA / f'{name}.png')
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    return torch.from_numpy(rgb).permute(2, 0, 1)[None].float()


def forbid_network(mp: pytest.MonkeyPatch) -> None:
    def refuse(*args, **kwargs):
        raise AssertionError('the network or a subprocess was touched at run time')

    for name in ('socket', 'create_connection', 'getaddrinfo'):
        mp.setattr(socket, name, refuse)
    mp.setattr(subprocess, 'run', refuse)
    mp.setattr(subprocess, 'Popen', refuse)


def require_cached(name: str) -> None:
    try:
        cache.weights_path(name)
    except WeightsError as e:
        if os.environ.get('CI'):
            pytest.fail(f'CI fetches the weights before the tests, yet: {e}')
        pytest.skip(f'{name} weights are not cached here: {e}')


@pytest.fixture(scope='module')
def pretrained() -> Callable[[str], Encoder]:
    """Builds each cached encoder once per module, with the network forbidden."""
    built: dict[str, Encoder] = {}

    def get(name: str) -> Encoder:
        if name not in built:
            require_cached(name)
            with pytest.MonkeyPatch.context() as mp:
                forbid_network(mp)
                built[name] = build_encoder(name)
        return built[name]

    return get


@pytest.mark.parametrize('name', weights.FETCHABLE)
def test_cached_encoder_builds_offline_and_maps_to_14x14(pretrained, name):
    enc = pretrained(name)
    with torch.inference_mode():
        f = enc(enc.preprocess(photo('coffee')))
    assert enc.channels == CHANNELS[name]
    assert enc.input_size == 224
    assert f.shape == (1, CHANNELS[name], 14, 14)
    assert f.dtype == torch.float32
    assert torch.isfinite(f).all()
    assert not enc.training


@pytest.mark.parametrize('name', ['efficientnet_lite0', 'resnet50'])
@pytest.mark.parametrize('picture, classes', [('coffee', {ESPRESSO}), ('chelsea', CATS)])
def test_top1_on_real_photos(pretrained, name, picture, classes):
    enc = pretrained(name)
    assert enc.has_classifier
    with torch.inference_mode():
        logits = enc.classify(enc.preprocess(photo(picture)))
    assert logits.shape == (1, 1000)
    assert int(logits.argmax()) in classes


@pytest.mark.parametrize('name', ['efficientnet_lite0', 'resnet50'])
def test_preprocessing_channel_order_matches_the_weights(pretrained, name):
    # Swapping R and B keeps the class but costs confidence; a wrong order would gain it.
    enc = pretrained(name)
    x = photo('coffee')
    with torch.inference_mode():
        right = enc.classify(enc.preprocess(x)).softmax(1)[0, ESPRESSO]
        swapped = enc.classify(enc.preprocess(x.flip(1))).softmax(1)[0, ESPRESSO]
    assert right > swapped


def views(x: torch.Tensor) -> torch.Tensor:
    """Three views of one photo: as is, mirrored, zoomed in."""
    zoom = F.interpolate(x[..., 16:208, 16:208], size=224, mode='bilinear',
                         align_corners=False)
    return torch.cat([x, x.flip(3), zoom])


def separation(enc: Encoder) -> float:
    """Worst same-photo cosine minus best cross-photo cosine of pooled features."""
    batch = torch.cat([views(photo('coffee')), views(photo('chelsea'))])
    with torch.inference_mode():
        g = F.normalize(enc(enc.preprocess(batch)).mean((2, 3)), dim=1)
    sim = g @ g.T
    n = len(batch)
    label = torch.arange(n) // (n // 2)
    same = (label[:, None] == label[None, :]) & ~torch.eye(n, dtype=torch.bool)
    return float(sim[same].min() - sim[label[:, None] != label[None, :]].max())


def test_vgg19_features_tell_two_photos_apart_where_random_ones_do_not(pretrained):
    # Measured: 0.234 with the weights, 0.003 random, 0.116 with block4's conv2 and conv3
    # swapped, 0.011 with block3's, 0.154 with the input scaled to 0..1.
    torch.manual_seed(0)
    real = separation(pretrained('vgg19'))
    rand = separation(build_encoder('vgg19', pretrained=False))
    assert real > 0.19
    assert real > rand + 0.1


@pytest.mark.parametrize('name, expected', [
    # a pure red pixel (255, 0, 0) in RGB, as each encoder's weights want to see it
    ('vgg16', [(255 / 255 - 0.485) / 0.229, (0 - 0.456) / 0.224, (0 - 0.406) / 0.225]),
    ('vgg19', [0 - 103.939, 0 - 116.779, 255 - 123.68]),  # caffe: BGR, mean pixel
    ('resnet50', [0 - 103.939, 0 - 116.779, 255 - 123.68]),
    ('efficientnet_lite0', [(255 - 127) / 128, (0 - 127) / 128, (0 - 127) / 128]),
])
def test_preprocess_arithmetic(name, expected):
    enc = build_encoder(name, pretrained=False, classifier=False)
    x = torch.zeros(2, 3, 224, 224)
    x[:, 0] = 255.0
    y = enc.preprocess(x)
    assert y.shape == x.shape
    assert torch.allclose(y[0, :, 5, 7], torch.tensor(expected), atol=1e-4)


def test_preprocess_rejects_a_frame_of_the_wrong_shape():
    enc = build_encoder('efficientnet_lite0', pretrained=False)
    with pytest.raises(FrameError, match='RGB'):
        enc.preprocess(torch.zeros(1, 224, 224, 3))


@pytest.mark.parametrize('name', ENCODERS)
def test_random_weights_need_no_cache(monkeypatch, tmp_path, name):
    monkeypatch.setenv(cache.CACHE_ENV, str(tmp_path))
    forbid_network(monkeypatch)
    enc = build_encoder(name, pretrained=False, classifier=False)
    with torch.inference_mode():
        f = enc(enc.preprocess(torch.rand(1, 3, 224, 224) * 255))
    assert f.shape == (1, enc.channels, 14, 14)
    assert enc.channels == CHANNELS[name]
    assert not enc.has_classifier
    with pytest.raises(NotImplementedError):
        enc.classify(torch.zeros(1, 3, 224, 224))


@pytest.mark.parametrize('name', weights.FETCHABLE)
def test_empty_cache_names_the_fetch_command(monkeypatch, tmp_path, name):
    monkeypatch.setenv(cache.CACHE_ENV, str(tmp_path))
    with pytest.raises(WeightsError) as info:
        build_encoder(name)
    assert f'python -m activeloc_ros.perception.weights fetch --encoders {name}' in str(
        info.value)


def test_unknown_encoder_and_contradictory_options():
    with pytest.raises(ConfigError, match='vgg15'):
        build_encoder('vgg15')
    with pytest.raises(ConfigError):
        build_encoder('vgg19', pretrained=False, weights='x.pth')


# --- VGG-16 from a torchvision file ---------------------------------------------------

def torchvision_vgg16_trunk(seed: int = 0) -> dict[str, torch.Tensor]:
    """Random tensors under the keys and shapes of torchvision's vgg16 features[:24]."""
    g = torch.Generator().manual_seed(seed)
    state = {}
    for i, (cout, cin) in TORCHVISION_VGG16_CONVS.items():
        state[f'features.{i}.weight'] = torch.randn(cout, cin, 3, 3, generator=g) * (
            2.0 / (9 * cin)) ** 0.5
        state[f'features.{i}.bias'] = torch.randn(cout, generator=g) * 0.01
    return state


def reference_vgg16_pool4(state: dict[str, torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """torchvision's features[:24] spelled out: conv+ReLU at the conv indices, pools."""
    for i in range(24):
        if i in TORCHVISION_VGG16_CONVS:
            x = F.relu(F.conv2d(x, state[f'features.{i}.weight'], state[f'features.{i}.bias'],
                                padding=1))
        elif i in TORCHVISION_VGG16_POOLS:
            x = F.max_pool2d(x, 2)
    return x


@pytest.mark.parametrize('zip_format', [False, True])
def test_vgg16_loads_a_torchvision_layout_file(tmp_path, zip_format):
    # torchvision's vgg16-397923af.pth (2017) predates torch's zip format
    state = torchvision_vgg16_trunk()
    path = tmp_path / 'vgg16-trunk.pth'
    torch.save(state, path, _use_new_zipfile_serialization=zip_format)
    enc = build_encoder('vgg16', weights=path)
    assert enc.channels == 512 and not enc.has_classifier
    x = torch.rand(1, 3, 64, 64) * 255
    with torch.inference_mode():
        got = enc(enc.preprocess(x))
        want = reference_vgg16_pool4(state, enc.preprocess(x))
    assert got.shape == (1, 512, 4, 4)
    assert torch.allclose(got, want, rtol=1e-4, atol=1e-5)


def test_vgg16_needs_a_file(tmp_path):
    with pytest.raises(WeightsError, match='torchvision'):
        build_encoder('vgg16')
    with pytest.raises(WeightsError, match='vgg16-397923af'):
        build_encoder('vgg16', weights=tmp_path / 'absent.pth')


def test_vgg16_wrong_layout_names_the_keys(tmp_path):
    state = torchvision_vgg16_trunk()
    state['features.1.weight'] = state.pop('features.2.weight')  # a BN-style index shift
    path = tmp_path / 'shifted.pth'
    torch.save(state, path)
    with pytest.raises(WeightsError) as info:
        build_encoder('vgg16', weights=path)
    message = str(info.value)
    assert 'missing keys: features.2.weight' in message
    assert 'unexpected keys: features.1.weight' in message


def test_vgg16_half_a_classifier_is_refused(tmp_path):
    state = torchvision_vgg16_trunk()
    state['classifier.6.bias'] = torch.zeros(1000)
    path = tmp_path / 'half-head.pth'
    torch.save(state, path)
    with pytest.raises(WeightsError, match='missing keys: .*classifier.0.weight'):
        build_encoder('vgg16', weights=path)


def test_vgg16_wrong_shapes_are_named(tmp_path):
    state = torchvision_vgg16_trunk()
    state['features.0.weight'] = torch.zeros(64, 1, 3, 3)
    path = tmp_path / 'grey.pth'
    torch.save(state, path)
    with pytest.raises(WeightsError, match=r'features\.0\.weight \(64, 1, 3, 3\)'):
        build_encoder('vgg16', weights=path)


@pytest.mark.parametrize('content', [b'not a torch file', 'a list'])
def test_a_file_that_is_no_state_dict_is_refused(tmp_path, content):
    path = tmp_path / 'bad.pth'
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        torch.save([torch.zeros(1)], path)
    with pytest.raises(WeightsError):
        build_encoder('vgg16', weights=path)


# --- module behaviour ------------------------------------------------------------------

def test_batchnorm_statistics_stay_frozen_in_train_mode():
    torch.manual_seed(0)
    enc = build_encoder('efficientnet_lite0', pretrained=False, classifier=False).train()
    before = {k: v.clone() for k, v in enc.state_dict().items() if 'running' in k}
    out = enc(torch.randn(2, 3, 64, 64))
    out.mean().backward()
    after = enc.state_dict()
    assert all(torch.equal(v, after[k]) for k, v in before.items())
    bns = [m for m in enc.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    assert bns and not any(m.training for m in bns)
    assert enc.training
    assert all(m.weight.grad is not None for m in bns)  # the affine part still learns


@pytest.mark.parametrize('name', ['efficientnet_lite0', 'resnet50'])
def test_channels_last_gives_the_same_features(name):
    torch.manual_seed(0)
    enc = build_encoder(name, pretrained=False, classifier=False)
    x = enc.preprocess(torch.rand(1, 3, 96, 96) * 255)
    with torch.inference_mode():
        plain = enc(x)
        enc = enc.to(memory_format=torch.channels_last)
        fast = enc(x.contiguous(memory_format=torch.channels_last))
    assert torch.allclose(plain, fast, rtol=1e-4, atol=1e-4)


# --- the weights module ----------------------------------------------------------------

@pytest.mark.parametrize('layer, key', [
    ('conv1', 'conv1'), ('bn_conv1', 'bn1'), ('fc1000', 'fc'),
    ('res2a_branch1', 'layer1.0.downsample.0'), ('bn2a_branch1', 'layer1.0.downsample.1'),
    ('res3a_branch2a', 'layer2.0.conv1'), ('bn4f_branch2c', 'layer3.5.bn3'),
    ('res5c_branch2b', 'layer4.2.conv2'),
])
def test_keras_resnet_names_map_to_torchvision_keys(layer, key):
    assert weights.keras_resnet_key(layer) == key


def test_state_digest_survives_a_save_and_sees_one_changed_value():
    state = {'b': torch.arange(6.0).view(2, 3), 'a': torch.zeros((), dtype=torch.long)}
    buf = io.BytesIO()
    torch.save(state, buf)
    buf.seek(0)
    again = torch.load(buf, weights_only=True)
    assert cache.state_digest(again) == cache.state_digest(state)
    again['b'][1, 2] += 1
    assert cache.state_digest(again) != cache.state_digest(state)


@pytest.mark.parametrize('damage', ['zeroed', 'one_value'])
def test_a_cached_file_of_the_right_name_but_wrong_weights_is_refused(tmp_path, damage):
    """
    A zeroed or altered file would load and give features of nothing: the digest the
    cache file is named by must match.
    """
    require_cached('efficientnet_lite0')
    good = cache.weights_path('efficientnet_lite0')
    bad = tmp_path / good.name
    if damage == 'zeroed':
        bad.write_bytes(bytes(good.stat().st_size))
        match = 'cannot be read'
    else:
        state = torch.load(good, weights_only=True)
        next(iter(state.values())).view(-1)[0] += 1
        torch.save(state, bad)
        match = 'not the ones fetched'
    with pytest.raises(WeightsError, match=match) as info:
        cache.weights_path('efficientnet_lite0', cache=tmp_path)
    assert 'fetch' in str(info.value)


def test_fetch_is_a_no_op_when_the_cache_is_current(monkeypatch, capsys):
    require_cached('efficientnet_lite0')
    forbid_network(monkeypatch)
    paths = weights.fetch(['efficientnet_lite0'])
    assert paths['efficientnet_lite0'] == cache.weights_path('efficientnet_lite0')
    err = capsys.readouterr().err
    assert 'up to date' in err
    assert 'Apache-2.0' in err


def test_fetch_refuses_an_archive_with_the_wrong_checksum(monkeypatch, tmp_path):
    def fake_download(source, dest):
        path = dest / source.archive
        path.write_bytes(b'tampered')
        return path

    monkeypatch.setattr(weights, 'download', fake_download)
    with pytest.raises(WeightsError, match='sha256'):
        weights.fetch(['vgg19'], cache=tmp_path / 'cache', stream=io.StringIO())
    assert not any((tmp_path / 'cache').glob('*.pt'))


def test_fetch_refuses_vgg16():
    with pytest.raises(ConfigError, match='torchvision'):
        weights.fetch(['vgg16'], stream=io.StringIO())


def test_write_state_leaves_nothing_behind_on_a_bad_digest(tmp_path):
    path = tmp_path / 'x.pt'
    with pytest.raises(WeightsError):
        weights.write_state({'w': torch.ones(3)}, path, '0' * 64)
    assert list(tmp_path.iterdir()) == []
    state = {'w': torch.ones(3)}
    weights.write_state(state, path, cache.state_digest(state))
    assert [p.name for p in tmp_path.iterdir()] == ['x.pt']


def test_cli_help_and_status(tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        weights.main(['fetch', '--help'])
    assert info.value.code == 0
    assert '--encoders' in capsys.readouterr().out
    assert weights.main(['status', '--cache', str(tmp_path)]) == 1
    assert 'vgg19' in capsys.readouterr().out


@pytest.mark.parametrize('name', ['efficientnet_lite0', 'resnet50'])
def test_folded_copy_computes_the_same_features_without_batchnorm(name):
    torch.manual_seed(0)
    enc = build_encoder(name, pretrained=False)
    for m in enc.modules():  # non-trivial statistics, or folding would be a no-op
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
    folded = fold_batchnorm(enc)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
    assert not any(p.requires_grad for p in folded.parameters())
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in enc.modules())  # a copy
    x = enc.preprocess(torch.rand(1, 3, 96, 96) * 255)  # small: the maths is size-free
    with torch.inference_mode():
        assert torch.allclose(folded(x), enc(x), rtol=1e-3, atol=1e-4)
        assert torch.allclose(folded.classify(x), enc.classify(x), rtol=1e-3, atol=1e-3)
