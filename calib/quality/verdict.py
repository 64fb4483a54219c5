"""The overall verdict on a calibration result, for the top of the panel's results and of the report:
the trust check and the quality gate (calib.quality.trust) run on the result as it is given (a file is
untrusted: what calibration.json records about itself is not taken on its word), plus what the rig
requires of it (a mirror plane when the rig sees the projector through a mirror).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from calib.quality.trust import check_calibration



class Level(str, enum.Enum):
    TRUSTED = "trusted"
    LOW_QUALITY = "low quality"
    UNTRUSTED = "not trusted"


HEADLINES = {
    Level.TRUSTED: "TRUSTED: passes the trust check and the quality gate",
    Level.LOW_QUALITY: "LOW QUALITY: passes the trust check, fails the quality gate",
    Level.UNTRUSTED: "NOT TRUSTED: fails the trust check; do not use this calibration",
}


@dataclass(frozen=True)
class Verdict:
    level: Level
    reasons: tuple[str, ...] = ()  # why it is not trusted, or why of low quality (with what to do)

    @property
    def headline(self) -> str:
        return HEADLINES[self.level]

    def lines(self) -> list[str]:
        return [self.headline] + list(self.reasons)


def overall_verdict(result, mirror_rig: bool | None = None) -> Verdict:
    """The verdict on `result`; `mirror_rig` True when the session's rig is seen through a mirror."""
    needs = []
    if mirror_rig and getattr(result, "mirror", None) is None:
        needs.append("the rig sees the projector through a mirror, but the result has no mirror plane")
    try:
        report = check_calibration(result)
    except (ArithmeticError, ValueError, TypeError, IndexError, KeyError, AttributeError) as e:
        return Verdict(Level.UNTRUSTED, tuple(needs) + (f"the trust check cannot run on it ({type(e).__name__}: {e})",))
    failed = needs + [r.message for r in report.reasons]
    if failed:
        return Verdict(Level.UNTRUSTED, tuple(failed))
    if report.quality:
        return Verdict(Level.LOW_QUALITY, tuple(f"{q.message}: {q.advice}" for q in report.quality))
    return Verdict(Level.TRUSTED)
