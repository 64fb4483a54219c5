"""Intrinsics held or constrained by their previous covariance as a prior (issue 15), on the simulated rig.

Per seed: a full session, then `procam recalibrate` after a projector bump, a mirror bump and a camera
bump. On each recalibration's own captures (same images, same order) the re-estimate is run again in
both modes (calib.recalib.reestimate, intrinsics="held" | "prior"), on every prefix the flow would have
looked at (the check's 4 captures, then 2 more per round): the captures each mode needs to reach its
1-sigma targets, and on all the captures the errors against the bumped truth with the reported 1-sigma
(error / 1-sigma near 1 is an honest uncertainty; far above 1 is overconfidence).

    PYTHONPATH=$PWD python benchmarks/recalibration_prior.py [--seeds 0 1 2 3] [--work DIR]
"""

import argparse
import json
import subprocess
import sys
import tempfile
from dataclasses import replace
from pathlib import Path


def procam(*args) -> int:
    r = subprocess.run([sys.executable, "-m", "app", *args], capture_output=True, text=True)
    if r.returncode not in (0, 1, 3):
        sys.exit(f"procam {' '.join(args)} failed ({r.returncode}):\n{r.stderr[-2000:]}")
    return r.returncode


def subset(obs, ids: set):
    return replace(obs, projector_views=tuple(v for v in obs.projector_views if v.capture_id in ids),
                   mirror_views=tuple(v for v in obs.mirror_views if v.capture_id in ids))


def evaluate(folder: Path, parts: tuple) -> dict:
    from calib.detection.detect import detect_session
    from calib.formats.session import SessionStore
    from calib.models.result import CalibrationResult
    from calib.quality.metrics import compare
    from calib.recalib import reestimate

    prev = CalibrationResult.load_json(folder / "previous" / "calibration.json")
    gt = CalibrationResult.load_json(folder / "ground_truth.json")
    with SessionStore.open(folder) as store:
        ids = [c.id for c in store.manifest.captures]
        obs = detect_session(store, 2)
    out = {}
    for mode in ("held", "prior"):
        need = None
        for n in range(4, len(ids) + 1, 2):
            if reestimate(prev, subset(obs, set(ids[:n])), parts, intrinsics=mode).reached:
                need = n
                break
        re = reestimate(prev, obs, parts, intrinsics=mode)
        m = compare(re.result, gt)
        u = prev.units
        row = {"need": need, "n": len(ids), "reached": re.reached}
        if "projector" in parts:
            s = re.sigma["projector"]
            row.update(t=m.distance, t_sig=s[f"t_{u}"], rot=m.angle_deg, rot_sig=s["rot_deg"])
        if "mirror" in parts:
            s = re.sigma["mirror"]
            row.update(mir=m.mirror_angle_deg, mir_sig=s["normal_deg"])
        row.update(camk=m.cam_k_px, projk=m.proj_k_px)
        out[mode] = row
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    ap.add_argument("--work", default=None)
    a = ap.parse_args()
    work = Path(a.work or tempfile.mkdtemp(prefix="procam-recal-prior-"))
    rows, camera_rows = [], []
    for seed in a.seeds:
        full = work / f"full-{seed}"
        if not (full / "calibration.json").exists():
            procam("session", "--rig", "sim", "--auto", "--seed", str(seed), "--out", str(full))
        for bump in ("projector", "mirror", "camera"):
            d = work / f"recal-{seed}-{bump}"
            rc = procam("recalibrate", str(full), "--rig", "sim", "--auto", "--seed", str(seed), "--sim-bump", bump,
                        "--out", str(d)) if not (d / "recalibration.json").exists() else None
            rec = json.loads((d / "recalibration.json").read_text())
            if bump == "camera":
                camera_rows.append((seed, rec["verdict"], rec["check"]["parts"]["camera"]["mahalanobis2"],
                                    rec["check"]["parts"]["camera"]["threshold"], rec["captures"]["total"], rc))
                continue
            if rec["check"]["parts"][bump]["status"] != "moved":
                print(f"seed {seed} bump {bump}: the check said {rec['verdict']}; skipped", flush=True)
                continue
            ev = evaluate(d, (bump,))
            rows.append((seed, bump, rc, ev))
            print(seed, bump, rc, json.dumps(ev), flush=True)
    print("\n| seed | bump | mode | captures to target | distance mm (1-sigma) | angle deg (1-sigma) | "
          "mirror deg (1-sigma) | CamK px | ProjK px |\n|---|---|---|---|---|---|---|---|---|")
    for seed, bump, rc, ev in rows:
        for mode, r in ev.items():
            t = f"{r['t']:.3f} ({r['t_sig']:.3f})" if "t" in r else "-"
            rot = f"{r['rot']:.4f} ({r['rot_sig']:.4f})" if "rot" in r else "-"
            mir = f"{r['mir']:.4f} ({r['mir_sig']:.4f})" if "mir" in r else "-"
            need = r["need"] if r["need"] is not None else f">{r['n']}"
            print(f"| {seed} | {bump} | {mode} | {need} | {t} | {rot} | {mir} | {r['camk']:.2f} | {r['projk']:.2f} |")
    print("\nmean error / 1-sigma (1 = honest; >> 1 overconfident):")
    for bump, keys in (("projector", ("t", "rot")), ("mirror", ("mir",))):
        for mode in ("held", "prior"):
            ev = [e[mode] for _, b, _, e in rows if b == bump]
            if ev:
                def mean(f):
                    return sum(f(r) for r in ev) / len(ev)

                print(f"  {bump} {mode}: " + ", ".join(
                    f"{k} {mean(lambda r: r[k] / r[k + '_sig']):.2f} (error {mean(lambda r: r[k]):.4f}, "
                    f"1-sigma {mean(lambda r: r[k + '_sig']):.4f})" for k in keys))
    print("\ncamera bump (the check, unchanged by the mode, runs first):")
    for seed, verdict, m2, thr, n, rc in camera_rows:
        print(f"  seed {seed}: {verdict} (camera m2 {m2:.1f} > {thr:.1f}), {n} captures, exit {rc}")
    print(f"\n(work folder: {work})")


if __name__ == "__main__":
    main()
