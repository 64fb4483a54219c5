"""The session's calibration files: calibration.json with the default exports beside it, and an untrusted
result kept apart for diagnosis; the calibration core's pipeline as the session machine's default."""

from __future__ import annotations

from pathlib import Path

from calib.formats import session_files
from calib.models.result import CalibrationResult

CALIBRATION_FILE = session_files.CALIBRATION
CALIBRATION_REJECTED = "calibration.rejected.json"  # an untrusted result, for diagnosis only


def write_calibration(folder, result: CalibrationResult, log) -> None:
    """calibration.json and the default exports (calib.export.registry.DEFAULTS) in the session folder."""
    from calib.export.registry import DEFAULTS, write_exports

    result.save_json(Path(folder) / CALIBRATION_FILE)
    try:
        for warning in write_exports(result, DEFAULTS, Path(folder), Path(CALIBRATION_FILE).stem):
            log(f"export: {warning}")
    except Exception as e:  # noqa: BLE001 - the exports are a convenience; the JSON is the result
        log(f"export of {', '.join(DEFAULTS)} failed: {e}")


def keep_rejected(folder, work):
    """work(); a calibration the trust check rejects (calib.quality.trust) is kept as calibration.rejected.json
    for diagnosis (never as calibration.json) before the error goes on to the panel with its reasons."""
    from calib.errors import UntrustedCalibration

    try:
        return work()
    except UntrustedCalibration as e:
        if e.result is not None:
            try:
                e.result.save_json(Path(folder) / CALIBRATION_REJECTED)
            except OSError:
                pass  # the diagnosis file is a convenience; the error itself still reaches the operator
        raise


def default_calibrate(folder, camera_intrinsics, progress=None, workers: int = 2,
                      method: str | None = None) -> CalibrationResult:
    """The calibration core's pipeline on the session folder (its default method unless given)."""
    from calib.pipeline import calibrate_session

    kw = {} if method is None else {"method": method}
    return calibrate_session(folder, camera_intrinsics=camera_intrinsics, workers=workers, progress=progress, **kw)
