"""The record a recalibration keeps of what it was made from (RecalibrationRecord)."""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field

from calib.errors import ProcamError
from calib.formats.fileio import RESULT_MAX_BYTES, open_regular
from calib.recalib.check import CheckReport
from calib.recalib.reestimate import Reestimate


# ---- the record -------------------------------------------------------------------------------------
def sha256_file(path, *, unreadable_ok: bool = False) -> str | None:
    """SHA-256 (hex) of a regular file, never hashed through a link (calib.formats.fileio.open_regular).
    With `unreadable_ok`, None instead of the error when it cannot be read or is not a regular file."""
    h = hashlib.sha256()
    try:
        with os.fdopen(open_regular(path, RESULT_MAX_BYTES, "calibration file"), "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
    except (OSError, ProcamError):
        if unreadable_ok:
            return None
        raise
    return h.hexdigest()


@dataclass(frozen=True, eq=False)
class RecalibrationRecord:
    """recalibration.json: where the previous calibration came from, the check, the re-estimate, the
    comparison, the captures used."""

    previous_path: str
    previous_sha256: str
    archived_as: str
    check: CheckReport
    reestimate: Reestimate | None
    comparison: dict | None
    captures: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"schema": "procam-recalibration-1",
                "previous": {"path": self.previous_path, "sha256": self.previous_sha256, "archived_as": self.archived_as},
                "verdict": self.check.verdict, "check": self.check.to_dict(),
                # how the intrinsics were treated by the re-estimate (None: nothing was re-estimated)
                "intrinsics": None if self.reestimate is None else self.reestimate.intrinsics,
                "reestimate": None if self.reestimate is None else self.reestimate.to_dict(),
                "comparison": self.comparison, "captures": self.captures}
