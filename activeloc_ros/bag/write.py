"""
Write rosbag2 MCAP bags with `rosbags`, which writes the metadata `ros2 bag info` reads.
A write error (a full disk) closes the bag at its last complete chunk (`recover.reindex`).
"""
from pathlib import Path
from typing import Callable

from activeloc_ros.bag.read import typestore
from activeloc_ros.bag.recover import reindex
from activeloc_ros.errors import ActivelocError, SourceError


class RecordingError(ActivelocError):
    """A bag could not be written (disk full, read-only, path under a file...)."""


class BagWriter:
    """
    Write CDR messages to a rosbag2 MCAP bag (a folder with metadata.yaml).

    A write error (a full disk...) ends the recording, not the program: the bag is cut back
    to its last complete chunk and indexed, so it reads up to the error, and RecordingError
    says what happened. Every later write is refused with the same error.

    :param wrap_stream: wraps the open .mcap file object (tests: a disk that fills up).
    """

    def __init__(self, path: Path, *, wrap_stream: Callable | None = None):
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.rosbag2.errors import WriterError
        self.path = Path(path)
        if self.path.exists():
            raise SourceError(f'will not overwrite existing bag {self.path}')
        self._store = typestore()
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        try:
            self._writer.open()
        except (OSError, WriterError) as exc:
            raise RecordingError(f'cannot create bag {self.path}: {exc}') from exc
        if wrap_stream is not None:
            self._writer.storage.bio = wrap_stream(self._writer.storage.bio)
        self._connections: dict[str, object] = {}
        self.error: RecordingError | None = None
        self.closed = False
        # after a write error: the messages the bag still holds, a topic (None: unknown)
        self.held: dict[str, int] | None = None

    def add_topic(self, topic: str, msgtype: str) -> None:
        if topic not in self._connections:
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=self._store)

    def write_cdr(self, topic: str, stamp_ns: int, data: bytes) -> None:
        if self.error is not None:
            raise self.error
        try:
            self._writer.write(self._connections[topic], stamp_ns, data)
        except OSError as exc:
            self._fail(exc)
            raise self.error from exc

    def write(self, topic: str, msgtype: str, stamp_ns: int, message) -> None:
        """Write a rosbags-typestore message object."""
        self.add_topic(topic, msgtype)
        self.write_cdr(topic, stamp_ns, self._store.serialize_cdr(message, msgtype))

    @property
    def store(self):
        return self._store

    def close(self) -> None:
        """
        Finish the bag (index, metadata.yaml). Raises RecordingError if it could not be
        finished as written; the bag then holds what reached the disk before the error.
        """
        if self.closed:
            if self.error is not None:
                raise self.error
            return
        try:
            self._writer.close()
            self.closed = True
        except OSError as exc:
            self._fail(exc)
            raise self.error from exc

    def _fail(self, exc: OSError) -> None:
        """Stop writing; keep what is on disk up to the last complete chunk, indexed."""
        self.closed = True
        try:
            self._writer.abort()        # closes the file; flushing what is buffered may fail
        except OSError:
            pass
        problem = f'writing bag {self.path} failed: {exc.strerror or exc}'
        try:
            report = reindex(self.path)
        except (OSError, SourceError) as again:
            self.error = RecordingError(
                f'{problem}; it could not be closed either ({again}): run '
                f'`python -m activeloc_ros.bag reindex {self.path}` once there is room')
        else:
            self.held = report.topics
            self.error = RecordingError(f'{problem}; the bag was closed at the last complete '
                                        f'chunk and holds {report.messages} messages')
