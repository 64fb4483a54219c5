"""Named simulated rigs with exact ground truth (the paper's evaluation set-ups).

A Scenario is a frozen description: the rig (camera, projector, mirror), the boards, the pattern, the
mirror-calibration method, render settings, and the seed from which every board pose follows
deterministically (calib.synthetic: the paper's protocol, 13 pattern positions x 4 poses, plus the
mirror-calibration placements). `get_scenario(name, seed)`; `list_scenarios()`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from calib.errors import SpecError
from calib.models.boards import CharucoSpec
from calib.models.camera import CameraModel
from calib.models.pattern import PatternSpec
from calib.models.result import CalibrationResult
from calib.models.vocab import LengthUnit, MirrorMethod, PatternKind, Step
from calib.synthetic import (
    BoardLayout,
    SyntheticRig,
    _frame_from_normal,
    projector_pose_ok,
    make_direct_rig,
    make_rig,
    mirror_poses,
    portable_projector,
    projector_pose,
    projector_poses,
)
from calib.transforms import make_T, rotation_about, transform_points
from drivers.sim.render import RenderSettings

DEFAULT_SCENARIO = "nonoverlap-136"
STEP_PROJECTOR = Step.PROJECTOR
STEP_REAL_VIRTUAL = Step.REAL_VIRTUAL
STEP_REAL_MIRROR = Step.REAL_MIRROR
STEP_VERIFICATION = Step.VERIFICATION
OPERATOR_STEPS = tuple(Step)


def default_projector_board() -> CharucoSpec:
    """The board the projector lights: 8 x 6 squares of 50 mm, DICT_4X4_50 markers of 30 mm (big
    cells, so that they decode at the distances of a mirrored view)."""
    return CharucoSpec(8, 6, "DICT_4X4_50", 50.0, 30.0, LengthUnit.MM)


def default_mirror_board() -> CharucoSpec:
    """The small board used to calibrate the mirror (held between camera and mirror, or laid on it)."""
    return CharucoSpec(8, 6, "DICT_4X4_50", 22.0, 13.2, LengthUnit.MM)


def default_render(focus_mm: float = 0.0, aperture_mm: float | None = None) -> RenderSettings:
    """A plausible camera and projector: slight optical blur, read noise and shot noise (about 2 levels
    at mid-grey), and the photometric realism of docs/SIMULATOR.md: the projector's gamma 2.2 and black
    level 1/500, its lens (`aperture_mm`, default 7 mm) focused at `focus_mm` (0: the renderer's reference
    distance), the camera's BT.709-like tone curve (gamma 2.2) and vignetting to 0.6 in the image corners."""
    aperture = PROJECTOR_APERTURE_MM if aperture_mm is None else float(aperture_mm)
    return RenderSettings(blur_sigma_px=0.5, read_noise_dn=0.8, electrons_per_dn=40.0,
                          projector_gamma=PROJECTOR_GAMMA, projector_black_level=PROJECTOR_BLACK_LEVEL,
                          projector_aperture_mm=aperture, projector_focus_mm=float(focus_mm),
                          vignetting_corner=VIGNETTING_CORNER, camera_gamma=CAMERA_GAMMA)


# photometric defaults (justified in docs/SIMULATOR.md "Photometric realism")
PROJECTOR_GAMMA = 2.2  # a projector's standard picture mode follows the sRGB / BT.709 display curve
PROJECTOR_BLACK_LEVEL = 0.002  # 500:1 on/off contrast: a small DLP projector with its lens flare
PROJECTOR_APERTURE_MM = 7.0  # f 12.4 mm (2304 px at a 5.4 um DMD pitch) at f/1.8
SHORT_THROW_APERTURE_MM = 2.3  # f 4.1 mm (768 px at the same pitch) at f/1.8
VIGNETTING_CORNER = 0.6  # a wide (90 deg) lens' fall-off after the image processor's partial correction
CAMERA_GAMMA = 2.2  # the D455 colour stream is gamma-encoded video, not linear raw


@dataclass(frozen=True, eq=False)
class Scenario:
    name: str
    description: str
    rig: SyntheticRig
    layout: BoardLayout  # the projector-calibration board (ChArUco + blank region)
    mirror_board: CharucoSpec | None
    pattern: PatternSpec
    mirror_method: str | None  # "real-virtual" | "real-mirror" | None (direct rig)
    board_thickness_mm: float = 0.0  # real-mirror: printed face above the mirror surface
    render: RenderSettings = field(default_factory=RenderSettings)
    seed: int = 0
    per_position: int = 4
    mirror_count: int = 14  # as the published ProcamCalib recordings (52 projector + 14 mirror images)
    max_tilt_deg: float = 28.0  # the projector board's largest tilt away from facing projector and camera

    @property
    def projector_board(self) -> CharucoSpec:
        return self.layout.charuco

    @property
    def units(self) -> str:
        return self.rig.units

    @property
    def view(self) -> str:
        return self.rig.view

    def ground_truth(self) -> CalibrationResult:
        return self.rig.ground_truth()

    def with_seed(self, seed: int) -> "Scenario":
        return replace(self, seed=int(seed))

    # ---- poses (deterministic in the seed) ----------------------------------------------------------
    @cached_property
    def projector_poses(self) -> list[tuple[int, np.ndarray]]:
        """[(pattern_position, T_cam_board)], `per_position` per position, position-major."""
        return projector_poses(self.rig, self.layout, self.pattern, self.per_position, self.seed, self.max_tilt_deg)

    @cached_property
    def mirror_poses(self) -> list[np.ndarray]:
        if self.mirror_method is None:
            return []
        return self.mirror_poses_for(self.mirror_method, self.mirror_count)

    def mirror_poses_for(self, method: str, count: int, seed: int | None = None) -> list[np.ndarray]:
        """`count` mirror-calibration placements for `method` ('real-virtual' / 'real-mirror')."""
        if self.rig.mirror is None:
            raise SpecError(f"scenario '{self.name}' has no mirror to calibrate")
        board = self.mirror_board or default_mirror_board()
        thick = self.board_thickness_mm if method == MirrorMethod.REAL_MIRROR else 0.0
        if method == MirrorMethod.REAL_MIRROR and thick == 0.0:
            thick = 3.0
        s = self.seed + 1 if seed is None else seed
        if method == MirrorMethod.REAL_MIRROR:
            return mirror_poses(self.rig, board, method, count, s, thick)
        # real-virtual: keep the placements where the board and its reflection are well apart in the
        # image (a person would not hold the board where it touches its own reflection)
        poses = []
        for k in range(400):
            cand = mirror_poses(self.rig, board, method, 1, s * 1009 + k, thick)[0]
            if _apart_in_image(self.rig, board, cand):
                poses.append(cand)
                if len(poses) == count:
                    return poses
        raise RuntimeError(f"found only {len(poses)} of {count} real-virtual placements for '{self.name}'")

    def extra_projector_pose(self, position: int, index: int) -> np.ndarray:
        """A further valid pose for `position`, beyond the scripted ones (deterministic)."""
        rng = np.random.default_rng([self.seed, 7001, position, index])
        return projector_pose(self.rig, self.layout, self.pattern, position, rng, self.max_tilt_deg)

    @cached_property
    def centre_position(self) -> int:
        """The pattern position nearest the projector's centre."""
        proj = self.rig.projector
        c = np.array([(proj.width - 1) / 2, (proj.height - 1) / 2])
        d = [np.linalg.norm(self.pattern.points_px(proj.width, proj.height, p).mean(axis=0) - c)
             for p in range(self.pattern.positions)]
        return int(np.argmin(d))

    @cached_property
    def verification_pose(self) -> np.ndarray:
        return self.verification_pose_for(0)

    def verification_pose_for(self, index: int) -> np.ndarray:
        """A calm board pose, frontal to the projector, its blank region on the projector's central
        ray (for epipolar checks); index > 0 gives small deterministic variations."""
        rig, proj = self.rig, self.rig.projector
        T_cp = rig.T_cam_proj
        P = T_cp[:3, 3]
        centre = np.array([[(proj.width - 1) / 2, (proj.height - 1) / 2]])
        ray = T_cp[:3, :3] @ proj.rays(centre)[0]
        V = transform_points(rig.S(), np.zeros((1, 3)))[0]
        rng = np.random.default_rng([self.seed, 9001, index])
        for attempt in range(300):
            jitter = 0.0 if (index == 0 and attempt == 0) else 1.0
            D = rig.projector_distance_mm * (1.0 + jitter * rng.uniform(-0.08, 0.08))
            C = P + D * ray
            to_p = (P - C) / np.linalg.norm(P - C)
            to_v = (V - C) / np.linalg.norm(V - C)
            # mostly frontal to the projector, turned a little towards the (virtual) camera
            w = 0.25 + 0.1 * attempt / 300
            R = _frame_from_normal((1 - w) * to_p + w * to_v, T_cp[:3, 0])
            if jitter:
                R = rotation_about(R[:, 0], rng.uniform(-4, 4)) @ rotation_about(R[:, 1], rng.uniform(-4, 4)) @ R
            if attempt % 2 == 1:
                R = rotation_about(R[:, 2], 180.0) @ R
            T = make_T(R, C - R @ self.layout.blank_centre)
            if projector_pose_ok(rig, self.layout, self.pattern, self.centre_position, T):
                return T
        raise RuntimeError(f"no valid verification pose for scenario '{self.name}'")

    # ---- description ---------------------------------------------------------------------------
    def to_dict(self) -> dict:
        rig = self.rig
        d = {
            "name": self.name,
            "description": self.description,
            "seed": self.seed,
            "units": self.units,
            "view": self.view,
            "angle_deg": rig.angle_deg,
            "camera": rig.camera.to_dict(),
            "projector": rig.projector.to_dict(),
            "T_cam_proj": rig.T_cam_proj.tolist(),
            "mirror": None if rig.mirror is None else rig.mirror.to_dict(),
            "mirror_rect": None if rig.mirror_rect is None else {
                "centre": rig.mirror_rect.centre.tolist(), "axis_u": rig.mirror_rect.axis_u.tolist(),
                "axis_v": rig.mirror_rect.axis_v.tolist(), "size_mm": list(rig.mirror_rect.size)},
            "projector_board": self.layout.charuco.to_dict(),
            "board_layout": {"blank_width": self.layout.blank_width, "gap": self.layout.gap,
                             "blank_rect": list(self.layout.blank_rect), "outline": list(self.layout.outline)},
            "mirror_board": None if self.mirror_board is None else self.mirror_board.to_dict(),
            "pattern": self.pattern.to_dict(),
            "mirror_method": self.mirror_method,
            "board_thickness_mm": self.board_thickness_mm,
            "per_position": self.per_position,
            "mirror_count": self.mirror_count,
            "max_tilt_deg": self.max_tilt_deg,
            "render": self.render.to_dict(),
        }
        return d


def _apart_in_image(rig: SyntheticRig, board: CharucoSpec, T: np.ndarray, gap_px: int = 12) -> bool:
    """The board's outline (with its white border) and its reflection's are `gap_px` apart in the image."""
    import cv2

    from calib.synthetic import BoardLayout as _BL

    x0, y0, x1, y1 = _BL(board, 0.0, 0.0).outline
    t = np.linspace(0, 1, 12)
    edge = np.concatenate([np.column_stack([x0 + (x1 - x0) * t, np.full_like(t, y0)]),
                           np.column_stack([np.full_like(t, x1), y0 + (y1 - y0) * t]),
                           np.column_stack([x1 - (x1 - x0) * t, np.full_like(t, y1)]),
                           np.column_stack([np.full_like(t, x0), y1 - (y1 - y0) * t])])
    X = np.column_stack([edge, np.zeros(len(edge))])
    cam = rig.camera
    masks = []
    for TT in (T, rig.S() @ T):
        uv = cam.project(transform_points(TT, X))
        if not np.all(np.isfinite(uv)):
            return False
        m = np.zeros((cam.height, cam.width), np.uint8)
        cv2.fillPoly(m, [np.round(uv).astype(np.int32)], 1)
        masks.append(m)
    grown = cv2.dilate(masks[0], np.ones((2 * gap_px + 1, 2 * gap_px + 1), np.uint8))
    return not np.any(grown & masks[1])


# ---- the library ---------------------------------------------------------------------------------
def wide_angle_camera() -> CameraModel:
    """A wide-angle 1920x1080 camera: fx about 700 px (107 deg horizontal field of view), strong barrel
    distortion (k1 -0.2) with a small k3. Through the mirror it sees the board only in the middle of its
    image: the corners get no observations (issue 18's corner-poor case)."""
    return CameraModel(1920, 1080, [[700.0, 0, 963.5], [0, 700.8, 536.0], [0, 0, 1]],
                       [-0.2, 0.035, 0.0004, -0.0003, 0.0])


def short_throw_projector(width: int = 1920, height: int = 1080) -> CameraModel:
    """A short-throw projector: throw ratio 0.4 (a 1 m wide image from 40 cm, 100 deg across), its image
    almost wholly above its axis (principal point at 95% of the height), barrel and pincushion terms
    that nearly cancel in the corners."""
    f = 0.4 * width
    return CameraModel(width, height, [[f, 0, (width - 1) / 2 + 0.01 * width], [0, f * 1.002, 0.95 * height],
                                       [0, 0, 1]], [-0.04, 0.012, 0.0, 0.0, 0.0])


def _mirrored(name, description, angle_deg=136.0, projector=None, kind=PatternKind.CIRCLES, method=MirrorMethod.REAL_VIRTUAL,
              thickness_mm=0.0, seed=0, camera=None, mirror_board=None, max_tilt_deg=28.0, aperture_mm=None,
              **rig_kw) -> Scenario:
    rig = make_rig(angle_deg, camera=camera, projector=projector, **rig_kw)
    layout = BoardLayout(default_projector_board())
    pattern = PatternSpec.default_for(rig.projector.width, rig.projector.height, kind=kind)
    # the projector's light as bright on the boards as at the other rigs' distance
    render = replace(default_render(rig.projector_distance_mm, aperture_mm),
                     reference_distance_mm=rig.projector_distance_mm)
    return Scenario(name, description, rig, layout, mirror_board or default_mirror_board(), pattern, method,
                    thickness_mm, render, seed, max_tilt_deg=max_tilt_deg)


def _direct(seed=0) -> Scenario:
    rig = make_direct_rig()
    layout = BoardLayout(default_projector_board())
    pattern = PatternSpec.default_for(rig.projector.width, rig.projector.height)
    return Scenario("direct", "overlapping control: camera and projector side by side, no mirror", rig, layout,
                    None, pattern, None, 0.0, default_render(rig.projector_distance_mm), seed)


_BUILDERS = {
    "direct": _direct,
    "nonoverlap-90": lambda seed=0: _mirrored(
        "nonoverlap-90", "non-overlapping 90 deg, seen through a mirror, real-virtual mirror calibration", 90.0,
        seed=seed),
    "nonoverlap-136": lambda seed=0: _mirrored(
        "nonoverlap-136", "non-overlapping 136 deg (the paper's Unreal set-up), real-virtual; the default", 136.0,
        seed=seed),
    "nonoverlap-180": lambda seed=0: _mirrored(
        "nonoverlap-180", "non-overlapping 180 deg (projector facing the camera's back), real-virtual", 180.0,
        seed=seed),
    "nonoverlap-136-realmirror": lambda seed=0: _mirrored(
        "nonoverlap-136-realmirror", "136 deg, mirror calibrated with a 3 mm board lying on the mirror (real-mirror)",
        136.0, method=MirrorMethod.REAL_MIRROR, thickness_mm=3.0, seed=seed),
    "nonoverlap-136-720p": lambda seed=0: _mirrored(
        "nonoverlap-136-720p", "136 deg with a 1280x720 projector, real-virtual", 136.0,
        projector=portable_projector(1280, 720), seed=seed),
    "nonoverlap-136-chessboard": lambda seed=0: _mirrored(
        "nonoverlap-136-chessboard", "136 deg, projected chessboard pattern instead of circles, real-virtual",
        136.0, kind=PatternKind.CHESSBOARD, seed=seed),
    "wideangle-realmirror": lambda seed=0: _mirrored(
        "wideangle-realmirror", "136 deg, wide-angle 1920x1080 camera (fx 700 px, k1 -0.2), real-mirror: few views "
        "reach the image corners", 136.0, method=MirrorMethod.REAL_MIRROR, thickness_mm=3.0, seed=seed,
        camera=wide_angle_camera(), mirror_size_mm=(1000.0, 650.0), mirror_distance_mm=300.0),
    "shortthrow": lambda seed=0: _mirrored(
        "shortthrow", "short-throw projector (throw ratio 0.4) 14 cm from the camera, 136 deg, boards 34-46 cm in "
        "front of it tilted up to 45 deg, mirror at 13 cm, real-mirror with a 16 mm board", 136.0,
        projector=short_throw_projector(), method=MirrorMethod.REAL_MIRROR, thickness_mm=3.0, seed=seed,
        mirror_board=CharucoSpec(8, 6, "DICT_4X4_50", 16.0, 9.6, LengthUnit.MM), max_tilt_deg=45.0,
        aperture_mm=SHORT_THROW_APERTURE_MM, mirror_distance_mm=130.0, board_distance_mm=500.0,
        projector_distance_mm=400.0, elevation_deg=30.0),
}


def list_scenarios() -> list[tuple[str, str]]:
    """[(name, description)] of every named scenario, the default first."""
    names = [DEFAULT_SCENARIO] + [n for n in _BUILDERS if n != DEFAULT_SCENARIO]
    return [(n, get_scenario(n).description) for n in names]


def scenario_names() -> list[str]:
    return [DEFAULT_SCENARIO] + [n for n in _BUILDERS if n != DEFAULT_SCENARIO]


def get_scenario(name: str = DEFAULT_SCENARIO, seed: int = 0) -> Scenario:
    if name not in _BUILDERS:
        raise SpecError(f"unknown scenario '{name}' (one of: {', '.join(scenario_names())}; "
                        "`procam simulate --list` describes them)")
    return _BUILDERS[name](seed=int(seed))
