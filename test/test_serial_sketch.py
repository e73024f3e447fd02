"""
The real sketch, braccio_serial.ino, compiled for this machine with stand-ins for the
Arduino API, on a pseudo-terminal: BraccioLink against the code that runs on the board.

Skipped where no C++ compiler is installed.
"""
import os
import select
import shutil
import subprocess
import time
import tty

import pytest

from activeloc_ros.control import HOME_DEG, SAFETY_DEG
from activeloc_ros.control import protocol
from activeloc_ros.control.serial_link import BraccioLink, open_serial
from conftest import REPO

SKETCH = REPO / 'activeloc_ros' / 'arduino' / 'braccio_serial' / 'braccio_serial.ino'

ARDUINO_H = r"""
// Host stand-ins for the Arduino API that braccio_serial.ino uses (tests only).
#pragma once
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <string>
#include <fcntl.h>
#include <unistd.h>

inline unsigned long millis() {
  static const auto t0 = std::chrono::steady_clock::now();
  return std::chrono::duration_cast<std::chrono::milliseconds>(
      std::chrono::steady_clock::now() - t0).count();
}

struct HostSerial {  // the board's UART: a pty master passed as SKETCH_FD
  int fd = -1;
  std::string in;
  void begin(long) {
    fd = std::atoi(std::getenv("SKETCH_FD"));
    fcntl(fd, F_SETFL, fcntl(fd, F_GETFL) | O_NONBLOCK);
  }
  int available() {
    char buf[256];
    ssize_t n = ::read(fd, buf, sizeof buf);
    if (n > 0) in.append(buf, n);
    return (int)in.size();
  }
  int read() {
    if (in.empty()) return -1;
    int c = (unsigned char)in[0];
    in.erase(0, 1);
    return c;
  }
  void print(const char *s) { (void)!::write(fd, s, std::strlen(s)); }
  void print(char c) { (void)!::write(fd, &c, 1); }
  void print(int v) { print(std::to_string(v).c_str()); }
};
inline HostSerial Serial;

struct Servo { int value = -1; void write(int v) { value = v; } };
struct BraccioClass { void begin() {} };
inline BraccioClass Braccio;
"""

MAIN = r"""
#include "Braccio.h"
#include "braccio_serial.ino"
#include <thread>
int main() {
  setup();
  for (;;) {
    loop();
    std::this_thread::sleep_for(std::chrono::microseconds(500));
  }
}
"""


@pytest.fixture(scope='module')
def sketch_binary(tmp_path_factory):
    compiler = shutil.which('g++') or shutil.which('c++')
    if compiler is None:
        pytest.skip('no C++ compiler to build the sketch for this machine')
    build = tmp_path_factory.mktemp('sketch')
    (build / 'Braccio.h').write_text(ARDUINO_H)
    (build / 'Servo.h').write_text('#pragma once\n')
    shutil.copy(SKETCH, build / 'braccio_serial.ino')
    (build / 'main.cpp').write_text(MAIN)
    binary = build / 'braccio_serial'
    result = subprocess.run([compiler, '-std=c++17', '-Wall', '-Werror', '-x', 'c++',
                             '-I', str(build), str(build / 'main.cpp'), '-o', str(binary)],
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    return binary


@pytest.fixture
def board(sketch_binary, tmp_path):
    """The sketch running on a pty; yields the port's path (a symlink, like by-id)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    path = tmp_path / 'ttyACM'
    path.symlink_to(os.ttyname(slave))
    process = subprocess.Popen([str(sketch_binary)], pass_fds=(master,),
                               env=dict(os.environ, SKETCH_FD=str(master)))
    try:
        yield str(path)
    finally:
        process.terminate()
        process.wait()
        os.close(master)
        os.close(slave)


def poll_until(link, condition, timeout):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not condition():
        fd = link.fileno()
        if fd is not None:
            select.select([fd], [], [], 0.005)  # wake on the sketch's answer
        else:
            select.select([], [], [], 0.005)
        link.poll(time.monotonic())
    return condition()


def test_the_link_drives_the_real_sketch(board):
    link = BraccioLink(board)
    try:
        assert poll_until(link, lambda: link.joints is not None, 5.0)
        assert link.joints == SAFETY_DEG
        link.command(HOME_DEG)
        assert poll_until(link, lambda: link.joints == HOME_DEG, 10.0)
        assert link.stats.problems == 0
    finally:
        link.close()


def ask(port, frame: bytes, count=1, timeout=2.0) -> list[protocol.Frame]:
    port.write(frame)
    reader, frames = protocol.FrameReader(), []
    deadline = time.monotonic() + timeout
    while len(frames) < count and time.monotonic() < deadline:
        if select.select([port.fileno()], [], [], 0.05)[0]:
            frames += reader.feed(port.read(256))
    return frames


@pytest.mark.parametrize('frame, answers', [
    (b'<l>', ['ok']), (b'<r>', ['s']), (b'<w,90,90,45,45,90,73>', ['s']),
    (b'<w,90,90,45,45,90>', ['e']),               # five joints
    (b'<w,90,90,45,45,90,73,1>', ['e']),          # seven
    (b'<w,90,14,45,45,90,73>', ['e']),            # shoulder below its limit
    (b'<w,90,90,45,45,90,x>', ['e']), (b'<hello>', ['e']),
    (b'noise<l>', ['ok']), (b'<w,' + b'1' * 60 + b'><l>', ['e', 'ok'])])  # overlong
def test_the_sketch_answers_each_frame(board, frame, answers):
    port = open_serial(board)
    try:
        frames = ask(port, frame, count=len(answers))
        assert [f.kind for f in frames] == answers
        if frame.startswith(b'<w,') and answers[0] == 'e':
            state = ask(port, b'<r>')[0]
            assert state.joints == SAFETY_DEG  # a refused target is not taken
    finally:
        port.close()
