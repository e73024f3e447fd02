"""
Check the docstrings as ament_pep257 does.

That is pydocstyle with the ament convention: every check but D100-D107 (missing
docstrings), D203, D212 and D404. The code predates the check, and many docstrings open
with a summary longer than a line or with a noun ("The arm's pose at ..."), so the
findings each file had when the check came are its baseline (`pep257_baseline.json`, by
file and code). The test fails on a finding beyond it, so new code follows the
convention, and when a file has fewer than its baseline, so the baseline only goes down:
after fixing docstrings, write it again with
``python test/test_pep257.py --write-baseline``.
"""
from collections import Counter
import json
from pathlib import Path
import sys

import pytest

REPO = Path(__file__).resolve().parents[1]
BASELINE = Path(__file__).with_name('pep257_baseline.json')
PATHS = ('activeloc_ros', 'test', 'bags/make_sample.py', 'setup.py')
# ament_pep257's "ament" convention (ament_pep257/main.py, _ament_ignore)
AMENT_IGNORE = ('D100', 'D101', 'D102', 'D103', 'D104', 'D105', 'D106', 'D107', 'D203',
                'D212', 'D404')


def findings() -> Counter:
    """Count the findings by (file relative to the repo, code)."""
    from pydocstyle import check
    from pydocstyle.violations import ErrorRegistry

    select = sorted(set(ErrorRegistry.get_error_codes()) - set(AMENT_IGNORE))
    files = sorted(str(f) for p in PATHS
                   for f in ([REPO / p] if (REPO / p).is_file() else (REPO / p).rglob('*.py')))
    counts = Counter()
    for error in check(files, select=select):
        if not hasattr(error, 'code'):           # a file pydocstyle could not parse
            raise AssertionError(f'pydocstyle: {error}')
        counts[Path(error.filename).relative_to(REPO).as_posix(), error.code] += 1
    return counts


def as_table(counts: Counter) -> dict:
    table: dict = {}
    for (name, code), n in sorted(counts.items()):
        table.setdefault(name, {})[code] = n
    return table


def test_no_docstring_finding_beyond_the_baseline():
    pytest.importorskip('pydocstyle', reason="install the 'test' extra")
    baseline = Counter({(name, code): n
                        for name, codes in json.loads(BASELINE.read_text()).items()
                        for code, n in codes.items()})
    now = findings()
    new = {key: (n, baseline[key]) for key, n in now.items() if n > baseline[key]}
    fewer = {key: (now[key], n) for key, n in baseline.items() if now[key] < n}
    assert not new, ('docstrings that break ament_pep257 (file, code: now, baseline); see '
                     f'`python -m pydocstyle FILE`: {new}')
    assert not fewer, ('fewer findings than the baseline: write it again with '
                       f'`python test/test_pep257.py --write-baseline` ({fewer})')


if __name__ == '__main__':
    if sys.argv[1:] != ['--write-baseline']:
        raise SystemExit(f'usage: python {sys.argv[0]} --write-baseline')
    counts = findings()
    BASELINE.write_text(json.dumps(as_table(counts), indent=1, sort_keys=True) + '\n')
    print(f'{BASELINE.name}: {sum(counts.values())} findings in '
          f'{len({name for name, _ in counts})} files')
