"""pyrealsense2, imported on first use, and the RealSense devices it lists (behind drivers/realsense.py).

pyrealsense2 is imported lazily, so the rest of procam works on machines without it (or without
Debian's libusb-1.0-0, which the wheel needs): `_rs()` raises DeviceError saying what to install.
"""

from __future__ import annotations

from drivers.errors import DeviceError

#: Unit of the colour sensor's `exposure` option. librealsense passes the UVC control through: on the
#: D400 RGB sensor it counts 100 microseconds (range 1..10000), unlike the depth sensor's microseconds.
COLOUR_EXPOSURE_UNIT_US = 100.0

_rs_module = None


def _import_error_message(e: BaseException) -> str:
    """What to do when pyrealsense2 does not import, from the import error itself."""
    text = str(e)
    if "libusb" in text:
        return (f"pyrealsense2 cannot be loaded because Debian's libusb is missing ({text}): install it with "
                "`sudo apt-get install libusb-1.0-0`, or use the simulated rig (--rig sim)")
    if isinstance(e, ModuleNotFoundError) and getattr(e, "name", "") == "pyrealsense2":
        return ("pyrealsense2 is not installed: install it with `pip install 'procam-station[realsense]'` "
                "(PyPI has wheels for Linux x86_64 and Windows; elsewhere build librealsense with "
                "-DBUILD_PYTHON_BINDINGS=ON; on Linux it also needs `apt-get install libusb-1.0-0`), "
                "or use the simulated rig (--rig sim)")
    return (f"pyrealsense2 cannot be imported ({text}); install it with pip and Debian's libusb-1.0-0 "
            "(apt-get install libusb-1.0-0), or use the simulated rig (--rig sim)")


def _rs():
    """pyrealsense2, imported on first use."""
    global _rs_module
    if _rs_module is None:
        try:
            import pyrealsense2 as rs
        except ImportError as e:  # pragma: no cover - depends on the machine
            raise DeviceError(_import_error_message(e)) from None
        _rs_module = rs
    return _rs_module


def realsense_import_error() -> str | None:
    """Why pyrealsense2 is not usable here (what to install), or None when it is."""
    try:
        _rs()
        return None
    except DeviceError as e:
        return str(e)


def realsense_available() -> bool:
    """True when pyrealsense2 imports on this machine."""
    return realsense_import_error() is None


# ---- device discovery -----------------------------------------------------------------------------

def _info(dev, key: str) -> str | None:
    rs = _rs()
    ci = getattr(rs.camera_info, key)
    try:
        if dev.supports(ci):
            return str(dev.get_info(ci))
    except RuntimeError:
        pass
    return None


def device_info(dev) -> dict:
    """serial, name, firmware, usb_type (and product line / port when known) of a librealsense device."""
    return {
        "serial": _info(dev, "serial_number"),
        "name": _info(dev, "name"),
        "firmware": _info(dev, "firmware_version"),
        "usb_type": _info(dev, "usb_type_descriptor"),
        "product_line": _info(dev, "product_line"),
        "port": _info(dev, "physical_port"),
    }


def list_realsense_devices(context=None) -> list[dict]:
    """Connected RealSense devices as dicts (serial, name, firmware, usb_type, ...); [] when there is
    none or pyrealsense2 is not usable here."""
    try:
        rs = _rs()
    except DeviceError:
        return []
    ctx = context if context is not None else rs.context()
    try:
        devices = list(ctx.query_devices())
    except RuntimeError:
        return []
    return [device_info(d) for d in devices]


def _colour_profiles(sensor) -> list:
    rs = _rs()
    out = []
    for p in sensor.get_stream_profiles():
        if p.stream_type() == rs.stream.color and p.is_video_stream_profile():
            out.append(p.as_video_stream_profile())
    return out


def _colour_sensor(dev):
    """The device's sensor that streams colour, or None."""
    for s in dev.query_sensors():
        if _colour_profiles(s):
            return s
    return None


def _depth_sensor(dev, colour_sensor=None):
    """The device's sensor with an IR emitter control (the D4xx "Stereo Module"), or None."""
    rs = _rs()
    try:
        sensors = list(dev.query_sensors())
    except RuntimeError:
        return None
    for s in sensors:
        if colour_sensor is not None and s == colour_sensor:
            continue
        try:
            if s.supports(rs.option.emitter_enabled):
                return s
        except RuntimeError:
            continue
    return None
