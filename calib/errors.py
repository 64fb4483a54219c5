"""The project's exception types. Every message says what is wrong and what to do about it."""


class ProcamError(Exception):
    """Base of every error procam-station raises on purpose."""


class SpecError(ProcamError, ValueError):
    """A board or pattern specification does not parse or is inconsistent."""


class OptionError(ProcamError, ValueError):
    """A command-line option that does not parse, is out of range, or names what cannot be used (a host
    that is not this machine's). The message names the option; `prog`, when known, is the command that
    was given it ("procam station")."""

    def __init__(self, message: str, prog: str | None = None):
        super().__init__(message)
        self.prog = prog


class FormatError(ProcamError, ValueError):
    """A file (session manifest, calibration result...) is malformed. `field` names the culprit."""

    def __init__(self, path, field: str, problem: str):
        self.path = str(path)
        self.field = field
        self.problem = problem
        super().__init__(f"{self.path}: field '{field}': {problem}")


class SessionError(ProcamError):
    """A capture session cannot be opened or written (missing folder, unreadable image...)."""


class UnsafeFileError(SessionError):
    """A file a session folder holds is a link, a hard link, not a regular file (a FIFO, a device) or
    larger than such a file can be: it is refused before it is read."""


class CalibrationError(ProcamError):
    """The data cannot be calibrated (too few views, no mirror images for a mirrored rig...). `code`,
    when set, names the failure for programs (stable across wordings), e.g. "non_finite"."""

    def __init__(self, message: str = "", code: str | None = None):
        super().__init__(message)
        self.code = code


class ExportError(ProcamError):
    """A calibration cannot be exported: an unknown format, a rejected calibration, a bad option."""


class DiskFullError(ProcamError, OSError):
    """The disk (or the user's quota) filled up while writing `filename`. Writes are atomic, so the file
    being replaced is intact and nothing written before was lost; an OSError, so code that tolerates a
    failed write (the detection cache) still does."""

    def __init__(self, path, errno_: int):
        super().__init__(errno_, f"disk full writing {path}: free some space and try again (or resume); "
                                 "nothing already saved was lost")
        self.filename = str(path)

    def __str__(self) -> str:
        return self.strerror


class UntrustedCalibration(CalibrationError):
    """A calibration ran but its result cannot be trusted (calib.quality.trust): `report` (a TrustReport) lists
    the reasons, each with a stable code; `result` is the rejected CalibrationResult, kept for
    diagnosis only (never hand it on as a calibration)."""

    def __init__(self, report, result=None):
        self.report = report
        self.result = result
        reasons = "; ".join(r.message for r in report.reasons)
        super().__init__(f"the calibration is not trustworthy and was not saved as a result: {reasons}",
                         code="untrusted")

    @property
    def codes(self) -> list[str]:
        return [r.code for r in self.report.reasons]
