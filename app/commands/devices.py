"""`procam devices`: what hardware this machine offers the station: RealSense cameras, the cameras OpenCV
opens and screens."""

from __future__ import annotations

import json

NAME = "devices"
HELP = "list connected RealSense cameras, OpenCV cameras and the screens a projector window can use"
DESCRIPTION = (
    "Lists the connected Intel RealSense cameras (serial, name, firmware, USB type), the cameras OpenCV opens "
    "(the index --rig uvc --camera takes, backend, frame size), and every display output "
    "(index, name, primary flag, resolution, position, refresh rate; the index is what --screen / "
    "--projector-screen take) and which one the station would use for the projector: the non-primary screen "
    "of two (with more than two, --projector-screen is required). Empty lists are not an error: without "
    "cameras the station runs the simulated rig, without a display no projector window can open; the reason "
    "is printed with what to install or fix."
)


def add_arguments(p) -> None:
    p.add_argument("--json", action="store_true", help="print the lists as JSON")


def collect() -> dict:
    """{'realsense': [...], 'realsense_available': bool, 'realsense_error': str|None, 'opencv_cameras': [...],
    'screens': [...], 'display_error': str|None, 'projector_screen': int|None, 'projector_screen_note': str|None}"""
    from drivers.errors import DeviceError
    from drivers.projector_window import choose_projector_screen, list_screens
    from drivers.realsense import list_realsense_devices, realsense_import_error

    error = realsense_import_error()
    out = {"realsense": list_realsense_devices() if error is None else [], "realsense_available": error is None,
           "realsense_error": error, "screens": [], "display_error": None, "projector_screen": None,
           "projector_screen_note": None}
    from drivers.opencv_camera import list_opencv_cameras

    # a RealSense shows up among them too (its colour node is a UVC camera): the realsense rig drives it better
    out["opencv_cameras"] = list_opencv_cameras()
    try:
        out["screens"] = list_screens()
    except DeviceError as e:
        out["display_error"] = str(e)
    if out["screens"]:
        try:
            out["projector_screen"] = choose_projector_screen(out["screens"])
        except DeviceError as e:
            out["projector_screen_note"] = str(e)
    return out


def run(args) -> int:
    from drivers.projector_window import screen_line

    found = collect()
    if args.json:
        print(json.dumps(found, indent=2))
        return 0
    print("RealSense cameras:")
    if found["realsense_error"]:
        print(f"  none usable: {found['realsense_error']}")
    elif not found["realsense"]:
        print("  none connected (plug the D455 into a USB 3 port; the station uses the simulated rig without one)")
    for d in found["realsense"]:
        print(f"  {d.get('serial') or '?'}  {d.get('name') or '?'}  firmware {d.get('firmware') or '?'}  "
              f"USB {d.get('usb_type') or '?'}")
    print("OpenCV cameras (index for --rig uvc --camera):")
    if not found["opencv_cameras"]:
        print("  none found (a webcam another program streams from cannot be opened; on Linux check /dev/video* "
              "and that you are in the 'video' group)")
    for c in found["opencv_cameras"]:
        print(f"  {c['source']}  {c['backend']}  {c['width']}x{c['height']}" + (f" @ {c['fps']:g} fps" if c["fps"] else ""))
    print("Screens (index for --screen / --projector-screen):")
    if found["display_error"]:
        print(f"  none: {found['display_error']}")
    elif not found["screens"]:
        print("  none")
    for s in found["screens"]:
        mark = "  <- projector (default)" if s["index"] == found["projector_screen"] else ""
        print(f"  {screen_line(s)}{mark}")
    if found["projector_screen_note"]:
        print(f"  {found['projector_screen_note']}")
    elif len(found["screens"]) == 1:
        print("  only one screen: the pattern window would cover it (connect the projector as a second screen)")
    return 0
