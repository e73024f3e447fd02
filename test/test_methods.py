"""The benchmarks' methods: the paper preset, params files, and the flow anchor."""

import math

import numpy as np
import pytest

from activeloc_ros.bench import methods
from activeloc_ros.errors import ConfigError
from activeloc_ros.world import View


def test_the_paper_preset_is_the_papers_choices():
    settings, _ = methods.method_parts('ours-paper')
    assert settings['location'] == 'peak' and settings['location_prior'] == 0.0
    assert settings['feature_norm'] == 'none' and settings['motion'] == 'sigmoid'
    assert settings['optimizer'] == 'sgd' and settings['lr'] == 1e-6
    assert settings['update_encoder'] is True and settings['adaptive_lr'] is True
    pd = methods.controller_for('ours-paper', {})
    assert (pd.pd.kp, pd.pd.kd, pd.pd.derivative, pd.pd.dead_band) == (1.0, 0.1, 'error', 0.0)
    assert pd.settle_time == 0.0 and pd.min_peak == 0.0


def test_settings_given_win_over_the_preset():
    assert methods.controller_for('ours-paper', {'kd': 0.0}).pd.kd == 0.0
    assert methods.controller_for('ours-paper', {'settle_time': 0.3}).settle_time == 0.3
    assert methods.controller_for('ours', {}).settle_time == 0.3     # the default's own


def test_a_params_file_gives_perception_and_controller(tmp_path):
    path = tmp_path / 'p.yaml'
    path.write_text('perception:\n  ros__parameters:\n    lr: 0.01\n    publish_overlay: false\n'
                    'controller:\n  ros__parameters:\n    dead_band_deg: 1.0\n'
                    '    actuator: arm\n')
    settings, control = methods.params_file(path)
    assert settings == {'lr': 0.01}            # the node's own parameters are no model's
    assert control == {'dead_band_deg': 1.0}
    path.write_text('perception:\n  ros__parameters:\n    location: nowhere\n')
    with pytest.raises(ConfigError, match='location'):
        methods.params_file(path)


def view(rgb, index):
    h, w = rgb.shape[:2]
    return View(rgb=rgb, index=index, t=0.1 * index, pan=0.0, tilt=0.0,
                truth_px=np.zeros((0, 2)), primary_px=None,
                centre_px=np.array([(w - 1) / 2, (h - 1) / 2]))


def test_flow_steers_to_what_moved():
    pointer = methods.make_pointer('flow', {}, 0)
    pointer.reset('s')
    rng = np.random.default_rng(0)
    background = rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)
    got = None
    for i in range(4):
        frame = background.copy()
        frame[150:190, 200 + 6 * i:240 + 6 * i] = 255        # a block moving right
        got = pointer.locate(view(frame, i))
    assert got.location is not None
    x, y = got.location
    assert 190 <= x <= 270 and 140 <= y <= 200


def test_the_node_and_the_benchmarks_make_one_pd_law_of_the_same_settings():
    from activeloc_ros.control.params import config_from, PARAMS, PD_PARAMS
    values = {**{p.name: p.default for p in PARAMS},
              'kd': 0.3, 'dead_band_deg': 1.5, 'derivative': 'error'}
    node = config_from(values).pd
    assert node.dead_band == pytest.approx(math.radians(1.5))
    assert methods.controller_for('ours', {k: values[k] for k in PD_PARAMS}).pd == node


def test_the_arm_takes_the_papers_pd_law_and_a_base_keeps_its_own():
    from activeloc_ros.control.params import base_config_from, config_from, PARAMS, unread
    values = {p.name: p.default for p in PARAMS}
    arm = config_from(values).pd
    assert (arm.kp, arm.kd, arm.derivative, arm.dead_band) == (1.0, 0.1, 'error', 0.0)
    base = base_config_from(values).pd
    assert (base.kp, base.kd, base.derivative) == (1.0, 0.0, 'target')
    assert base.dead_band == pytest.approx(math.radians(2.0))
    assert base_config_from({**values, 'pd_variant': 'paper'}).pd.kd == 0.1
    assert {'kd', 'derivative', 'dead_band_deg'} <= set(unread('base'))
