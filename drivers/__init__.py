"""Devices: the simulated rig and the real hardware, behind the interfaces in drivers.base."""

from drivers.base import CameraDriver, Frame, Operator, ProjectorDriver
from drivers.errors import DeviceDisconnected, DeviceError, DeviceTimeout

__all__ = ["CameraDriver", "Frame", "Operator", "ProjectorDriver", "DeviceError", "DeviceDisconnected", "DeviceTimeout"]
