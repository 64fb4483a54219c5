"""The report's figures, each returned as PNG (or JPEG) bytes.

matplotlib's object API (Figure + its Agg canvas, never pyplot): no global state, no display, safe in a
thread. Image coordinates are drawn as the images are: x right, y down, pixel (0, 0) the centre of the
top-left pixel, one data unit per pixel (equal aspect).
"""

from __future__ import annotations

import io
import math

import cv2
import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from calib.models.camera import CameraModel
from calib.models.vocab import Step
from calib.quality.coverage import grid_shape

STEP_COLOURS = {Step.PROJECTOR: "#1f77b4", Step.REAL_VIRTUAL: "#ff7f0e", Step.REAL_MIRROR: "#2ca02c"}
KIND_COLOURS = {"board": "#1f77b4", "pattern": "#d62728", "mirror-real": "#ff7f0e", "mirror-virtual": "#9467bd"}
DPI = 100


def _margins(fig: Figure, left=0.06, right=0.98, bottom=0.12, top=0.92, wspace=0.22) -> None:
    """Fixed margins, chosen per figure (tight_layout would cost a third of the drawing time)."""
    fig.subplots_adjust(left=left, right=right, bottom=bottom, top=top, wspace=wspace)


def png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return buf.getvalue()


def _image_axes(ax, width: int, height: int, title: str) -> None:
    ax.set_xlim(-0.5, width - 0.5)
    ax.set_ylim(height - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("x (px)", fontsize=8)
    ax.set_ylabel("y (px)", fontsize=8)
    ax.tick_params(labelsize=7)


# ---- distortion --------------------------------------------------------------------------------------
def distortion_displacement(model: CameraModel, nx: int = 96) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(xs, ys, |d|): how far the lens model moves each pixel (distorted pixel vs the pixel an ideal
    pinhole would give for the same ray), on an nx-column grid over the image, in pixels."""
    W, H = model.width, model.height
    ny = max(2, round(nx * H / W))
    xs, ys = np.linspace(-0.5, W - 0.5, nx), np.linspace(-0.5, H - 0.5, ny)
    X, Y = np.meshgrid(xs, ys)
    uv = np.column_stack([X.ravel(), Y.ravel()])
    xy = model.undistort_normalized(uv)
    ideal = np.column_stack([model.fx * xy[:, 0] + model.cx, model.fy * xy[:, 1] + model.cy])
    mag = np.linalg.norm(uv - ideal, axis=1).reshape(ny, nx)
    return xs, ys, mag


def distortion_figure(devices: list[tuple[str, CameraModel]]) -> bytes:
    fig = Figure(figsize=(5.2 * len(devices), 3.6))
    for i, (name, model) in enumerate(devices):
        ax = fig.add_subplot(1, len(devices), i + 1)
        xs, ys, mag = distortion_displacement(model)
        finite = mag[np.isfinite(mag)]
        top = float(finite.max()) if finite.size else 0.0
        if top <= 1e-9:
            ax.set_facecolor("#f4f4f4")
            ax.text(0.5, 0.5, "no distortion", transform=ax.transAxes, ha="center", va="center")
        else:
            im = ax.imshow(mag, extent=(xs[0], xs[-1], ys[-1], ys[0]), cmap="viridis", vmin=0, vmax=top,
                           interpolation="bilinear")
            ax.contour(xs, ys, mag, levels=np.linspace(0, top, 7)[1:-1], colors="white", linewidths=0.5, alpha=0.8)
            cb = fig.colorbar(im, ax=ax, shrink=0.85)
            cb.set_label("displacement (px)", fontsize=8)
            cb.ax.tick_params(labelsize=7)
        ax.plot(model.cx, model.cy, "+", color="red", ms=9, mew=1.5)
        _image_axes(ax, model.width, model.height, f"{name}: up to {top:.1f} px")
    _margins(fig, left=0.08, right=0.97, bottom=0.13, top=0.9, wspace=0.3)
    return png(fig)


def projection_uncertainty_figure(devices: list[tuple[str, dict]], large_px: float) -> bytes:
    """Heat maps of the projection-uncertainty grids (calib.quality.projection_uncertainty), one per device, the
    cells above `large_px` outlined by a contour."""
    fig = Figure(figsize=(5.2 * len(devices), 3.6))
    for i, (name, g) in enumerate(devices):
        ax = fig.add_subplot(1, len(devices), i + 1)
        s = np.asarray(g["sigma_px"], float)
        xs, ys = np.asarray(g["x_px"], float), np.asarray(g["y_px"], float)
        W, H = int(g["width"]), int(g["height"])
        finite = s[np.isfinite(s)]
        top = float(finite.max()) if finite.size else 1.0
        im = ax.imshow(np.where(np.isfinite(s), s, top), extent=(-0.5, W - 0.5, H - 0.5, -0.5), cmap="magma",
                       vmin=0, vmax=max(top, 1e-9), interpolation="nearest")
        if np.nanmin(s) <= large_px < top:
            ax.contour(xs, ys, s, levels=[large_px], colors="cyan", linewidths=1.2)
        cb = fig.colorbar(im, ax=ax, shrink=0.85)
        cb.set_label("1-sigma (px)", fontsize=8)
        cb.ax.tick_params(labelsize=7)
        _image_axes(ax, W, H, f"{name}: median {np.median(s):.3f}, max {top:.3f} px")
    _margins(fig, left=0.08 if len(devices) > 1 else 0.13, right=0.97, bottom=0.13, top=0.9, wspace=0.3)
    return png(fig)


# ---- residuals ---------------------------------------------------------------------------------------
def binned(uv: np.ndarray, res: np.ndarray, width: int, height: int, nx: int = 16):
    """Per grid cell: RMS of the residual norm, mean residual vector and point count."""
    nx, ny = grid_shape(width, height, nx)
    ix = np.clip((uv[:, 0] + 0.5) / width * nx, 0, nx - 1e-9).astype(int)
    iy = np.clip((uv[:, 1] + 0.5) / height * ny, 0, ny - 1e-9).astype(int)
    cell = iy * nx + ix
    n = np.bincount(cell, minlength=nx * ny).astype(float)
    e2 = np.bincount(cell, np.einsum("ij,ij->i", res, res), minlength=nx * ny)
    mx = np.bincount(cell, res[:, 0], minlength=nx * ny)
    my = np.bincount(cell, res[:, 1], minlength=nx * ny)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(e2 / n)
        mean = np.column_stack([mx / n, my / n])
    return rms.reshape(ny, nx), mean.reshape(ny, nx, 2), n.reshape(ny, nx)


def _nice(x: float) -> float:
    """A round number (1, 2 or 5 x 10^k) near x."""
    if not x > 0 or not math.isfinite(x):
        return 1.0
    e = math.floor(math.log10(x))
    f = x / 10**e
    return (1 if f < 1.5 else 2 if f < 3.5 else 5 if f < 7.5 else 10) * 10**e


def residual_figure(name: str, uv: np.ndarray, res: np.ndarray, width: int, height: int, unit: str) -> bytes:
    """Heat map of the RMS residual per image cell, and the mean residual vector per cell (arrows)."""
    fig = Figure(figsize=(11, 3.9))
    ok = np.isfinite(res).all(axis=1) & np.isfinite(uv).all(axis=1)
    uv, res = uv[ok], res[ok]
    rms, mean, n = binned(uv, res, width, height)
    nx, ny = rms.shape[1], rms.shape[0]
    cw, ch = width / nx, height / ny
    ax = fig.add_subplot(1, 2, 1)
    top = float(np.nanpercentile(rms[n > 0], 98)) if (n > 0).any() else 1.0
    im = ax.imshow(np.where(n > 0, rms, np.nan), extent=(-0.5, width - 0.5, height - 0.5, -0.5), cmap="magma",
                   vmin=0, vmax=max(top, 1e-6), interpolation="nearest")
    ax.set_facecolor("#dddddd")
    cb = fig.colorbar(im, ax=ax, shrink=0.85)
    cb.set_label(f"RMS residual ({unit})", fontsize=8)
    cb.ax.tick_params(labelsize=7)
    _image_axes(ax, width, height, f"{name}: RMS residual per cell (grey: no points)")
    ax2 = fig.add_subplot(1, 2, 2)
    cx = (np.arange(nx) + 0.5) * cw - 0.5
    cy = (np.arange(ny) + 0.5) * ch - 0.5
    X, Y = np.meshgrid(cx, cy)
    has = n > 0
    lengths = np.linalg.norm(mean[has], axis=1)
    longest = float(lengths.max()) if lengths.size else 0.0
    if longest > 0:
        key = _nice(longest / 2)
        scale = key / (0.9 * cw)  # a `key`-long residual is drawn 0.9 cells long
        ax2.scatter(uv[:, 0], uv[:, 1], s=0.3, c="#bbbbbb", linewidths=0, rasterized=True)
        q = ax2.quiver(X[has], Y[has], mean[has][:, 0], mean[has][:, 1], lengths, cmap="viridis", angles="xy",
                       scale_units="xy", scale=scale, width=0.004)
        ax2.quiverkey(q, 0.82, 1.045, key, f"{key:g} {unit}", labelpos="E", coordinates="axes",
                      fontproperties={"size": 8})
    _image_axes(ax2, width, height, f"{name}: mean residual per cell")
    _margins(fig, left=0.06, right=0.98, bottom=0.13, top=0.9, wspace=0.18)
    return png(fig)


# ---- per view ----------------------------------------------------------------------------------------
def per_view_figure(rows: list[tuple[str, str, float]], worst: set) -> bytes:
    """rows: (capture id, step, rms px) in capture order; `worst` ids are outlined and labelled."""
    fig = Figure(figsize=(11, 3.2))
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(rows))
    vals = np.array([r[2] for r in rows], float)
    colours = [STEP_COLOURS.get(r[1], "#7f7f7f") for r in rows]
    edge = ["black" if r[0] in worst else "none" for r in rows]
    ax.bar(x, vals, color=colours, edgecolor=edge, linewidth=1.2)
    for i, r in enumerate(rows):
        if r[0] in worst:
            ax.annotate(r[0], (i, vals[i]), xytext=(0, 3), textcoords="offset points", ha="center", fontsize=7,
                        rotation=90, va="bottom")
    ax.set_xticks(x)
    ax.set_xticklabels([r[0] for r in rows], rotation=90, fontsize=6)
    ax.set_xlim(-0.7, len(rows) - 0.3)
    ax.set_ylim(0, (np.nanmax(vals) if len(vals) else 1) * 1.45)
    ax.set_ylabel("RMS residual (camera px)", fontsize=8)
    ax.tick_params(axis="y", labelsize=7)
    for step, c in STEP_COLOURS.items():
        if any(r[1] == step for r in rows):
            ax.bar([0], [0], color=c, label=step)
    ax.legend(fontsize=8, loc="lower left", bbox_to_anchor=(0.0, 1.0), ncols=3, frameon=False)
    ax.grid(axis="y", alpha=0.3)
    _margins(fig, left=0.06, right=0.99, bottom=0.2, top=0.9)
    return png(fig)


def view_thumbnail(image: np.ndarray, uv: np.ndarray, res: np.ndarray, rejected: np.ndarray,
                   width_px: int = 420) -> tuple[bytes, float]:
    """The capture, dimmed, with its detected points (green) and residual vectors magnified (red);
    rejected points as magenta crosses. Returns (JPEG bytes, magnification)."""
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.dtype != np.uint8:
        image = cv2.convertScaleAbs(image, alpha=255.0 / max(float(image.max()), 1.0))
    H, W = image.shape[:2]
    # crop to the points (with a margin), at the image's aspect ratio, so that the residuals show
    fin = uv[np.isfinite(uv).all(axis=1)]
    x0, y0, x1, y1 = 0, 0, W, H
    if len(fin):
        lo, hi = fin.min(axis=0), fin.max(axis=0)
        cw = max(hi[0] - lo[0], (hi[1] - lo[1]) * W / H) * 1.25 + 40
        cw = min(cw, W)
        ch = cw * H / W
        cx, cy = (lo + hi) / 2
        x0 = int(np.clip(cx - cw / 2, 0, W - cw))
        y0 = int(np.clip(cy - ch / 2, 0, H - ch))
        x1, y1 = int(x0 + cw), int(y0 + ch)
    image = image[y0:y1, x0:x1]
    uv = uv - [x0, y0]
    f = width_px / image.shape[1]
    small = cv2.resize(image, (width_px, max(1, round(image.shape[0] * f))), interpolation=cv2.INTER_AREA)
    small = (small.astype(np.float32) * 0.6).astype(np.uint8)
    e = np.linalg.norm(res, axis=1)
    good = np.isfinite(e) & ~rejected
    longest = float(e[good].max()) if good.any() else 0.0
    mag = _nice(15.0 / f / longest) if longest > 0 else 1.0  # the longest residual ~15 thumbnail px
    for (u, v), r, bad in zip(uv, res, rejected):
        p = (int(round(u * f * 16)), int(round(v * f * 16)))
        if bad:
            cv2.drawMarker(small, (p[0] // 16, p[1] // 16), (255, 0, 255), cv2.MARKER_TILTED_CROSS, 9, 2)
            continue
        cv2.circle(small, p, 2 * 16, (80, 220, 80), 1, cv2.LINE_AA, shift=4)
        if np.isfinite(r).all():
            q = (int(round((u + r[0] * mag) * f * 16)), int(round((v + r[1] * mag) * f * 16)))
            cv2.line(small, p, q, (60, 60, 255), 1, cv2.LINE_AA, shift=4)
    ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 88])
    return buf.tobytes(), mag


# ---- coverage ----------------------------------------------------------------------------------------
def coverage_figure(camera_points: list[tuple[str, np.ndarray]], cam_size, proj_points: np.ndarray, proj_size,
                    cam_fraction: float, proj_fraction: float) -> bytes:
    fig = Figure(figsize=(11, 3.8))
    ax = fig.add_subplot(1, 2, 1)
    for kind, uv in camera_points:
        if len(uv):
            ax.scatter(uv[:, 0], uv[:, 1], s=1.5, c=KIND_COLOURS.get(kind, "#555555"), label=f"{kind} ({len(uv)})",
                       linewidths=0, rasterized=True)
    _draw_cells(ax, cam_size)
    _image_axes(ax, *cam_size, f"camera image: {cam_fraction:.0%} of cells hold a point")
    ax.legend(fontsize=7, markerscale=5, loc="upper right", framealpha=0.8)
    ax2 = fig.add_subplot(1, 2, 2)
    if len(proj_points):
        uniq, counts = np.unique(np.round(proj_points, 1), axis=0, return_counts=True)
        if counts.min() == counts.max():
            ax2.scatter(uniq[:, 0], uniq[:, 1], s=7, c=KIND_COLOURS["pattern"], linewidths=0,
                        label=f"pattern points ({len(uniq)}), each used by {counts[0]} view(s)")
            ax2.legend(fontsize=7, loc="upper right", framealpha=0.8)
        else:
            sc = ax2.scatter(uniq[:, 0], uniq[:, 1], s=7, c=counts, cmap="viridis", linewidths=0)
            cb = fig.colorbar(sc, ax=ax2, shrink=0.85)
            cb.set_label("views using the point", fontsize=8)
            cb.ax.tick_params(labelsize=7)
    _draw_cells(ax2, proj_size)
    _image_axes(ax2, *proj_size, f"projector image: {proj_fraction:.0%} of cells hold a point")
    _margins(fig, left=0.06, right=0.97, bottom=0.12, top=0.92, wspace=0.2)
    return png(fig)


def _draw_cells(ax, size) -> None:
    nx, ny = grid_shape(*size)
    for i in range(1, nx):
        ax.axvline(i * size[0] / nx - 0.5, color="#cccccc", lw=0.4, zorder=0)
    for j in range(1, ny):
        ax.axhline(j * size[1] / ny - 0.5, color="#cccccc", lw=0.4, zorder=0)


# ---- the rig in 3D -----------------------------------------------------------------------------------
def _frustum(model: CameraModel, T_cam_dev: np.ndarray, depth: float) -> tuple[np.ndarray, np.ndarray]:
    """(centre, 4 far corners) in the camera frame of a device's viewing pyramid `depth` deep."""
    W, H = model.width, model.height
    corners = np.array([[-0.5, -0.5], [W - 0.5, -0.5], [W - 0.5, H - 0.5], [-0.5, H - 0.5]])
    xy = model.undistort_normalized(corners)
    P = np.column_stack([xy * depth, np.full(4, depth)])
    P = P @ T_cam_dev[:3, :3].T + T_cam_dev[:3, 3]
    return T_cam_dev[:3, 3].copy(), P


def rig_figure(camera: CameraModel, projector: CameraModel, T_cam_proj: np.ndarray, mirror, boards: list,
               units: str) -> bytes:
    """Camera, projector (viewing pyramids), mirror plane and board outlines in the camera frame, in
    perspective (OpenCV's camera axes drawn as (x, z, -y), so that up is up) and from above (x, z).
    boards: (step, 4x3 outline corners)."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = Figure(figsize=(11, 5.2))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    top = fig.add_subplot(1, 2, 2)

    def P(X):  # camera frame -> 3D plot axes
        X = np.asarray(X, float).reshape(-1, 3)
        return X[:, 0], X[:, 2], -X[:, 1]

    def line(X, **kw):
        X = np.asarray(X, float).reshape(-1, 3)
        ax.plot(*P(X), **kw)
        kw.pop("label", None)
        top.plot(X[:, 0], X[:, 2], **kw)

    allp = np.vstack([np.zeros((1, 3)), T_cam_proj[:3, 3][None]] + [b for _, b in boards])
    extent = float(np.ptp(allp, axis=0).max()) or 1.0
    depth = 0.15 * extent
    for name, model, T, colour in (("camera", camera, np.eye(4), "#1f1f1f"),
                                   ("projector", projector, T_cam_proj, "#d62728")):
        c, F = _frustum(model, T, depth)
        for k in range(4):
            line(np.vstack([c, F[k]]), color=colour, lw=1.0)
        line(np.vstack([F, F[:1]]), color=colour, lw=1.6, label=name)
        ax.text(*[a[0] for a in P(c)], f"  {name}", color=colour, fontsize=9, fontweight="bold")
        top.annotate(name, (c[0], c[2]), xytext=(-6, -12), textcoords="offset points", color=colour, fontsize=9,
                     fontweight="bold", ha="right")
        allp = np.vstack([allp, F])
    seen = set()
    for kind, outline in boards:
        colour = STEP_COLOURS.get(kind, "#7f7f7f")
        label = None if kind in seen else f"board poses ({kind})"
        seen.add(kind)
        line(np.vstack([outline, outline[:1]]), color=colour, lw=0.7, alpha=0.7, label=label)
    if mirror is not None:
        n, d = np.asarray(mirror.normal, float), float(mirror.d)
        # centre: where the camera's optical axis meets the mirror (else the foot of the perpendicular)
        centre = -d * n
        if abs(n[2]) > 1e-6 and -d / n[2] > 0:
            centre = np.array([0.0, 0.0, -d / n[2]])
        e1 = np.cross(n, [0.0, 1.0, 0.0])
        if np.linalg.norm(e1) < 1e-6:
            e1 = np.cross(n, [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        h = 0.2 * extent
        quad = np.array([centre + a * h * e1 + b * h * e2 for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
        xs, ys, zs = P(quad)
        ax.add_collection3d(Poly3DCollection([list(zip(xs, ys, zs))], facecolor="#66b3ff", alpha=0.3,
                                             edgecolor="#3385cc", lw=1.0))
        top.fill(quad[:, 0], quad[:, 2], facecolor="#66b3ff", alpha=0.3, edgecolor="#3385cc", lw=1.5)
        ax.plot([], [], color="#66b3ff", lw=6, alpha=0.5, label="mirror plane")
        allp = np.vstack([allp, quad])
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    mid, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-6)
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[2] - half, mid[2] + half)
    ax.set_zlim(-mid[1] - half, -mid[1] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel(f"x ({units})", fontsize=8)
    ax.set_ylabel(f"z ({units})", fontsize=8)
    ax.set_zlabel(f"-y ({units})", fontsize=8)
    ax.tick_params(labelsize=6)
    ax.view_init(elev=24, azim=-58)
    ax.set_title("perspective", fontsize=10)
    top.set_aspect("equal")
    top.set_xlabel(f"x ({units})", fontsize=8)
    top.set_ylabel(f"z ({units}, the camera's viewing direction)", fontsize=8)
    top.tick_params(labelsize=7)
    top.set_title("from above (looking down the camera's -y axis)", fontsize=10)
    top.grid(alpha=0.3)
    fig.legend(*ax.get_legend_handles_labels(), fontsize=8, loc="lower center", ncols=5, frameon=False)
    _margins(fig, left=0.0, right=0.98, bottom=0.12, top=0.94, wspace=0.12)
    return png(fig)


# ---- verification --------------------------------------------------------------------------------------
VERDICT_COLOURS = {"pass": "#2ca02c", "above mean limit": "#ff9f1c", "fail": "#d62728", "not measured": "#7f7f7f"}


def check_verdict(check, threshold: float, worst_factor: float) -> str:
    """A check's (app.verification.PixelCheck) own verdict: within the threshold (pass), within the
    worst-case limit (above mean limit: allowed for some pixels), beyond it (fail), or not measured."""
    if not check.ok or check.distance_proj_px is None:
        return "not measured"
    d = float(check.distance_proj_px)
    return "pass" if d <= threshold else "above mean limit" if d <= worst_factor * threshold else "fail"


def verification_figure(checks: list, cam_size, threshold: float, worst_factor: float) -> bytes:
    """Left: the whole camera image frame with the checked pixels. Right: zoomed to them, the detected
    strokes (solid, coloured by each check's verdict) and the predicted curves (dashed), each pixel
    numbered with its distance in projector pixels."""
    W, H = cam_size
    fig = Figure(figsize=(11, 4.6))
    full = fig.add_subplot(1, 3, 1)
    ax = fig.add_subplot(1, 3, (2, 3))
    pix = np.array([c.pixel for c in checks], float).reshape(-1, 2)
    for a in (full, ax):
        a.add_patch(Rectangle((-0.5, -0.5), W, H, facecolor="#1e1e1e", edgecolor="none", zorder=0))
    for i, c in enumerate(checks, 1):
        verdict = check_verdict(c, threshold, worst_factor)
        colour = VERDICT_COLOURS[verdict]
        for a in (full, ax):
            for key in ("predicted_curve", "detected_curve"):
                curve = getattr(c, key)
                if curve is not None and len(curve):
                    pts = np.asarray(curve, float).reshape(-1, 2)
                    if key == "detected_curve":
                        a.plot(pts[:, 0], pts[:, 1], color=colour, lw=1.8 if a is ax else 1.0)
                    else:
                        a.plot(pts[:, 0], pts[:, 1], color="#e8e8e8", ls=(0, (4, 3)), lw=0.9)
        x, y = c.pixel
        full.plot(x, y, "o", ms=3, color=colour)
        ax.plot(x, y, "o", ms=8, mfc="none", mec="white", mew=1.5)
        dist = c.distance_proj_px
        label = f"{i}: {dist:.2f}" if verdict != "not measured" and dist is not None else f"{i}: n/a"
        ax.annotate(label, (x, y), xytext=(7, 7), textcoords="offset points", color=colour, fontsize=8.5,
                    fontweight="bold", bbox={"boxstyle": "round,pad=0.15", "fc": "#000000", "ec": "none", "alpha": 0.7})
    _image_axes(full, W, H, "camera image: checked pixels")
    if len(pix):
        span = max(float(np.ptp(pix[:, 0])), float(np.ptp(pix[:, 1])) * 2, 40.0)
        mid = pix.mean(axis=0)
        half_w = 0.62 * span + 30
        half_h = half_w / 2
        x0, x1 = max(-0.5, mid[0] - half_w), min(W - 0.5, mid[0] + half_w)
        y0, y1 = max(-0.5, mid[1] - half_h), min(H - 0.5, mid[1] + half_h)
        full.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, edgecolor="#ffd400", lw=1.0))
        ax.set_xlim(x0, x1)
        ax.set_ylim(y1, y0)
        ax.set_aspect("equal")
        ax.set_title("zoomed (yellow box): pixel number: distance (projector px)", fontsize=10)
        ax.set_xlabel("x (px)", fontsize=8)
        ax.tick_params(labelsize=7)
    ax.plot([], [], color="#e8e8e8", ls=(0, (4, 3)), label="predicted curve")
    for verdict, colour in VERDICT_COLOURS.items():
        if any(check_verdict(c, threshold, worst_factor) == verdict for c in checks):
            ax.plot([], [], color=colour, lw=2, label=f"detected stroke: {verdict}")
    leg = ax.legend(fontsize=7.5, loc="lower left", facecolor="#333333", edgecolor="none", framealpha=0.85)
    for t in leg.get_texts():
        t.set_color("white")
    _margins(fig, left=0.06, right=0.99, bottom=0.11, top=0.92, wspace=0.12)
    return png(fig)
