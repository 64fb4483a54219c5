"""The structured-light sequence on the simulated rig: its camera images, and the exact projector
coordinates every camera pixel sees (the ground truth decoding is measured against).

`render_sequence` renders each frame of a calib.models.structured_light.StructuredLightSpec onto a
board that stands still, with the renderer's photometric effects (defocus, gamma, black level,
vignetting, blur, noise). `placement_poses` picks a few of a scenario's projector poses for a structured
session. `true_projector_px` traces camera pixels to the board (through the mirror when
the rig has one) and projects the hit points into the projector, its distortion included.
"""

from __future__ import annotations

import numpy as np

from calib.models.structured_light import StructuredLightSpec, placement_order
from calib.synthetic import BoardLayout
from calib.transforms import invert_T, rays_to_board_plane, transform_points
from drivers.sim.render import PlacedBoard, Renderer, SceneState


def render_sequence(renderer: Renderer, layout: BoardLayout, T_cam_board: np.ndarray, spec: StructuredLightSpec,
                    rng: np.random.Generator | None = None, settings=None) -> list[np.ndarray]:
    """The camera images (BGR uint8) of every frame of `spec`, in its order, for a board at T_cam_board."""
    P = renderer.projector
    board = (PlacedBoard(layout, np.asarray(T_cam_board, float)),)
    rng = rng or np.random.default_rng(0)
    return [renderer.render(SceneState(board, img), rng, settings) for img in spec.images(P.width, P.height)]


def true_projector_px(renderer: Renderer, layout: BoardLayout, T_cam_board: np.ndarray,
                      uv: np.ndarray) -> np.ndarray:
    """(N, 2) projector pixels lighting the board points seen at camera pixels `uv` (N, 2); NaN where the
    pixel's ray misses the board's outline or meets it from behind. Through the mirror the camera sees
    the board at S @ T_cam_board (the mirror's finite extent is not checked: compare decoded pixels)."""
    uv = np.asarray(uv, float).reshape(-1, 2)
    T = np.asarray(T_cam_board, float)
    T_view = T if renderer.mirror is None else renderer.mirror.reflection() @ T
    Xb, t = rays_to_board_plane(invert_T(T_view), renderer.camera.rays(uv))
    x0, y0, x1, y1 = layout.outline
    ok = (t > 0) & (Xb[:, 0] >= x0) & (Xb[:, 0] <= x1) & (Xb[:, 1] >= y0) & (Xb[:, 1] <= y1)
    q = renderer.projector.project(transform_points(renderer.T_proj_cam @ T, Xb))
    q[~ok] = np.nan
    return q


def placement_poses(scenario, n: int) -> list[tuple[int, int]]:
    """(pattern position, pose index in that position) of `n` of the scenario's scripted projector poses:
    one pose of each position in calib.models.structured_light.POSITION_ORDER, then the next pose of each, ..."""
    per = scenario.per_position
    n_poses = len(scenario.projector_poses)
    return [(p, k) for p, k in placement_order(scenario.pattern.positions, per) if p * per + k < n_poses][:n]
