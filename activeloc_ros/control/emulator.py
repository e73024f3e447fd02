"""
An emulated ``braccio_serial.ino`` on a pseudo-terminal, for tests and for trying the
serial back end without hardware.

The host side opens ``emulator.path``: a symlink to the pty's slave, like the udev links
under /dev/serial/by-id, so the port can vanish and come back under the same name. Every
``poll_ms`` the emulator answers the frames that arrived, like the sketch's loop; the
joints follow their targets one degree per ``step_delay_ms`` (``SimArm``).

Run ``python -m activeloc_ros.control.emulator`` to get a port for ``arm_node``'s
``port`` parameter.
"""
import os
import tempfile
import threading
import time
import tty
from typing import Sequence

from activeloc_ros.control import protocol
from activeloc_ros.control.braccio import SAFETY_DEG
from activeloc_ros.control.sim_arm import SimArm


class ArduinoEmulator:
    """The sketch's behaviour on the master side of a pty, in a background thread."""

    def __init__(self, *, path: str | None = None, start_deg: Sequence[int] = SAFETY_DEG,
                 step_delay_ms: float = 20.0, poll_ms: float = 20.0, t0: float | None = None):
        self.path = path or os.path.join(tempfile.mkdtemp(prefix='braccio-'), 'ttyBRACCIO')
        self.poll = poll_ms / 1000.0
        # t0: the clock ``step`` is driven with (monotonic in the background thread; a test
        # may drive ``step`` itself in simulated time instead of calling ``start``).
        self.arm = SimArm(start_deg, time.monotonic() if t0 is None else t0,
                          step_delay_ms=step_delay_ms)
        self.received: list[protocol.Frame] = []
        self.silent = False
        self._lock = threading.Lock()
        self._outbox = bytearray()
        self._reader = protocol.FrameReader()
        self._master: int | None = None
        self._slave: int | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.reappear()

    # -- the device ------------------------------------------------------------------------

    def reappear(self) -> None:
        """Plug the device in (again): a fresh pty behind ``path``."""
        with self._lock:
            master, slave = os.openpty()
            tty.setraw(slave)  # no echo of our own answers before the host sets raw mode
            os.set_blocking(master, False)
            self._master, self._slave = master, slave
            self._reader = protocol.FrameReader()
            tmp = self.path + '.new'
            if os.path.lexists(tmp):
                os.unlink(tmp)
            os.symlink(os.ttyname(slave), tmp)
            os.replace(tmp, self.path)

    def vanish(self) -> None:
        """Unplug the device: the host's descriptor fails and the path disappears."""
        with self._lock:
            if os.path.lexists(self.path):
                os.unlink(self.path)
            for fd in (self._master, self._slave):
                if fd is not None:
                    os.close(fd)
            self._master = self._slave = None

    def inject(self, data: bytes) -> None:
        """Send raw bytes (noise, malformed frames) to the host with the next answers."""
        with self._lock:
            self._outbox += data

    @property
    def joints(self) -> tuple[int, ...]:
        return self.arm.joints

    def host_writes(self) -> list[tuple[int, ...]]:
        """Targets of the ``<w>`` frames received so far."""
        return [f.joints for f in list(self.received) if f.kind == 'w']

    # -- the sketch's loop -----------------------------------------------------------------

    def start(self) -> 'ArduinoEmulator':
        self._thread = threading.Thread(target=self._run, name='arduino-emulator', daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.vanish()

    def __enter__(self) -> 'ArduinoEmulator':
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _run(self) -> None:
        while not self._stop.wait(self.poll):
            self.step(time.monotonic())

    def step(self, now: float) -> None:
        """One pass of the sketch's loop at time ``now``."""
        with self._lock:
            self.arm.advance(now)
            if self._master is None:
                return
            try:
                data = os.read(self._master, 4096)
            except (BlockingIOError, OSError):
                data = b''  # OSError: nobody has the port open
            out = bytearray(self._outbox)
            self._outbox.clear()
            for frame in self._reader.feed(data):
                self.received.append(frame)
                if self.silent:
                    continue
                if frame.kind == 'l':
                    out += protocol.OK
                elif frame.kind == 'r':
                    out += protocol.encode_state(self.arm.joints)
                elif frame.kind == 'w':
                    self.arm.command(frame.joints, now)
                    out += protocol.encode_state(self.arm.joints)
                else:
                    out += protocol.ERROR
            if out:
                try:
                    os.write(self._master, bytes(out))
                except OSError:
                    pass


def main() -> None:
    with ArduinoEmulator() as emulator:
        print(f'emulated Braccio on {emulator.path} (Ctrl-C to stop)', flush=True)
        try:
            threading.Event().wait()
        except KeyboardInterrupt:
            pass


if __name__ == '__main__':
    main()
