"""Importer of recordings made with the published reference implementation (EDM-Research/ProcamCalib).

Entry function: `import_procamcalib(recording, patterns, board, out, mirror=None, mirror_board=None)`.

The layout it reads (described in issue 2):
- a recording folder of PNGs named by number (0.png, 1.png, ..., in numeric order). A folder whose name
  starts with "S" was seen through the mirror; any other first letter means a direct view.
- a patterns folder named <Name>_<cols>_<rows> (e.g. Asym_4_9) holding the projector images in order
  (01.png ... 13.png): white asymmetric circles on black, possibly with other marks (e.g. a small coloured
  label). The circle centres are found in each pattern image itself, with sub-pixel centroids.
- consecutive recording images share a pattern: images / patterns of them each.
- an optional mirror folder: name starting with "M" = real-virtual images, "F" = real-mirror images.

The result is an ordinary session folder (calib.formats.session), written through SessionStore: images are
copied losslessly (decoded and re-encoded as PNG with every pixel and bit depth kept; equal colour
channels stored once, as calib.formats.session does), each projector
capture records the projector pixels of the pattern it showed.
"""

from __future__ import annotations

import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calib.errors import ProcamError
from calib.formats.session import RigInfo, SessionManifest, SessionStore
from calib.models.boards import CharucoSpec
from calib.models.observations import STEP_PROJECTOR, STEP_REAL_MIRROR, STEP_REAL_VIRTUAL, VIEW_DIRECT, VIEW_MIRROR
from calib.models.pattern import PatternSpec
from calib.models.vocab import MirrorMethod, PatternKind


class RecordingError(ProcamError):
    """A ProcamCalib recording cannot be imported (missing folder, no images, unparsable names...)."""


_NUMBERED = re.compile(r"(\d+)\.png", re.IGNORECASE)
_PATTERN_DIR = re.compile(r"(.+)_(\d+)_(\d+)")


@dataclass(frozen=True)
class PatternImages:
    """What the patterns folder holds: the grid size, the measured spec, and per image its points."""

    name: str
    spec: PatternSpec
    size: tuple[int, int]  # projector (width, height)
    points_px: tuple[np.ndarray, ...]  # per pattern image, (N, 2) in PatternSpec order
    files: tuple[Path, ...]


def numbered_pngs(folder, what: str = "folder") -> list[Path]:
    """The PNGs of `folder` named by a number, in numeric order (2.png before 10.png)."""
    folder = Path(folder)
    if not folder.exists():
        raise RecordingError(f"{what} {folder} does not exist")
    if not folder.is_dir():
        raise RecordingError(f"{what} {folder} is not a folder")
    found = []
    for p in folder.iterdir():
        m = _NUMBERED.fullmatch(p.name)
        if m and p.is_file():
            found.append((int(m.group(1)), p))
    if not found:
        raise RecordingError(f"{what} {folder} holds no numbered PNG images (0.png, 1.png, ...)")
    found.sort(key=lambda t: t[0])
    numbers = [n for n, _ in found]
    if len(set(numbers)) != len(numbers):
        dup = sorted({n for n in numbers if numbers.count(n) > 1})
        raise RecordingError(f"{what} {folder}: image number(s) {dup} appear twice (e.g. 1.png and 01.png)")
    return [p for _, p in found]


def parse_pattern_folder_name(folder) -> tuple[str, int, int]:
    """'Asym_4_9' -> ('Asym', 4, 9): name, columns and rows of the asymmetric circle grid."""
    name = Path(folder).name
    m = _PATTERN_DIR.fullmatch(name)
    if not m or int(m.group(2)) < 2 or int(m.group(3)) < 2:
        raise RecordingError(
            f"patterns folder name '{name}' does not parse; expected <Name>_<cols>_<rows> with the circle "
            "grid's size, e.g. Asym_4_9")
    return m.group(1), int(m.group(2)), int(m.group(3))


def _read(path: Path, flags=cv2.IMREAD_UNCHANGED) -> np.ndarray:
    img = cv2.imread(str(path), flags)
    if img is None:
        raise RecordingError(f"image {path} cannot be read (not a valid PNG?)")
    return img


def _white_only(img: np.ndarray) -> np.ndarray:
    """8-bit grayscale where only white stays bright: the minimum over the colour channels, so that a
    coloured label or mark (saturated colours) is dark and cannot be taken for a circle."""
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.ndim == 3:
        img = img[:, :, :3].min(axis=2) if img.shape[2] >= 3 else img[:, :, 0]
    return np.ascontiguousarray(img)


def detect_pattern_image(image: np.ndarray, cols: int, rows: int) -> tuple[np.ndarray, float, float] | None:
    """(points (N, 2) in PatternSpec order, spacing_px, radius_px) of the white asymmetric circle grid
    drawn in a projector image, or None when the grid is not found."""
    from calib.detection.detect import DetectionFailure, detect_pattern

    gray = _white_only(image)
    probe = PatternSpec(PatternKind.CIRCLES, cols, rows, spacing_px=10.0, radius_px=1.0, positions=1)
    pts = detect_pattern(gray, probe, mirrored=False)
    if isinstance(pts, DetectionFailure):
        return None
    # spacing: least-squares similarity from the unit-spacing grid to the found centres
    local = PatternSpec(PatternKind.CIRCLES, cols, rows, spacing_px=1.0, radius_px=0.1, positions=1).local_points()
    lc, pc = local - local.mean(axis=0), pts - pts.mean(axis=0)
    spacing = float(np.sqrt((pc ** 2).sum() / (lc ** 2).sum()))
    # radius: the covered area of each (anti-aliased) disc, within half the distance to its neighbours
    reach = 0.5 * spacing * np.sqrt(2.0)
    radii = []
    for x, y in pts:
        x0, x1 = max(int(x - reach), 0), min(int(x + reach) + 2, gray.shape[1])
        y0, y1 = max(int(y - reach), 0), min(int(y + reach) + 2, gray.shape[0])
        win = gray[y0:y1, x0:x1].astype(float) / 255.0
        ys, xs = np.mgrid[y0:y1, x0:x1]
        inside = np.hypot(xs - x, ys - y) <= reach
        radii.append(np.sqrt(win[inside].sum() / np.pi))
    return pts, spacing, float(np.median(radii))


def read_patterns(folder) -> PatternImages:
    """Detect the circle grid in every image of a ProcamCalib patterns folder."""
    folder = Path(folder)
    name, cols, rows = parse_pattern_folder_name(folder)
    files = numbered_pngs(folder, "patterns folder")
    points, spacings, radii, size = [], [], [], None
    for f in files:
        img = _read(f)
        h, w = img.shape[:2]
        if size is None:
            size = (w, h)
        elif size != (w, h):
            raise RecordingError(f"pattern image {f} is {w}x{h}, the others are {size[0]}x{size[1]}")
        found = detect_pattern_image(img, cols, rows)
        if found is None:
            raise RecordingError(
                f"no {cols}x{rows} asymmetric circle grid found in pattern image {f}; check that the folder "
                f"name gives the grid's columns and rows (<Name>_<cols>_<rows>)")
        pts, spacing, radius = found
        points.append(pts)
        spacings.append(spacing)
        radii.append(radius)
    spacing = float(np.median(spacings))
    radius = float(np.median(radii))
    radius = min(radius, 0.69 * spacing)
    spec = PatternSpec(PatternKind.CIRCLES, cols, rows, spacing_px=round(spacing, 3), radius_px=round(radius, 3),
                       positions=len(files))
    return PatternImages(name, spec, size, tuple(points), tuple(files))


def _mirror_method(folder: Path) -> str:
    first = folder.name[:1]
    if first == "M":
        return MirrorMethod.REAL_VIRTUAL
    if first == "F":
        return MirrorMethod.REAL_MIRROR
    raise RecordingError(
        f"mirror folder name '{folder.name}' must start with 'M' (real-virtual images: board seen directly and "
        "in the mirror) or 'F' (real-mirror images: board lying on the mirror)")


def _png_size(path: Path) -> tuple[int, int]:
    """(width, height) from a PNG's header, without decoding the image."""
    with open(path, "rb") as f:
        head = f.read(24)
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        raise RecordingError(f"image {path} is not a valid PNG file")
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def _image_size(files, what: str) -> tuple[int, int]:
    size = None
    for f in files:
        w, h = _png_size(f)
        if size is None:
            size = (w, h)
        elif size != (w, h):
            raise RecordingError(f"{what} image {f} is {w}x{h}, the first one is {size[0]}x{size[1]}")
    return size


def import_procamcalib(recording, patterns, board: CharucoSpec, out, mirror=None,
                       mirror_board: CharucoSpec | None = None, board_thickness: float = 0.0,
                       progress=None) -> SessionStore:
    """Convert a ProcamCalib recording into a session folder `out`; returns the open SessionStore.

    `progress(done, total, name)` is called after each image is written."""
    recording = Path(recording)
    rec_files = numbered_pngs(recording, "recording folder")
    view = VIEW_MIRROR if recording.name.startswith("S") else VIEW_DIRECT
    pats = read_patterns(patterns)
    n_img, n_pat = len(rec_files), len(pats.points_px)
    if n_img % n_pat:
        raise RecordingError(
            f"recording {recording} has {n_img} images, not a multiple of the {n_pat} pattern images in "
            f"{patterns}: consecutive images must share a pattern, the same number per pattern")
    per = n_img // n_pat
    mirror_files, method = [], None
    if mirror is not None:
        mirror = Path(mirror)
        method = _mirror_method(mirror)
        mirror_files = numbered_pngs(mirror, "mirror folder")
        if view == VIEW_DIRECT:
            raise RecordingError(
                f"recording {recording.name} is a direct view (its name does not start with 'S'); mirror "
                "images belong to mirrored recordings only")
    cam_size = _image_size(rec_files + mirror_files, "recording")
    manifest = SessionManifest(
        rig=RigInfo(cam_size, pats.size, view, {}, "procamcalib"),
        projector_board=board,
        pattern=pats.spec,
        mirror_board=(mirror_board or board) if method else None,
        mirror_method=method,
        board_thickness=float(board_thickness) if method == MirrorMethod.REAL_MIRROR else 0.0,
        state={"imported_from": "ProcamCalib", "recording": str(recording.resolve()),
               "patterns": str(Path(patterns).resolve()), "mirror": None if mirror is None else str(mirror.resolve()),
               "images_per_pattern": per},
    )
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise RecordingError(f"output folder {out} exists and is not empty; choose a new folder")
    # write into a hidden sibling and rename it at the end: an interrupted import leaves no half session
    tmp = out.with_name(f".{out.name}.importing")
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        store = SessionStore.create(tmp, manifest)
        total = len(mirror_files) + n_img
        done = 0
        step = STEP_REAL_VIRTUAL if method == MirrorMethod.REAL_VIRTUAL else STEP_REAL_MIRROR
        for f in mirror_files:
            store.add_capture(step, _read(f), meta={"source": f"{mirror.name}/{f.name}"})
            done += 1
            if progress is not None:
                progress(done, total, f.name)
        for k, f in enumerate(rec_files):
            pos = k // per
            store.add_capture(STEP_PROJECTOR, _read(f), pos, pats.points_px[pos],
                              meta={"source": f"{recording.name}/{f.name}", "pattern_image": pats.files[pos].name})
            done += 1
            if progress is not None:
                progress(done, total, f.name)
        if out.exists():
            out.rmdir()
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return SessionStore.open(out)
