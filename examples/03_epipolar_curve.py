"""03: the epipolar curve a projector draws for a camera pixel seen through the mirror.

With lens distortion on both devices the "line" is a curve; it passes through the projector pixel
that lights the board point the camera sees at that pixel.

    python examples/03_epipolar_curve.py
"""

import numpy as np

from calib.epipolar import distance_to_polyline, epipolar_curve
from calib.synthetic import make_rig, make_session, projector_points_on_board
from calib.transforms import transform_points

rig = make_rig(136)
truth = rig.ground_truth()
session = make_session(rig, seed=0)
position, T_cam_board = session.projector_T_cam_board[0]

# a board point lit by projector pixel q, and the camera pixel where it is seen through the mirror
q = np.array([[700.0, 400.0]])
X_board = projector_points_on_board(rig, T_cam_board, q)
X_cam = transform_points(T_cam_board, X_board)
cam_px = rig.camera.project(transform_points(rig.S(), X_cam))[0]

curve = epipolar_curve(truth, cam_px)
gap = distance_to_polyline(q, curve)
print(f"camera pixel {cam_px.round(3)} -> projector curve of {len(curve)} samples")
print(f"distance of the lighting projector pixel {q[0]} to the curve: {np.ravel(gap.distance)[0]:.2e} px")
