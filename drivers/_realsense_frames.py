"""The RealSense colour frames the capture thread takes in: which are accepted, and when each exposure
began (behind drivers/realsense.py).

Frame numbers: `Frame.frame_number` is the driver's own counter, +1 for every frame it accepts, so it
increases strictly for the camera object's whole life (also across reconnects, where the device's own
counter restarts). A frame is accepted only when its device frame number or its device timestamp is
larger than the last accepted frame's: a duplicate (both equal) or a late frame (both smaller or
equal) is dropped and counted; a counter reset (number smaller, time larger) or a timestamp wrap
(number larger, time smaller) is accepted. The device's own number is kept in
`Frame.meta["device_frame_number"]`, its timestamp is `Frame.timestamp_ms` (the device clock: librealsense's
global time or hardware clock, `meta["timestamp_domain"]`), and `meta["host_time_s"]` is the host's
time.monotonic() when the frame arrived.

Frame times: `Frame.exposure_start_s` is the host `time.monotonic()` second at which the frame's
exposure began, estimated from what the frame carries (see `_exposure_start`):
- global_time domain (librealsense maps the device clock onto the host's system clock; the default on
  the D4xx when frame metadata is available): the frame time minus the part of the frame that precedes
  it, converted to the monotonic clock with the offset time.time() - time.monotonic() measured when the
  frame arrives. When the frame carries both `frame_timestamp` (start of readout) and `sensor_timestamp`
  (middle of exposure) metadata, the exposure start is the middle of exposure minus half the exposure;
  otherwise the frame time is taken as the start of readout, i.e. the end of the exposure.
- system_time domain (no frame metadata: the V4L2 backend without librealsense's kernel patch, Windows
  without its registry switch; librealsense #13241): the host's clock at the frame's arrival, so the
  exposure began one frame interval (readout and transfer) and the exposure before it. These times are
  the host's, with its transfer jitter: drivers.base.TimeSource.HOST (the rig check says so).
- hardware_clock domain: the device clock mapped to the host clock by the smallest (arrival - device
  time) of the last frames (transfer delays are never negative, so the smallest one has the least
  jitter), minus one frame interval for the readout and transfer that smallest delay still contains.
- otherwise: the host arrival time minus the exposure and one frame interval (readout and transfer).
The exposure is the frame's `actual_exposure` metadata, else the manual exposure set, else a whole
frame interval (the longest an exposure can be at the stream's rate). A constant error in these
estimates is harmless to the station: the projector latency it measures is measured against the same
exposure_start_s, so the bias ends up in the latency; what matters is the jitter, which the offsets above keep small.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from drivers._realsense_lib import COLOUR_EXPOSURE_UNIT_US
from drivers.base import Frame


@dataclass
class _Stats:
    accepted: int = 0
    duplicates: int = 0
    late: int = 0
    bad: int = 0
    gaps: int = 0  # jumps in the device's frame numbers: frames lost between the device and the driver
    missing: int = 0  # frames those jumps skipped
    resets: int = 0  # stalled streams reset (hardware_reset)
    held: int = 0  # frames dropped after a (re)start, until the re-applied exposure shows


class RealSenseFrames:
    """The capture thread of drivers.realsense.RealSenseCamera (a part of that class, not a driver of its
    own): it fills the state the camera keeps under `_cond` (`_latest`, `_counter`, `_last_key`,
    `_last_arrival_s`, `stats`, `_thread_error`) from the frames of the camera's `rs.frame_queue`, by
    the settings it keeps (`_rs`, `fps`, `serial`, `_manual`, `_hold_until_s`, `_offsets`)."""

    def _capture_loop(self, queue, stop_evt: threading.Event) -> None:
        try:
            while not stop_evt.is_set():
                ok, f = queue.try_wait_for_frame(100)
                if ok:
                    self._accept(f)
        except Exception as e:  # noqa: BLE001 - reported to the caller of get_frame
            with self._cond:
                self._thread_error = e
                self._cond.notify_all()

    def _accept(self, f) -> None:
        rs = self._rs
        host_t = time.monotonic()
        if not f.is_video_frame():
            return
        vf = f.as_video_frame()
        key = (int(vf.get_frame_number()), float(vf.get_timestamp()))
        with self._cond:
            last = self._last_key
            if last is not None and key[0] <= last[0] and key[1] <= last[1]:
                if key == last:
                    self.stats.duplicates += 1
                else:
                    self.stats.late += 1
                return
        img = np.asanyarray(vf.get_data())
        h, w = vf.get_height(), vf.get_width()
        if img.dtype != np.uint8 or img.size != h * w * 3:
            with self._cond:
                self.stats.bad += 1
            return
        img = np.array(img, copy=True).reshape(h, w, 3)
        if vf.get_profile().format() == rs.format.rgb8:
            img = np.ascontiguousarray(img[:, :, ::-1])
        img.setflags(write=False)
        meta = {"device_frame_number": key[0], "timestamp_domain": str(vf.get_frame_timestamp_domain()).split(".")[-1],
                "host_time_s": host_t, "serial": self.serial}
        md = rs.frame_metadata_value
        for name, value, scale in (("actual_exposure_us", md.actual_exposure, COLOUR_EXPOSURE_UNIT_US),
                                  ("frame_timestamp_us", md.frame_timestamp, 1.0),
                                  ("sensor_timestamp_us", md.sensor_timestamp, 1.0),
                                  ("gain", md.gain_level, 1.0)):
            try:
                if vf.supports_frame_metadata(value):
                    meta[name] = float(vf.get_frame_metadata(value)) * scale
            except RuntimeError:
                pass
        if "actual_exposure_us" not in meta and self._manual is not None:
            # no metadata: the manual exposure last set (the rig check confirms it shows before timing
            # anything by it), so a frame that caught a change part-way can still be timed
            meta["exposure_us_set"] = float(self._manual["exposure_us"])
        start_s, source = self._exposure_start(key[1], meta, host_t, time.time() - time.monotonic())
        meta["exposure_start_source"] = source
        with self._cond:
            last = self._last_key
            if last is not None and key[0] <= last[0] and key[1] <= last[1]:
                self.stats.late += 1
                return
            if last is not None and key[0] > last[0] + 1:  # frames the device numbered never reached us
                self.stats.gaps += 1
                self.stats.missing += key[0] - last[0] - 1
            self._last_key = key
            self._last_arrival_s = host_t
            if start_s < self._hold_until_s:
                self.stats.held += 1
                return
            self._counter += 1
            self.stats.accepted += 1
            self._latest = Frame(img, self._counter, key[1], meta, start_s)
            self._cond.notify_all()

    def _exposure_start(self, timestamp_ms: float, meta: dict, arrival_s: float,
                        wall_minus_mono_s: float) -> tuple[float, str]:
        """(host monotonic seconds at which the exposure began, how it was estimated); see the module doc."""
        period_s = 1.0 / max(self.fps, 1)
        exposure_s = meta.get("actual_exposure_us")
        if exposure_s is None and self._manual is not None:
            exposure_s = self._manual["exposure_us"]
        exposure_s = period_s if exposure_s is None else float(exposure_s) * 1e-6
        # the exposure start relative to the instant the frame's timestamp stands for
        if "frame_timestamp_us" in meta and "sensor_timestamp_us" in meta:
            before_ref_s = (meta["frame_timestamp_us"] - meta["sensor_timestamp_us"]) * 1e-6 + exposure_s / 2
        else:
            before_ref_s = exposure_s  # the timestamp marks the start of readout = the end of the exposure
        domain = meta.get("timestamp_domain")
        if domain == "global_time":
            return timestamp_ms * 1e-3 - wall_minus_mono_s - before_ref_s, domain
        if domain == "system_time":
            # no hardware timestamp (no frame metadata, librealsense #13241): librealsense stamped the
            # frame with the host's clock when it arrived, after the exposure, the readout and the transfer
            return timestamp_ms * 1e-3 - wall_minus_mono_s - period_s - exposure_s, domain
        if domain == "hardware_clock":
            self._offsets.append(arrival_s - timestamp_ms * 1e-3)
            del self._offsets[:-max(8, 2 * self.fps)]
            ref_s = timestamp_ms * 1e-3 + min(self._offsets)
            # a device-clock jump (reset, wrap) makes the mapped time land after the arrival or
            # implausibly long before it: start over
            if not arrival_s - 1.0 <= ref_s <= arrival_s:
                self._offsets = [arrival_s - timestamp_ms * 1e-3]
                ref_s = arrival_s
            return ref_s - period_s - before_ref_s, domain
        return arrival_s - period_s - exposure_s, "arrival"
