"""Epipolar verification of a calibration, live at the rig and automatic (the paper's check, measured).

For a camera pixel u the calibration predicts the curve of projector pixels that can light what u sees
(calib.epipolar.epipolar_curve). The projector draws that curve as a bright stroke on the board; the
camera sees it (through the mirror); calib.detection.curves finds the stroke's sub-pixel centre line;
the distance from u to it is the measurement. With a correct calibration the stroke passes through u
whatever the board's pose.

Three frames per check: projector black (`off`), projector full white (`white`, shared by all checks:
it normalises the board's albedo and gives the region the projector lights) and the curve (`on`).

Units. The distance is measured in CAMERA pixels (`distance_px`). It is also converted to PROJECTOR
pixels (`distance_proj_px`) with the local scale measured from the stroke itself: drawn `w` projector
pixels wide, the stroke's cross-section (integral of the normalised signal across it) is its width in
camera pixels, so scale = cross_section / w camera px per projector px, independent of blur. The
verdict is taken in projector pixels: they measure what the calibration is for (where the projector
draws), and they do not depend on how much finer or coarser the camera's pixels are than the
projector's on the board (on the simulated rigs one camera pixel covers about four projector pixels,
so a 5-pixel error of the projector's principal point moves the stroke by only 0.5 to 1 camera pixel).

Verdict (VerificationReport.passed): at least `min_measured` checks and half of them measured, the
mean distance <= threshold_px and the worst <= 2 x threshold_px (projector pixels). Pixels where no
curve is detected are reported with their reason and never count as passes. See docs/VERIFICATION.md
for the measurements behind the default threshold.

Entry points: `verify_pixel` (one pixel: the station's panel calls it when the operator clicks a
pixel), `verify` (the automatic grid), `VerificationReport.save_json` / `from_json` (verification.json).

The jobs behind them live in private modules (their public names are re-exported here):
app/_verification_report.py (PixelCheck, VerificationReport, the verdict `judge`),
app/_verification_capture.py (frames exposed after an image became visible, the references),
app/_verification_measure.py (a stroke found and measured, several strokes in one image) and
app/_verification_pixels.py (where to look: the lit board, the grid of pixels, the board's pose).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from app._verification_capture import (
    Grabber,
    ReferenceFrames,
    capture_references,
    draw_stroke,
    grey,
)
from app._verification_measure import (
    MAX_CURVES_PER_IMAGE,
    MIN_SEPARATION_PX,
    group_pixels,
    measure_pixel,
    stroke_line,
    stroke_rois,
)
from app._verification_pixels import (
    DEFAULT_GRID,
    estimate_board_pose,
    grid_pixels,
    region_mask,
)
from app._verification_report import (
    DEFAULT_THRESHOLD_PX,
    SCHEMA,
    VERSION,
    WORST_FACTOR,
    PixelCheck,
    VerificationError,
    VerificationReport,
    judge,
)
from calib.detection.curves import stripe_signal
from calib.detection.response import CameraResponse
from calib.epipolar import epipolar_curve
from calib.errors import ProcamError
from calib.formats import session_files
from calib.formats.fileio import RESULT_MAX_BYTES, read_json
from calib.models.result import CalibrationResult
from calib.models.vocab import RigKind, Step, choices

__all__ = ["DEFAULT_GRID", "DEFAULT_THRESHOLD_PX", "INITIAL_STROKE_PX", "MAX_CURVES_PER_IMAGE", "MIN_SEPARATION_PX",
           "SCHEMA", "TARGET_STROKE_CAM_PX", "VERIFY_RIGS", "VERSION", "WORST_FACTOR", "Grabber", "PixelCheck",
           "ReferenceFrames", "VerificationError", "VerificationReport", "capture_references", "estimate_board_pose",
           "grid_pixels", "group_pixels", "judge", "measure_pixel", "perturbed", "region_mask", "session_response",
           "stroke_line", "verification_is_stale", "verify", "verify_command", "verify_pixel"]

#: Width of the drawn stroke in camera pixels the automatic stroke width aims for.
TARGET_STROKE_CAM_PX = 3.5
#: Stroke width (projector pixels) before the scale is known.
INITIAL_STROKE_PX = 12.0

Progress = Callable[[int, int, str], None]


def verify_pixel(camera, projector, result: CalibrationResult, pixel, *, references: ReferenceFrames | None = None,
                 stroke_px: float | None = None, board_pose: np.ndarray | None = None, settle_frames: int = 1,
                 average: int = 1, leave_dark: bool = True, response: CameraResponse | None = None) -> PixelCheck:
    """Verify one camera pixel: draw its epipolar curve, detect it, measure. `references`: shared
    black/white frames (captured here when None). `stroke_px`: stroke width in projector pixels
    (default: INITIAL_STROKE_PX). `board_pose`: T_cam_board of the board (or (n, d) of its plane) for
    the predicted curve overlay. `response`: the camera's tone curve, for the references captured here
    (given `references` carry their own). The projector is left black afterwards unless `leave_dark`
    is False."""
    pixel = (float(pixel[0]), float(pixel[1]))
    cw, ch = result.camera.size
    if not (-0.5 <= pixel[0] <= cw - 0.5 and -0.5 <= pixel[1] <= ch - 0.5):
        raise VerificationError(f"pixel ({pixel[0]:g}, {pixel[1]:g}) is outside the {cw}x{ch} camera image")
    if tuple(projector.size) != tuple(result.projector.size):
        raise VerificationError(f"the projector is {projector.size[0]}x{projector.size[1]} but the calibration is for "
                                f"{result.projector.width}x{result.projector.height}")
    stroke = float(stroke_px or INITIAL_STROKE_PX)
    curve = epipolar_curve(result, pixel)
    if len(curve) < 2:
        return PixelCheck(pixel, curve, np.zeros((0, 2)), None, None, None, None, None, stroke, None,
                          "the projector cannot light what this pixel sees: its epipolar curve misses the "
                          "projector image (pick a pixel on the board in the projector's light)")
    refs = references or capture_references(camera, projector, settle_frames, average, response=response)
    g = Grabber(camera, projector, settle_frames, average)
    on = g.grab(draw_stroke(projector.size, curve, stroke))
    if leave_dark:
        W, H = projector.size
        projector.wait_presented(projector.show(np.zeros((H, W), np.uint8)))
    return measure_pixel(result, pixel, curve, on, refs, stroke, board_pose)


def verify(camera, projector, operator, result: CalibrationResult, pixels=None, grid=DEFAULT_GRID,
           threshold_px: float = DEFAULT_THRESHOLD_PX, board_region=None, progress: Progress | None = None, *,
           board=None, board_pose=None, stroke_px: float | None = None, settle_frames: int = 1, average: int = 1,
           min_measured: int = 3, calibration_info: dict | None = None, session_dir=None,
           curves_per_image: int = MAX_CURVES_PER_IMAGE, response: CameraResponse | None = None) -> VerificationReport:
    """The automatic epipolar check. `operator` (may be None) is asked for the 'verification' pose
    first. `pixels`: (N, 2) camera pixels to verify, default a `grid` (cols, rows) spread over the
    region the projector lights (within `board_region` when given). One pixel after another; the
    stroke width adapts to TARGET_STROKE_CAM_PX camera pixels once the scale is measured (unless
    `stroke_px` is given). `board_pose` (T_cam_board) or `board` (the CharucoSpec, found in the white
    frame; default the session's projector board when `session_dir` is given) add the predicted curve
    to each check (overlay only). `session_dir`: write the report there as verification.json. Returns
    the report (the projector is left black). `curves_per_image`: strokes drawn together in one
    projector image (pixels grouped by group_pixels; 1: one image per pixel). `response`: the camera's
    tone curve (the session's recorded one, calib.detection.response.recorded_response): every frame is
    linearised before the stroke's signal is formed, so the white and black frames divide out light
    (None: the camera's levels as they are); the report records it."""
    if tuple(projector.size) != tuple(result.projector.size):
        raise VerificationError(f"the projector is {projector.size[0]}x{projector.size[1]} but the calibration is for "
                                f"{result.projector.width}x{result.projector.height}")
    if operator is not None:
        operator.request_pose(Step.VERIFICATION, None, 0)
    ref_grabber = Grabber(camera, projector, settle_frames, average)
    refs = capture_references(camera, projector, settle_frames, average, grabber=ref_grabber, response=response)
    H, W = refs.off.shape[:2]
    if (W, H) != tuple(result.camera.size):
        raise VerificationError(f"the camera delivers {W}x{H} frames but the calibration is for "
                                f"{result.camera.width}x{result.camera.height}")
    if board_pose is None and board is None and session_dir is not None:
        board = _session_board(session_dir)
    if board_pose is None and board is not None:
        board_pose = estimate_board_pose(refs.white, board, result, refs.response)
    if pixels is None:
        region = region_mask((H, W), refs.lit, board_region)
        if not region.any():
            raise VerificationError("the camera sees nothing lit by the projector: put the board in the projector's "
                                    "light where the camera sees it (through the mirror), and check both devices")
        pts = grid_pixels(region, grid, prefer=refs.lit)
    else:
        pts = np.asarray(pixels, float).reshape(-1, 2)
    if len(pts) == 0:
        raise VerificationError("no pixel to verify: the lit region is too small for the grid")
    stroke = float(stroke_px or INITIAL_STROKE_PX)
    Wp, Hp = projector.size
    # several pixels per projected image: their strokes lie on well separated camera-side lines
    curves = [epipolar_curve(result, (float(p[0]), float(p[1]))) for p in pts]
    lines = [stroke_line(result, p, c) for p, c in zip(pts, curves)]
    groups = group_pixels(pts, lines, curves_per_image)
    results: dict[int, PixelCheck] = {}
    g = Grabber(camera, projector, settle_frames, average)
    off_light, white_light = refs.light()  # converted once, not per check
    done = 0
    for group in groups:
        if progress is not None:
            progress(done, len(pts), f"pixel ({pts[group[0]][0]:.0f}, {pts[group[0]][1]:.0f})"
                     + (f" and {len(group) - 1} more" if len(group) > 1 else ""))
        drawable = [i for i in group if len(curves[i]) >= 2]
        for i in group:
            if i not in drawable:
                results[i] = verify_pixel(camera, projector, result, pts[i], references=refs, stroke_px=stroke)
        if drawable:
            from drivers.projector_images import draw_polylines

            image = draw_polylines((Wp, Hp), [curves[i] for i in drawable], thickness_px=stroke, antialias=True)
            on = grey(g.grab(image), response)
            signal = stripe_signal(on, off_light, white_light)
            rois = stroke_rois((H, W), [lines[i] for i in drawable], MIN_SEPARATION_PX / 2) \
                if len(drawable) > 1 else [None]
            for i, roi in zip(drawable, rois):
                results[i] = measure_pixel(result, pts[i], curves[i], on, refs, stroke, board_pose, roi=roi,
                                           signal=signal)
        done += len(group)
        if stroke_px is None:
            scales = [c.scale for c in results.values() if c.scale]
            if scales:
                stroke = float(np.clip(TARGET_STROKE_CAM_PX / np.median(scales), 3.0, 60.0))
    checks = [results[i] for i in range(len(pts))]
    projector.wait_presented(projector.show(np.zeros((Hp, Wp), np.uint8)))
    if progress is not None:
        progress(len(pts), len(pts), "done")
    info = {"method": result.method, "units": result.units, **(calibration_info or {})}
    if info.get("path") and "sha256" not in info:  # which calibration file this report verified
        from calib.recalib import sha256_file

        info["sha256"] = sha256_file(info["path"], unreadable_ok=True)
    settings = {"grid": list(grid) if pixels is None else None, "settle_frames": settle_frames, "average": average,
                "stroke_px": stroke_px, "min_measured": min_measured, "board_pose_known": board_pose is not None,
                "curves_per_image": curves_per_image, "projector_images": 2 + len(groups),
                "frames": [list(x) for x in ref_grabber.seen + g.seen]}  # [camera frame, projector ticket]
    report = replace(judge(checks, threshold_px, min_measured, info, settings),
                     response=None if response is None else response.to_dict())
    if session_dir is not None:
        report.save_json(Path(session_dir) / session_files.VERIFICATION)
    return report


VERIFY_RIGS = choices(RigKind)  # procam verify's --rig choices


def verify_command(session: Path) -> str:
    """`procam verify SESSION --rig KIND` with the rig the session recorded (when verify knows it)."""
    from calib.formats.session import SessionStore

    try:
        kind = SessionStore.open(session).manifest.rig.driver
    except ProcamError:
        kind = None
    return f"procam verify {session} --rig {kind if kind in VERIFY_RIGS else '|'.join(VERIFY_RIGS)}"


def verification_is_stale(report_file, calibration_file) -> bool | None:
    """Whether the verification report in `report_file` describes another calibration than the one now in
    `calibration_file` (the report records the SHA-256 of the file it verified). None when it cannot
    tell: no report, or a report written before the hash was recorded."""
    try:
        data = read_json(report_file, RESULT_MAX_BYTES, "verification report")
        recorded = (data.get("calibration") or {}).get("sha256")
    except (OSError, ProcamError, AttributeError):
        return None
    if not isinstance(recorded, str):
        return None
    from calib.recalib import sha256_file

    return recorded != sha256_file(calibration_file, unreadable_ok=True)


def _session_board(folder):
    """The projector board of the session in `folder`, or None when it cannot be read."""
    from calib.formats.session import SessionStore

    try:
        return SessionStore.open(folder).manifest.projector_board
    except ProcamError:
        return None


def session_response(folder) -> CameraResponse | None:
    """The camera's response the session in `folder` recorded (rig.camera_settings["response"]; the rig
    check records it), or None when it recorded none, a malformed one, or cannot be read."""
    from calib.detection.response import recorded_response
    from calib.formats.session import SessionStore

    try:
        return recorded_response(SessionStore.open(folder).manifest.rig.camera_settings)
    except ProcamError:
        return None


def perturbed(result: CalibrationResult, rotation_deg: float = 0.0, axis=(0.0, 1.0, 0.0),
              principal_shift_px=(0.0, 0.0)) -> CalibrationResult:
    """A deliberately wrong copy of a calibration (for tests, benchmarks and demos): T_cam_proj rotated
    by `rotation_deg` about `axis` (projector frame, about the projector's centre) and the projector's
    principal point shifted by `principal_shift_px`."""
    from calib.transforms import make_T, rotation_about

    T = np.array(result.T_cam_proj) @ make_T(rotation_about(axis, rotation_deg), np.zeros(3)) \
        if rotation_deg else np.array(result.T_cam_proj)
    K = np.array(result.projector.K)
    K[0, 2] += principal_shift_px[0]
    K[1, 2] += principal_shift_px[1]
    return replace(result, T_cam_proj=T, projector=result.projector.with_params(K=K),
                   method=f"{result.method} (perturbed)")
