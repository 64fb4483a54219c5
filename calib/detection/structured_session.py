"""The structured-light captures of a session folder, detected in detect_session's threads.

A structured capture (calib.formats.session_captures) names its sequence's frames; its job reads each
one as detect_session reads an image (calib.formats.fileio.read_regular: no link, FIFO or device, a size
cap; the PNG header checked before decoding), then detects the view
(calib.detection.structured_view.detect_structured_view). A frame that is missing, refused, of another
size or undecodable, or a frame list that is not the sequence's, makes that capture a DetectionFailure
naming the frame: the session's other captures are unaffected.

The job's result is (board, points) like a circle capture's, the points an (N, 5) array of camera
pixels, the projector pixels that light them and each point's camera-pixel sigma, so the detection
cache's encoding and the copy check take it unchanged; `projector_view` makes the ProjectorView of it.

Entry points: `job_for(store, capture) -> StructuredJob`, `StructuredJob.run()`, `projector_view`.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calib.detection.response import CameraResponse, recorded_response
from calib.errors import SessionError
from calib.formats.fileio import read_regular
from calib.formats.session import image_header_problem, image_max_bytes
from calib.models.boards import CharucoSpec
from calib.models.observations import VIEW_MIRROR, DetectionFailure, ProjectorView
from calib.models.structured_light import StructuredLightSpec


@dataclass(frozen=True)
class StructuredJob:
    capture_id: str
    frame_paths: tuple[str, ...]
    spec: StructuredLightSpec
    board: CharucoSpec
    mirrored: bool
    camera_size: tuple[int, int]
    projector_size: tuple[int, int]
    refused: str | None = None  # why no frame is read (a path leads out of the session folder)
    response: CameraResponse | None = None

    def run(self):
        """(capture_id, (board, (N, 5) points) or DetectionFailure, None): never cached, so no image hash."""
        return self.capture_id, self._detect(), None

    def _detect(self):
        from calib.detection.structured_view import detect_structured_view

        if self.refused is not None:
            return DetectionFailure(self.refused)
        n = len(self.spec.frames(*self.projector_size))
        if len(self.frame_paths) != n:
            return DetectionFailure(f"structured-light capture has {len(self.frame_paths)} frames, its sequence "
                                    f"has {n}: capture this placement again")
        images = []
        for k, path in enumerate(self.frame_paths):
            img = _read_frame(path, self.camera_size)
            if isinstance(img, str):
                return DetectionFailure(f"frame {k + 1} of {n}: {img}; capture this placement again")
            images.append(img)
        sv = detect_structured_view(images, self.spec, self.board, self.projector_size, self.mirrored,
                                    self.capture_id, response=self.response)
        if isinstance(sv, DetectionFailure):
            return sv
        v = sv.view
        return v.board, np.hstack([v.pattern_cam_px, v.pattern_proj_px, v.pattern_sigma_px[:, None]])


def _read_frame(path: str, camera_size) -> np.ndarray | str:
    """A frame's grey image, or why it cannot be used."""
    try:
        data = np.frombuffer(read_regular(path, image_max_bytes(camera_size), "image"), np.uint8)
    except FileNotFoundError:
        return f"image missing: {path}"
    except SessionError as e:  # a link, FIFO, device or huge file: never read
        return str(e)
    problem = image_header_problem(data, camera_size, path)
    if problem is not None:
        return problem
    gray = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)
    if gray is None or gray.shape[::-1] != tuple(camera_size):
        return f"image unreadable: {path} cannot be decoded"
    return gray


def job_for(store, capture) -> StructuredJob:
    """The job of structured capture `capture` of a SessionStore."""
    m = store.manifest
    try:
        paths, refused = tuple(str(store.file_path(capture, f)) for f in capture.frames), None
    except SessionError as e:
        paths, refused = (), f"{e}; capture this placement again"
    return StructuredJob(capture.id, paths, capture.structured_light, m.projector_board, m.rig.view == VIEW_MIRROR,
                         tuple(m.rig.camera_size), tuple(m.rig.projector_size), refused,
                         recorded_response(m.rig.camera_settings))


def projector_view(capture, board, points) -> ProjectorView:
    """The ProjectorView of a structured job's result."""
    pts = np.asarray(points, float).reshape(-1, 5)
    return ProjectorView(capture.id, board, pts[:, :2], pts[:, 2:4], None, pts[:, 4])
