"""The rig check's raw evidence: the frames a camera handed out while the station measured its exposure,
latency and response, kept at reduced size with their metadata, so a rig that fails can be diagnosed
offline (which frames showed which settings, how they were timed).

    recorder = FrameRecorder(camera)          # a camera: what it hands out is recorded
    search_exposure(recorder, refresh_hz)     # ... anything that reads frames
    recorder.write(folder / "rig_check")      # frames.json and one small PNG per frame

The recorder passes every other attribute on to the camera, so it is the camera for its callers.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

#: every frame is kept at 1/SHRINK of its size (a 1280x800 frame: 160x100, a few kB as a PNG)
SHRINK = 8
#: frames kept at most (the first ones; the check uses 150-400)
MAX_FRAMES = 600


def _json_safe(value):
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(float(value)) else None
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    return str(value)


class FrameRecorder:
    """A camera whose handed-out frames are recorded (module doc)."""

    def __init__(self, camera, max_frames: int = MAX_FRAMES):
        self._camera = camera
        self._max = int(max_frames)
        self.frames: list[dict] = []
        self.images: list[np.ndarray] = []
        self._seen: set[int] = set()

    def __getattr__(self, name):
        return getattr(self._camera, name)

    def get_frame(self, *args, **kwargs):
        f = self._camera.get_frame(*args, **kwargs)
        if f.frame_number not in self._seen and len(self.frames) < self._max:
            self._seen.add(f.frame_number)
            meta = {k: v for k, v in (f.meta or {}).items() if k != "T_cam_board"}
            self.frames.append({"frame_number": int(f.frame_number), "timestamp_ms": _json_safe(f.timestamp_ms),
                                "exposure_start_s": _json_safe(f.exposure_start_s), "meta": _json_safe(meta),
                                "image": f"f{len(self.frames):04d}.png"})
            a = np.asarray(f.image)
            self.images.append(np.ascontiguousarray(a[SHRINK // 2::SHRINK, SHRINK // 2::SHRINK]))
        return f

    def write(self, folder) -> int:
        """frames.json and the small PNGs into `folder` (created; atomic writes); returns the frames written."""
        import cv2

        from calib.formats.fileio import atomic_write_bytes

        folder = Path(folder)
        folder.mkdir(exist_ok=True)
        for rec, img in zip(self.frames, self.images):
            ok, buf = cv2.imencode(".png", img)
            if ok:
                atomic_write_bytes(folder / rec["image"], buf.tobytes())
        doc = {"shrink": SHRINK, "frames": self.frames}
        atomic_write_bytes(folder / "frames.json", json.dumps(doc, indent=1).encode("utf-8"))
        return len(self.frames)
