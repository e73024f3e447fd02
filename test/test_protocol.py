"""The selection protocol: its statistics (bench.protocol) and how compare reads its sides."""
import json

import numpy as np
import pytest

from activeloc_ros.bench import compare, protocol
from activeloc_ros.errors import ConfigError

SEQUENCES = [f'seq{i}' for i in range(8)]


def scores(values, seeds=(0, 1, 2), noise=0.0, rng_seed=0):
    rng = np.random.default_rng(rng_seed)
    return {n: {s: float(v + rng.normal(0, noise)) for s in seeds}
            for n, v in zip(SEQUENCES, values)}


BASE = [10.0, 12.0, 8.0, 20.0, 15.0, 9.0, 11.0, 14.0]


@pytest.mark.parametrize('shift, verdict', [(-1.0, protocol.BETTER), (1.0, protocol.WORSE)])
def test_a_shift_on_every_sequence_is_a_verdict(shift, verdict):
    base = scores(BASE, noise=0.3)
    cand = scores([v + shift for v in BASE], noise=0.3, rng_seed=1)
    c = protocol.compare(base, cand, resamples=2000)
    assert c.verdict == verdict
    assert c.low < c.mean < c.high
    assert c.mean == pytest.approx(shift, abs=0.3)
    assert c.wins == (8 if shift < 0 else 0)


def test_a_gain_on_some_sequences_and_a_loss_on_others_is_no_difference():
    cand = [v + (1.5 if i % 2 else -1.5) for i, v in enumerate(BASE)]
    c = protocol.compare(scores(BASE), scores(cand), resamples=2000)
    assert c.verdict == protocol.LEVEL
    assert c.low < 0 < c.high
    assert c.wins == 4


def test_seed_noise_widens_the_interval():
    cand = [v - 0.5 for v in BASE]
    quiet = protocol.compare(scores(BASE, noise=0.05), scores(cand, noise=0.05, rng_seed=1),
                             resamples=2000)
    noisy = protocol.compare(scores(BASE, noise=3.0), scores(cand, noise=3.0, rng_seed=1),
                             resamples=2000)
    assert noisy.high - noisy.low > 2 * (quiet.high - quiet.low)


def test_the_report_is_reproduced_exactly():
    base, cand = scores(BASE, noise=1.0), scores(BASE, noise=1.0, rng_seed=3)
    assert protocol.compare(base, cand, resamples=500) == protocol.compare(base, cand,
                                                                           resamples=500)


def test_a_side_without_seeds_is_compared_with_every_seed_of_the_other():
    base = scores(BASE, seeds=(0,))                     # mog2: one run a sequence
    cand = scores([v - 2 for v in BASE], noise=0.2)
    c = protocol.compare(base, cand, resamples=1000)
    assert c.verdict == protocol.BETTER
    assert c.mean == pytest.approx(-2.0, abs=0.2)


@pytest.mark.parametrize('base, cand, match', [
    ({'a': {0: 1.0}}, {'b': {0: 1.0}}, 'no sequence in common'),
    ({'a': {0: float('nan')}}, {'a': {0: 1.0}}, 'non-finite'),
    ({'a': {}}, {'a': {0: 1.0}}, 'no runs'),
])
def test_bad_scores_are_refused(base, cand, match):
    with pytest.raises(ConfigError, match=match):
        protocol.compare(base, cand, resamples=100)


def test_leave_one_out_chooses_on_the_other_sequences():
    worse = [v + 1 for v in BASE]
    best = [v - 1 for v in BASE]
    # a side that is best on one sequence alone is never chosen when that one is left out
    lucky = [v + 2 for v in BASE]
    lucky[3] = BASE[3] - 10
    loo = protocol.leave_one_out([scores(BASE), scores(worse), scores(best), scores(lucky)],
                                 resamples=500)
    assert loo.chosen['seq3'] == 2
    assert set(loo.chosen.values()) <= {2, 3}
    assert loo.estimate['seq0'] == pytest.approx(BASE[0] - 1)
    assert loo.against_base.mean < 0


def test_a_side_is_a_method_with_its_settings():
    side = compare.parse_side('ours --set location=peak lr=0.01 --control kd=0.1')
    assert side['method'] == 'ours'
    assert side['settings'] == {'location': 'peak', 'lr': 0.01}
    assert side['control'] == {'kd': 0.1}
    paper = compare.parse_side('ours --params params/paper.yaml --set lr=0.5')
    assert paper['settings']['location'] == 'peak' and paper['settings']['lr'] == 0.5
    assert paper['control']['kd'] == 0.1


@pytest.mark.parametrize('spec, match', [
    ('nosuch', 'unknown method'),
    ('ours --set location=nowhere', 'location'),
    ('ours --control kp=-1', 'kp'),
    ('ours --params params/missing.yaml', 'not found'),
])
def test_a_bad_side_is_refused_before_any_run(spec, match):
    with pytest.raises(ConfigError, match=match):
        compare.parse_side(spec)


def test_a_saved_side_reads_screen_results_one_file_per_seed(tmp_path):
    for seed in (0, 1):
        folder = tmp_path / f'seed{seed}'
        folder.mkdir()
        (folder / 'screen.json').write_text(json.dumps({
            'settings': {'seed': seed},
            'methods': [{'method': 'ours', 'sequences': {
                'a': {'aae_deg': 5.0 + seed}, 'b': {'aae_deg': 7.0 + seed}}}]}))
    got = compare.load_saved(f'{tmp_path}/seed*/screen.json#ours', 'aae_deg')
    assert got == {'a': {0: 5.0, 1: 6.0}, 'b': {0: 7.0, 1: 8.0}}
    with pytest.raises(ConfigError, match='no method'):
        compare.load_saved(f'{tmp_path}/seed*/screen.json#mog2', 'aae_deg')


def test_the_report_names_every_side_and_round_trips(tmp_path):
    sides = [{'label': 'ours'}, {'label': 'ours --set lr=1'}, {'label': 'mog2'}]
    table, result = compare.report(
        sides, [scores(BASE), scores([v - 1 for v in BASE]), scores(BASE, seeds=(0,))],
        metric='aae_deg', resamples=500)
    assert 'ours --set lr=1' in table and 'leave one sequence out' in table
    assert result['comparisons'][0]['verdict'] == protocol.BETTER
    path = tmp_path / 'compare.json'
    path.write_text(json.dumps(result))
    assert compare.load_saved(f'{path}#1', 'aae_deg')['seq0'] == {0: 9.0, 1: 9.0, 2: 9.0}
