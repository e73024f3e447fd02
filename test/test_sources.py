"""Image conversion, bag reading/writing and camera sources, without ROS."""
from pathlib import Path

import cv2
import numpy as np
import pytest

from activeloc_ros.bag.read import bag_facts, choose_image_topic, format_facts, read_messages
from activeloc_ros.bag.write import BagWriter
from activeloc_ros.errors import FrameError, SourceError
from activeloc_ros.images import image_to_rgb, rgb_to_image_fields
from activeloc_ros.sources import open_source, Pacer, pinhole_matrix

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / 'bags' / 'vtest'


def rgb_frame(height=48, width=64, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)


@pytest.mark.parametrize('encoding', ['rgb8', 'bgr8'])
def test_image_fields_round_trip(encoding):
    rgb = rgb_frame()
    fields = rgb_to_image_fields(rgb, encoding)
    back = image_to_rgb(fields['encoding'], fields['height'], fields['width'], fields['step'],
                        fields['data'])
    np.testing.assert_array_equal(back, rgb)


def test_padded_rows_and_other_encodings():
    rgb = rgb_frame(4, 5)
    padded = np.zeros((4, 5 * 4 + 3), np.uint8)
    bgra = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGRA)
    padded[:, :20] = bgra.reshape(4, 20)
    np.testing.assert_array_equal(image_to_rgb('bgra8', 4, 5, 23, padded.tobytes()), rgb)
    gray = image_to_rgb('mono8', 4, 5, 5, rgb[..., 0].tobytes())
    np.testing.assert_array_equal(gray[..., 2], rgb[..., 0])


@pytest.mark.parametrize('encoding,height,width,step,size,match', [
    ('16UC1', 4, 4, 8, 32, 'unsupported image encoding'),
    ('rgb8', 0, 4, 12, 0, 'unsupported image size'),
    ('rgb8', 4, 4, 6, 48, 'step'),
    ('rgb8', 4, 4, 12, 47, 'bytes'),
])
def test_bad_images_raise_frame_error(encoding, height, width, step, size, match):
    with pytest.raises(FrameError, match=match):
        image_to_rgb(encoding, height, width, step, bytes(size))


def test_sample_bag_facts():
    facts = bag_facts(SAMPLE)
    topic = choose_image_topic(facts)
    assert topic.msgtype == 'sensor_msgs/msg/CompressedImage'
    assert topic.count == facts.message_count > 100
    assert 20.0 < facts.duration_s < 60.0
    assert facts.size_bytes < 20 * 2**20
    text = format_facts(facts)
    assert 'Storage id:        mcap' in text and topic.name in text


def test_bag_source_reads_frames_in_order():
    source = open_source(f'bag:{SAMPLE}', clock=lambda: 0.0)
    frames = [source.read() for _ in range(3)]
    assert [f.index for f in frames] == [0, 1, 2]
    assert frames[0].rgb.shape == (480, 640, 3) and frames[0].rgb.dtype == np.uint8
    assert frames[1].stamp - frames[0].stamp == pytest.approx(0.1, abs=1e-6)
    assert not np.array_equal(frames[0].rgb, frames[2].rgb)
    source.rewind()
    assert source.read().index == 0


def write_bag(path, messages):
    """messages: (topic, msgtype, builder(store) -> msg)"""
    writer = BagWriter(path)
    for i, (topic, msgtype, build) in enumerate(messages):
        writer.write(topic, msgtype, 10**9 + i * 10**8, build(writer.store))
    writer.close()
    return path


def raw_image(store, encoding='rgb8', height=8, width=8):
    Image = store.types['sensor_msgs/msg/Image']
    Header = store.types['std_msgs/msg/Header']
    Time = store.types['builtin_interfaces/msg/Time']
    channels = 2 if encoding == '16UC1' else 3
    data = np.full(height * width * channels, 7, np.uint8)
    return Image(header=Header(stamp=Time(sec=1, nanosec=0), frame_id='cam'), height=height,
                 width=width, encoding=encoding, is_bigendian=0, step=width * channels,
                 data=data)


def test_bag_with_raw_images_and_a_bad_encoding(tmp_path):
    path = write_bag(tmp_path / 'raw', [
        ('/cam/image', 'sensor_msgs/msg/Image', lambda s: raw_image(s, '16UC1')),
        ('/cam/image', 'sensor_msgs/msg/Image', lambda s: raw_image(s)),
    ])
    source = open_source(f'bag:{path}', clock=lambda: 0.0)
    frame = source.read()
    assert frame.rgb.shape == (8, 8, 3) and int(frame.rgb[0, 0, 0]) == 7
    assert source.read() is None
    assert any('16UC1' in problem for problem in source.skipped)


def test_a_message_of_another_type_on_the_image_topic_is_skipped_and_named(tmp_path):
    """Before, a String among the images raised AttributeError and killed the camera."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    path = tmp_path / 'mixed'
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        image = writer.add_connection('/cam/image', 'sensor_msgs/msg/Image', typestore=store)
        text = writer.add_connection('/cam/image', 'std_msgs/msg/String', typestore=store)
        data = store.serialize_cdr(raw_image(store), 'sensor_msgs/msg/Image')
        writer.write(image, 10**9, data)
        writer.write(text, 10**9 + 1, store.serialize_cdr(
            store.types['std_msgs/msg/String'](data='hello'), 'std_msgs/msg/String'))
        writer.write(image, 10**9 + 2, data)
    source = open_source(f'bag:{path}', clock=lambda: 0.0)
    assert source.read() is not None and source.read() is not None
    assert source.read() is None
    assert source.skipped == {'not an image: std_msgs/msg/String': 1}


def test_bag_without_image_topic(tmp_path):
    def string(store):
        return store.types['std_msgs/msg/String'](data='hello')
    path = write_bag(tmp_path / 'text', [('/chatter', 'std_msgs/msg/String', string)])
    with pytest.raises(SourceError, match='no image topic'):
        open_source(f'bag:{path}', clock=lambda: 0.0)


def test_missing_empty_and_corrupt_bags(tmp_path):
    with pytest.raises(SourceError, match='not found'):
        bag_facts(tmp_path / 'nope.mcap')
    (tmp_path / 'empty.mcap').write_bytes(b'')
    with pytest.raises(SourceError, match='empty'):
        bag_facts(tmp_path / 'empty.mcap')
    good = (SAMPLE / 'vtest.mcap').read_bytes()
    (tmp_path / 'cut.mcap').write_bytes(good[:len(good) // 2])
    with pytest.raises(SourceError, match='cut.mcap'):
        bag_facts(tmp_path / 'cut.mcap')
    (tmp_path / 'junk.mcap').write_bytes(b'not an mcap file at all' * 10)
    with pytest.raises(SourceError, match='junk.mcap'):
        bag_facts(tmp_path / 'junk.mcap')
    (tmp_path / 'folder').mkdir()
    with pytest.raises(SourceError, match='no .mcap'):
        bag_facts(tmp_path / 'folder')


def test_a_corrupt_message_is_skipped_and_named_and_the_rest_is_read(tmp_path):
    """A message whose bytes do not deserialise (a cut payload) costs that frame alone."""
    from mcap.reader import make_reader
    from mcap.writer import Writer
    with open(SAMPLE / 'vtest.mcap', 'rb') as stream:
        schema, channel, message = next(make_reader(stream).iter_messages())
    path = tmp_path / 'one_bad.mcap'
    with open(path, 'wb') as out:
        writer = Writer(out)
        writer.start('ros2', '')
        schema_id = writer.register_schema(schema.name, schema.encoding, schema.data)
        channel_id = writer.register_channel(channel.topic, channel.message_encoding, schema_id)
        for i, data in enumerate([message.data, message.data[:40], message.data]):
            writer.add_message(channel_id, log_time=10**9 + i * 10**8, data=data,
                               publish_time=10**9 + i * 10**8)
        writer.finish()
    source = open_source(f'bag:{path}', clock=lambda: 0.0)
    assert [source.read().stamp, source.read().stamp, source.read()] == [1.0, 1.2, None]
    assert dict(source.skipped) == {
        f'corrupt {schema.name} message on {channel.topic}': 1}
    with pytest.raises(SourceError, match=r'one_bad.mcap: corrupt .* at log time 1.100 s'):
        list(read_messages(path, [channel.topic]))


def test_video_and_folder_sources(tmp_path):
    folder = tmp_path / 'frames'
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f'{i:03d}.png'), rgb_frame(seed=i))
    (folder / 'notes.txt').write_text('not an image')
    source = open_source(f'folder:{folder}', clock=lambda: 0.0, folder_fps=5.0)
    frames = [source.read() for _ in range(4)]
    assert frames[3] is None and frames[2].stamp == pytest.approx(0.4)
    np.testing.assert_array_equal(frames[1].rgb, cv2.cvtColor(rgb_frame(seed=1),
                                                              cv2.COLOR_BGR2RGB))
    (folder / '001.png').unlink()            # gone since the start: counted, not silent
    source.rewind()
    assert [source.read().index for _ in range(2)] == [0, 2] and source.read() is None
    assert source.skipped == {'unreadable image file': 1}
    with pytest.raises(SourceError, match='not found'):
        open_source(f'video:{tmp_path / "none.mp4"}', clock=lambda: 0.0)
    (tmp_path / 'bad.mp4').write_bytes(b'garbage')
    with pytest.raises(SourceError):
        open_source(f'video:{tmp_path / "bad.mp4"}', clock=lambda: 0.0).read()
    with pytest.raises(SourceError, match='unknown camera source'):
        open_source('webcam', clock=lambda: 0.0)


def test_a_video_cut_short_is_an_error_not_its_end(tmp_path):
    whole = tmp_path / 'whole.avi'
    writer = cv2.VideoWriter(str(whole), cv2.VideoWriter_fourcc(*'MJPG'), 10, (64, 48))
    for i in range(30):
        writer.write(rgb_frame(seed=i))
    writer.release()
    source = open_source(f'video:{whole}', clock=lambda: 0.0)
    assert sum(1 for _ in iter(source.read, None)) == 30
    cut = tmp_path / 'cut.avi'
    cut.write_bytes(whole.read_bytes()[:whole.stat().st_size * 6 // 10])
    source = open_source(f'video:{cut}', clock=lambda: 0.0)
    frames = [source.read() for _ in range(5)]
    assert all(f is not None for f in frames)
    with pytest.raises(SourceError, match=r'cut.avi stopped after \d+ of the 30 frames'):
        while source.read() is not None:
            pass


def test_realsense_without_sdk_or_device_is_a_clear_error():
    with pytest.raises(SourceError, match='RealSense|pyrealsense2'):
        open_source('realsense', clock=lambda: 0.0)


def test_pacer_replays_recorded_timing_and_reanchors_on_loop():
    pacer = Pacer(rate=2.0)
    assert pacer.due(10.0, now=100.0) == 100.0
    assert pacer.due(11.0, now=100.1) == pytest.approx(100.5)
    assert pacer.due(10.0, now=200.0) == 200.0      # loop restart
    with pytest.raises(SourceError):
        Pacer(rate=0.0)


def test_pinhole_matrix_matches_field_of_view():
    k = pinhole_matrix(640, 480, 90.0)
    assert k[0, 0] == pytest.approx(320.0) and k[0, 2] == 320.0 and k[1, 2] == 240.0
