"""Recordings survive what ends them: a full disk, a killed writer (`bag reindex`)."""
import errno
import importlib.util
import subprocess
import sys

import cv2
import numpy as np
import pytest

from activeloc_ros.bag.read import bag_facts
from activeloc_ros.bag.recover import reindex
from activeloc_ros.bag.write import BagWriter, RecordingError
from conftest import REPO

PAYLOAD = 100_000          # bytes a message: about ten to a 1 MiB chunk


def write_bag(path, count, *, wrap_stream=None):
    """A bag of `count` String messages of PAYLOAD bytes; returns how many were written."""
    writer = BagWriter(path, wrap_stream=wrap_stream)
    String = writer.store.types['std_msgs/msg/String']
    written = 0
    try:
        for i in range(count):
            writer.write('/big', 'std_msgs/msg/String', 1000 + i, String(data='x' * PAYLOAD))
            written += 1
    finally:
        try:
            writer.close()
        except RecordingError:
            pass
    return written, writer


def message_count(path) -> int:
    from rosbags.highlevel import AnyReader
    with AnyReader([path]) as reader:
        return sum(1 for _ in reader.messages())


class FillsUp:
    """A file object whose disk is full after `room` bytes."""

    def __init__(self, stream, room):
        self.stream, self.room = stream, room

    def write(self, data):
        if self.stream.tell() + len(data) > self.room:
            raise OSError(errno.ENOSPC, 'No space left on device')
        return self.stream.write(data)

    def __getattr__(self, name):
        return getattr(self.stream, name)


def test_a_full_disk_closes_the_bag_readable_up_to_the_error(tmp_path):
    path = tmp_path / 'bag'
    with pytest.raises(RecordingError, match='No space left'):
        write_bag(path, 60, wrap_stream=lambda s: FillsUp(s, 3_500_000))
    kept = message_count(path)          # metadata.yaml and the index were written
    assert 20 <= kept < 60
    assert [(t.name, t.count) for t in bag_facts(path).topics] == [('/big', kept)]


@pytest.mark.parametrize('cut', [0.5, 0.77, 1.0])
def test_reindex_recovers_every_complete_chunk_of_a_killed_recording(tmp_path, cut):
    whole = tmp_path / 'whole'
    write_bag(whole, 45)
    data = (whole / 'whole.mcap').read_bytes()
    # what a SIGKILL leaves: the data section up to some byte, no summary, no metadata.yaml
    killed = tmp_path / 'killed'
    killed.mkdir()
    footer = data[-8 - 29:-8]                 # opcode, length, summary_start, ...
    data_end = int.from_bytes(footer[9:17], 'little') - 13     # the DataEnd record
    left = data[:int(min(cut * len(data), data_end))]
    (killed / 'killed.mcap').write_bytes(left)
    with pytest.raises(Exception):
        message_count(killed)
    report = reindex(killed)
    assert (killed / 'metadata.yaml').is_file()
    # nothing the writer left is lost: the bytes cut off the bag are kept beside it
    tail = killed / 'killed.mcap.incomplete'
    cut_off = tail.read_bytes() if tail.exists() else b''
    assert (killed / 'killed.mcap').read_bytes()[:len(left) - len(cut_off)] + cut_off == left
    assert cut_off or cut == 1.0
    recovered = message_count(killed)
    assert recovered == report.messages
    assert recovered >= int(cut * 45) - 12     # at most the chunk being written is lost
    assert recovered <= 45


def test_reindex_cli_leaves_a_complete_bag_as_it_was(tmp_path):
    path = tmp_path / 'ok'
    write_bag(path, 3)
    before = (path / 'ok.mcap').read_bytes()
    done = subprocess.run([sys.executable, '-m', 'activeloc_ros.bag', 'reindex', str(path)],
                          capture_output=True, text=True, cwd=REPO, timeout=60)
    assert done.returncode == 0, done.stderr
    assert 'complete, 3 messages' in done.stdout
    assert (path / 'ok.mcap').read_bytes() == before
    assert message_count(path) == 3


def test_reindex_cli_fails_when_nothing_could_be_recovered(tmp_path):
    write_bag(tmp_path / 'whole', 45)
    data = (tmp_path / 'whole' / 'whole.mcap').read_bytes()
    killed = tmp_path / 'killed'
    killed.mkdir()
    (killed / 'killed.mcap').write_bytes(data[:3000])   # in the middle of the first chunk
    done = subprocess.run([sys.executable, '-m', 'activeloc_ros.bag', 'reindex', str(killed)],
                          capture_output=True, text=True, cwd=REPO, timeout=60)
    assert done.returncode == 1, done.stdout
    assert 'nothing could be recovered from killed.mcap' in done.stderr
    kept = (killed / 'killed.mcap').read_bytes()
    tail = (killed / 'killed.mcap.incomplete').read_bytes()
    assert kept[:3000 - len(tail)] + tail == data[:3000]     # no byte lost


def test_reindex_refuses_what_is_not_a_bag(tmp_path):
    (tmp_path / 'x.mcap').write_bytes(b'not an mcap file at all')
    done = subprocess.run([sys.executable, '-m', 'activeloc_ros.bag', 'reindex',
                           str(tmp_path / 'x.mcap')], capture_output=True, text=True, cwd=REPO,
                          timeout=60)
    assert done.returncode == 1 and 'not an MCAP file' in done.stderr


def test_make_sample_replaces_a_bag_but_never_another_folder(tmp_path, capsys):
    spec = importlib.util.spec_from_file_location('make_sample', REPO / 'bags' / 'make_sample.py')
    make_sample = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(make_sample)
    video = tmp_path / 'clip.avi'
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*'MJPG'), 10.0, (64, 48))
    for i in range(4):
        writer.write(np.full((48, 64, 3), 40 * i, np.uint8))
    writer.release()
    out = tmp_path / 'sample'
    args = ['--video', str(video), '--out', str(out), '--width', '32']
    assert make_sample.main(args) == 0 and bag_facts(out).message_count == 4
    assert make_sample.main(args + ['--frames', '2']) == 0 and bag_facts(out).message_count == 2
    precious = tmp_path / 'precious'
    precious.mkdir()
    (precious / 'notes.txt').write_text('kept')
    assert make_sample.main(['--video', str(video), '--out', str(precious)]) == 1
    assert 'is not a bag' in capsys.readouterr().err
    assert (precious / 'notes.txt').read_text() == 'kept'
    assert make_sample.main(args + ['--width', '0']) == 1 and 'width' in capsys.readouterr().err
    assert make_sample.main(['--video', str(video), '--out', '/proc/x/y']) == 1
    assert capsys.readouterr().err.startswith('error:')
    assert sorted(p.name for p in tmp_path.iterdir()) == ['clip.avi', 'precious', 'sample']


def test_a_type_the_bag_cannot_describe_is_left_out_and_named_not_fatal(tmp_path, context):
    """
    nav_msgs/Goals is in the installed interfaces but not in rosbags' Jazzy types: its
    add_topic raised TypesysError out of the discovery timer, which ended the recorder (and
    bringup's monitor with it) in the middle of the run.
    """
    from nav_msgs.msg import Goals
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from std_msgs.msg import String
    from activeloc_ros.nodes.recorder import RecorderNode
    from conftest import spin_until
    recorder = RecorderNode(tmp_path / 'bag', context=context)
    talker = Node('talker', context=context)
    goals = talker.create_publisher(Goals, 'rec_test_goals', 10)
    words = talker.create_publisher(String, 'rec_test_words', 10)
    executor = SingleThreadedExecutor(context=context)
    for node in (recorder, talker):
        executor.add_node(node)
    try:
        def heard():
            goals.publish(Goals())
            words.publish(String(data='kept'))
            return recorder.counts.get('/rec_test_words', 0) >= 2
        assert spin_until(executor, heard, 20)
    finally:
        executor.shutdown()
        recorder.close()
        for node in (recorder, talker):
            node.destroy_node()
    assert "nav_msgs/msg/Goals is not among the bag's types" in recorder.unrecorded[
        '/rec_test_goals']
    assert recorder.error is None
    assert bag_facts(tmp_path / 'bag').message_count >= 2


def test_on_a_full_disk_the_recorder_counts_what_the_bag_holds(tmp_path, context):
    """
    The summary listed 29 messages recorded while the bag held 15: the chunk being
    written when the disk filled is lost, and the counts must say so.
    """
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from std_msgs.msg import String
    from activeloc_ros.nodes.recorder import RecorderNode
    from conftest import spin_until
    recorder = RecorderNode(tmp_path / 'bag', context=context,
                            wrap_stream=lambda s: FillsUp(s, 3_500_000))
    talker = Node('talker', context=context)
    words = talker.create_publisher(String, 'rec_test_full', 100)
    executor = SingleThreadedExecutor(context=context)
    for node in (recorder, talker):
        executor.add_node(node)
    try:
        def full():
            words.publish(String(data='x' * PAYLOAD))
            return recorder.error is not None
        assert spin_until(executor, full, 30)
    finally:
        executor.shutdown()
        recorder.close()
        for node in (recorder, talker):
            node.destroy_node()
    held = message_count(tmp_path / 'bag')
    assert held > 0
    assert recorder.counts == {'/rec_test_full': held}
