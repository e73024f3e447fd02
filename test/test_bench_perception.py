"""
`bench perception` names the CPU, the precisions and the update share of every row it
times, and marks the shipped default.
"""
import json

import pytest
import torch

from activeloc_ros.bench import perception as bench


def test_every_row_names_its_cpu_flags_and_precision(capsys):
    argv = ['--encoder', 'efficientnet_lite0', '--random-weights', '--frames', '3',
            '--warmup', '1', '--update-encoder', 'no', '--size', '96x64', '--threads', '1']
    assert bench.main(argv + ['--set', 'encoder_precision=float32', '--json']) == 0
    row, = json.loads(capsys.readouterr().out)
    assert row['precision'] == 'float32' and row['frames'] == 3
    assert row['predictor_precision'] in ('float32', 'bfloat16')
    assert row['update_share'] == 1.0           # one update per frame after the warm-up
    assert row['default'] is False              # random weights and a --set
    cpu = row['cpu']
    assert cpu['model'] and cpu['cores'] >= 1
    assert ('AVX512_BF16' in cpu['flags']) == torch.cpu._is_avx512_bf16_supported()
    assert ('AMX' in cpu['flags']) == torch.cpu._is_amx_tile_supported()

    assert bench.main(argv) == 0
    out = capsys.readouterr().out
    assert f'CPU: {cpu["model"]}' in out
    assert 'enc/pred' in out.splitlines()[2]


def test_a_params_file_adds_its_configurations_rows_beside_the_defaults(tmp_path, capsys):
    from conftest import PARAMS
    argv = ['--encoder', 'efficientnet_lite0', '--random-weights', '--frames', '3',
            '--warmup', '1', '--update-encoder', 'no', '--size', '96x64', '--threads', '1',
            '--set', 'encoder_precision=float32']
    assert bench.main(argv + ['--params', str(PARAMS / 'mirrored_border.yaml'), '--json']) == 0
    default, border = json.loads(capsys.readouterr().out)
    assert (default['configuration'], border['configuration']) == ('default +set',
                                                                   'mirrored_border +set')
    assert (default['config']['encoder_pad'], default['config']['conv_padding']) == (0, 'zeros')
    assert (border['config']['encoder_pad'], border['config']['conv_padding']) == (32, 'zeros')

    other = tmp_path / 'controller_only.yaml'
    other.write_text('controller:\n  ros__parameters:\n    kp: 0.5\n')
    broken, plain = tmp_path / 'broken.yaml', tmp_path / 'plain.yaml'
    broken.write_text('a: [b\n')
    plain.write_text('just a string\n')
    for path, message in ((tmp_path / 'missing.yaml', 'no such file'),
                          (other, 'sets no perception model parameter'),
                          (broken, 'cannot be read'), (plain, 'not in ROS 2 format')):
        assert bench.main(argv + ['--params', str(path)]) == 2
        assert message in capsys.readouterr().err
    for bad in (['--threads', '0'], ['--warmup', '-5']):
        with pytest.raises(SystemExit) as exc:
            bench.main(argv + bad)
        assert exc.value.code == 2 and '--threads >= 1' in capsys.readouterr().err


def test_the_cpu_line_says_what_is_missing():
    line = bench.describe_cpu({'model': 'X', 'cores': 2, 'flags': ['AVX2', 'AVX512']})
    assert line == 'X, 2 cores, AVX2, AVX512; no VNNI, AVX512_BF16, AMX'


def test_floor_counts_each_stage_and_divides_by_a_measured_peak(capsys):
    argv = ['--encoder', 'efficientnet_lite0', '--random-weights', '--frames', '3',
            '--warmup', '1', '--update-encoder', 'no', '--size', '96x64', '--threads', '1',
            '--set', 'encoder_precision=float32', '--set', 'predictor_precision=float32',
            '--set', 'hidden=64', '--floor', '--json']
    assert bench.main(argv) == 0
    floor = json.loads(capsys.readouterr().out)[0]['floor']
    assert set(floor['peak_gflops']) == {'float32'} and floor['peak_gflops']['float32'] > 0
    stages = floor['stages']
    assert list(stages) == ['encode', 'predict', 'update']
    for v in stages.values():
        assert v['gflop'] > 0 and v['measured_ms'] > 0
        assert v['floor_ms'] * 1e-3 == pytest.approx(v['gflop'] / floor['peak_gflops']['float32'])
        assert v['ratio'] == pytest.approx(v['measured_ms'] / v['floor_ms'])
    # a backward pass costs about twice its forward
    assert 1.0 < stages['update']['gflop'] / stages['predict']['gflop'] < 3.0


@pytest.mark.parametrize('config, default', [
    ({'num_threads': 2}, True), ({'hidden': 512, 'num_threads': 1}, True),
    ({'hidden': 64}, False), ({'pretrained': False}, False),
    ({'update_encoder': True}, False)])
def test_only_the_shipped_configuration_is_the_default_row(config, default):
    assert bench.is_default(config) is default


@pytest.mark.parametrize('dtype', ['float32', 'int8'])
def test_the_matmul_peak_is_measured_in_each_precision(dtype):
    assert bench.matmul_peak_gflops(dtype, n=256, seconds=0.05) > 0


def test_feature_gap_compares_each_precision_with_float32(tmp_path, monkeypatch, capsys):
    from activeloc_ros.perception import int8
    from test_passive import make_moving_square
    monkeypatch.setenv('ACTIVELOC_CACHE', str(tmp_path / 'cache'))
    monkeypatch.setattr(int8, 'CALIBRATION_FRAMES', 4)
    make_moving_square(tmp_path / 'data', 'square', n=4)
    argv = ['--feature-gap', '--data', str(tmp_path / 'data'), '--every', '2', '--threads',
            '1', '--encoder', 'efficientnet_lite0', '--random-weights', '--json']
    assert bench.main(argv) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r['precision'] for r in rows] == ['bfloat16', 'int8']
    for r in rows:
        assert r['frames'] == 2 and r['sequences'] == 1
        assert 0 < r['mean'] <= r['max'] < 0.5


def test_every_bench_command_reads_set_the_same_way():
    """
    One parser: `lr=1e-4` is a number everywhere (YAML 1.1 made it a string here), and
    repeated --set options add up instead of replacing each other.
    """
    from activeloc_ros.bench import key_values
    from activeloc_ros.bench import passive, screen
    argv = ['--set', 'lr=1e-4', 'motion_source=image', '--set', 'hidden=8']
    for args in (bench.parse_args(argv), passive.parser().parse_args(argv),
                 screen.parser().parse_args(argv)):
        assert key_values(args.set, '--set') == {'lr': 1e-4, 'motion_source': 'image',
                                                 'hidden': 8}
