"""How still the simulated operator keeps the board once it is placed.

A person's board is never exactly still. Held by hand it sways slowly (the arms' posture drifting,
0.1-1 Hz) and shakes with physiological tremor (6-12 Hz); resting on a stand it only picks up the floor's
vibration; a board laid on the mirror does not move at all. The motion matters wherever the station
uses several frames of one placement (a structured-light sequence, the mean of a mirror placement's
frames): there a hand-held board moves between the first and the last frame, and the station has to
notice. A single frame's exposure (a few milliseconds) blurs none of it.

The offset is a deterministic function of (seed, placement, time since the placement), a sum of
sinusoids with drawn frequencies and phases, so a frame rendered twice, or out of order, shows the
board where it was at that moment.

Magnitudes: the tremor's is from the normative range of postural hand tremor (a modal 0.01 g peak at
about 7 Hz, some 0.05 mm; Elble & Randall's and Marsden's studies put the normal range at 0.0015-0.035 g);
the sway's is an assumption of this simulator (a person holding a board still with two hands, a few
tenths of a millimetre), stated here so that a reader can change it.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from calib.models.vocab import Step
from calib.transforms import make_T, rotation_about


class Hold(enum.StrEnum):
    """How the board of a placement is held."""

    STILL = "still"  # does not move (laid on the mirror; the ideal rig)
    STAND = "stand"  # rests on a stand or tripod: the floor's vibration
    HAND = "hand"  # held by hand: postural sway and tremor


class MirrorHold(enum.StrEnum):
    """How a rendered session's averaged mirror placements are held (`procam bench placements
    --mirror-hold`): still, or as the simulated operator holds the step's board (STEP_HOLD)."""

    STILL = "still"
    PERSON = "person"


@dataclass(frozen=True)
class HoldModel:
    """1-sigma sizes of the board's motion about where it was placed, per axis."""

    sway_mm: float = 0.0  # slow drift of the board's centre, 0.1-1 Hz
    sway_deg: float = 0.0  # slow rotation about the board's centre, 0.1-1 Hz
    tremor_mm: float = 0.0  # physiological tremor of the board's centre, 6-12 Hz

    @property
    def moves(self) -> bool:
        return self.sway_mm > 0 or self.sway_deg > 0 or self.tremor_mm > 0


HOLD_MODELS = {
    Hold.STILL: HoldModel(),
    Hold.STAND: HoldModel(sway_mm=0.002, sway_deg=0.0002, tremor_mm=0.001),
    Hold.HAND: HoldModel(sway_mm=0.25, sway_deg=0.03, tremor_mm=0.035),
}

#: how the simulated operator holds each step's board unless the station asks for a stand: by hand, but
#: a board laid on the mirror lies still
STEP_HOLD = {
    Step.REAL_VIRTUAL: Hold.HAND,
    Step.REAL_MIRROR: Hold.STILL,
    Step.PROJECTOR: Hold.HAND,
    Step.VERIFICATION: Hold.STAND,
}


def hold_of(step, on_stand: bool) -> Hold:
    """How a person holds `step`'s board: on a stand when the station asks for one (it uses several
    frames of the placement), else as STEP_HOLD says."""
    usual = STEP_HOLD[Step(step)]
    return Hold.STAND if on_stand and usual is Hold.HAND else usual


_SWAY_HZ = (0.1, 1.0)
_TREMOR_HZ = (6.0, 12.0)
_TERMS = 4  # sinusoids per axis and band


def _band(rng: np.random.Generator, sigma: float, band: tuple[float, float], t_s: float) -> np.ndarray:
    """Three axes of a stationary band-limited motion with 1-sigma `sigma` at time t_s."""
    f = rng.uniform(band[0], band[1], (3, _TERMS))
    phase = rng.uniform(0.0, 2 * np.pi, (3, _TERMS))
    amp = sigma * np.sqrt(2.0 / _TERMS)
    return amp * np.sin(2 * np.pi * f * float(t_s) + phase).sum(axis=1)


def held_offset(model: HoldModel, key, t_s: float, centre_board: np.ndarray) -> np.ndarray:
    """T_board_moved: where the board is at t_s seconds after its placement, in its placed frame, rotated
    about `centre_board` (a point on the board, board frame). `key`: a sequence of ints naming the
    placement (the same key and time give the same offset)."""
    if not model.moves:
        return np.eye(4)
    rng = np.random.default_rng([abs(int(k)) for k in key])
    shift = _band(rng, model.sway_mm, _SWAY_HZ, t_s) + _band(rng, model.tremor_mm, _TREMOR_HZ, t_s)
    rot = _band(rng, model.sway_deg, _SWAY_HZ, t_s)
    angle = float(np.linalg.norm(rot))
    R = rotation_about(rot / angle, angle) if angle > 0 else np.eye(3)
    c = np.asarray(centre_board, float).reshape(3)
    return make_T(R, c - R @ c + shift)


def held_pose(model: HoldModel, key, T_cam_board: np.ndarray, outline, t_s: float) -> np.ndarray:
    """T_cam_board of a board placed at `T_cam_board` and held by `model`, t_s seconds after its
    placement, rotating about the middle of its `outline` (x0, y0, x1, y1, board frame)."""
    if not model.moves:
        return T_cam_board
    x0, y0, x1, y1 = outline
    return T_cam_board @ held_offset(model, key, t_s, np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0]))
