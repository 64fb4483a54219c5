"""What the panel shows of the results, and what leaves the browser: the calibration's parameters with
their 1-sigma (or "fixed" for a given camera), distortion, the worst views, the session's files, the
results zip the Download button sends, and the captures table with thumbnails.

Pure functions of the session folder and its machine (no viser): the panel puts their text in place.
"""

from __future__ import annotations

import base64
import html
import io
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from app.words import plural
from calib.errors import ProcamError, SessionError
from calib.formats import session_files
from calib.formats.fileio import RESULT_MAX_BYTES, read_regular

#: The files the results zip carries, in this order, when they exist in the session folder.
RESULT_FILES = session_files.RESULTS
REPORT_FILE = session_files.REPORT
REPORT_MISSING = "the report module is not installed"
THUMB_WIDTH = 112


def _pm(u: dict, group: str, key: str, digits: int = 2) -> str:
    g = u.get(group) if isinstance(u, dict) else None
    if not isinstance(g, dict):
        return ""
    if g.get("fixed"):
        return " (fixed)"
    v = g.get(key)
    return f" ± {v:.{digits}f}" if isinstance(v, (int, float)) else ""


def _dist_names(n: int) -> list[str]:
    return ["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"][:n]


def parameters_text(result, given_camera: bool = False) -> str:
    """Intrinsics (px) with their 1-sigma, or "fixed" for a camera given by the operator, and the
    distortion coefficients of both devices."""
    u = result.uncertainty or {}
    lines = ["| device | fx px | fy px | cx px | cy px |", "|---|---|---|---|---|"]
    for name, cam in (("camera", result.camera), ("projector", result.projector)):
        fixed = name == "camera" and given_camera
        cells = []
        for key, v in (("fx", cam.fx), ("fy", cam.fy), ("cx", cam.cx), ("cy", cam.cy)):
            cells.append(f"{v:.2f} (fixed)" if fixed else f"{v:.2f}{_pm(u, name, key)}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append("**Distortion** (OpenCV order, unitless):")
    lines.append("")
    for name, cam in (("camera", result.camera), ("projector", result.projector)):
        d = np.asarray(cam.dist, float).reshape(-1)
        if d.size == 0:
            lines.append(f"- {name}: none (pinhole)")
            continue
        g = u.get(name) if isinstance(u.get(name), dict) else {}
        sd = g.get("dist") if isinstance(g.get("dist"), list) else None
        fixed = (name == "camera" and given_camera) or bool(g.get("fixed"))
        parts = []
        for i, (k, v) in enumerate(zip(_dist_names(d.size), d)):
            s = f"{k} {v:+.5f}"
            if fixed:
                pass
            elif sd is not None and i < len(sd) and isinstance(sd[i], (int, float)) and sd[i] > 0:
                s += f" ± {sd[i]:.5f}"
            parts.append(s)
        lines.append(f"- {name}{' (fixed)' if fixed else ''}: " + ", ".join(parts))
    return "\n".join(lines)


def worst_views_text(result, n: int = 5) -> str:
    """The views with the largest reprojection RMS (diagnostics.worst_views, else per_view)."""
    worst = (result.diagnostics or {}).get("worst_views")
    if not isinstance(worst, list) or not worst:
        pv = [p for p in result.per_view if isinstance(p, dict) and isinstance(p.get("rms_px"), (int, float))]
        worst = sorted(pv, key=lambda p: -p["rms_px"])[:n]
    rows = [w for w in worst if isinstance(w, dict) and isinstance(w.get("rms_px"), (int, float))][:n]
    if not rows:
        return "No per-view residuals in this calibration."
    lines = ["| capture | step | RMS px |", "|---|---|---|"]
    for w in rows:
        lines.append(f"| {html.escape(str(w.get('capture_id', '?')))} | {html.escape(str(w.get('step', '')))} | "
                     f"{w['rms_px']:.3f} |")
    return "\n".join(lines)


def check_passes(check, threshold_px: float, worst_factor: float) -> bool:
    """One verified pixel passes when it was measured and its distance (projector px when the scale is
    known, else camera px) is within the largest distance any single check may have (worst_factor x
    the threshold, the report's rule for its worst check)."""
    if not getattr(check, "ok", False):
        return False
    d = check.distance_proj_px if check.distance_proj_px is not None else check.distance_px
    return d is not None and d <= worst_factor * threshold_px


@dataclass(frozen=True)
class FileEntry:
    name: str
    size_bytes: int


def folder_files(folder) -> list[FileEntry]:
    """Every file of the session folder (captures summarised as one line by the caller)."""
    folder = Path(folder)
    out = []
    try:
        for p in sorted(folder.rglob("*")):
            if p.is_file() and not p.is_symlink() and not p.name.startswith("."):  # not the folder's lock
                out.append(FileEntry(str(p.relative_to(folder)), p.stat().st_size))
    except OSError:
        pass
    return out


def folder_stamp(folder) -> tuple:
    """The top of the session folder as (name, size, mtime) of each entry: changes whenever a file is
    written there, so the files list is redrawn then (whoever wrote it)."""
    try:
        return tuple(sorted((p.name, st.st_size, st.st_mtime_ns) for p in Path(folder).iterdir()
                            for st in [p.stat()]))
    except OSError:
        return ()


def _size(n: int) -> str:
    for unit in ("bytes", "kB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024.0
    return str(n)


def files_text(folder) -> str:
    """The session folder and the files written in it (each capture folder as one line)."""
    folder = Path(folder)
    files = folder_files(folder)
    top = [f for f in files if "/" not in f.name]
    groups: dict[str, list[FileEntry]] = {}
    for f in files:
        if "/" in f.name:
            groups.setdefault(f.name.split("/", 1)[0], []).append(f)
    lines = [f"Session folder: `{folder}`", ""]
    for f in top:
        lines.append(f"- `{f.name}` ({_size(f.size_bytes)})")
    for g, fs in sorted(groups.items()):
        lines.append(f"- `{g}/`: {len(fs)} files ({_size(sum(f.size_bytes for f in fs))})")
    return "\n".join(lines)


def write_report_if_available(folder) -> tuple[Path | None, str | None]:
    """report.html through app.report.write_report when that module is installed: (path, None), or
    (None, why not)."""
    try:
        from app.report import write_report
    except ImportError:
        return None, REPORT_MISSING
    try:
        return Path(write_report(Path(folder), Path(folder) / REPORT_FILE)), None
    except ProcamError as e:
        return None, str(e)
    except OSError as e:
        return None, f"cannot write the report: {e.strerror or e}"
    except Exception as e:  # a bug in the report must not keep the results from leaving: said, not hidden
        return None, f"the report failed ({type(e).__name__}: {e})"


#: The panel's choice of exports in the zip (calib.export.registry.EXPORTERS): every one, none, or one.
EXPORTS_ALL, EXPORTS_NONE = "all exports", "no exports"
EXPORTS_FOLDER = "exports"
EXPORT_NOTES = "exports/NOTES.txt"


def export_choices() -> tuple[str, ...]:
    from calib.export.registry import EXPORTERS

    return (EXPORTS_ALL, EXPORTS_NONE) + tuple(EXPORTERS)


def export_names(choice: str) -> tuple[str, ...]:
    """The exporters a dropdown choice names (an unknown choice: none)."""
    from calib.export.registry import EXPORTERS

    if choice == EXPORTS_ALL:
        return tuple(EXPORTERS)
    return (choice,) if choice in EXPORTERS else ()


def _exports(folder: Path, names) -> list[tuple[str, bytes]]:
    """(name in the zip, bytes) of the exports `names` of folder/calibration.json, written in a private
    temporary folder (never the session's); the warnings, or why nothing could be exported, in NOTES.txt."""
    import tempfile

    from calib.export.registry import EXPORTERS, trust_reasons, write_exports
    from calib.models.result import CalibrationResult

    try:
        result = CalibrationResult.load_json(folder / session_files.CALIBRATION)
        reasons = trust_reasons(result)
        if reasons:
            return [(EXPORT_NOTES, ("not exported: the trust check rejects this calibration: "
                                    + "; ".join(reasons) + "\n").encode())]
        out = []
        with tempfile.TemporaryDirectory(prefix="procam-exports-") as tmp:
            warnings = write_exports(result, names, Path(tmp), "calibration")
            for n in names:
                for p in EXPORTERS[n].paths(tmp, "calibration"):
                    out.append((f"{EXPORTS_FOLDER}/{p.name}", p.read_bytes()))
        if warnings:
            out.append((EXPORT_NOTES, ("".join(f"warning: {w}\n" for w in warnings)).encode()))
        return out
    except ProcamError as e:  # an export that cannot be written must not keep the results from leaving
        return [(EXPORT_NOTES, f"not exported: {e}\n".encode())]


def results_zip(folder, exports=()) -> tuple[bytes, list[str]]:
    """A zip of the result files that exist in `folder` (RESULT_FILES) and, under exports/, the calibration
    in the formats `exports` names (calib.export; docs/FORMATS.md): (bytes, names in it). Each file is read
    as a regular file of the folder (calib.formats.fileio.read_regular): a link, a pipe or a device there
    is refused with its name, never followed into the zip."""
    folder = Path(folder)
    names = [n for n in RESULT_FILES if os.path.lexists(folder / n)]
    if session_files.CALIBRATION not in names:
        raise ProcamError("there is no calibration.json in the session yet; calibrate first")
    files = [(n, read_regular(folder / n, RESULT_MAX_BYTES, "result file")) for n in names]
    if exports:
        files += _exports(folder, tuple(exports))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for n, data in files:
            z.writestr(n, data)
    return buf.getvalue(), [n for n, _ in files]


def thumbnail_data_url(data: bytes, width: int = THUMB_WIDTH) -> str | None:
    """A small JPEG of a capture image's PNG bytes as a data: URL (None when they do not decode)."""
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_REDUCED_COLOR_4)
    if img is None:
        return None
    h, w = img.shape[:2]
    small = cv2.resize(img, (width, max(1, int(round(h * width / w)))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 70])
    return "data:image/jpeg;base64," + base64.b64encode(buf.tobytes()).decode() if ok else None


def _thumbnail(store, capture) -> str | None:
    """The capture's thumbnail; None when its file is missing or refused (a link, a pipe, too large, not
    the camera's size: SessionStore.read_image_bytes), so nothing outside the folder is ever shown."""
    try:
        return thumbnail_data_url(store.read_image_bytes(capture))
    except SessionError:
        return None


def _pose_number(meta) -> str:
    """The pose number a capture's metadata gives (1-based), or "?" for a malformed one (untrusted file)."""
    k = meta.get("pose_index", 0) if isinstance(meta, dict) else None
    return str(k + 1) if isinstance(k, int) and not isinstance(k, bool) else "?"


def captures_html(captures, store, per_view_rms: dict, thumbs: dict) -> str:
    """Every capture of SessionStore `store`, newest first, in a scrollable table with thumbnails
    (`thumbs`: capture id -> data URL, filled here for the ones missing; the caller keeps the dict)."""
    caps = list(captures)
    if not caps:
        return "<p>No captures yet.</p>"
    rows = []
    for c in reversed(caps):
        if c.id not in thumbs:
            thumbs[c.id] = _thumbnail(store, c)
        t = thumbs[c.id]
        img = f"<img src='{t}' alt='{html.escape(c.id)}' style='width:{THUMB_WIDTH}px;display:block'>" if t else ""
        pos = "" if c.pattern_position is None else str(c.pattern_position + 1)
        rms = per_view_rms.get(c.id)
        rms_s = f"{rms:.3f}" if isinstance(rms, (int, float)) else ""
        rows.append(f"<tr><td>{img}</td><td>{html.escape(c.id)}<br><small>{html.escape(c.step)}</small></td>"
                    f"<td>{pos}</td><td>{_pose_number(c.meta)}</td>"
                    f"<td>{html.escape(str(c.meta.get('how', '')))}</td><td>{rms_s}</td></tr>")
    head = ("<tr><th></th><th>capture</th><th>position</th><th>pose</th><th>how</th><th>RMS px</th></tr>")
    return (f"<p>{plural(len(caps), 'capture')} (newest first)</p><div style='max-height:70vh;overflow-y:auto'>"
            f"<table style='font-size:0.85em;border-collapse:collapse' cellpadding='3'>{head}{''.join(rows)}"
            "</table></div>")
