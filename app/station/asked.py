"""The whole board pose a projector step asks for next (Plan.ask_pose, `--ask-pose`).

After each calibration of the captures so far (app/station/confidence_watch.py, stopping on
confidence), while the projector step is not confident: candidate poses at the positions the step may
ask for next (app/station/targets.candidate_positions), drawn through the estimated rig as a person
would hold the board and seen in the part of the mirror boards were seen in so far, each ranked by the
1-sigmas its observations are predicted to leave (calib.asked_pose); the least worst one is
asked for. The panel dashes that board's outline on the camera image (through the mirror on a mirror
rig), the instruction and the log say why, and the simulated operator holds it as a person would:
a few degrees and millimetres off.

An asked pose belongs to the count of projector captures it was computed after: once another capture
is taken it no longer applies, and the target falls back to the plan's order until the next
calibration gives a new one. It is not saved: a resumed session computes it again when it judges its
captures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.errors import ProcamError
from calib.models.observations import STEP_PROJECTOR

#: candidate poses per position (each one prediction: a Jacobian of the session's observations)
PER_POSITION = 2
#: points along each edge of the board's outline drawn on the camera image (the lens bends them)
OUTLINE_POINTS = 12


@dataclass(frozen=True, eq=False)
class AskedTarget:
    """The pose asked for (calib.asked_pose.AskedPose), the projector captures it was computed
    after, and the board's outline on the camera image (fractions of its width and height)."""

    asked: object  # calib.asked_pose.AskedPose
    for_captures: int
    outline: np.ndarray  # (M, 2) fractions of the camera image, a closed polygon

    @property
    def position(self) -> int:
        return self.asked.position

    @property
    def T_cam_board(self) -> np.ndarray:
        return self.asked.candidate.T_cam_board

    def reason(self) -> str:
        return self.asked.reason()


#: the blank area (width, gap) of `procam board --assets`' projector board, mm: a session that gives none
DEFAULT_BLANK_MM = (320.0, 20.0)


def board_layout(rig, manifest):
    """The projector board's layout (ChArUco and blank area): the blank area session.json records
    (`--blank-area`, a simulated scenario's own), else the simulated rig's scenario's, else the one of
    `procam board --assets`' projector board (DEFAULT_BLANK_MM, in the board's units)."""
    from calib.models.boards import MM_PER_UNIT
    from calib.synthetic import BoardLayout

    board = manifest.projector_board
    if getattr(manifest, "blank_area", None) is not None:
        return BoardLayout(board, *manifest.blank_area)
    layout = getattr(getattr(rig, "scenario", None), "layout", None)
    if layout is not None:
        return layout
    per_mm = 1.0 / MM_PER_UNIT.get(board.units, 1.0)
    return BoardLayout(board, DEFAULT_BLANK_MM[0] * per_mm, DEFAULT_BLANK_MM[1] * per_mm)


def outline_px(result, layout, T_cam_board: np.ndarray) -> np.ndarray:
    """The board's outline (with its white border) imaged by the estimated camera at T_cam_board
    (through the estimated mirror on a mirror rig): (4 * OUTLINE_POINTS, 2) camera pixels."""
    from calib.transforms import transform_points

    x0, y0, x1, y1 = layout.outline
    t = np.linspace(0.0, 1.0, OUTLINE_POINTS, endpoint=False)
    edge = np.concatenate([np.column_stack([x0 + (x1 - x0) * t, np.full_like(t, y0)]),
                           np.column_stack([np.full_like(t, x1), y0 + (y1 - y0) * t]),
                           np.column_stack([x1 - (x1 - x0) * t, np.full_like(t, y1)]),
                           np.column_stack([np.full_like(t, x0), y1 - (y1 - y0) * t])])
    X = np.column_stack([edge, np.zeros(len(edge))])
    S = np.eye(4) if result.mirror is None else result.mirror.reflection()
    return result.camera.project(transform_points(S @ np.asarray(T_cam_board, float), X))


def asked_target(machine, result, layout, positions) -> AskedTarget | None:
    """The pose to ask for next among `positions`, from `result` (the joint calibration of the session's
    captures so far); None when no candidate could be drawn or predicted."""
    from calib.detection.session_jobs import detect_session
    from calib.asked_pose import ask_pose, candidate_poses, mirror_seen

    if not positions:
        return None
    n = len(machine.captures_of(STEP_PROJECTOR))
    try:
        obs = detect_session(machine.store, 1, None, cache="use")  # the detections just made: from the cache
        rect = mirror_seen(obs, result)
        cands = candidate_poses(obs, result, layout, machine.manifest.pattern, list(positions),
                                np.random.default_rng(n), PER_POSITION, mirror_rect=rect)
        asked = ask_pose(obs, result, cands)
    except ProcamError:
        return None
    if asked is None:
        return None
    W, H = machine.manifest.rig.camera_size
    frac = (outline_px(result, layout, asked.candidate.T_cam_board) + 0.5) / np.array([W, H], float)
    return AskedTarget(asked, n, frac)
