"""The project's vocabularies, each defined once.

Every word that names one of a fixed set of things (a capture step, a rig kind, a distortion model, a
length unit, ...) is a member of one `enum.StrEnum` here. A StrEnum member *is* its string
(`Step.PROJECTOR == "projector"`, `json.dumps(Step.PROJECTOR) == '"projector"'`), so session.json,
calibration.json and the command line read and write exactly the words they always did; code compares,
iterates and offers choices through the enum, and a new member is added in one place.

`choices(E)` gives an enum's words as a tuple, for argparse `choices=` and for error messages.
"""

from __future__ import annotations

import enum


class Step(enum.StrEnum):
    """A capture step of a session (the `step` of a capture in session.json)."""

    PROJECTOR = "projector"
    REAL_VIRTUAL = "mirror-real-virtual"
    REAL_MIRROR = "mirror-real-mirror"
    VERIFICATION = "verification"

    @property
    def is_mirror(self) -> bool:
        return self in (Step.REAL_VIRTUAL, Step.REAL_MIRROR)


#: the steps whose captures feed the calibration (verification captures only check it)
CALIBRATION_STEPS = (Step.PROJECTOR, Step.REAL_VIRTUAL, Step.REAL_MIRROR)


class MirrorMethod(enum.StrEnum):
    """How the mirror plane is measured: a board seen directly and in the mirror (real-virtual), or a
    board lying on the mirror (real-mirror)."""

    REAL_VIRTUAL = "real-virtual"
    REAL_MIRROR = "real-mirror"

    @property
    def step(self) -> Step:
        return Step.REAL_VIRTUAL if self is MirrorMethod.REAL_VIRTUAL else Step.REAL_MIRROR


class View(enum.StrEnum):
    """How the camera sees the board of a capture."""

    MIRROR = "mirror"
    DIRECT = "direct"


class RigKind(enum.StrEnum):
    """The rigs the station drives (`--rig`): simulated worlds and real devices."""

    SIM = "sim"
    SIM_REALSENSE = "sim-realsense"
    SIM_UVC = "sim-uvc"
    REALSENSE = "realsense"
    UVC = "uvc"

    @property
    def is_simulated(self) -> bool:
        """A simulated world (a scripted operator and a ground truth), whatever the camera path."""
        return self.value.startswith("sim")


class DistortionModel(enum.StrEnum):
    """Lens distortion models, nested, simplest first: the free coefficients of OpenCV's 8-vector."""

    NONE = "none"
    K1 = "k1"
    K1K2 = "k1k2"
    FOURCOEF = "4coef"
    FIVECOEF = "5coef"
    RATIONAL = "rational"


class PatternKind(enum.StrEnum):
    """What the projector shows in the projector step."""

    CIRCLES = "circles"
    CHESSBOARD = "chessboard"
    #: a coded sequence per board placement (docs/STRUCTURED_LIGHT.md); the calibration reads its points
    #: as points (no circle model)
    STRUCTURED = "structured"


class CalibrationMethod(enum.StrEnum):
    """The calibration pipelines: the published one (paper) and the joint adjustment (joint)."""

    PAPER = "paper"
    JOINT = "joint"


class RenderQuality(enum.StrEnum):
    """The simulator's rendering: fast enough for a live session, or the supersampled session quality."""

    LIVE = "live"
    SESSION = "session"


class LengthUnit(enum.StrEnum):
    """The unit a board's lengths (and so a calibration's translations) are given in."""

    MM = "mm"
    CM = "cm"
    M = "m"
    IN = "in"

    @property
    def mm(self) -> float:
        """Millimetres per unit."""
        return _MM_PER[self]


_MM_PER = {LengthUnit.MM: 1.0, LengthUnit.CM: 10.0, LengthUnit.M: 1000.0, LengthUnit.IN: 25.4}


def choices(vocabulary: type[enum.StrEnum]) -> tuple[str, ...]:
    """The words of a vocabulary, in definition order (argparse `choices=`, error messages)."""
    return tuple(m.value for m in vocabulary)
