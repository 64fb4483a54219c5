"""The previous calibration's intrinsics as a Gaussian prior on a re-estimate (IntrinsicsPrior)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from calib.models.camera import CameraModel
from calib.models.result import CalibrationResult

# ---- the intrinsics prior ---------------------------------------------------------------------------
#: eigenvalues of the prior's correlation matrix below PRIOR_EIG_FLOOR x the largest are raised to it:
#: along directions the previous session could not separate (e.g. k3 against k1, k2) the prior becomes
#: weaker, never stronger, and its Cholesky factor exists
PRIOR_EIG_FLOOR = 1e-9


INTRINSICS_MODES = ("held", "prior")


_DEVICE_BLOCK = {"cam": "cam_intr", "proj": "proj_intr"}


@dataclass(frozen=True, eq=False)
class IntrinsicsPrior:
    """A Gaussian prior on device intrinsics (fx, fy, cx, cy and the distortion coefficients the
    previous calibration estimated): the previous values as its mean, the previous covariance of those
    parameters (the marginal: the matching rows and columns of the stored covariance) as its
    covariance. Its residuals are W (x - x_prev), W = L^-1 D^-1 where D^-1 C D^-1 = L L^T (Cholesky of
    the correlation matrix, eigenvalues floored at PRIOR_EIG_FLOOR): |r|^2 = (x - x_prev)^T C^-1 (x - x_prev)."""

    blocks: tuple[str, ...]  # "cam_intr" and/or "proj_intr"
    params: dict  # block -> tuple of names ("cam.fx", ..., "cam.dist1", ...)
    offset: np.ndarray  # the model's start minus the prior's mean, in the order of the blocks' names
    W: np.ndarray  # (n, n) whitening matrix
    floored: int  # eigenvalues raised to the floor

    @property
    def n(self) -> int:
        return len(self.offset)

    def block_size(self, block: str) -> int:
        return len(self.params[block])

    def names_of(self, block: str) -> tuple[str, ...]:
        return self.params[block]

    def residual(self, blocks: dict) -> np.ndarray:
        return self.W @ (self.offset + np.concatenate([blocks[b] for b in self.blocks]))

    @cached_property
    def W_inv(self) -> np.ndarray:
        return np.linalg.inv(self.W)

    def unwhiten(self, z: np.ndarray) -> np.ndarray:
        """The corrections (all blocks, in order) whose residual is z."""
        return self.W_inv @ z - self.offset

    def device(self, dev: CameraModel, block: str, blocks: dict) -> CameraModel:
        """`dev` with the correction of `block` applied (unchanged when the block is not there)."""
        if block not in blocks:
            return dev
        return _with_intrinsics(dev, self.params[block], _intrinsics(dev, self.params[block]) + blocks[block])


def _dist_index(name: str) -> int | None:
    tail = name.rsplit(".", 1)[-1]
    return int(tail[4:]) if tail.startswith("dist") and tail[4:].isdigit() else None


def _intrinsics(dev: CameraModel, names) -> np.ndarray:
    K = np.asarray(dev.K, float)
    d8 = np.zeros(8)
    d8[:dev.dist.size] = dev.dist
    val = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
    return np.array([val[n.rsplit(".", 1)[-1]] if _dist_index(n) is None else d8[_dist_index(n)] for n in names])


def _with_intrinsics(dev: CameraModel, names, values) -> CameraModel:
    K = np.array(dev.K, float)
    top = max([_dist_index(n) for n in names if _dist_index(n) is not None], default=-1)
    d = np.zeros(8 if max(top, dev.dist.size - 1) >= 5 else 5)
    d[:dev.dist.size] = dev.dist
    pos = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}
    for n, v in zip(names, values):
        i = _dist_index(n)
        if i is None:
            K[pos[n.rsplit(".", 1)[-1]]] = v
        else:
            d[i] = v
    return dev.with_params(K=K, dist=d)


def _stored_covariance(previous: CalibrationResult) -> tuple[list, np.ndarray] | None:
    u = previous.uncertainty if isinstance(previous.uncertainty, dict) else {}
    cv = u.get("covariance") if isinstance(u.get("covariance"), dict) else {}
    names = cv.get("names")
    try:
        M = np.array(cv.get("matrix"), float)
    except (TypeError, ValueError):
        return None
    if not isinstance(names, list) or M.ndim != 2 or M.shape != (len(names), len(names)) or \
            not np.all(np.isfinite(M)):
        return None
    return names, (M + M.T) / 2


def intrinsics_prior(previous: CalibrationResult, current: CalibrationResult,
                     devices=("cam", "proj")) -> IntrinsicsPrior | None:
    """The prior on the intrinsics of `devices` ("cam", "proj") from `previous`'s stored covariance, for
    a model started at `current`; None when the previous calibration stored no covariance of them (held
    fixed, another method, or an unreadable file): then they can only be held."""
    stored = _stored_covariance(previous)
    if stored is None:
        return None
    names, M = stored
    idx = {n: i for i, n in enumerate(names)}
    params = {}
    for dev in devices:
        core = [f"{dev}.{k}" for k in ("fx", "fy", "cx", "cy")]
        if not all(n in idx for n in core):
            continue
        dist = sorted((n for n in names if n.startswith(f"{dev}.dist") and _dist_index(n) is not None),
                      key=_dist_index)
        params[_DEVICE_BLOCK[dev]] = tuple(core + dist)
    if not params:
        return None
    blocks = tuple(params)
    order = [n for b in blocks for n in params[b]]
    ii = [idx[n] for n in order]
    C = M[np.ix_(ii, ii)]
    sd = np.sqrt(np.diag(C))
    if not np.all(sd > 0):
        return None
    R = C / sd[:, None] / sd[None, :]
    lam, V = np.linalg.eigh((R + R.T) / 2)
    floor = PRIOR_EIG_FLOOR * float(lam[-1])
    floored = int(np.sum(lam < floor))
    L = np.linalg.cholesky((V * np.maximum(lam, floor)) @ V.T)
    from scipy.linalg import solve_triangular

    W = solve_triangular(L, np.diag(1.0 / sd), lower=True)
    devs = {"cam_intr": (current.camera, previous.camera), "proj_intr": (current.projector, previous.projector)}
    offset = np.concatenate([_intrinsics(devs[b][0], params[b]) - _intrinsics(devs[b][1], params[b]) for b in blocks])
    return IntrinsicsPrior(blocks, params, offset, W, floored)
