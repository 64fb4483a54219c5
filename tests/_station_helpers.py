"""Helpers for the station tests: small session stores and stand-in calibration/verification callables
for tests of the state machine's logic (the end-to-end tests use the real pipeline on the sim rig)."""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib.boards import CharucoSpec
from calib.observations import VIEW_DIRECT, VIEW_MIRROR
from calib.pattern import PatternSpec
from calib.session import RigInfo, SessionManifest, SessionStore
from calib.synthetic import make_rig

REPO = Path(__file__).resolve().parents[1]
CAM_SIZE = (1280, 800)
PROJ_SIZE = (1920, 1080)
TINY = np.zeros((6, 8, 3), np.uint8)


def make_store(folder, view: str = VIEW_MIRROR, positions: int = 13) -> SessionStore:
    man = SessionManifest(
        RigInfo(CAM_SIZE, PROJ_SIZE, view, {}, "test"),
        CharucoSpec(8, 6, "DICT_5X5_50", 50.0, 25.0),
        PatternSpec.default_for(*PROJ_SIZE, positions=positions),
        CharucoSpec(8, 6, "DICT_5X5_50", 22.0, 11.0) if view == VIEW_MIRROR else None,
    )
    return SessionStore.create(folder, man)


@dataclass
class FakeReport:
    mean_px: float
    worst_px: float
    threshold_px: float = 2.0

    @property
    def passed(self) -> bool:
        return self.worst_px <= self.threshold_px


class Recorder:
    """Calibration / verification stand-ins that record their calls and return ground truth."""

    def __init__(self, fail_calibration: str | None = None):
        self.calibrations = []
        self.verifications = []
        self.fail_calibration = fail_calibration

    def calibrate(self, folder, intrinsics, progress):
        from calib.errors import CalibrationError

        self.calibrations.append((Path(folder), intrinsics, len(SessionStore.open(folder).manifest.captures)))
        if self.fail_calibration:
            raise CalibrationError(self.fail_calibration)
        return make_rig(136).ground_truth().with_(method="stand-in", rms={"camera": 0.1, "projector": 0.2})

    def verify(self, result, **kw):
        self.verifications.append(result)
        return FakeReport(0.4, 0.9)


def run_procam(*args, timeout=300, env_extra=None, **kw) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONUNBUFFERED="1", **(env_extra or {}))
    return subprocess.run([sys.executable, "-m", "app", *args], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=timeout, **kw)


def popen_procam(*args, env_extra=None) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1", **(env_extra or {}))
    return subprocess.Popen([sys.executable, "-m", "app", *args], cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
