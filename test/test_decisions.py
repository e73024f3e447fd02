"""
The generated docs: the verdicts kept as data (a row made from a compare result, the page
rendered from the data) and the parameters page made from the declarations, never stale.
"""
import json

import pytest
import yaml

from activeloc_ros.bench import compare, decisions
from activeloc_ros.errors import ConfigError


def test_the_page_is_rendered_from_the_data():
    """docs/decisions.md is what `bench decisions render` makes of docs/decisions.yaml."""
    assert decisions.main(['render', '--check']) == 0, \
        'run python -m activeloc_ros.bench decisions render'


def _result(shifts: tuple) -> dict:
    """
    A compare result of a candidate `shifts` degrees worse than its base, one sequence
    each, the second seed 0.1 deg more.
    """
    base = {f's{i}': {0: 10.0 + i, 1: 10.5 + i} for i in range(len(shifts))}
    candidate = {n: {k: v + shift + 0.1 * k for k, v in r.items()}
                 for (n, r), shift in zip(base.items(), shifts)}
    _, result = compare.report([{'label': 'ours'}, {'label': 'ours --set x=1'}],
                               [base, candidate], metric='aae_deg', resamples=1000)
    result['settings'] = compare.provenance(['--base', 'ours', '--candidate', 'ours --set x=1'])
    return result


def test_a_row_takes_every_figure_from_the_compare_result(tmp_path, capsys):
    data = tmp_path / 'decisions.yaml'
    data.write_text(yaml.safe_dump({'preamble': 'p', 'rows': []}))
    result = tmp_path / 'compare.json'
    result.write_text(json.dumps(_result((2.0, 2.0, 2.0, 2.0))))
    assert decisions.main(['add', str(result), '--setting', 'x', '--value', '0', '--against',
                           '1', '--set', 'real', '--decision', 'kept', '--data',
                           str(data)]) == 0
    row, = decisions.load(data)['rows']
    assert row['difference'] == pytest.approx(2.05) and row['verdict'] == 'worse'
    assert row['interval'][0] > 0 and row['lower_on'] == '0/4'
    assert row['command'].startswith('python -m activeloc_ros.bench compare --base ours')
    assert 'cores' in row['cpu'] and row['date'].startswith('20')
    page = tmp_path / 'decisions.md'
    assert decisions.main(['render', '--data', str(data), '--page', str(page)]) == 0
    assert '| 1 | `x` | 0 | 1 | real | +2.05 [' in page.read_text()
    data.write_text(data.read_text().replace('decision: kept', 'decision: changed'))
    assert decisions.main(['render', '--check', '--data', str(data), '--page',
                           str(page)]) == 1
    assert 'stale' in capsys.readouterr().err


def test_a_row_whose_verdict_contradicts_its_interval_is_refused(tmp_path):
    row = decisions.row_from_compare(_result((1.0, -1.0, 0.5, -0.5)), 1, setting='x',
                                     default='0', candidate='1', set='synthetic',
                                     decision='kept')
    assert row['verdict'] == 'no difference' and decisions.row_problem(row) is None
    row['verdict'] = 'better'
    assert 'does not match' in decisions.row_problem(row)
    data = tmp_path / 'decisions.yaml'
    data.write_text(yaml.safe_dump({'rows': [row]}))
    with pytest.raises(ConfigError, match='row 1'):
        decisions.load(data)


def test_the_parameters_page_is_made_from_the_declarations():
    """docs/parameters.md lists every node's declared parameters as they are now."""
    from activeloc_ros.nodes import params_doc
    assert params_doc.main(['--check']) == 0, 'run python -m activeloc_ros.nodes.params_doc'
