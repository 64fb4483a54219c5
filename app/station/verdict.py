"""The overall verdict (calib.quality.verdict) as the panel shows it, first in the results."""

from __future__ import annotations

from calib.quality.verdict import Level, overall_verdict

_MARKS = {Level.TRUSTED: "✔", Level.LOW_QUALITY: "⚠", Level.UNTRUSTED: "✖"}


_last: list = [None, None, ""]  # (result, mirror_rig, text): the panel asks every refresh; a result is frozen


def verdict_text(result, mirror_rig: bool) -> str:
    """Markdown: the headline in bold, then each reason as a bullet."""
    if _last[0] is result and _last[1] == mirror_rig:
        return _last[2]
    v = overall_verdict(result, mirror_rig)
    lines = [f"**{_MARKS[v.level]} Verdict: {v.headline}.**"]
    lines += [f"- {r}" for r in v.reasons]
    _last[:] = [result, mirror_rig, "\n".join(lines) + "\n"]
    return _last[2]
