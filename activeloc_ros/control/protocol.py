"""
The ASCII serial protocol between the host and ``braccio_serial.ino`` (115200 baud, 8N1).

Host -> Arduino:  ``<w,d0,d1,d2,d3,d4,d5>`` set targets (whole degrees, JOINT_NAMES order),
                  ``<r>`` read the state, ``<l>`` are you alive?
Arduino -> host:  ``<s,d0,d1,d2,d3,d4,d5>`` the joints' current positions (the answer to
                  ``<w>`` and ``<r>``; the servos give no feedback, so this is what the
                  sketch drives them to), ``<ok>`` the answer to ``<l>``, ``<e>`` a frame it
                  could not use.
Bytes outside ``<...>`` are noise; a frame longer than MAX_FRAME is dropped.
"""
from dataclasses import dataclass
import math
from typing import Sequence

from activeloc_ros.control.braccio import JOINT_NAMES, within_limits

MAX_FRAME = 48
BAUD = 115200


def encode_write(joints_deg: Sequence[float]) -> bytes:
    """``<w,...>`` with the angles rounded to whole degrees."""
    if len(joints_deg) != len(JOINT_NAMES) or not all(math.isfinite(q) for q in joints_deg):
        raise ValueError(f'need {len(JOINT_NAMES)} finite angles, got {tuple(joints_deg)}')
    return ('<w,' + ','.join(str(int(round(q))) for q in joints_deg) + '>').encode('ascii')


def encode_state(joints_deg: Sequence[int]) -> bytes:
    return ('<s,' + ','.join(str(int(q)) for q in joints_deg) + '>').encode('ascii')


READ = b'<r>'
ALIVE = b'<l>'
OK = b'<ok>'
ERROR = b'<e>'


@dataclass(frozen=True)
class Frame:
    """
    A decoded frame: ``kind`` is 'w', 'r', 'l', 's', 'ok', 'e' or 'bad' (with a reason);
    ``joints`` is set for 'w' and 's'.
    """

    kind: str
    joints: tuple[int, ...] | None = None
    reason: str = ''


def _ints(fields: list[str]) -> tuple[int, ...] | None:
    try:
        values = tuple(int(f) for f in fields)
    except ValueError:
        return None
    return values if len(values) == len(JOINT_NAMES) else None


def decode(body: str) -> Frame:
    """Decode the text between ``<`` and ``>``; malformed or out-of-range frames are 'bad'."""
    fields = body.split(',')
    head = fields[0]
    if head in ('r', 'l', 'ok', 'e') and len(fields) == 1:
        return Frame(head)
    if head in ('w', 's'):
        joints = _ints(fields[1:])
        if joints is None:
            return Frame('bad', reason=f'malformed {head!r} frame <{body}>')
        if not within_limits(joints):
            return Frame('bad', reason=f'out-of-range {head!r} frame <{body}>')
        return Frame(head, joints)
    return Frame('bad', reason=f'unknown frame <{body}>')


class FrameReader:
    """Splits a byte stream into frames; counts noise bytes and overlong frames."""

    def __init__(self):
        self._buf = bytearray()
        self._in_frame = False
        self.noise_bytes = 0
        self.overlong = 0

    def feed(self, data: bytes) -> list[Frame]:
        frames = []
        for byte in data:
            if byte == 0x3C:  # '<' starts a frame, even inside a broken one
                if self._in_frame:
                    self.noise_bytes += len(self._buf) + 1
                self._buf.clear()
                self._in_frame = True
            elif not self._in_frame:
                if byte not in b'\r\n':
                    self.noise_bytes += 1
            elif byte == 0x3E:  # '>'
                self._in_frame = False
                try:
                    body = self._buf.decode('ascii')
                except UnicodeDecodeError:
                    body = None
                self._buf.clear()
                frames.append(decode(body) if body is not None and body.isprintable()
                              else Frame('bad', reason='non-ASCII frame'))
            else:
                self._buf.append(byte)
                if len(self._buf) > MAX_FRAME:
                    self.overlong += 1
                    self.noise_bytes += len(self._buf)
                    self._buf.clear()
                    self._in_frame = False
        return frames
