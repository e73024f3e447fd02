"""
bringup's supervision of node processes: start each in a session of its own that ends
with bringup, stop it in steps with deadlines, read its log's errors; and how a Ctrl-C or
SIGTERM asks the graph to stop.
"""
import ctypes
from pathlib import Path
import re
import signal
import subprocess
import sys
import time

from activeloc_ros.graph_plan import node_arguments, node_values

STOP_DEADLINE_S = 10.0
# A node's log line that bringup repeats on its console: errors, not warnings.
ERROR_LINE = re.compile(r'\[(ERROR|FATAL)\]|^error:|^\w*Error\b|^Traceback')
# and the warnings a node prints about itself (e.g. an encoder run slower than asked): shown,
# not counted as errors
WARNING_LINE = re.compile(r'^warning:')

PR_SET_PDEATHSIG = 1          # prctl(2)


def _die_with_parent() -> None:
    """In a child before exec: SIGTERM it when bringup dies, even of SIGKILL (Linux)."""
    if sys.platform.startswith('linux'):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def stop_deadline(node: str, args) -> float:
    """
    How long a node gets to end after SIGINT before SIGTERM: the arm may take its own
    ``stop_timeout`` to hold or go home, which must never be cut short.
    """
    if node != 'arm':
        return STOP_DEADLINE_S
    values = node_values('arm', args.params, args.ros_args)
    return max(STOP_DEADLINE_S, float(values['stop_timeout']) + 2.0)


HANDLER_DEADLINE_S = 5.0       # how long a starting node may take to handle a stop


def handles_stops(process: subprocess.Popen, deadline: float) -> bool:
    """
    Wait until `process` handles stops itself, it ends, or `deadline` seconds pass;
    whether it handles them. Python catches SIGINT from its first moment, raising
    KeyboardInterrupt wherever it is, so the sign is SIGTERM, which a node's stop handling
    (`nodes.start`, then `process.run`) catches with it (Linux: /proc lists it as caught).
    Where /proc cannot say, it is taken to.
    """
    give_up = time.monotonic() + deadline
    while process.poll() is None:
        try:
            status = Path(f'/proc/{process.pid}/status').read_text()
        except OSError:
            return True
        caught = next((line.split()[1] for line in status.splitlines()
                       if line.startswith('SigCgt:')), None)
        if caught is None or int(caught, 16) & (1 << (signal.SIGTERM - 1)):
            return True
        if time.monotonic() > give_up:
            return False
        time.sleep(0.01)
    return False


class Child:
    """
    One node process, in a session of its own (a terminal's Ctrl-C reaches bringup only,
    which stops the nodes in order) that ends when bringup ends, however it ends.
    """

    def __init__(self, node: str, args, log_dir: Path, env):
        self.name = node
        self.log_path = log_dir / f'{node}.log'
        self.log = open(self.log_path, 'w')
        # (nodes.start: a stop while the node's module loads ends it cleanly)
        self.process = subprocess.Popen(
            [sys.executable, '-u', '-m', 'activeloc_ros.nodes.start', node]
            + node_arguments(node, args),
            stdout=self.log, stderr=subprocess.STDOUT, env=env, start_new_session=True,
            preexec_fn=_die_with_parent)
        self.stop_deadline = stop_deadline(node, args)

    @property
    def returncode(self):
        return self.process.poll()

    def stop(self) -> int:
        """
        SIGINT (the node stops on purpose), then SIGTERM, then SIGKILL, each with a deadline.
        A process still starting Python gets its SIGINT once it handles stops (`nodes.start`
        installs that first): before, the signal would kill it, -2 and no line in its log.
        """
        handles_stops(self.process, HANDLER_DEADLINE_S)
        for sig, wait in ((signal.SIGINT, self.stop_deadline), (signal.SIGTERM, 3.0),
                          (signal.SIGKILL, 3.0)):
            if self.process.poll() is not None:
                break
            self.process.send_signal(sig)
            try:
                self.process.wait(wait)
            except subprocess.TimeoutExpired:
                print(f'{self.name}: still running {wait:g} s after {sig.name}, which it '
                      f'did not end on (a hang? its log: {self.log_path})', file=sys.stderr,
                      flush=True)
                continue
        self.log.close()
        return self.process.returncode

    def tail(self, lines: int = 15) -> str:
        return '\n'.join(self.log_path.read_text(errors='replace').splitlines()[-lines:])

    def errors(self, pattern: re.Pattern = ERROR_LINE) -> list[str]:
        """The error lines of the node's log (ERROR_LINE), or those ``pattern`` finds."""
        try:
            text = self.log_path.read_text(errors='replace')
        except OSError:
            return []
        return [line for line in text.splitlines() if pattern.search(line)]


class StopRequest:
    """
    SIGINT and SIGTERM ask bringup to stop; the graph is then stopped in order and the
    bag closed. A signal while stopping is told to wait, not obeyed. While the nodes of an
    in-process graph are being made (a first use of an int8 encoder builds it for a minute)
    the first signal ends that at once, unless OpenVINO's model conversion swallows it: then
    the graph stops once it is made (a node process ends in any case: `process.run`).
    """

    def __init__(self):
        self.reason: str | None = None
        self.starting = False
        self._previous = {}

    def install(self) -> None:
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self._on_signal)

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    def _on_signal(self, signum, frame) -> None:
        name = 'Ctrl-C' if signum == signal.SIGINT else signal.Signals(signum).name
        if self.reason is None:
            self.reason = name
            if self.starting:
                raise KeyboardInterrupt
        else:
            try:
                print(f'\n{name}: already stopping the nodes and closing the recording, '
                      'please wait', file=sys.stderr, flush=True)
            except RuntimeError:    # the signal came in the middle of another print
                pass
