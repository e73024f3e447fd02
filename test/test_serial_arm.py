"""
The serial back end: the protocol, and BraccioLink against an emulated sketch on a pty.

The emulator and the link are stepped in the same simulated time (the emulator every 20 ms,
like the sketch's loop), so these tests are deterministic and need no sleeps.
"""
import os

import pytest

from activeloc_ros.control import HOME_DEG, SAFETY_DEG
from activeloc_ros.control import protocol
from activeloc_ros.control.emulator import ArduinoEmulator
from activeloc_ros.control.serial_link import BraccioLink, open_serial
from activeloc_ros.errors import ArmLinkError, ConfigError


# -- the protocol -----------------------------------------------------------------------------

def test_encode_rounds_to_whole_degrees():
    assert protocol.encode_write([90.4, 89.6, 45, 45.5, 0, 73]) == b'<w,90,90,45,46,0,73>'
    with pytest.raises(ValueError):
        protocol.encode_write([90] * 5)


@pytest.mark.parametrize('body, kind, joints', [
    ('ok', 'ok', None), ('r', 'r', None), ('l', 'l', None), ('e', 'e', None),
    ('s,90,90,45,45,90,73', 's', (90, 90, 45, 45, 90, 73)),
    ('w,0,15,0,0,0,10', 'w', (0, 15, 0, 0, 0, 10)),
    ('s,90,90,45,45,90', 'bad', None),                 # five joints
    ('s,90,90,45,45,90,73,1', 'bad', None),            # seven
    ('s,90,x,45,45,90,73', 'bad', None),               # not a number
    ('s,90,9.5,45,45,90,73', 'bad', None),
    ('s,181,90,45,45,90,73', 'bad', None),             # out of range
    ('s,90,14,45,45,90,73', 'bad', None),              # shoulder below 15
    ('w,90,90,45,45,90,74', 'bad', None),              # gripper above 73
    ('ok,1', 'bad', None), ('zz', 'bad', None), ('', 'bad', None)])
def test_decode(body, kind, joints):
    frame = protocol.decode(body)
    assert (frame.kind, frame.joints) == (kind, joints)


def test_reader_splits_frames_and_counts_noise():
    reader = protocol.FrameReader()
    frames = reader.feed(b'xx<s,90,90,4')
    frames += reader.feed(b'5,45,90,73>\r\n<o')
    frames += reader.feed(b'k>junk<s,1<ok>')  # '<' inside a frame starts a new one
    assert [f.kind for f in frames] == ['s', 'ok', 'ok']
    assert reader.noise_bytes == len('xx') + len('junk') + len('<s,1')


def test_reader_drops_overlong_and_binary_frames():
    reader = protocol.FrameReader()
    frames = reader.feed(b'<' + b'9' * 100 + b'><\xff\x00><ok>')
    assert [f.kind for f in frames] == ['bad', 'ok']
    assert reader.overlong == 1 and reader.noise_bytes >= 100


# -- the link against the emulated sketch ----------------------------------------------------

class Bench:
    """A link and an emulator in one simulated clock."""

    def __init__(self, tmp_path, **link_options):
        self.t = 0.0
        self.emulator = ArduinoEmulator(path=str(tmp_path / 'ttyBRACCIO'), t0=0.0)
        self.link = BraccioLink(self.emulator.path, **link_options)
        self._next_loop = 0.0

    def run(self, seconds: float, until=None) -> list[str]:
        events = []
        end = self.t + seconds
        while self.t < end - 1e-9:
            self.t += 0.005
            events += self.link.poll(self.t)
            if self.t >= self._next_loop:  # the sketch's 20 ms loop
                self.emulator.step(self.t)
                self._next_loop += 0.02
            if until is not None and until():
                break
        return events

    def close(self):
        self.link.close()
        self.emulator.vanish()


@pytest.fixture
def bench(tmp_path):
    b = Bench(tmp_path)
    yield b
    b.close()


def test_handshake_then_the_echoed_state(bench):
    events = bench.run(0.2)
    assert bench.link.state == 'connected'
    assert any('connected' in e for e in events)
    assert bench.link.joints == SAFETY_DEG  # where Braccio.begin() left the arm
    assert bench.emulator.received[0].kind == 'l'
    assert os.get_blocking(bench.link.fileno()) is False  # poll can never block


def test_commands_are_followed_at_the_servos_speed(bench):
    bench.run(0.1)
    bench.link.command([10.4, 40, 180, 170, 0, 73])
    bench.run(0.1)
    assert bench.emulator.host_writes() == [(10, 40, 180, 170, 0, 73)]
    assert 0 < bench.link.joints[0] <= 6  # 20 ms per degree
    bench.run(0.5)
    assert bench.link.joints == (10, 40, 180, 170, 0, 73)
    assert not bench.link.busy


def test_the_newest_command_wins(bench):
    bench.run(0.1)
    for base in range(20, 31):
        bench.link.command([base, 40, 180, 170, 0, 73])
    bench.run(0.2)
    assert bench.emulator.host_writes() == [(30, 40, 180, 170, 0, 73)]


def test_a_lost_or_garbled_write_is_sent_again(bench):
    """
    A write is sent once per new target: lost (no answer) or garbled on the way (the
    sketch answers <e>), the arm stayed short of it, a hold or a stop's home pose for good.
    """
    bench.run(0.1)
    bench.emulator.silent = True                    # this write is never answered
    bench.link.command([30, 40, 180, 170, 0, 73])
    bench.run(0.05)
    bench.emulator.silent = False
    bench.run(2.5)
    assert bench.link.joints == (30, 40, 180, 170, 0, 73) and not bench.link.busy
    target = (40, 40, 180, 170, 0, 73)
    bench.emulator.silent = True
    bench.link.command(target)
    bench.run(0.03)                                 # written, not taken
    bench.emulator.silent = False
    bench.emulator.inject(b'<e>')                   # the sketch's answer to a garbled write
    bench.run(0.1)                                  # well within the 0.2 s reply timeout
    assert bench.emulator.host_writes()[-2:] == [target, target]
    bench.run(1.0)
    assert bench.link.joints == target and not bench.link.busy
    assert bench.link.state == 'connected' and bench.link.stats.losses == 0


def test_noise_malformed_and_out_of_range_frames_are_counted_and_ignored(bench):
    bench.run(0.1)
    bench.link.command(HOME_DEG)
    bench.emulator.inject(b'\x00\xffnoise<s,1,2,3><s,999,90,45,45,90,73><hello>'
                          b'<s,90,90,45,45,90,' + b'7' * 80 + b'>')
    bench.run(3.5)  # 135 degrees of elbow at 20 ms per degree
    stats = bench.link.stats
    assert stats.bad_frames >= 3 and stats.noise_bytes >= 7
    assert bench.link.state == 'connected' and stats.losses == 0
    assert bench.link.joints == HOME_DEG  # garbage never became a state


def test_a_state_faster_than_the_servos_is_refused_as_implausible(bench):
    """
    Serial garbage that happens to parse as a state (the hostile test: a 750 deg/s jump)
    never becomes the arm's state; the real echo that follows does.
    """
    bench.run(0.2)
    here = bench.link.joints
    bench.emulator.inject(b'<s,170,40,100,10,150,20>')
    bench.run(0.1, until=lambda: bench.link.stats.implausible > 0)
    assert bench.link.stats.implausible == 1
    assert bench.link.joints == here and 'faster than the servos' in bench.link.stats.last_bad
    bench.run(0.1)
    assert bench.link.joints == here and bench.link.stats.states > 3   # the echo goes on
    bench.link.command([30, 40, 180, 170, 0, 73])                      # real motion is
    bench.run(3.0)                                                     # believed
    assert bench.link.joints == (30, 40, 180, 170, 0, 73)
    assert bench.link.stats.implausible == 1


def test_a_silent_arm_is_detected_and_reconnected(bench):
    bench.run(0.1)
    bench.link.command(HOME_DEG)
    bench.emulator.silent = True
    events = bench.run(1.5, until=lambda: bench.link.state != 'connected')
    assert any('silent' in e for e in events) and bench.link.state == 'closed'
    bench.run(1.5)
    assert bench.link.state == 'handshake'  # re-opened, still no <ok>
    bench.emulator.silent = False
    events = bench.run(2.0, until=lambda: bench.link.state == 'connected')
    assert bench.link.state == 'connected' and bench.link.stats.connects == 2


def test_a_vanished_port_is_reported_and_reopened_when_it_returns(bench):
    bench.run(0.1)
    bench.link.command(HOME_DEG)
    bench.run(0.1)
    bench.emulator.vanish()
    events = bench.run(0.1)
    assert bench.link.state == 'closed'
    assert any('lost' in e for e in events)
    events = bench.run(3.0)  # the port is gone: retried quietly
    assert sum('cannot open' in e for e in events) == 1
    writes = len(bench.emulator.host_writes())
    bench.emulator.reappear()
    events = bench.run(1.5, until=lambda: len(bench.emulator.host_writes()) > writes)
    assert bench.link.state == 'connected' and bench.link.stats.losses == 1
    assert bench.emulator.host_writes()[-1] == HOME_DEG  # the last target is sent again


def test_the_link_answers_nothing_on_a_missing_or_bad_port(tmp_path):
    with pytest.raises(ArmLinkError, match='cannot open'):
        open_serial(str(tmp_path / 'nothing'))
    plain = tmp_path / 'file'
    plain.write_text('')
    with pytest.raises(ArmLinkError, match='not a usable serial port'):
        open_serial(str(plain))
    link = BraccioLink(str(tmp_path / 'nothing'))
    assert link.poll(0.0) and link.state == 'closed' and link.poll(0.1) == []


@pytest.mark.parametrize('options', [
    {'poll_period': 0.0}, {'silence_timeout': -1.0}, {'baud': 12345},
    {'reconnect_period': float('nan')}])
def test_bad_link_options_are_refused(options):
    with pytest.raises(ConfigError):
        BraccioLink('/dev/null', **options)
