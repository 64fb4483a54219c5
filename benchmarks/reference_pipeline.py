"""A port of the reference pipeline's shape, for timing: OpenCV's own detectors, calibrateCamera and
stereoCalibrate, no refinement, on a saved session folder.

    python benchmarks/reference_pipeline.py SESSION [--json]

What it does, as the published reference implementation does it, and nothing more:
- every image read in colour (cv2.imread) and converted to grey;
- ChArUco boards with cv2.aruco.CharucoDetector (default parameters) in the image, in the flipped image
  for views seen through the mirror; a real-virtual mirror image is searched twice (as it is and flipped);
- the projected circle grid with cv2.findCirclesGrid (asymmetric grid) on the whole image, with OpenCV's
  blob detector set for bright blobs of 10 px and more, after the image's 31 px local mean is subtracted
  (on a lit board the circles are only a little brighter than the board: without it OpenCV's detector
  found no grid in these sessions); a chessboard with cv2.findChessboardCorners;
- the camera by cv2.calibrateCamera over every board view (the projector step's boards in the flipped
  image: the virtual camera), the pattern points mapped onto the board by the board's homography, the
  projector by cv2.calibrateCamera over those, the pose by cv2.stereoCalibrate with both intrinsics
  fixed, and the mirror plane from each real-virtual pair's board origins.

It is a timing reference for benchmarks/detection_speed.py --reference, not a calibration to use: no
corner refinement, no outlier rejection, no conic model. `--json` prints one line with its stage times
(detection_s, calibration_s) and reprojection errors.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calib.formats.session import SessionStore  # noqa: E402
from calib.models.observations import STEP_PROJECTOR, STEP_REAL_VIRTUAL, VIEW_MIRROR  # noqa: E402


def _charuco(detector, gray):
    corners, ids, _, _ = detector.detectBoard(gray)
    if ids is None or len(ids) < 6:
        return None
    return np.asarray(corners, np.float32).reshape(-1, 2), np.asarray(ids, int).ravel()


def _blob_detector():
    p = cv2.SimpleBlobDetector_Params()
    p.blobColor = 255  # projected circles are bright
    p.minArea = 10  # and small at 1280x800
    p.minDistBetweenBlobs = 2
    return cv2.SimpleBlobDetector_create(p)


def _flattened(gray):
    return cv2.normalize(cv2.subtract(gray, cv2.blur(gray, (31, 31))), None, 0, 255, cv2.NORM_MINMAX)


def detect(store):
    m = store.manifest
    pboard, mboard = m.projector_board, m.mirror_board or m.projector_board
    pdet = cv2.aruco.CharucoDetector(pboard.cv_board())
    mdet = cv2.aruco.CharucoDetector(mboard.cv_board())
    blobs = _blob_detector()
    flip = m.rig.view == VIEW_MIRROR
    proj, mirror = [], []
    for c in m.captures:
        img = cv2.imread(str(store.image_path(c)), cv2.IMREAD_COLOR)
        if img is None:
            continue
        gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        if c.step == STEP_PROJECTOR:
            g = cv2.flip(gray, 1) if flip else gray
            board = _charuco(pdet, g)
            if board is None:
                continue
            if m.pattern.kind == "circles":
                ok, pts = cv2.findCirclesGrid(_flattened(g), m.pattern.pattern_size, flags=cv2.CALIB_CB_ASYMMETRIC_GRID,
                                              blobDetector=blobs)
            else:
                ok, pts = cv2.findChessboardCorners(g, m.pattern.pattern_size)
            if ok:
                proj.append((board, np.asarray(pts, np.float32).reshape(-1, 2), c.pattern_points_px))
        else:
            real = _charuco(mdet, gray)
            virtual = _charuco(mdet, cv2.flip(gray, 1)) if c.step == STEP_REAL_VIRTUAL else None
            if real is not None:
                mirror.append((real, virtual))
    return proj, mirror


def calibrate(store, proj, mirror) -> dict:
    m = store.manifest
    size = tuple(m.rig.camera_size)
    pobj = m.projector_board.corner_points().astype(np.float32)
    mobj = (m.mirror_board or m.projector_board).corner_points().astype(np.float32)
    # the camera (the virtual one of the mirrored views: its boards are found in the flipped image)
    obj = [pobj[ids] for (_, ids), _, _ in proj]
    img = [c for (c, _), _, _ in proj]
    rms_cam, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, size, None, None)
    # the pattern points on the board: the board's homography of each view (undistorted)
    board_pts, proj_pts = [], []
    for ((corners, ids), cam_pts, shown) in proj:
        und = cv2.undistortPoints(corners.reshape(-1, 1, 2), K, dist, P=K).reshape(-1, 2)
        H, _ = cv2.findHomography(und, pobj[ids, :2])
        pu = cv2.undistortPoints(cam_pts.reshape(-1, 1, 2), K, dist, P=K).reshape(-1, 2)
        on_board = cv2.perspectiveTransform(pu.reshape(-1, 1, 2), H).reshape(-1, 2)
        board_pts.append(np.column_stack([on_board, np.zeros(len(on_board))]).astype(np.float32))
        proj_pts.append(np.asarray(shown, np.float32).reshape(-1, 2))
    psize = tuple(m.rig.projector_size)
    rms_proj, Kp, distp, _, _ = cv2.calibrateCamera(board_pts, proj_pts, psize, None, None)
    cam_pts = [p for (_, p, _) in proj]
    rms_stereo, *_, R, T, _, _ = cv2.stereoCalibrate(board_pts, cam_pts, proj_pts, K, dist, Kp, distp, size,
                                                      flags=cv2.CALIB_FIX_INTRINSIC)
    # the mirror plane: the normal along the real board's origin minus its reflection's (virtual) origin
    normals = []
    for real, virtual in mirror:
        if virtual is None:
            continue
        poses = []
        for corners, ids in (real, virtual):
            ok, rv, tv = cv2.solvePnP(mobj[ids], corners, K, dist)
            poses.append(tv.ravel() if ok else None)
        if poses[0] is not None and poses[1] is not None:
            v = poses[1] * [-1.0, 1.0, 1.0]  # the flipped image's board, back in the camera's frame
            d = poses[0] - v
            normals.append(d / np.linalg.norm(d))
    normal = np.mean(normals, axis=0).tolist() if normals else None
    return {"rms_camera_px": rms_cam, "rms_projector_px": rms_proj, "rms_stereo_px": rms_stereo,
            "T_proj_cam_t": np.asarray(T).ravel().tolist(), "mirror_normal": normal}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("session", type=Path)
    ap.add_argument("--json", action="store_true", help="one line of JSON: stage times and errors")
    args = ap.parse_args()
    store = SessionStore.open(args.session)
    t0 = time.perf_counter()
    proj, mirror = detect(store)
    t1 = time.perf_counter()
    out = calibrate(store, proj, mirror)
    t2 = time.perf_counter()
    out.update(detection_s=t1 - t0, calibration_s=t2 - t1, projector_views=len(proj), mirror_views=len(mirror))
    print(json.dumps(out) if args.json else "\n".join(f"{k}: {v}" for k, v in out.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
