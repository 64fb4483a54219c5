"""Faults of real hardware the simulated rig can emulate, one by one (`--sim-faults NAME,...|all`).

The default simulated rig is kinder than a D455 and a real projector in exactly the places where the
station could go silently wrong; each fault here makes one of them as unkind as the hardware, so a
test (or an operator rehearsing) covers that case. FAULTS is the one registry: the option's help,
its check and the emulation all read it.

Where each applies: the hardware model (drivers/sim/hardware.py, so both `--rig sim` and
`--rig sim-realsense`): apply-lag, latency-jitter, flicker. The librealsense software device
(drivers/sim/realsense_bridge.py, `--rig sim-realsense` only): no-metadata, auto-white-balance, stall, usb2.
gain-range names what the software device always emulates (a D455's colour gain, 0..128 from 64);
the plain simulated camera keeps its 1..8 gain. On `--rig sim` the software device's faults do nothing. The simulated stream's controls
(drivers/sim/stream.py, `--rig sim-uvc` only): ignores-exposure.
"""

from __future__ import annotations

from calib.errors import SpecError

#: name -> what it emulates (shown in --help)
FAULTS = {
    "no-metadata": "frames carry no metadata (exposure, gain, sensor times): Linux's V4L2 backend without "
                   "librealsense's kernel patch, Windows without its registry switch",
    "apply-lag": "exposure and gain apply 5 frames after they are written (instead of 3)",
    "gain-range": "colour gain 0..128 starting at 64, as a D455's (always so on sim-realsense's software device)",
    "auto-white-balance": "auto white balance on at power-up, its colour gains drifting with the scene "
                          "(sim-realsense)",
    "latency-jitter": "the projector's latency jitters by one refresh period",
    "ignores-exposure": "the camera accepts manual exposure and gain writes and ignores them, as many webcams "
                        "(sim-uvc)",
    "usb2": "the camera on a USB 2 link: fewer, slower colour modes (sim-realsense: 15 and 5 fps only)",
    "stall": "the colour stream drops a few frames, then stops until the camera is reset (hardware_reset) "
             "(sim-realsense)",
    "flicker": "an exposure that is not a whole number of refresh periods flickers from frame to frame at "
               "any phase (a global shutter; the camera's and the projector's clocks not locked)",
}

#: settings applied this many frames late under apply-lag (a D455: librealsense #11228)
APPLY_LAG_FRAMES = 5.0


def parse_faults(text: str | None, option: str = "--sim-faults") -> frozenset[str]:
    """The faults `text` names ("a,b", "all", "" or None for none); SpecError for an unknown name."""
    if text is None:
        return frozenset()
    names = [n.strip() for n in str(text).split(",") if n.strip()]
    if names == ["all"]:
        return frozenset(FAULTS)
    unknown = [n for n in names if n not in FAULTS]
    if unknown:
        raise SpecError(f"{option}: unknown fault(s) {', '.join(unknown)} (known: {', '.join(FAULTS)}, or all)")
    return frozenset(names)


def hardware_overrides(faults, refresh_hz: float = 60.0) -> dict:
    """drivers.sim.hardware.HardwareModel fields the faults change."""
    out = {}
    if "apply-lag" in faults:
        out["settings_lag_frames"] = APPLY_LAG_FRAMES
    if "latency-jitter" in faults:
        out["jitter_ms"] = 1000.0 / refresh_hz
    if "flicker" in faults:
        out["flicker_random"] = True
    return out


def help_text() -> str:
    """The option's help: every fault and what it emulates."""
    return ("simulated rig: emulate hardware faults, comma-separated or 'all': "
            + "; ".join(f"{k} ({v})" for k, v in FAULTS.items()))
