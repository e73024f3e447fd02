"""A dependency-free progress line for long work (benchmarks, fetching weights)."""
import sys
import time


class Progress:
    """
    Prints `label  done/total  rate  eta` on stderr, redrawn in place on a terminal.

    :param total: number of steps expected (0 when unknown).
    :param label: what is being counted.
    """

    def __init__(self, total: int, label: str, *, stream=None, min_interval: float = 0.5):
        self.total = total
        self.label = label
        self.stream = stream or sys.stderr
        self.min_interval = min_interval
        self.done = 0
        self.start = time.monotonic()
        self._last = 0.0
        self._tty = self.stream.isatty()

    def update(self, n: int = 1, *, note: str = '') -> None:
        self.done += n
        now = time.monotonic()
        if now - self._last < self.min_interval and self.done < self.total:
            return
        if not self._tty and self.done < self.total and now - self._last < 10.0:
            return
        self._last = now
        self._draw(now, note)

    def close(self, note: str = '') -> None:
        self._draw(time.monotonic(), note)
        if self._tty:
            self.stream.write('\n')
        self.stream.flush()

    def _draw(self, now: float, note: str) -> None:
        elapsed = max(now - self.start, 1e-9)
        rate = self.done / elapsed
        if self.total:
            eta = (self.total - self.done) / rate if rate > 0 else float('inf')
            line = (f'{self.label}  {self.done}/{self.total}  {rate:.1f}/s  '
                    f'eta {eta:.0f}s {note}')
        else:
            line = f'{self.label}  {self.done}  {rate:.1f}/s {note}'
        self.stream.write(('\r' + line.ljust(78)) if self._tty else line + '\n')
        self.stream.flush()
