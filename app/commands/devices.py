"""`procam devices`: what hardware this machine offers the station: RealSense cameras and screens."""

from __future__ import annotations

import json

NAME = "devices"
HELP = "list connected RealSense cameras and the screens a projector window can use"
DESCRIPTION = (
    "Lists the connected Intel RealSense cameras (serial, name, firmware, USB type) and the screens "
    "pyglet sees (index, size, position; the index is what --screen / --projector-screen take). "
    "Empty lists are not an error: without cameras the station runs the simulated rig, without a "
    "display no projector window can open."
)


def add_arguments(p) -> None:
    p.add_argument("--json", action="store_true", help="print the lists as JSON")


def collect() -> dict:
    """{'realsense': [...], 'realsense_available': bool, 'screens': [...], 'display_error': str|None}"""
    from drivers.errors import DeviceError
    from drivers.projector_window import list_screens
    from drivers.realsense import list_realsense_devices, realsense_available

    out = {"realsense": list_realsense_devices(), "realsense_available": realsense_available(),
           "screens": [], "display_error": None}
    try:
        out["screens"] = list_screens()
    except DeviceError as e:
        out["display_error"] = str(e)
    return out


def run(args) -> int:
    found = collect()
    if args.json:
        print(json.dumps(found, indent=2))
        return 0
    print("RealSense cameras:")
    if not found["realsense"]:
        why = "" if found["realsense_available"] else " (pyrealsense2 is not usable on this machine)"
        print(f"  none connected{why}")
    for d in found["realsense"]:
        print(f"  {d.get('serial') or '?'}  {d.get('name') or '?'}  firmware {d.get('firmware') or '?'}  "
              f"USB {d.get('usb_type') or '?'}")
    print("Screens (index for --screen / --projector-screen):")
    if found["display_error"]:
        print(f"  no display available: {found['display_error']}")
    elif not found["screens"]:
        print("  none")
    for s in found["screens"]:
        print(f"  {s['index']}: {s['width']}x{s['height']} at ({s['x']}, {s['y']})")
    return 0
