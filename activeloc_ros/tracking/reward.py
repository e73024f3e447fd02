"""
AD-VAT's tracking reward and the scores of the paper's Table 1.

The reward of one step (gym-unrealcv ``envs/tracking/reward.py``; the paper's Eq. 5 with
rho_max = 250 cm, theta_max = 90 deg is the same quantity)::

    r = 1 - min(|rho* - d cos(theta)| / rho*, 2) - min(|theta| / 45 deg, 2),  at least -1

``d`` is the target's distance and ``theta`` its bearing from the tracker's heading;
rho* = 2.5 m is the distance to keep. An episode ends after ``max_steps`` steps, or once the
target has been lost (r = -1) for ``lost_steps`` steps in a row.

The paper's scores, as we read its figures: recall = episode length / max_steps, precision
= summed reward / max_steps. The relaxed precision (the paper's figures in parentheses)
counts the distance term as 0 while the target is within twice rho* along the heading
(|rho* - d cos(theta)| < rho*), else 1.
"""
from dataclasses import dataclass
import math
from typing import Sequence

RHO_STAR = 2.5            # m, gym-unrealcv's 250 cm
THETA_MAX_DEG = 45.0
LOST = -1.0


def _terms(distance: float, bearing: float, rho: float) -> tuple[float, float]:
    along = abs(rho - distance * math.cos(bearing)) / rho
    return along, abs(math.degrees(bearing)) / THETA_MAX_DEG


def reward(distance: float, bearing: float, *, rho: float = RHO_STAR) -> float:
    """AD-VAT's reward for a target ``distance`` m away at ``bearing`` radians."""
    along, angle = _terms(distance, bearing, rho)
    return max(1.0 - min(along, 2.0) - min(angle, 2.0), LOST)


def reward_relaxed(distance: float, bearing: float, *, rho: float = RHO_STAR) -> float:
    """The reward with its distance term 0 (target within 2 rho* ahead) or 1."""
    along, angle = _terms(distance, bearing, rho)
    return max(1.0 - (0.0 if along < 1.0 else 1.0) - min(angle, 2.0), LOST)


@dataclass(frozen=True)
class EpisodeScore:
    length: int
    reward: float               # AD-VAT's accumulated reward
    reward_relaxed: float
    max_steps: int

    @property
    def recall(self) -> float:
        return self.length / self.max_steps

    @property
    def precision(self) -> float:
        return self.reward / self.max_steps

    @property
    def precision_relaxed(self) -> float:
        return self.reward_relaxed / self.max_steps

    @property
    def success(self) -> bool:
        return self.length >= self.max_steps

    def as_dict(self) -> dict:
        return {'episode_length': self.length, 'reward': self.reward,
                'recall': self.recall, 'precision': self.precision,
                'precision_relaxed': self.precision_relaxed, 'success': float(self.success)}


def score(rewards: Sequence[float], relaxed: Sequence[float], max_steps: int) -> EpisodeScore:
    """The scores of an episode from its steps' rewards."""
    return EpisodeScore(len(rewards), float(sum(rewards)), float(sum(relaxed)), max_steps)


LOST_CAUSES = ('pinned', 'hidden', 'out of view', 'other')


def lost_cause(seen: Sequence[bool], bearing_deg: Sequence[float], blocked: Sequence[bool],
               *, half_fov_deg: float, window: int = 60) -> str:
    """
    Why an episode lost its target, from its last ``window`` steps: ``pinned`` when a
    bump held the base back on half of them or more, else ``hidden`` when the target stood
    inside the view unseen (an obstacle between them) on a third or more, else ``out of
    view`` when it stood outside the view on a third or more, else ``other``.
    """
    seen, bearing, blocked = (list(x)[-window:] for x in (seen, bearing_deg, blocked))
    inside = [abs(b) < half_fov_deg for b in bearing]
    if 2 * sum(blocked) >= len(blocked):
        return 'pinned'
    if 3 * sum(i and not s for i, s in zip(inside, seen)) >= len(seen):
        return 'hidden'
    if 3 * sum(not i for i in inside) >= len(inside):
        return 'out of view'
    return 'other'
