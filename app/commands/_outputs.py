"""What a command may write, checked before its long work starts.

Every `--out` of the command line goes through here (issue 13 item 5):
- an output is never a file that a session or the command itself reads: a session's manifest, its
  detection cache, its images, lock files, ground truth, scene and verification report, or any input
  named on the command line;
- the JSON result and its YAML export never share a name (`result_paths`);
- a folder that cannot be written (read-only, full, a path under a file, a directory where a file is
  expected) is found by creating and removing a probe file, so the user gets one line at once instead
  of a failure after the calibration or the rendering.
Each refusal is a SessionError with a message naming the path and what to do.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from calib.errors import ProcamError, SessionError
from calib.formats import session_files
from calib.formats.session import read_manifest_json

MANIFEST = session_files.MANIFEST
#: files of a session folder that an output must never replace, and what they are
SESSION_FILES = session_files.PROTECTED
IMAGES_DIR = session_files.IMAGES_DIR


def _resolved(path) -> Path:
    p = Path(path).expanduser()
    try:
        return p.resolve(strict=False)
    except RuntimeError:  # a link loop (Python 3.11 raises): the path itself, absolute
        return Path(os.path.abspath(p))


def _unfollowed(path) -> Path:
    """`path` absolute with its folders' links resolved, its last part as it is: an atomic write replaces
    a link there, it never writes where the link points."""
    path = Path(path).expanduser()
    return _resolved(path.parent) / path.name


def session_folder_of(path) -> Path | None:
    """The session folder that holds `path` (the nearest ancestor with a session.json), or None."""
    p = _resolved(path)
    for folder in p.parents:
        if (folder / MANIFEST).is_file():
            return folder
    return None


def _capture_images(folder: Path) -> set[Path]:
    """The image files a manifest names (best effort: an unreadable manifest names none)."""
    try:
        caps = read_manifest_json(folder).get("captures") or []
        return {_resolved(folder / c["image"]) for c in caps if isinstance(c, dict) and isinstance(c.get("image"), str)}
    except (OSError, ProcamError, TypeError, AttributeError):
        return set()


def refuse_session_file(path, what: str = "--out") -> None:
    """Raise when `path` is (or is inside) a file a session reads: manifest, detection cache, images,
    lock files, ground truth, scene, verification report, or a capture the manifest names."""
    p = _resolved(path)
    folder = session_folder_of(p)
    if folder is None:
        return
    rel = p.relative_to(folder)
    name = rel.parts[0]
    reason = None
    if len(rel.parts) == 1 and name in SESSION_FILES:
        reason = SESSION_FILES[name]
    elif name == IMAGES_DIR:
        reason = "inside the session's images folder"
    elif name.startswith(".") or "lock" in name.lower():
        reason = "a session's lock or temporary file"
    elif p in _capture_images(folder):
        reason = "an image of the session"
    if reason is not None:
        raise SessionError(f"{what} {path} is {reason} (session {folder}); writing it could destroy the "
                           f"session: choose another file name")


def refuse_inputs(path, inputs, what: str = "--out") -> None:
    """Raise when `path` is one of the command's inputs, or lies inside an input folder."""
    p = _resolved(path)
    for inp in inputs:
        if inp is None:
            continue
        q = _resolved(inp)
        if p == q:
            raise SessionError(f"{what} {path} is also an input of this command ({inp}); it would be overwritten: "
                               f"choose another name")
        if q.is_dir() and q in p.parents:
            raise SessionError(f"{what} {path} is inside the input folder {inp}; choose a place outside it")


def probe_writable(folder: Path) -> None:
    """Create and remove a probe file in existing folder `folder`; a SessionError saying why not."""
    try:
        fd, name = tempfile.mkstemp(prefix=".procam-probe-", dir=str(folder))
    except OSError as e:
        raise SessionError(f"cannot write in {folder}: {e.strerror or e}") from None
    try:
        os.close(fd)
    finally:
        try:
            os.unlink(name)
        except OSError:
            pass


def _existing_ancestor(p: Path, path, what: str) -> Path:
    """The nearest existing ancestor of `p`; a SessionError when it is not a folder."""
    anc = p.parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        raise SessionError(f"{what} {path} cannot be created: {anc} is a file, not a folder")
    return anc


def check_output_file(path, what: str = "--out", inputs=()) -> Path:
    """Check that file `path` can be written and destroys nothing; returns it as a Path."""
    path = Path(path)
    p = _resolved(path)
    if p.is_dir():
        raise SessionError(f"{what} {path} is a folder; give a file name (e.g. {path / 'calibration.json'})")
    refuse_session_file(path, what)
    refuse_inputs(path, inputs, what)
    probe_writable(_existing_ancestor(_unfollowed(path), path, what))
    return path


def check_output_folder(path, what: str = "--out", inputs=()) -> Path:
    """Check that folder `path` (new or existing) can be created and written; returns it as a Path."""
    path = Path(path)
    p = _resolved(path)
    if p.exists() and not p.is_dir():
        raise SessionError(f"{what} {path} is a file, not a folder; give a folder to create")
    folder = session_folder_of(p)
    if folder is not None:
        raise SessionError(f"{what} {path} is inside the session {folder}; choose a folder outside it")
    refuse_inputs(path, inputs, what)
    probe_writable(p if p.is_dir() else _existing_ancestor(p, path, what))
    return path


def result_paths(out) -> tuple[Path, Path]:
    """(JSON, YAML) for a calibration result written to `out`. The name must end in .json; the YAML
    export takes the same name with .yaml, so the two can never be the same file."""
    out = Path(out)
    if out.is_dir():
        raise SessionError(f"--out {out} is a folder; give a file name (e.g. {out / 'calibration.json'})")
    suffix = out.suffix.lower()
    if suffix in (".yaml", ".yml"):
        raise SessionError(f"--out {out} names the YAML export, which is written beside the JSON result: give "
                           f"--out {out.with_suffix('.json')} (writes {out.with_suffix('.json').name} and "
                           f"{out.with_suffix('.yaml').name})")
    if suffix != ".json":
        raise SessionError(f"--out {out}: the result is a JSON file, name it *.json (e.g. {out.with_suffix('.json')});"
                           f" the YAML export goes beside it")
    return out, out.with_suffix(".yaml")


def write_error(path, e: OSError) -> SessionError:
    """The one-line error for a write that failed after all (full disk, removed folder...)."""
    return SessionError(f"cannot write {path}: {e.strerror or e}")
