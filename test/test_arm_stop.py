"""
Ctrl-C on the real node processes: the arm stops on purpose before the context ends,
and a node still being made (an int8 encoder built on first use) stops at once.
"""
import math
import os
import signal
import subprocess
import sys
import time

import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from activeloc_ros.control import HOME_DEG, JOINT_NAMES
from activeloc_ros.control.emulator import ArduinoEmulator
from conftest import params_args, REPO, spin_until


def command(joints_deg) -> JointState:
    return JointState(name=list(JOINT_NAMES), position=[math.radians(q) for q in joints_deg])


@pytest.fixture
def probe(context):
    node = Node('stop_probe', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    yield node, executor
    executor.shutdown()
    node.destroy_node()


@pytest.fixture
def launch(tmp_path):
    """Start `activeloc_ros.<module>` with its params file; stop leftovers at teardown."""
    started = []

    def start(module: str, *overrides: str, env: dict | None = None) -> subprocess.Popen:
        log = open(tmp_path / f'{module}.log', 'w')
        process = subprocess.Popen(
            [sys.executable, '-m', f'activeloc_ros.nodes.{module}',
             *params_args(*overrides)],
            cwd=REPO, env=dict(os.environ, PYTHONUNBUFFERED='1', **(env or {})), stdout=log,
            stderr=subprocess.STDOUT)
        started.append((process, log))
        return process

    yield start
    for process, log in started:
        if process.poll() is None:
            process.kill()
            process.wait()
        log.close()


def wait_for_log(process, log, text: str, timeout: float) -> None:
    """Until ``text`` is in the node's log (at most ``timeout`` s); the node must live."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and text not in log.read_text():
        assert process.poll() is None, log.read_text()
        time.sleep(0.05)


def interrupt(process, executor, timeout=15.0) -> int:
    """Ctrl-C, spinning our side meanwhile so the node's last messages arrive."""
    process.send_signal(signal.SIGINT)
    spin_until(executor, lambda: process.poll() is not None, timeout)
    return process.wait(timeout=1.0)


def test_controller_holds_on_ctrl_c(probe, launch, tmp_path):
    node, executor = probe
    commands = []
    node.create_subscription(JointState, 'joint_commands', commands.append,
                             QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    states = node.create_publisher(JointState, 'joint_states', 10)
    process = launch('controller_node')
    assert spin_until(executor, lambda: node.count_publishers('joint_commands') > 0
                      and states.get_subscription_count() > 0, 20.0)
    where = (120.0, 90.0, 45.0, 60.0, 90.0, 73.0)
    msg = command(where)
    msg.header.stamp = node.get_clock().now().to_msg()
    node.create_timer(0.05, lambda: states.publish(msg))  # the arm is here: hold it here
    spin_until(executor, lambda: False, 1.0)  # (the other side may discover us later)
    assert interrupt(process, executor) == 0, (tmp_path / 'controller_node.log').read_text()
    assert spin_until(executor, lambda: commands, 2.0)
    assert [math.degrees(p) for p in commands[-1].position] == pytest.approx(where)
    assert 'stopped: arm told to hold' in (tmp_path / 'controller_node.log').read_text()


@pytest.mark.parametrize('mode', ['hold', 'home'])
def test_serial_arm_stops_on_purpose_on_ctrl_c(probe, launch, tmp_path, mode):
    node, executor = probe
    pub = node.create_publisher(JointState, 'joint_commands',
                                QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE))
    start = (40, 90, 45, 45, 90, 73)
    with ArduinoEmulator(path=str(tmp_path / 'ttyBRACCIO'), start_deg=start,
                         step_delay_ms=30) as emulator:
        process = launch('arm_node', 'backend:=serial', f'port:={emulator.path}',
                         f'stop_mode:={mode}', 'home_speed_deg_s:=60.0')
        assert spin_until(executor, lambda: pub.get_subscription_count() > 0, 20.0)
        assert spin_until(executor, lambda: any(f.kind == 'r' for f in emulator.received), 10.0)
        pub.publish(command((170.0,) + HOME_DEG[1:]))  # a long move, 4 s at 30 ms/deg
        assert spin_until(executor, lambda: emulator.joints[0] > 50, 10.0)
        log = tmp_path / 'arm_node.log'
        base_at_interrupt = emulator.joints[0]
        assert interrupt(process, executor) == 0, log.read_text()
        assert f'stopped ({mode})' in log.read_text()
        last = emulator.host_writes()[-1]
        if mode == 'hold':  # stopped on the way, where it was (its echo is <= 20 ms old)
            assert base_at_interrupt - 2 <= last[0] < 170
        else:
            assert last == HOME_DEG
        deadline = time.monotonic() + 5.0  # the emulated servos settle on the last target
        while emulator.joints != last and time.monotonic() < deadline:
            spin_until(executor, lambda: emulator.joints == last, 0.1)
        assert emulator.joints == last


def test_sim_arm_goes_home_slowly_on_ctrl_c(probe, launch, tmp_path):
    node, executor = probe
    states = []
    node.create_subscription(JointState, 'joint_states', states.append, QoSProfile(depth=500))
    process = launch('arm_node', 'backend:=sim', 'stop_mode:=home',
                     'sim_start_deg:=[60,90,45,45,90,73]', 'home_speed_deg_s:=30.0')
    assert spin_until(executor, lambda: states, 20.0)
    assert interrupt(process, executor) == 0
    bases = [round(math.degrees(s.position[0])) for s in states]
    assert bases[-1] == HOME_DEG[0]
    assert bases == sorted(bases) and len(set(bases)) > 10  # on its way, step by step


@pytest.mark.parametrize('module', ['arm_node', 'camera_node'])
def test_a_burst_of_sigterms_stops_a_node_cleanly(launch, tmp_path, module):
    """
    A dying parent can signal its nodes more than once. A signal landing inside the
    stop handler once deadlocked the camera for good (threading.Event.set in a handler).
    """
    overrides = ('backend:=sim',) if module == 'arm_node' else ('loop:=true',)
    process = launch(module, *overrides)
    log = tmp_path / f'{module}.log'
    wait_for_log(process, log, '[INFO]', 30)
    for _ in range(400):                  # spread over the node's stop (about a second)
        if process.poll() is not None:
            break
        process.send_signal(signal.SIGTERM)
        time.sleep(0.002)
    # (one that lands while Python ends the process is ignored: process.ignore_late_stops)
    assert process.wait(timeout=15) == 0
    text = log.read_text()
    assert 'stopped' in text and 'Traceback' not in text, text[-2000:]


def test_a_node_that_ended_by_itself_survives_a_stop_in_its_last_moments(graph_env):
    """
    bringup stops a graph's source the moment its run is over: once in nine runs the
    Ctrl-C landed after the node's own end, while Python ended the process with its
    handlers back at the default, and the sim exited -2 with an error on the console.
    Stopped many times, at random moments in the fraction of a second after the end.
    """
    import random
    rng = random.Random(62)
    for attempt in range(8):
        node = subprocess.Popen(
            [sys.executable, '-u', '-m', 'activeloc_ros.nodes.start', 'camera',
             *params_args('max_frames:=2', 'wait_for_subscriber:=0.0')],
            cwd=REPO, env=graph_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True, start_new_session=True)
        try:
            lines = []
            for line in node.stdout:           # as bringup starts it: nodes.start
                lines.append(line)
                if 'max_frames reached' in line:
                    break
            delay = rng.uniform(0.0, 0.4)
            time.sleep(delay)
            node.send_signal(signal.SIGINT)
            out = ''.join(lines) + node.stdout.read()
            code = node.wait(timeout=15)
        finally:
            if node.poll() is None:
                node.kill()
                node.wait()
        assert code == 0, f'attempt {attempt}, Ctrl-C {delay:.3f} s after the end: {out}'
        assert 'Traceback' not in out, out


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_a_stop_while_perception_builds_its_int8_encoder_ends_the_build(launch, tmp_path,
                                                                        sig):
    """
    The first use of an int8 encoder builds it for about a minute before the node is
    ready. A stop then ends the build at once, as on any frame, and leaves no model in the
    cache (bringup once had to SIGKILL the node after 13 s).
    """
    from activeloc_ros.perception.cache import weights_path
    weights = weights_path('vgg19')       # the real weights, in a cache without int8
    cache = tmp_path / 'cache'
    cache.mkdir()
    (cache / weights.name).symlink_to(weights)
    log_path = tmp_path / 'perception_node.log'
    process = launch('perception_node', 'encoder_precision:=int8',
                     env={'ACTIVELOC_CACHE': str(cache)})
    wait_for_log(process, log_path, 'building the int8', 60)
    time.sleep(1.0)                               # into the conversion and calibration
    process.send_signal(sig)
    code = process.wait(timeout=10)
    text = log_path.read_text()
    assert code == 0, text[-2000:]
    assert 'before the node was ready' in text and 'Traceback' not in text, text[-2000:]
    # no model; a build folder only if the start went on (the next build removes it)
    left = [p.name for p in (cache / 'int8').iterdir() if not p.name.startswith('.build-')]
    assert left == []


SWALLOWING_START = """
import sys, time
from activeloc_ros.nodes.process import run

def make_node(context):           # a start that swallows every KeyboardInterrupt
    announce = [True]
    while True:
        try:                          # the signal, sent once 'starting' is read, lands here
            if announce:
                announce.clear()
                print('starting', flush=True)
            time.sleep(30)
            raise SystemExit('the start was not ended')
        except KeyboardInterrupt:
            pass

sys.exit(run(make_node, [], on_stop=lambda node: None))
"""


def test_a_start_that_swallows_the_stop_is_ended_all_the_same(tmp_path):
    """
    Third-party code in a node's start can swallow the KeyboardInterrupt a stop raises
    (OpenVINO's model conversion does): the process ends within the grace all the same.
    """
    from activeloc_ros.nodes.process import START_STOP_GRACE_S
    process = subprocess.Popen([sys.executable, '-c', SWALLOWING_START], cwd=REPO,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                               env=dict(os.environ, PYTHONUNBUFFERED='1'))
    try:
        assert process.stdout.readline().strip() == 'starting'
        process.send_signal(signal.SIGTERM)
        code = process.wait(timeout=START_STOP_GRACE_S + 10)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    text = process.stdout.read()
    assert code == 0 and 'before the node was ready: its start went on' in text, text


EXTENSION_START = """
import ctypes, sys
from activeloc_ros.nodes.process import run

def make_node(context):        # a start inside an extension's call into Python
    call = ctypes.pythonapi.PyRun_String          # (as pybind11's exec does)
    call.restype = ctypes.py_object
    call.argtypes = [ctypes.c_char_p, ctypes.c_int, ctypes.py_object, ctypes.py_object]
    call(b"print('starting', flush=True); import time; time.sleep(30)", 257, {}, {})
    raise SystemExit('the start was not ended')

sys.exit(run(make_node, [], on_stop=lambda node: None))
"""


def test_a_stop_inside_an_extensions_call_into_python_exits_0(tmp_path):
    """
    End with 0 after a Ctrl-C inside an extension's call into Python.

    A KeyboardInterrupt that passes through such a call leaves CPython marked to end a
    ``python -m`` run with SIGINT, however it was caught: perception, stopped 3.5 s into
    its start, once exited -2 after saying it had stopped.
    """
    (tmp_path / 'extension_start.py').write_text(EXTENSION_START)
    process = subprocess.Popen([sys.executable, '-m', 'extension_start'], cwd=tmp_path,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                               env=dict(os.environ, PYTHONPATH=os.pathsep.join(
                                   filter(None, [str(REPO), os.environ.get('PYTHONPATH')]))))
    try:
        assert process.stdout.readline().strip() == 'starting'
        process.send_signal(signal.SIGINT)
        code = process.wait(timeout=10)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    text = process.stdout.read()
    assert code == 0 and 'before the node was ready' in text, (code, text)
