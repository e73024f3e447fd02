"""
The serial link to ``braccio_serial.ino`` over pyserial, never blocking.

``BraccioLink.poll(now)`` does a bounded amount of non-blocking I/O and returns at once, so
a ROS timer can drive it without ever blocking the executor. It opens the port, waits for
``<ok>`` (an Arduino resets when its port opens), then alternates one request at a time:
``<w,...>`` when a new target is pending, else ``<r>``. A port that vanishes or goes silent
is closed and re-opened every ``reconnect_period`` until it answers again.
"""
from dataclasses import dataclass
import math
from typing import Sequence

import serial

from activeloc_ros.control import protocol
from activeloc_ros.control.sim_arm import quantize
from activeloc_ros.errors import ArmLinkError, ConfigError

BAUDS = (9600, 19200, 38400, 57600, 115200)


def open_serial(path: str, baud: int = protocol.BAUD) -> serial.Serial:
    """
    Open ``path`` raw 8N1 at ``baud`` for this process alone; reads and writes return at
    once (timeout 0).

    Raises ArmLinkError when the port is missing, busy or not a terminal.
    """
    if baud not in BAUDS:
        raise ArmLinkError(f'unsupported baud rate {baud}; use one of {list(BAUDS)}')
    try:
        return serial.Serial(path, baud, timeout=0, write_timeout=0, exclusive=True)
    except (serial.SerialException, ValueError) as exc:
        if getattr(exc, 'errno', None):  # the open itself failed
            raise ArmLinkError(f'cannot open {path}: {exc.strerror or exc}') from exc
        raise ArmLinkError(f'{path} is not a usable serial port: {exc}') from exc


@dataclass
class LinkStats:
    """Counters of what came over the link."""

    states: int = 0
    noise_bytes: int = 0
    bad_frames: int = 0
    rejected: int = 0  # '<e>' answers: the sketch refused one of our frames
    implausible: int = 0  # states that moved faster than the servos can: not the arm's
    writes: int = 0    # '<w>' commands sent
    blocked_writes: int = 0
    connects: int = 0
    losses: int = 0
    last_bad: str = ''

    @property
    def problems(self) -> int:
        return self.noise_bytes + self.bad_frames + self.rejected + self.implausible


class BraccioLink:
    """
    State machine ``closed`` -> ``handshake`` -> ``connected``, driven by ``poll(now)``.

    :param poll_period: seconds between requests (the sketch polls every 20 ms).
    :param reply_timeout: a request unanswered this long is superseded by the next one.
    :param silence_timeout: connected but no valid frame this long: the link is lost.
    :param handshake_timeout: no ``<ok>`` this long after opening: close and retry.
    :param reconnect_period: seconds between attempts to re-open the port.
    """

    def __init__(self, path: str, *, baud: int = protocol.BAUD, poll_period: float = 0.02,
                 reply_timeout: float = 0.2, silence_timeout: float = 1.0,
                 handshake_timeout: float = 4.0, reconnect_period: float = 1.0,
                 handshake_period: float = 0.25, max_speed_deg_s: float = 50.0):
        for name, value in (('poll_period', poll_period), ('reply_timeout', reply_timeout),
                            ('silence_timeout', silence_timeout),
                            ('handshake_timeout', handshake_timeout),
                            ('reconnect_period', reconnect_period),
                            ('handshake_period', handshake_period)):
            if not math.isfinite(value) or value <= 0:
                raise ConfigError(f'{name} must be > 0 s, got {value}')
        if not (math.isfinite(max_speed_deg_s) and max_speed_deg_s > 0):
            raise ConfigError(f'max_speed_deg_s must be > 0, got {max_speed_deg_s}')
        if baud not in BAUDS:
            raise ConfigError(f'unsupported baud rate {baud}; use one of {list(BAUDS)}')
        self.path = path
        self.baud = baud
        self.poll_period = poll_period
        self.reply_timeout = reply_timeout
        self.silence_timeout = silence_timeout
        self.handshake_timeout = handshake_timeout
        self.reconnect_period = reconnect_period
        self.handshake_period = handshake_period
        self.max_speed_deg_s = max_speed_deg_s
        self.stats = LinkStats()
        self.state = 'closed'
        self.joints: tuple[int, ...] | None = None
        self.joints_time = -math.inf
        self.target: tuple[int, ...] | None = None
        self._port: serial.Serial | None = None
        self._reader = protocol.FrameReader()
        self._tx = bytearray()
        self._pending = False
        self._next_open = -math.inf
        self._open_failed = False
        self._t_opened = 0.0
        self._last_rx = 0.0
        self._next_request = 0.0
        self._awaiting_since: float | None = None
        self._write_unanswered = False

    # -- commands --------------------------------------------------------------------------

    def command(self, joints_deg: Sequence[float]) -> None:
        """Ask for new targets (clamped, whole degrees); the newest one wins."""
        target = quantize(joints_deg)
        if target != self.target:
            self.target = target
            self._pending = True

    @property
    def busy(self) -> bool:
        """True until the newest target has been sent and answered with a state."""
        return self._pending or self._write_unanswered

    def fileno(self) -> int | None:
        """The open descriptor (non-blocking), or None while closed."""
        return self._port.fileno() if self._port is not None else None

    def fresh(self, now: float) -> bool:
        """True when the echoed state is newer than the silence timeout."""
        return self.joints is not None and now - self.joints_time <= self.silence_timeout

    # -- I/O -------------------------------------------------------------------------------

    def poll(self, now: float) -> list[str]:
        """Do the pending non-blocking I/O; return descriptions of state changes."""
        events: list[str] = []
        if self._port is None:
            if now < self._next_open:
                return events
            self._open(now, events)
            if self._port is None:
                return events
        if not self._read(now, events):
            return events
        if self.state == 'handshake' and now - self._t_opened > self.handshake_timeout:
            self._lose(now, events, f'no <ok> within {self.handshake_timeout:g} s')
            return events
        if self.state == 'connected' and now - self._last_rx > self.silence_timeout:
            self._lose(now, events, f'silent for {now - self._last_rx:.1f} s')
            return events
        self._request(now)
        self._flush(now, events)
        return events

    def close(self) -> None:
        if self._port is not None:
            try:
                self._port.close()
            except (serial.SerialException, OSError):
                pass  # a vanished device: nothing left to close
        self._port = None
        self.state = 'closed'

    def _plausible(self, joints: tuple[int, ...], now: float) -> bool:
        """
        Could the servos have gone from the last state to ``joints`` by ``now``? A frame
        that passes the checksum-free protocol by chance usually could not. (One whole
        degree of rounding, and a poll's lateness, are slack.) The allowance grows with
        the time since the last state, so a refused arm is believed again soon.
        """
        if self.joints is None:
            return True
        dt = max(now - self.joints_time, 0.0) + self.poll_period
        allowed = self.max_speed_deg_s * dt + 1.0
        return max(abs(a - b) for a, b in zip(joints, self.joints)) <= allowed

    def _open(self, now: float, events: list[str]) -> None:
        try:
            self._port = open_serial(self.path, self.baud)
        except ArmLinkError as exc:
            self._next_open = now + self.reconnect_period
            if not self._open_failed:
                events.append(f'{exc}; retrying every {self.reconnect_period:g} s')
                self._open_failed = True
            return
        self._open_failed = False
        self.state = 'handshake'
        self.joints = None           # whatever the arm did while the link was down
        self._t_opened = self._last_rx = now
        self._reader = protocol.FrameReader()
        self._tx.clear()
        self._awaiting_since = None
        self._next_request = now
        events.append(f'opened {self.path}, waiting for <ok>')

    def _lose(self, now: float, events: list[str], reason: str) -> None:
        was_connected = self.state == 'connected'
        self.close()
        self.stats.losses += 1
        self._next_open = now + self.reconnect_period
        self._pending = self.target is not None  # re-send the last target after reconnecting
        self._write_unanswered = False
        events.append(f'link to {self.path} lost: {reason}' if was_connected
                      else f'{self.path}: {reason}')

    def _read(self, now: float, events: list[str]) -> bool:
        chunks = []
        for _ in range(16):  # bounded: at most 64 KiB per poll
            try:
                data = self._port.read(4096)
            except serial.SerialException as exc:  # unplugged: read fails or hangs up
                self._lose(now, events, f'port vanished ({exc})')
                return False
            if not data:
                break
            chunks.append(data)
        if not chunks:
            return True
        reader = self._reader
        noise_before = reader.noise_bytes
        for frame in reader.feed(b''.join(chunks)):
            self._handle(frame, now, events)
        self.stats.noise_bytes += reader.noise_bytes - noise_before
        return True

    def _handle(self, frame: protocol.Frame, now: float, events: list[str]) -> None:
        if frame.kind == 'ok':
            self._last_rx = now
            self._awaiting_since = None
            if self.state == 'handshake':
                self.state = 'connected'
                self._next_request = now
                self.stats.connects += 1
                events.append(f'connected to the arm on {self.path}')
        elif frame.kind == 's' and self.state == 'connected':
            self._last_rx = now
            self._awaiting_since = None
            if not self._plausible(frame.joints, now):
                self.stats.implausible += 1
                self.stats.last_bad = (f'a state {frame.joints} that moved faster than the '
                                       f'servos ({self.max_speed_deg_s:g} deg/s)')
                return
            self.joints = frame.joints
            self.joints_time = now
            self._write_unanswered = False
            self.stats.states += 1
        elif frame.kind == 'e':
            self._awaiting_since = None
            self.stats.rejected += 1
            if self._write_unanswered:   # the write came garbled: send the target again
                self._write_unanswered = False
                self._pending = self.target is not None
        elif frame.kind == 'bad':
            self.stats.bad_frames += 1
            self.stats.last_bad = frame.reason
        # Anything else (a state before the handshake, an echoed request) is ignored.

    def _request(self, now: float) -> None:
        if self._tx:
            return
        if self.state == 'handshake':
            if now >= self._next_request:
                self._tx += protocol.ALIVE
                self._next_request = now + self.handshake_period
            return
        if self.state != 'connected' or now < self._next_request:
            return
        if self._awaiting_since is not None and now - self._awaiting_since < self.reply_timeout:
            return
        if self._awaiting_since is not None and self._write_unanswered:
            self._pending = self.target is not None    # the write was lost: send it again
        if self._pending and self.target is not None:
            self._tx += protocol.encode_write(self.target)
            self.stats.writes += 1
            self._pending = False
            self._write_unanswered = True
        else:
            self._tx += protocol.READ
        self._awaiting_since = now
        self._next_request = now + self.poll_period

    def _flush(self, now: float, events: list[str]) -> None:
        if not self._tx or self._port is None:
            return
        try:
            n = self._port.write(bytes(self._tx))
        except serial.SerialTimeoutException:  # the output buffer is full: try next poll
            self.stats.blocked_writes += 1
            return
        except serial.SerialException as exc:
            self._lose(now, events, f'port vanished ({exc})')
            return
        del self._tx[:n]
