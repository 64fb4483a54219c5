"""Interfaces every rig implements: the simulated one and the real hardware.

The station only talks to these protocols, so `--rig sim` and `--rig realsense` are swapped by a flag.
Images are numpy arrays in OpenCV layout: (H, W, 3) uint8 BGR, row 0 at the top.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from calib.camera import CameraModel


@dataclass(frozen=True)
class Frame:
    """One camera frame.

    `frame_number` increases strictly for every new frame a driver delivers, so a caller can ask for a
    frame newer than one it has already seen and never confuse a late frame with a new one.
    `timestamp_ms` is the device clock when there is one (RealSense), else the host clock.
    """

    image: np.ndarray
    frame_number: int
    timestamp_ms: float
    meta: dict = field(default_factory=dict)


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

    def close(self) -> None: ...


@runtime_checkable
class Operator(Protocol):
    """Whoever moves the board. On the real rig a person reads the panel's instruction and this is a
    no-op; on the simulated rig a scripted operator places the board where the protocol wants it."""

    def request_pose(self, step: str, pattern_position: int | None, pose_index: int) -> str:
        """Ask for the board pose `pose_index` of `step` ('mirror-real-virtual', 'mirror-real-mirror',
        'projector'), for projector steps at pattern position `pattern_position`. Returns the
        instruction in plain words (what the panel shows the person)."""
