"""What limits the mirror normal's 1-sigma, and how well the joint result's outlook predicts what more
placements give (calib.joint.uncertainty `_mirror_outlook`, docs/JOINT.md "Uncertainty").

    python3 benchmarks/mirror_outlook.py [--scenarios nonoverlap-136 nonoverlap-136-realmirror] [--seeds 3]

For each scenario and seed: a rendered structured-light session at live quality (its 14 mirror
placements, 8 structured placements), detected once, then calibrated (joint) on its first m mirror and
first p projector placements. Printed per scenario (means over the seeds): the normal's 1-sigma at
(m, p) = (5, 6), the station's point of choice after its projector step; its share were the camera known;
the outlook's prediction with 1, 4 and 9 more mirror placements and 2 more projector placements against
what adding the session's own next placements gives; the true errors of the normal and of the
projector's position at 5 and 14 mirror placements.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.commands._bench_placements import _calibrate, _ordered_projector  # noqa: E402
from app.commands.simulate import simulate_session  # noqa: E402
from calib.detection.detect import detect_session  # noqa: E402
from calib.quality.confidence import targets  # noqa: E402
from calib.quality.metrics import compare  # noqa: E402
from calib.models.vocab import Step  # noqa: E402
from drivers.sim.scenarios import get_scenario  # noqa: E402

M0, P0 = 5, 6  # the station's mirror_first and its structured step's maximum


def one_seed(name: str, seed: int, tmp: Path) -> dict:
    sc = get_scenario(name, seed)
    gt = sc.ground_truth()
    store = simulate_session(sc, tmp / f"{name}-{seed}", quality="live", workers=1, force=True, progress=False,
                             structured_placements=8)
    obs = detect_session(store, 1, cache="refresh")
    proj = _ordered_projector(store, obs)
    n_m = len(obs.mirror_views)
    res = {}
    for m, p in ((M0, P0), (M0 + 1, P0), (M0 + 4, P0), (n_m, P0), (M0, P0 + 2)):
        r, why = _calibrate(obs, obs.mirror_views[:m], proj[:p])
        if r is None:
            raise SystemExit(f"{name} seed {seed}: ({m}, {p}) does not calibrate: {why}")
        res[(m, p)] = r
    u = res[(M0, P0)].uncertainty["mirror"]
    more_m, more_p = u["normal_deg_with_more_mirror"], u["normal_deg_with_more_projector"]

    def sig(m, p):
        return res[(m, p)].uncertainty["mirror"]["normal_deg"]

    def err(m, p, key):
        return compare(res[(m, p)], gt).to_dict()[key]

    return {"normal": u["normal_deg"], "given_camera": u["normal_deg_given_camera"],
            "pred_m1": more_m[0], "act_m1": sig(M0 + 1, P0), "pred_m4": more_m[3], "act_m4": sig(M0 + 4, P0),
            "pred_m9": more_m[n_m - M0 - 1], "act_m9": sig(n_m, P0),
            "pred_p2": more_p[1], "act_p2": sig(M0, P0 + 2),
            "err_normal_5": err(M0, P0, "mirror_angle_deg"), "err_normal_14": err(n_m, P0, "mirror_angle_deg"),
            "err_t_5": err(M0, P0, "distance"), "err_t_14": err(n_m, P0, "distance")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenarios", nargs="+", default=["nonoverlap-136", "nonoverlap-136-realmirror"])
    ap.add_argument("--seeds", type=int, default=3)
    args = ap.parse_args()
    target = targets(Step.REAL_VIRTUAL)["mirror_normal_deg"]
    print(f"mirror normal target {target:.4f} deg; (m, p) = ({M0}, {P0}); means over {args.seeds} seeds; "
          "predicted / actual 1-sigma, deg")
    print("| scenario | 1-sigma at (5, 6) | were the camera known | +1 mirror | +4 mirror | +9 mirror "
          "| +2 projector | normal error at 5 / 14 mirror deg | position error at 5 / 14 mirror mm |")
    print("|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory(prefix="procam-outlook-") as tmp:
        for name in args.scenarios:
            rows = [one_seed(name, s, Path(tmp)) for s in range(args.seeds)]
            mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
            print(f"| {name} | {mean['normal']:.4f} | {mean['given_camera']:.4f} "
                  + " ".join(f"| {mean['pred_' + k]:.4f} / {mean['act_' + k]:.4f}" for k in ("m1", "m4", "m9", "p2"))
                  + f" | {mean['err_normal_5']:.4f} / {mean['err_normal_14']:.4f} "
                  f"| {mean['err_t_5']:.3f} / {mean['err_t_14']:.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
