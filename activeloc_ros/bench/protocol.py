"""
The selection protocol's statistics: is a candidate better than a base, or was it luck?

Pure numpy, no runs. A side's scores are ``{sequence: {seed: value}}`` (lower is better,
e.g. mean AAE). The sequence is the unit that must generalise, so the interval comes from a
two-stage bootstrap: draw the sequences with replacement, then, inside each drawn sequence,
its seeds with replacement. Where both sides ran the same seeds, a seed's two runs stay a
pair (the same initial weights); a side without seeds (mog2, centre) is one value a sequence.

The rule (docs/protocol.md): a default changes only when the interval excludes zero in the
candidate's favour, on the real static sequences and on the synthetic set alike.
"""
from dataclasses import dataclass

import numpy as np

from activeloc_ros.errors import ConfigError

Scores = dict[str, dict[int, float]]        # sequence -> seed -> value

BETTER, WORSE, LEVEL = 'better', 'worse', 'no difference'


@dataclass(frozen=True)
class Comparison:
    """
    A candidate against a base, over the sequences both have.

    :param per_sequence: candidate minus base, each sequence's mean over its seeds.
    :param mean: the mean of `per_sequence`.
    :param low: the 95% interval's lower end (two-stage bootstrap).
    :param high: its upper end.
    :param wins: sequences where the candidate is lower.
    """

    per_sequence: dict[str, float]
    mean: float
    low: float
    high: float
    wins: int

    @property
    def verdict(self) -> str:
        """`BETTER` (lower) or `WORSE` when the interval excludes zero, else `LEVEL`."""
        if self.high < 0:
            return BETTER
        if self.low > 0:
            return WORSE
        return LEVEL


def _check(scores: Scores, name: str) -> None:
    for seq, seeds in scores.items():
        if not seeds:
            raise ConfigError(f'{name}: sequence {seq!r} has no runs')
        bad = [s for s, v in seeds.items() if not np.isfinite(v)]
        if bad:
            raise ConfigError(f'{name}: sequence {seq!r} has a non-finite score (seed {bad[0]})')


def _draws(rng: np.random.Generator, base: dict[int, float], cand: dict[int, float],
           count: int) -> np.ndarray:
    """
    ``count`` bootstrap draws of a sequence's difference: its seeds drawn with
    replacement, the two runs of a seed together where both sides ran the same seeds.
    """
    if sorted(base) == sorted(cand):
        d = np.array([cand[s] - base[s] for s in sorted(base)])
        return d[rng.integers(0, len(d), size=(count, len(d)))].mean(axis=1)
    b, c = np.array(list(base.values())), np.array(list(cand.values()))
    return (c[rng.integers(0, len(c), size=(count, len(c)))].mean(axis=1)
            - b[rng.integers(0, len(b), size=(count, len(b)))].mean(axis=1))


def compare(base: Scores, candidate: Scores, *, resamples: int = 10000,
            seed: int = 0) -> Comparison:
    """
    The candidate's paired difference from the base, with its 95% interval.

    :param resamples: bootstrap draws.
    :param seed: the bootstrap's own seed, so a report is reproduced exactly.
    :raises ConfigError: no sequence in common, or a non-finite score.
    """
    _check(base, 'base')
    _check(candidate, 'candidate')
    names = sorted(set(base) & set(candidate))
    if not names:
        raise ConfigError('the two sides have no sequence in common')
    diffs = {n: float(np.mean(list(candidate[n].values())) - np.mean(list(base[n].values())))
             for n in names}
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(names), size=(resamples, len(names)))   # sequences drawn
    values = np.empty(picks.shape)
    for j, name in enumerate(names):      # each time a sequence is drawn, its seeds are too
        where = picks == j
        values[where] = _draws(rng, base[name], candidate[name], int(where.sum()))
    low, high = np.percentile(values.mean(axis=1), [2.5, 97.5])
    per_sequence = np.array(list(diffs.values()))
    return Comparison(diffs, float(per_sequence.mean()), float(low), float(high),
                      int((per_sequence < 0).sum()))


def sequence_means(scores: Scores) -> dict[str, float]:
    """Each sequence's mean over its seeds."""
    return {n: float(np.mean(list(s.values()))) for n, s in scores.items()}


@dataclass(frozen=True)
class LeaveOneOut:
    """
    Choosing among several values by the protocol, scored on a sequence it did not see.

    :param chosen: for each left-out sequence, the index of the side chosen on the others.
    :param estimate: for each left-out sequence, the chosen side's score there.
    :param against_base: the estimate's comparison with side 0 (the base).
    """

    chosen: dict[str, int]
    estimate: dict[str, float]
    against_base: Comparison


def leave_one_out(sides: list[Scores], *, resamples: int = 10000,
                  seed: int = 0) -> LeaveOneOut:
    """
    Leave-one-sequence-out selection over ``sides`` (side 0 is the base): for each
    sequence, the side with the lowest mean over the other sequences is chosen and scored on
    the one left out. Its interval is a bootstrap over sequences of the estimate minus the
    base (the seeds are already averaged into each sequence).
    """
    if len(sides) < 2:
        raise ConfigError('leave-one-out needs at least two sides')
    means = [sequence_means(s) for s in sides]
    names = sorted(set.intersection(*(set(m) for m in means)))
    if len(names) < 3:
        raise ConfigError('leave-one-out needs at least three sequences in common')
    chosen, estimate = {}, {}
    for left in names:
        rest = [n for n in names if n != left]
        totals = [np.mean([m[n] for n in rest]) for m in means]
        best = int(np.argmin(totals))          # ties go to the base, side 0
        chosen[left] = best
        estimate[left] = means[best][left]
    as_scores = {n: {0: v} for n, v in estimate.items()}
    base = {n: {0: means[0][n]} for n in names}
    return LeaveOneOut(chosen, estimate,
                       compare(base, as_scores, resamples=resamples, seed=seed))
