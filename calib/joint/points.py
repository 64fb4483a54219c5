"""The observations of the joint adjustment as frozen point sets: the ChArUco corners and the projected
pattern points of every view, flat arrays gathered once (calib.joint.assembly) and cut down by `subset`
when outliers are rejected. Arrays are read-only; `pose` indexes the problem's views, `cid` its list of
capture ids."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

#: what a corner observation is (CornerSet.kind) and the name its class and its records carry
KIND_BOARD, KIND_REAL, KIND_VIRTUAL = 0, 1, 2
KIND_NAMES = {KIND_BOARD: "board", KIND_REAL: "mirror-real", KIND_VIRTUAL: "mirror-virtual"}
#: the observation classes with a noise sigma of their own (a corner kind's, and the pattern points')
CLASS_OF_KIND = {KIND_BOARD: "board", KIND_REAL: "mirror_real", KIND_VIRTUAL: "mirror_virtual"}
PATTERN_CLASS = "pattern"


class _PointSet:
    """Shared by the point sets: read-only arrays, a length, subset and the views' renumbering."""

    def __post_init__(self):
        for f in fields(self):
            a = np.array(getattr(self, f.name))
            a.setflags(write=False)
            object.__setattr__(self, f.name, a)

    def __len__(self) -> int:
        return len(self.pose)

    def subset(self, mask: np.ndarray):
        """The points of the boolean `mask`."""
        return replace(self, **{f.name: getattr(self, f.name)[mask] for f in fields(self)})

    def renumbered(self, new_index: np.ndarray):
        """The same points with their views renumbered by `new_index[old view]`."""
        return replace(self, pose=np.asarray(new_index)[self.pose])


@dataclass(frozen=True, eq=False)
class CornerSet(_PointSet):
    """ChArUco corners: board coordinates X (N, 3), observed camera pixels uv (N, 2), whether each is seen
    through the mirror, its kind (KIND_*), capture index and corner id."""

    pose: np.ndarray
    X: np.ndarray
    uv: np.ndarray
    mirror: np.ndarray
    kind: np.ndarray
    cid: np.ndarray
    pid: np.ndarray


@dataclass(frozen=True, eq=False)
class PatternSet(_PointSet):
    """Projected pattern points: projector pixels q (M, 2), observed camera pixels uv (M, 2), whether each
    is seen through the mirror, capture index, the point's index in its view, and its noise relative to
    the class's (`rel`: 1 for points without a sigma of their own; calib.joint.assembly)."""

    pose: np.ndarray
    q: np.ndarray
    uv: np.ndarray
    mirror: np.ndarray
    cid: np.ndarray
    pid: np.ndarray
    rel: np.ndarray
