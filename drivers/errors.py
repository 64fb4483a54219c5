"""Errors raised by device drivers."""

from calib.errors import ProcamError


class DeviceError(ProcamError):
    """A device could not be opened, configured or read."""


class DeviceDisconnected(DeviceError):
    """The device went away mid-stream. The session may catch this and retry when it comes back."""


class DeviceTimeout(DeviceError):
    """No (new) frame arrived in time."""


class ExposureUnsupported(DeviceError):
    """The camera ignores manual exposure or gain (a webcam, a stream): its own auto exposure stays on."""


class StreamReset(DeviceTimeout):
    """The stream had stalled (no frame for a while, the device still connected) and the driver reset the
    device (hardware_reset); it streams again: ask for a frame again."""
