"""A simulated clock that runs back: a bag replayed in a loop with its ``/clock`` (``ros2 bag
play --loop --clock``) sends every node on ``use_sim_time`` back to the bag's start.

The controller and the arm hold times (the arm's recent poses, the last location, the
servos' last step); after a jump back each would wait, still and silent, until the clock is
where it was. `Rewinds` notes each jump so the node can start its core over at the new time
and say so.
"""
from rclpy.clock import JumpThreshold, TimeJump
from rclpy.duration import Duration
from rclpy.node import Node

REWIND_S = 0.2   # a smaller step back costs at most that long a wait: not worth a restart


class Rewinds:
    """Notes ``node``'s clock jumping back by more than `REWIND_S`.

    The jump arrives from the ``/clock`` subscription with the clock's own lock held, so it
    is only noted here; the node calls `take` under its own lock, where its core is safe
    to touch.
    """

    def __init__(self, node: Node):
        self._jump_s: float | None = None
        threshold = JumpThreshold(min_forward=None, min_backward=Duration(seconds=-REWIND_S),
                                  on_clock_change=False)
        # the handle must live as long as the node: dropped, it unregisters the callback
        self._handle = node.get_clock().create_jump_callback(threshold,
                                                             post_callback=self._on_jump)

    def _on_jump(self, jump: TimeJump) -> None:
        self._jump_s = jump.delta.nanoseconds * 1e-9

    def take(self) -> float | None:
        """The jump since the last call (seconds, negative), or None."""
        jump, self._jump_s = self._jump_s, None
        return jump
