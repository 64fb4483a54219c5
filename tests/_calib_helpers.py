"""Shared fixtures for the calibration-stage tests: synthetic sessions and their observations, cached
per process (building a session is deterministic and takes ~0.2 s)."""

from __future__ import annotations

import dataclasses
from functools import lru_cache

import numpy as np

from calib.metrics import compare
from calib.observations import SessionObservations
from calib.synthetic import make_direct_rig, make_rig, make_session, observe


@lru_cache(maxsize=16)
def session(rig: str = "136", mirror_method: str = "real-virtual", per_position: int = 4, seed: int = 0,
            thickness_mm: float = 3.0):
    """rig: '90', '136', '180' (mirrored) or 'direct'."""
    r = make_direct_rig() if rig == "direct" else make_rig(float(rig))
    return make_session(r, mirror_method=None if rig == "direct" else mirror_method, per_position=per_position,
                        seed=seed, thickness_mm=thickness_mm)


@lru_cache(maxsize=32)
def observations(rig: str = "136", noise_px: float = 0.0, noise_seed: int = 0, mirror_method: str = "real-virtual",
                 per_position: int = 4, seed: int = 0, thickness_mm: float = 3.0) -> SessionObservations:
    return observe(session(rig, mirror_method, per_position, seed, thickness_mm), noise_px, noise_seed)


def metrics(result, rig: str = "136", mirror_method: str = "real-virtual", per_position: int = 4, seed: int = 0):
    return compare(result, session(rig, mirror_method, per_position, seed).rig.ground_truth())


def replace_obs(obs: SessionObservations, **changes) -> SessionObservations:
    return dataclasses.replace(obs, **changes)


def rel_err(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-300))
