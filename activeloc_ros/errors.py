"""The project's own error types: every bad input ends in one of these, with a clear message."""


class ActivelocError(Exception):
    """Base of every error this package raises on purpose."""


class ConfigError(ActivelocError):
    """An invalid parameter or configuration value; the message names it."""


class FrameError(ActivelocError):
    """A frame of the wrong shape, dtype or encoding."""


class WeightsError(ActivelocError):
    """Encoder weights missing, corrupt or of the wrong layout."""


class SourceError(ActivelocError):
    """A camera source that cannot be opened or read (missing, empty or corrupt bag...)."""


class DataError(ActivelocError):
    """A malformed evaluation sequence (missing frames, bad ground-truth rows)."""


class ArmLinkError(ActivelocError):
    """The serial link to the arm failed (port vanished, silent, malformed frames)."""
