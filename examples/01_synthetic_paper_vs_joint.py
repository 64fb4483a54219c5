"""01: the two calibration methods on exact-geometry synthetic observations (no images).

A rig at 136 degrees (the paper's Unreal setup), the paper's protocol (7 real-virtual mirror images,
13 pattern positions x 4 board poses), 0.2 px detection noise and the projected circles reported where
a blob detector sees them (their imaged centroids, biased by perspective). Prints the paper's metrics
of the sequential "paper" method and of the joint maximum-likelihood refinement.

    python examples/01_synthetic_paper_vs_joint.py
"""

from calib.pipeline import calibrate_observations
from calib.quality.metrics import compare
from calib.synthetic import make_rig, make_session, observe

rig = make_rig(angle_deg=136)
session = make_session(rig, seed=1)
observations = observe(session, noise_px=0.2, seed=1, circle_centroids=True)

for method in ("paper", "joint"):
    result = calibrate_observations(observations, method=method)
    print(f"--- {method}")
    print(compare(result, rig.ground_truth()).format_table())
