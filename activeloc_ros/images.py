"""
Conversions between ROS image fields and RGB arrays, without ROS (cv_bridge's job, here).

Functions take and return plain fields so they can be tested without message types; the
nodes unpack messages into them. Every unsupported input raises FrameError.
"""
import sys

import cv2
import numpy as np

from activeloc_ros.errors import FrameError

# encoding -> (channels, conversion to RGB or None when already RGB)
_ENCODINGS = {
    'rgb8': (3, None),
    'bgr8': (3, cv2.COLOR_BGR2RGB),
    'rgba8': (4, cv2.COLOR_RGBA2RGB),
    'bgra8': (4, cv2.COLOR_BGRA2RGB),
    'mono8': (1, cv2.COLOR_GRAY2RGB),
}
SUPPORTED_ENCODINGS = tuple(_ENCODINGS)
MAX_SIDE = 8192


def check_size(width: int, height: int, max_pixels: int | None) -> None:
    """Raise FrameError for a frame of more than `max_pixels` pixels (None: no limit)."""
    if max_pixels is not None and width * height > max_pixels:
        raise FrameError(f'frame of {width}x{height} pixels is larger than the limit of '
                         f'{max_pixels} pixels (max_image_pixels)')


def image_to_rgb(encoding: str, height: int, width: int, step: int, data, *,
                 max_pixels: int | None = None) -> np.ndarray:
    """
    Return an (H, W, 3) uint8 RGB copy of a sensor_msgs/Image's pixels.

    :param max_pixels: refuse larger frames before touching their pixels.
    """
    if encoding not in _ENCODINGS:
        raise FrameError(f'unsupported image encoding {encoding!r} '
                         f'(supported: {", ".join(SUPPORTED_ENCODINGS)})')
    if not (0 < height <= MAX_SIDE and 0 < width <= MAX_SIDE):
        raise FrameError(f'unsupported image size {width}x{height}')
    check_size(width, height, max_pixels)
    channels, code = _ENCODINGS[encoding]
    if step < width * channels:
        raise FrameError(f'image step {step} too small for {width} px of {encoding}')
    buf = np.frombuffer(data, dtype=np.uint8)
    if buf.size < step * height:
        raise FrameError(f'image data has {buf.size} bytes, expected {step * height}')
    rows = buf[:step * height].reshape(height, step)[:, :width * channels]
    pixels = rows.reshape(height, width, channels)
    if code is None:
        return pixels.copy()
    return cv2.cvtColor(pixels, code).reshape(height, width, 3)


def rgb_to_image_fields(rgb: np.ndarray, encoding: str = 'rgb8') -> dict:
    """Return the fields of a sensor_msgs/Image holding `rgb` as 'rgb8' or 'bgr8'."""
    check_rgb(rgb)
    if encoding == 'bgr8':
        pixels = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    elif encoding == 'rgb8':
        pixels = np.ascontiguousarray(rgb)
    else:
        raise FrameError(f'cannot publish encoding {encoding!r}: use rgb8 or bgr8')
    height, width = rgb.shape[:2]
    return {'encoding': encoding, 'height': height, 'width': width, 'step': width * 3,
            'is_bigendian': 0, 'data': pixels.tobytes()}


def compressed_size(data) -> tuple[int, int] | None:
    """(width, height) from a PNG or JPEG header, without decoding; None for other data."""
    head = bytes(memoryview(data)[:65536])
    if head.startswith(b'\x89PNG\r\n\x1a\n') and head[12:16] == b'IHDR':
        return int.from_bytes(head[16:20], 'big'), int.from_bytes(head[20:24], 'big')
    if not head.startswith(b'\xff\xd8'):
        return None
    i = 2
    while i + 9 <= len(head) and head[i] == 0xFF:
        marker = head[i + 1]
        # SOF0..SOF15 carry the size; C4 (DHT), C8 (JPG) and CC (DAC) share the range
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            return int.from_bytes(head[i + 7:i + 9], 'big'), int.from_bytes(head[i + 5:i + 7],
                                                                            'big')
        if marker == 0xFF:      # fill byte
            i += 1
        elif 0xD0 <= marker <= 0xD7 or marker == 0x01:     # no length field
            i += 2
        else:
            i += 2 + int.from_bytes(head[i + 2:i + 4], 'big')
    return None


def decode_compressed(fmt: str, data, *, max_pixels: int | None = None) -> np.ndarray:
    """
    Decode a sensor_msgs/CompressedImage (jpeg/png) to RGB.

    :param max_pixels: refuse larger frames, for PNG and JPEG before decoding them.
    """
    size = compressed_size(data) if max_pixels is not None else None
    if size is not None:
        check_size(*size, max_pixels)
    buf = np.frombuffer(data, dtype=np.uint8)
    bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR) if buf.size else None
    if bgr is None:
        raise FrameError(f'cannot decode compressed image of format {fmt!r} ({buf.size} bytes)')
    check_size(bgr.shape[1], bgr.shape[0], max_pixels)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def float_image_fields(values: np.ndarray) -> dict:
    """The fields of a sensor_msgs/Image holding a (rows, cols) array as 32FC1."""
    if not isinstance(values, np.ndarray) or values.ndim != 2:
        raise FrameError(f'expected a (rows, cols) array, got {getattr(values, "shape", values)}')
    pixels = np.ascontiguousarray(values, dtype=np.float32)
    rows, cols = pixels.shape
    return {'encoding': '32FC1', 'height': rows, 'width': cols, 'step': cols * 4,
            'is_bigendian': int(sys.byteorder == 'big'), 'data': pixels.tobytes()}


def check_rgb(rgb: np.ndarray) -> None:
    if not isinstance(rgb, np.ndarray) or rgb.dtype != np.uint8 or rgb.ndim != 3 \
            or rgb.shape[2] != 3:
        shape = getattr(rgb, 'shape', None)
        dtype = getattr(rgb, 'dtype', type(rgb).__name__)
        raise FrameError(f'expected an (H, W, 3) uint8 RGB array, got shape {shape} {dtype}')


def overlay(rgb: np.ndarray, surprise_map: np.ndarray, *, alpha: float = 0.45) -> np.ndarray:
    """Blend a (rows, cols) map, stretched to its own range, onto the frame as a heat map."""
    height, width = rgb.shape[:2]
    span = float(surprise_map.max() - surprise_map.min())
    norm = (surprise_map - surprise_map.min()) / span if span > 0 else surprise_map * 0
    heat = cv2.resize((norm * 255).astype(np.uint8), (width, height),
                      interpolation=cv2.INTER_CUBIC)
    heat = cv2.cvtColor(cv2.applyColorMap(heat, cv2.COLORMAP_JET), cv2.COLOR_BGR2RGB)
    return cv2.addWeighted(rgb, 1.0 - alpha, heat, alpha, 0.0)
