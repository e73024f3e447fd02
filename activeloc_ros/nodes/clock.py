"""
A simulated clock that runs back: a bag replayed in a loop with its ``/clock`` (``ros2 bag
play --loop --clock``) sends every node on ``use_sim_time`` back to the bag's start.

The controller and the arm hold times (the arm's recent poses, the last location, the
servos' last step); after a jump back each would wait, still and silent, until the clock is
where it was. `Rewinds` notes each jump, and its `locked` starts the node's core over at
the new time, and says so, before a callback touches the core.
"""
import contextlib
import threading
from typing import Callable

from rclpy.clock import JumpThreshold, TimeJump
from rclpy.duration import Duration
from rclpy.node import Node

REWIND_S = 0.2   # a smaller step back costs at most that long a wait: not worth a restart


class Rewinds:
    """
    Notes ``node``'s clock jumping back by more than `REWIND_S`.

    The jump arrives from the ``/clock`` subscription with the clock's own lock held, so it
    is only noted here; `locked`, which holds the node's ``lock``, acts on it where the
    node's core is safe to touch.

    :param restart: called with the node's new time (s) to start its core over there.
    :param then: what the warning says happens next.
    """

    def __init__(self, node: Node, lock: threading.Lock, restart: Callable[[float], None],
                 then: str):
        self._jump_s: float | None = None
        self._node, self._lock, self._restart, self._then = node, lock, restart, then
        threshold = JumpThreshold(min_forward=None, min_backward=Duration(seconds=-REWIND_S),
                                  on_clock_change=False)
        # the handle must live as long as the node: dropped, it unregisters the callback
        self._handle = node.get_clock().create_jump_callback(threshold,
                                                             post_callback=self._on_jump)

    def _on_jump(self, jump: TimeJump) -> None:
        self._jump_s = jump.delta.nanoseconds * 1e-9

    @contextlib.contextmanager
    def locked(self):
        """
        Hold the node's lock, for a callback that touches its core.

        First, if the clock ran back since the last call, the core starts over at the new
        time.
        """
        with self._lock:
            jump, self._jump_s = self._jump_s, None
            if jump is not None:
                now = self._node.get_clock().now().nanoseconds * 1e-9
                self._restart(now)
                self._node.get_logger().warning(
                    f'the clock ran back {-jump:.1f} s, to {now:.2f} s (a bag replayed in a '
                    f'loop?): {self._then}')
            yield
