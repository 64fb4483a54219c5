"""The paper's sequential method (Vanherck et al. 2025), one module per stage with one entry function:

  camera      stage 1, the camera's intrinsics (Zhang, every board view): `calibrate_camera`
  mirror      stage 2, the mirror plane (real-virtual or real-mirror): `calibrate_mirror`
  projector   stage 3, the projector's intrinsics and T_cam_proj: `calibrate_projector`
  method      the three stages in order, the "paper" method of calib.pipeline: `calibrate_paper`
  board_pose  board poses by PnP and Zhang's calibration, shared by the stages (and by
              calib.recalib and the epipolar verification)

Nothing is re-exported: import from the stage's module (`from calib.paper.method import
calibrate_paper`).
"""
