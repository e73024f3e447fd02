"""
The arm in time as the sketch drives it: whole degrees, one degree per step delay.

Like ``Braccio.ServoMovement`` (and ``braccio_serial.ino``), every ``step_delay_ms`` each
joint that is not at its target moves one whole degree towards it; the steps run on a free
clock, so a new target is followed from the next step on.
"""
import math
from typing import Sequence

from activeloc_ros.control.braccio import clamp_to_limits, JOINT_NAMES, speed_deg_s
from activeloc_ros.errors import ConfigError


def quantize(joints_deg: Sequence[float]) -> tuple[int, ...]:
    """Clamp into the limits and round to the whole degrees a servo takes."""
    return tuple(int(round(q)) for q in clamp_to_limits(joints_deg))


class SimArm:
    """Servo kinematics of the Braccio in explicit time (seconds)."""

    def __init__(self, start_deg: Sequence[float], t0: float, *, step_delay_ms: float = 20.0):
        speed_deg_s(step_delay_ms)  # validates the range
        if not math.isfinite(t0):
            raise ConfigError(f'start time must be finite, got {t0}')
        self.step = step_delay_ms / 1000.0
        self.joints: tuple[int, ...] = quantize(start_deg)
        self.target: tuple[int, ...] = self.joints
        self.t = float(t0)
        self._t0 = self.t
        self._steps = 0           # steps taken; step k happens at t0 + k * step

    @property
    def moving(self) -> bool:
        return self.joints != self.target

    def command(self, target_deg: Sequence[float], t: float) -> None:
        """Aim at ``target_deg`` (clamped, rounded) from time ``t`` on."""
        self.advance(t)
        self.target = quantize(target_deg)

    def advance(self, t: float) -> tuple[int, ...]:
        """
        Move the joints up to time ``t`` (earlier or non-finite times change nothing).

        Steps are counted from the start time, not accumulated, so asking twice for the
        same time never moves the arm twice (float sums would drift across a step).
        """
        if not math.isfinite(t):
            return self.joints
        due = math.floor((t - self._t0) / self.step + 1e-9)
        n = due - self._steps
        self.t = max(self.t, t)
        if n <= 0:
            return self.joints
        self._steps = due
        self.joints = tuple(
            q + max(-n, min(n, goal - q)) for q, goal in zip(self.joints, self.target))
        return self.joints

    def restart(self, t: float) -> None:
        """
        The clock ran back to ``t``: the servos go on stepping from there (else they stood
        still until the clock was back where it was).
        """
        if not math.isfinite(t):
            raise ConfigError(f'restart time must be finite, got {t}')
        self.t = self._t0 = float(t)
        self._steps = 0

    def as_dict(self) -> dict[str, int]:
        return dict(zip(JOINT_NAMES, self.joints))
