"""One exception tree for the whole toolkit.

Catch :class:`DavisRigError` to handle every error the toolkit raises on purpose.
"""


class DavisRigError(Exception):
    """Base class of every error raised on purpose by davis_rig."""


# --- hardware and transport -------------------------------------------------------------------
class DeviceError(DavisRigError):
    """Something is wrong with the camera as a device."""


class DeviceNotFoundError(DeviceError):
    """No matching DAVIS camera is attached (or none with the requested serial number)."""


class DeviceBusyError(DeviceError):
    """The camera exists but another process holds its interface."""


class DevicePermissionError(DeviceError):
    """The OS denied access to the USB device (usually a missing udev rule)."""


class DeviceVersionError(DeviceError):
    """Firmware or FPGA logic version is outside what this driver supports."""


class TransportError(DeviceError):
    """A USB transfer failed (the device was unplugged, stalled, or timed out).

    Attributes:
        backend_error_code: the backend's error code when one was given, else ``None``.
    """

    def __init__(self, message: str, backend_error_code: int | None = None):
        super().__init__(message)
        self.backend_error_code = backend_error_code


class DeviceDisconnectedError(TransportError):
    """The camera disappeared from the bus while in use."""


# --- data formats -----------------------------------------------------------------------------
class ProtocolError(DavisRigError):
    """A byte stream or a configuration value violates the DAVIS protocol."""


class FormatError(DavisRigError):
    """A file (session.h5, replay file, checkpoint, ONNX model) is malformed or of the wrong kind."""


class SessionError(FormatError):
    """A session.h5 file is missing groups, truncated, or inconsistent."""


class CheckpointError(FormatError):
    """A detector checkpoint does not match the model (missing/unexpected keys, wrong shapes)."""


class ModelFormatError(FormatError):
    """An ONNX model has the wrong inputs/outputs or shapes for the requested use."""


class ConfigError(DavisRigError, ValueError):
    """A configuration value is out of its range or conflicts with another (a settings dataclass, an API argument).

    Attributes:
        field: the name of the offending field or argument (``conf_threshold``); a command maps it onto the
            option that set it, so the message names the option without parsing this text.
        reason: why the value is refused (``expected a number in [0, 1], got 1.5``).
    """

    def __init__(self, field: str, reason: str):
        super().__init__(field, reason)  # both in args: the error pickles (worker processes) and compares
        self.field = field
        self.reason = reason

    def __str__(self) -> str:
        return f"{self.field}: {self.reason}"


class ShapeError(DavisRigError, ValueError):
    """An array or tensor argument has the wrong shape; the message shows expected vs actual."""


class MissingDependencyError(DavisRigError, ImportError):
    """An optional dependency (torch, onnx, ...) is needed for this feature but not installed."""
