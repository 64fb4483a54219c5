"""The report as one self-contained HTML page: inline CSS, figures as data: URIs, no script, no
external resource (it opens offline, from a mail attachment or a USB stick)."""

from __future__ import annotations

import base64
import html
import math
import time

import numpy as np

from calib.quality.coverage import GRID_COLUMNS, coverage_fraction
from calib.quality.verdict import Level, overall_verdict
from calib.transforms import rotation_angle_deg

from . import figures
from .data import KINDS, ReportData
from calib.models.vocab import Step, View

CSS = """
body{font:14px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;color:#1d1d1f;margin:0;background:#f5f5f7}
main{max-width:1160px;margin:0 auto;padding:18px 28px 60px;background:#fff}
h1{font-size:24px;margin:8px 0 2px}h2{font-size:19px;margin:34px 0 8px;padding-top:10px;border-top:1px solid #ddd}
h3{font-size:15px;margin:18px 0 6px}.sub{color:#666;margin:0 0 12px}
table{border-collapse:collapse;margin:6px 0 10px;font-variant-numeric:tabular-nums}
th,td{padding:3px 10px;border-bottom:1px solid #e5e5e5;text-align:right;vertical-align:top}
th{background:#fafafa;font-weight:600}td.l,th.l{text-align:left}
.grid2{display:grid;grid-template-columns:1fr 1fr;gap:18px}
img.fig{max-width:100%;height:auto;display:block;margin:6px 0}img.thumb{width:100%;height:auto;display:block;border-radius:3px}
.note{color:#555;font-size:13px;max-width:980px}.fixed{color:#8a6d00}
.pass{color:#1e7e34;font-weight:600}.fail{color:#c0392b;font-weight:600}.warn{color:#b36b00;font-weight:600}
nav a{margin-right:12px;color:#0b62c4;text-decoration:none}
.thumbs{display:grid;grid-template-columns:repeat(auto-fill,minmax(420px,1fr));gap:14px}
figure{margin:0}figcaption{font-size:12px;color:#444}
code{background:#f2f2f2;padding:0 3px;border-radius:3px}
"""

SECTIONS = (("summary", "Summary"), ("parameters", "Parameters"), ("distortion", "Distortion"),
            ("residuals", "Residuals"), ("per-view", "Per view"), ("coverage", "Coverage"), ("rig", "Rig"),
            ("verification", "Verification"), ("exports", "Exports"))


def _e(x) -> str:
    return html.escape(str(x), quote=True)


def _img(data: bytes, alt: str, mime: str = "image/png", cls: str = "fig") -> str:
    return (f'<img class="{cls}" alt="{_e(alt)}" src="data:{mime};base64,'
            f'{base64.b64encode(data).decode("ascii")}">')


def fmt_pm(value: float, sigma, fixed: bool = False, unit: str = "") -> str:
    """'value ± sigma unit' with sigma to 2 significant digits and value to the same decimal place;
    'value unit (fixed)' for a parameter held fixed; the value alone when no sigma is known."""
    u = f" {html.escape(unit)}" if unit else ""
    if value is None or not math.isfinite(value):
        return "n/a"
    if fixed:
        return f'{value:.6g}{u} <span class="fixed">fixed</span>'
    if sigma is None or not math.isfinite(sigma) or sigma <= 0:
        return f"{value:.6g}{u}"
    dec = max(0, 1 - math.floor(math.log10(sigma)))
    return f"{value:.{dec}f} ± {sigma:.{dec}f}{u}"


def _cell(key: str, value, sigma=None, fixed=False, unit="") -> str:
    raw = "" if value is None else repr(float(value))
    return f'<td data-key="{_e(key)}" data-value="{raw}">{fmt_pm(value, sigma, fixed, unit)}</td>'


def _table(head: list[str], rows: list[str], cls_first: bool = True) -> str:
    h = "".join(f'<th class="{"l" if i == 0 and cls_first else ""}">{c}</th>' for i, c in enumerate(head))
    return f"<table><thead><tr>{h}</tr></thead><tbody>{''.join(rows)}</tbody></table>"


DIST_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


# ---- sections ----------------------------------------------------------------------------------------
_VERDICT_CLASS = {Level.TRUSTED: "pass", Level.LOW_QUALITY: "warn", Level.UNTRUSTED: "fail"}


def _verdict(d: ReportData) -> str:
    """The overall verdict, first: the trust check and the quality gate run on the calibration reported
    (calib.quality.verdict), not what the file says of itself."""
    v = overall_verdict(d.result, d.store.manifest.rig.view == View.MIRROR)
    items = "".join(f"<li>{_e(r)}</li>" for r in v.reasons)
    return (f'<p id="overall-verdict" data-level="{_e(v.level.value)}"><span class="{_VERDICT_CLASS[v.level]}">'
            f"{_e(v.headline)}</span></p>" + (f'<ul id="verdict-reasons">{items}</ul>' if items else ""))


def _summary(d: ReportData) -> str:
    r, cal = d.result, d.calibration
    m = d.store.manifest
    counts = {}
    for c in m.captures:
        counts[c.step] = counts.get(c.step, 0) + 1
    diag = d.diagnostics
    units = diag["rms_units"]
    rms = cal.get("rms") if isinstance(cal.get("rms"), dict) else {}
    rows = [f'<tr><td class="l">{_e(k)}</td><td data-key="rms.{_e(k)}" data-value="{float(v)!r}">{v:.4f} '
            f'{_e(units.get(k, "px"))}</td></tr>'
            for k, v in rms.items() if isinstance(v, (int, float)) and not isinstance(v, bool)]
    ver = "not verified"
    if d.verification is not None:
        v = d.verification
        ver = f'<span class="{"pass" if v.passed else "fail"}">{"PASS" if v.passed else "FAIL"}</span> ({_e(v.verdict)})'
    elif d.verification_problem:
        ver = f'<span class="warn">not verified: {_e(d.verification_problem)}</span>'
    skipped = cal.get("skipped") if isinstance(cal.get("skipped"), list) else []
    sk = ""
    if skipped:
        sk = "<h3>Captures not used</h3>" + _table(
            ["capture", "stage", "reason"],
            [f'<tr><td class="l">{_e(s.get("capture_id", ""))}</td><td class="l">{_e(s.get("stage", ""))}</td>'
             f'<td class="l">{_e(s.get("reason", ""))}</td></tr>' for s in skipped if isinstance(s, dict)])
    models = ""
    if diag["camera_model"]:
        models = (f"; distortion models: camera <code>{_e(diag.get('camera_model'))}</code>, projector "
                  f"<code>{_e(diag.get('projector_model'))}</code>")
    return f"""
<h2 id="summary">Summary</h2>
<table>
<tr><td class="l">session</td><td class="l">{_e(d.session_dir.resolve())}</td></tr>
<tr><td class="l">method</td><td class="l">{_e(r.method)}{models}</td></tr>
<tr><td class="l">rig</td><td class="l">camera {r.camera.width}x{r.camera.height} px, projector
{r.projector.width}x{r.projector.height} px, {"seen through a mirror" if m.rig.view == View.MIRROR else "direct view"},
driver <code>{_e(m.rig.driver)}</code>; lengths in {_e(r.units)}</td></tr>
<tr><td class="l">captures</td><td class="l">{", ".join(f"{n} {_e(s)}" for s, n in counts.items())};
{len(skipped)} not used</td></tr>
<tr><td class="l">verification</td><td class="l" id="verification-verdict">{ver}</td></tr>
</table>
<h3>RMS per stage or observation class (from calibration.json; px: pixels of the image observed)</h3>
{_table(["class", "RMS"], rows)}
{sk}"""


def _device_rows(name: str, prefix: str, model, unc: dict | None) -> tuple[list[str], list[str]]:
    """Table rows of one device's intrinsics and distortion; `unc` as data.clean_uncertainty."""
    u = unc[prefix] if unc else None
    fixed = bool(u and u["fixed"])
    rows = []
    for key, val in (("fx", model.fx), ("fy", model.fy), ("cx", model.cx), ("cy", model.cy)):
        s = None if not u else u[key]
        rows.append(f'<tr><td class="l">{name} {key}</td>{_cell(f"{prefix}.{key}", float(val), s, fixed, "px")}</tr>')
    drows = []
    sd = u["dist"] if u else []
    for i, val in enumerate(np.asarray(model.dist, float).tolist()):
        s = sd[i] if i < len(sd) else None
        f = fixed or (u is not None and s == 0.0)  # not estimated: held by the distortion model or given
        drows.append(f'<tr><td class="l">{name} {DIST_NAMES[i]}</td>{_cell(f"{prefix}.dist{i}", val, s, f)}</tr>')
    if not drows:
        drows.append(f'<tr><td class="l">{name}</td><td>no distortion coefficients</td></tr>')
    return rows, drows


def _parameters(d: ReportData) -> str:
    r, unc = d.result, d.uncertainty
    cam_rows, cam_d = _device_rows("camera", "camera", r.camera, unc)
    proj_rows, proj_d = _device_rows("projector", "projector", r.projector, unc)
    T = r.T_cam_proj
    tu = unc["T_cam_proj"] if unc else {"t": [None] * 3, "rot_deg": [None] * 3}
    ts, rs = tu["t"], tu["rot_deg"]
    trows = [f'<tr><td class="l">t{a}</td>{_cell(f"T_cam_proj.t{a}", float(T[i, 3]), ts[i], unit=r.units)}</tr>'
             for i, a in enumerate("xyz")]
    base = float(np.linalg.norm(T[:3, 3]))
    trows.append(f'<tr><td class="l">|t| (baseline)</td>{_cell("T_cam_proj.baseline", base, tu.get("t_total"), unit=r.units)}</tr>')
    trows.append(f'<tr><td class="l">rotation angle</td>{_cell("T_cam_proj.angle_deg", rotation_angle_deg(T[:3, :3]), tu.get("rot_total_deg"), unit="deg")}</tr>')
    for i, a in enumerate("xyz"):
        if rs[i] is not None:
            trows.append(f'<tr><td class="l">rotation 1-sigma about camera {a}</td>'
                         f'<td data-key="T_cam_proj.rot_sigma_{a}" data-value="{rs[i]!r}">{rs[i]:.2g} deg</td></tr>')
    R = "".join("<tr>" + "".join(f"<td>{v:.6f}</td>" for v in T[i]) + "</tr>" for i in range(4))
    mirror = '<p class="note">No mirror: a direct-view rig.</p>'
    if r.mirror is not None:
        mu = unc["mirror"] if unc else {}
        n = r.mirror.normal
        mrows = [f'<tr><td class="l">normal n{a}</td><td data-key="mirror.n{a}" data-value="{float(n[i])!r}">'
                 f'{float(n[i]):.6f}</td></tr>' for i, a in enumerate("xyz")]
        if mu.get("normal_deg") is not None:
            mrows.append(f'<tr><td class="l">normal direction 1-sigma</td><td data-key="mirror.normal_deg" '
                         f'data-value="{mu["normal_deg"]!r}">{mu["normal_deg"]:.2g} deg</td></tr>')
        mrows.append(f'<tr><td class="l">d (camera to mirror)</td>{_cell("mirror.d", r.mirror.d, mu.get("d"), unit=r.units)}</tr>')
        mirror = ("<p class=\"note\">The plane n·x + d = 0 in camera coordinates, n pointing to the camera.</p>"
                  + _table(["", "value"], mrows))
    if unc is None:
        sig = "<p class=\"note\">No 1-sigma values: this calibration did not compute its uncertainty.</p>"
    else:
        sig = (f"<p class=\"note\">± values are 1-sigma from the joint adjustment's covariance (variance factor "
               f"{unc['variance_factor'] or float('nan'):.3g}, {unc['dof'] or float('nan'):.0f} degrees of freedom; board poses "
               "marginalised). <span class=\"fixed\">fixed</span>: not estimated from this session: given "
               "intrinsics, or a coefficient the selected distortion model holds at its value.</p>")
    return f"""
<h2 id="parameters">Parameters</h2>
{sig}
<div class="grid2"><div><h3>Camera intrinsics</h3>{_table(["", "value"], cam_rows)}</div>
<div><h3>Projector intrinsics</h3>{_table(["", "value"], proj_rows)}</div></div>
<h3>T_cam_proj (projector to camera coordinates, p_cam = T_cam_proj · p_proj)</h3>
<div class="grid2"><div>{_table(["", "value"], trows)}</div><div><table>{R}</table>
<p class="note">Translation: the projector's centre in the camera frame ({_e(r.units)}).</p></div></div>
<h3>Mirror plane</h3>
{mirror}"""


def _distortion(d: ReportData) -> str:
    r, unc = d.result, d.uncertainty
    _, cam_d = _device_rows("camera", "camera", r.camera, unc)
    _, proj_d = _device_rows("projector", "projector", r.projector, unc)
    fig = figures.distortion_figure([("camera", r.camera), ("projector", r.projector)])
    return f"""
<h2 id="distortion">Distortion</h2>
<p class="note">OpenCV's model and order (k1, k2, p1, p2, k3[, k4, k5, k6]); the projector is an inverse camera.
The plot shows how far the model moves each pixel from where an ideal pinhole device would have it (pixels;
+: principal point).</p>
<div class="grid2"><div>{_table(["coefficient", "value"], cam_d)}</div><div>{_table(["coefficient", "value"], proj_d)}</div></div>
{_img(fig, "distortion displacement over the camera and projector images")}{_projection_uncertainty(d)}"""


def _projection_uncertainty(d: ReportData) -> str:
    """The projection-uncertainty heat maps (calib.quality.projection_uncertainty), when the result has them."""
    from calib.quality.projection_uncertainty import LARGE_SIGMA_PX, summary_line

    pu = d.result.projection_uncertainty
    if not isinstance(pu, dict):
        return ""
    devs = [(n, pu[n]) for n in ("camera", "projector") if isinstance(pu.get(n), dict) and pu[n].get("sigma_px")]
    if not devs:
        return ""
    fig = figures.projection_uncertainty_figure(devs, LARGE_SIGMA_PX)
    lines = "".join(f"<li>{_e(summary_line(pu, n))}</li>" for n, _ in devs)
    return f"""
<h3 id="projection-uncertainty">Projection uncertainty</h3>
<p class="note">How far the pixel of a ray moves at 1 sigma (worst direction), at each place of the image, from the
covariance of the intrinsics and distortion (the part a rotation of the device would absorb removed). Places
above {LARGE_SIGMA_PX:g} px are outlined: few or no observations reached them.</p>
<ul>{lines}</ul>
{_img(fig, "projection uncertainty over the camera and projector images")}"""


def _residuals(d: ReportData) -> str:
    head = '<h2 id="residuals">Reprojection residuals</h2>'
    res = d.residuals
    if res is None:
        return head + f'<p class="warn">The residuals could not be recomputed: {_e(d.residuals_problem)}</p>'
    r = d.result
    ok = ~res.cam_rejected
    cam = figures.residual_figure("camera", res.cam_uv[ok], res.cam_res[ok], r.camera.width, r.camera.height, "px")
    out = [head, f"""<p class="note">Recomputed from the session's detections (detections.json) with this calibration and
the board poses from {_e(res.poses_source)}: predicted minus detected position of every point. Camera: all
observations (board corners, projected pattern points, mirror-calibration corners), in camera pixels; recomputed RMS
<b id="recomputed-rms">{(res.rms() or float('nan')):.4f} px</b> over {int(ok.sum())} points
({int((~ok).sum())} rejected as outliers by the calibration, not counted). Projector: the pattern points' residuals
carried onto the board and into the projector image, in projector pixels. Arrows are the mean residual per cell
(a systematic pattern points to a model error; noise averages out).</p>""",
           "<h3>Camera</h3>", _img(cam, "camera residuals: heat map and vector field")]
    pk = ~res.proj_rejected & np.isfinite(res.proj_res).all(axis=1)
    if pk.any():
        prms = float(np.sqrt(np.mean(np.einsum("ij,ij->i", res.proj_res[pk], res.proj_res[pk]))))
        proj = figures.residual_figure("projector", res.proj_q[pk], res.proj_res[pk], r.projector.width,
                                       r.projector.height, "px")
        out += [f'<h3>Projector</h3><p class="note">RMS {prms:.4f} projector px over {int(pk.sum())} pattern points.</p>',
                _img(proj, "projector residuals: heat map and vector field")]
    kinds = []
    e2 = np.einsum("ij,ij->i", res.cam_res, res.cam_res)
    for k, name in enumerate(KINDS):
        sel = ok & (res.cam_kind == k)
        if sel.any():
            kinds.append(f'<tr><td class="l">{name}</td><td>{int(sel.sum())}</td><td>{np.sqrt(e2[sel].mean()):.4f} px</td>'
                         f'<td>{np.sqrt(e2[sel].max()):.4f} px</td></tr>')
    out.append(_table(["observation", "points", "RMS", "max"], kinds))
    return "\n".join(out)


def _per_view(d: ReportData) -> str:
    head = '<h2 id="per-view">Per-view RMS and the worst views</h2>'
    res = d.residuals
    entries = d.per_view
    ids = [pv["capture_id"] for pv in entries]
    # one entry per view (the joint method) is the view's RMS; a staged method lists a view per stage
    stored = {pv["capture_id"]: pv for pv in entries} if len(set(ids)) == len(ids) else {}
    recomputed = res.view_rms() if res is not None else {}
    step_of = {c.id: c.step for c in d.store.manifest.captures}
    rows = []
    for c in d.store.manifest.captures:
        v = stored.get(c.id, {}).get("rms_px")
        if not isinstance(v, (int, float)):
            v = recomputed.get(c.id)
        if v is not None:
            rows.append((c.id, c.step, float(v)))
    worst = d.diagnostics["worst_views"]
    source = "calibration.json's diagnostics.worst_views"
    if not worst:
        worst = [{"capture_id": cid, "step": st, "rms_px": v} for cid, st, v in sorted(rows, key=lambda t: -t[2])[:5]]
        source = "the largest per-view RMS"
    if not rows:
        return head + '<p class="note">This calibration holds no per-view residuals.</p>'
    fig = figures.per_view_figure(rows, {w["capture_id"] for w in worst})
    what = "calibration.json's per_view" if stored else "the recomputed residuals"
    out = [head, f'<p class="note">RMS of every view in capture order (camera px, from {what}; outlined: the worst '
                 f'views, from {source}).</p>',
           _img(fig, "per-view RMS"), "<h3>Worst views</h3>", '<div class="thumbs">']
    for w in worst:
        cid = w["capture_id"]
        cap = next((c for c in d.store.manifest.captures if c.id == cid), None)
        rms = w.get("rms_px")
        rms_txt = f"{rms:.4f} px" if isinstance(rms, (int, float)) else "n/a"
        cap_txt = (f'<b>{_e(cid)}</b> ({_e(w.get("step", step_of.get(cid, "")))}): RMS '
                   f'<span data-key="worst.{_e(cid)}" data-value="{rms!r}">{rms_txt}</span>')
        if cap is None or res is None or cid not in res.views:
            out.append(f"<figure><figcaption>{cap_txt}; no image or residuals to show</figcaption></figure>")
            continue
        try:
            image = d.store.load_image(cap)
        except Exception as e:  # noqa: BLE001 - a missing image must not stop the report
            out.append(f"<figure><figcaption>{cap_txt}; image not shown: {_e(e)}</figcaption></figure>")
            continue
        v = res.views.index(cid)
        sel = res.cam_view == v
        jpg, mag = figures.view_thumbnail(image, res.cam_uv[sel], res.cam_res[sel], res.cam_rejected[sel])
        n_rej = int(res.cam_rejected[sel].sum())
        out.append(f"<figure>{_img(jpg, f'capture {cid} with its residuals', 'image/jpeg', 'thumb')}"
                   f"<figcaption>{cap_txt}, {int(sel.sum())} points, max "
                   f"{np.sqrt(np.einsum('ij,ij->i', res.cam_res[sel], res.cam_res[sel]).max()):.3f} px; residuals "
                   f"drawn x{mag:g}{f', {n_rej} rejected (magenta)' if n_rej else ''}</figcaption></figure>")
    out.append("</div>")
    return "\n".join(out)


def _coverage(d: ReportData) -> str:
    head = '<h2 id="coverage">Coverage</h2>'
    res = d.residuals
    if res is None:
        return head + f'<p class="warn">No detections to show: {_e(d.residuals_problem)}</p>'
    r = d.result
    cam_pts = [(k, res.cam_uv[res.cam_kind == i]) for i, k in enumerate(KINDS)]
    corners = res.cam_uv[res.cam_kind == KINDS.index("board")]  # the definition the panel uses too
    cf = coverage_fraction(corners, r.camera.width, r.camera.height)
    pf = coverage_fraction(res.proj_q, r.projector.width, r.projector.height)
    fig = figures.coverage_figure(cam_pts, r.camera.size, res.proj_q, r.projector.size, cf, pf)
    return head + f"""<p class="note">Where the detected points landed in the camera image, and where the pattern points
that were used lie in the projector image. The image corners constrain the higher distortion terms: empty cells there
mean the model is extrapolated. Coverage is the share of an image's {GRID_COLUMNS}-column grid cells that hold a point
(the station's panel says the same): camera <b id="coverage-camera">{cf:.0%}</b> (board corners), projector
<b id="coverage-projector">{pf:.0%}</b> (pattern points).</p>{_img(fig, "coverage of the camera and projector images")}"""


def _rig(d: ReportData) -> str:
    r, res = d.result, d.residuals
    boards = []
    m = d.store.manifest
    if res is not None:
        for cid, T in res.board_poses.items():
            step = res.steps[res.views.index(cid)]
            spec = m.projector_board if step == Step.PROJECTOR else (m.mirror_board or m.projector_board)
            w, h = spec.size
            outline = np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], float)
            boards.append((step, outline @ T[:3, :3].T + T[:3, 3]))
    fig = figures.rig_figure(r.camera, r.projector, r.T_cam_proj, r.mirror, boards, r.units)
    mirror = (" the mirror plane (blue, a square around where the camera's optical axis meets it),"
              if r.mirror is not None else "")
    poses = "" if res is None else f" ({len(boards)}, {'from calibration.json' if res.poses_source == 'calibration.json' else 'found by PnP'})"
    return f"""
<h2 id="rig">The rig in 3D</h2>
<p class="note">Camera frame (OpenCV axes, drawn with up = -y), lengths in {_e(r.units)}. Viewing pyramids of the
camera (black) and the projector (red),{mirror} and the real position of every board pose the calibration
used{poses}.</p>
{_img(fig, "the rig in 3D")}"""


def _verification(d: ReportData) -> str:
    head = '<h2 id="verification">Verification</h2>'
    v = d.verification
    if v is None:
        from app.verification import verify_command

        why = d.verification_problem or ("this session has no verification.json; run "
                                          f"<code>{_e(verify_command(d.session_dir))}</code> to measure one")
        return head + f'<p id="verification-status"><b>not verified</b>: {why}</p>'
    from app.verification import WORST_FACTOR

    thr, wf = v.threshold_px, WORST_FACTOR
    checks = list(v.checks)

    def num(x, fmt=".3f"):
        return "n/a" if x is None else format(float(x), fmt)

    def tagged(key, x, tag="td"):
        return f'<{tag} data-key="{key}" data-value="{"" if x is None else repr(float(x))}">{num(x)}</{tag}>'

    rows = []
    for i, c in enumerate(checks, 1):
        verdict = figures.check_verdict(c, thr, wf)
        cls = {"pass": "pass", "fail": "fail", "above mean limit": "warn"}.get(verdict, "")
        rows.append(f'<tr><td class="l">{i}</td><td>({c.pixel[0]:.1f}, {c.pixel[1]:.1f})</td>'
                    f'{tagged(f"check{i}.distance_px", c.distance_px)}'
                    f'{tagged(f"check{i}.distance_proj_px", c.distance_proj_px)}<td class="l {cls}">{_e(verdict)}'
                    f'{": " + _e(c.reason) if c.reason else ""}</td></tr>')
    if any(len(c.detected_curve) for c in checks):
        fig = _img(figures.verification_figure(checks, d.result.camera.size, thr, wf),
                   "verification curves on the camera image")
    else:
        fig = '<p class="note">This verification.json holds no curves to draw.</p>'
    return head + f"""
<p id="verification-status"><span class="{"pass" if v.passed else "fail"}">{"PASS" if v.passed else "FAIL"}</span>:
{_e(v.verdict)}. {v.n_measured} of {len(checks)} pixels measured; mean
{tagged("verification.mean_proj_px", v.mean_proj_px, "span")}, worst
{tagged("verification.worst_proj_px", v.worst_proj_px, "span")} projector px (mean
{tagged("verification.mean_camera_px", v.mean_px, "span")}, worst
{tagged("verification.worst_camera_px", v.worst_px, "span")} camera px); measured {_e(v.created)}.</p>
<p class="note">For each checked camera pixel the projector drew the pixel's predicted epipolar curve; the camera saw
the stroke (solid, coloured by the check's own verdict: within {thr:g} projector px = pass, within {wf * thr:g} =
above the mean limit, beyond = fail); dashed: where the calibration expected it. The distance is from the pixel to the
detected stroke. Drawn over the camera image's frame (verification.json keeps the curves, not the image).</p>
{fig}
{_table(["#", "pixel (camera px)", "distance (camera px)", "distance (projector px)", "verdict"], rows)}"""


def _exports(d: ReportData) -> str:
    """The files other software loads this calibration from (calib.export), which of them the session
    holds, and the command that writes the others."""
    import os

    from calib.export.registry import EXPORTERS

    rows = []
    for name, e in EXPORTERS.items():
        files = [p.name for p in e.paths(d.session_dir, d.calibration_stem)]
        here = [f for f in files if os.path.lexists(d.session_dir / f)]  # named, never read
        rows.append(f'<tr><td class="l"><code>{_e(name)}</code></td><td class="l">{_e(e.summary)}</td>'
                    f'<td class="l">{"<br>".join(f"<code>{_e(f)}</code>" for f in files)}</td>'
                    f'<td class="l">{"in the session" if len(here) == len(files) else "not written yet"}</td></tr>')
    source = d.session_dir if d.calibration_stem == "calibration" else d.session_dir / f"{d.calibration_stem}.json"
    return f"""
<h2 id="exports">Exports</h2>
<p class="note">This calibration for the software that projects or reconstructs with it: ROS (camera_info), mrcal
(.cameramodel), OpenGL (projection and view matrices), Unity and three.js (virtual cameras), OpenCV (FileStorage
YAML). The station's download zip carries the ones chosen under <code>exports/</code>; write any of them with
<code>procam export {_e(source)} --format all --out DIR</code>. How to load each: docs/FORMATS.md, "Loading the
exports". A distortion a format cannot hold is left out with a warning giving its residual in px.</p>
{_table(["format", "what", "files", "here"], rows)}"""


def render(d: ReportData) -> str:
    """The whole page."""
    t0 = time.strftime("%Y-%m-%d %H:%M:%S %Z")
    nav = " ".join(f'<a href="#{i}">{t}</a>' for i, t in SECTIONS)
    body = "".join(f(d) for f in (_verdict, _summary, _parameters, _distortion, _residuals, _per_view, _coverage, _rig,
                                  _verification, _exports))
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>Calibration report: {_e(d.session_dir.resolve().name)}</title>
<style>{CSS}</style></head>
<body><main>
<h1>Calibration report: {_e(d.session_dir.resolve().name)}</h1>
<p class="sub">procam-station, written {_e(t0)}</p>
<nav>{nav}</nav>
{body}
</main></body></html>
"""
