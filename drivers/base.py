"""Interfaces every rig implements: the simulated one and the real hardware.

The station only talks to these protocols, so `--rig sim` and `--rig realsense` are swapped by a flag.
Images are numpy arrays in OpenCV layout: (H, W, 3) uint8 BGR, row 0 at the top.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from calib.models.camera import CameraModel


@dataclass(frozen=True)
class Frame:
    """One camera frame.

    `frame_number` increases strictly for every new frame a driver delivers, so a caller can ask for a
    frame newer than one it has already seen and never confuse a late frame with a new one.
    `timestamp_ms` is the device clock when there is one (RealSense), else the host clock.
    `exposure_start_s` is the host clock (`time.monotonic()`, seconds) at which this frame's exposure
    began, as well as the driver can tell; None when it cannot. A caller that needs a frame showing what
    the projector shows accepts it only if `exposure_start_s` is at or after the moment the projector's
    image became visible (`ProjectorDriver.wait_presented`).
    """

    image: np.ndarray
    frame_number: int
    timestamp_ms: float
    meta: dict = field(default_factory=dict)
    exposure_start_s: float | None = None


class TimeSource(str, enum.Enum):
    """Which clock a frame's exposure_start_s comes from. DEVICE: the camera's own clock (a RealSense's
    hardware timestamps in its frame metadata, mapped onto the host's; the simulated camera's clock):
    exact to a millisecond or so. HOST: the host's clock when the frame arrived (no device time: a
    RealSense without frame metadata), earlier than the true start by up to an exposure and a transfer."""

    DEVICE = "device clock"
    HOST = "host clock"


#: Frame.meta["exposure_start_source"] values -> the clock they read (librealsense's timestamp domains,
#: and "arrival" for a frame timed by its arrival alone); a frame without the key is on the device's clock
_SOURCE_CLOCK = {"global_time": TimeSource.DEVICE, "hardware_clock": TimeSource.DEVICE,
                 "system_time": TimeSource.HOST, "arrival": TimeSource.HOST}


def frame_time_source(frame: Frame) -> TimeSource | None:
    """The clock `frame.exposure_start_s` was read from (TimeSource); None when the frame has no time."""
    if frame.exposure_start_s is None:
        return None
    meta = frame.meta if isinstance(frame.meta, dict) else {}
    return _SOURCE_CLOCK.get(meta.get("exposure_start_source"), TimeSource.DEVICE)


@runtime_checkable
class CameraDriver(Protocol):
    """A camera that delivers frames on request."""

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""

    def start(self) -> None: ...

    def stop(self) -> None: ...

    def get_frame(self, timeout_s: float = 2.0, newer_than: int | None = None) -> Frame:
        """The newest frame; with `newer_than`, block until a frame with a larger frame_number arrives.

        Raises drivers.errors.DeviceTimeout / DeviceDisconnected (both DeviceError)."""

    def factory_intrinsics(self) -> CameraModel | None:
        """Intrinsics the device reports (RealSense factory calibration), or None."""

    def settings(self) -> dict:
        """Exposure, gain, white balance... as used now; recorded in the session manifest."""


@runtime_checkable
class ExposureControl(Protocol):
    """A camera whose exposure can be set by hand (RealSense, the simulated camera).

    On the D4xx RGB sensor exposure and gain are only meaningful in manual mode, so an exposure is
    chosen by searching in manual mode (drivers/exposure.py), never read back from auto exposure."""

    def exposure_limits(self) -> dict:
        """{"exposure_us": (min, max, step), "gain": (min, max, step)}."""

    def set_auto_exposure(self, enabled: bool) -> None: ...

    def set_manual_exposure(self, exposure_us: float, gain: float) -> dict:
        """Turn auto exposure off and apply; returns what the device applied: {"exposure_us", "gain"}."""

    def set_emitter(self, enabled: bool) -> None:
        """The depth sensor's IR dot projector (RealSense); on a camera without one, a no-op."""


@runtime_checkable
class ProjectorDriver(Protocol):
    """A projector showing full-screen images, pixel for pixel."""

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""

    def show(self, image: np.ndarray) -> int:
        """Request `image` ((H, W) or (H, W, 3) uint8, exactly the projector's size). Returns a ticket."""

    def wait_presented(self, ticket: int, timeout_s: float = 2.0) -> float:
        """Block until the image of `ticket` has been presented (after buffer swap and the projector's
        settle time); returns the host time (time.monotonic(), seconds) at which it counts as visible."""

    @property
    def refresh_hz(self) -> float:
        """The display's refresh rate (exposures are whole numbers of its period, against banding)."""

    def close(self) -> None: ...


@runtime_checkable
class Operator(Protocol):
    """Whoever moves the board. On the real rig a person reads the panel's instruction and this is a
    no-op; on the simulated rig a scripted operator places the board where the protocol wants it."""

    def request_pose(self, step: str, pattern_position: int | None, pose_index: int, asked=None,
                     on_stand: bool = False) -> str:
        """Ask for the board pose `pose_index` of `step` ('mirror-real-virtual', 'mirror-real-mirror',
        'projector'), for projector steps at pattern position `pattern_position`; `asked`: the whole
        projector-board pose the station asks for (T_cam_board, 4x4; the panel dashes its outline), None
        when it leaves the pose to the operator; `on_stand`: the board is to rest on a stand (the station
        uses several frames of the placement, which a hand-held board moves through). Returns the
        instruction in plain words (what the panel shows the person)."""
