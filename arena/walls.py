"""The walls around a track, as closed polylines shared by the physics and the lidar.

The walls stand ``runoff`` metres outside each road edge, so a car can run wide (off the
track, as DeepRacer counts it) before it hits a wall, as on a real circuit. The physics builds
its wall boxes from these polylines and the lidar casts against the very same lines, so what
a car sees is what it can hit.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tracks import Track

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

DEFAULT_RUNOFF = 0.4  # m of run-off between the road edge and the wall

# Track → run-off → (left, right) wall offsets: computing them projects thousands of points.
_OFFSETS: weakref.WeakKeyDictionary[Track, dict[float, tuple[FloatArray, FloatArray]]] = (
    weakref.WeakKeyDictionary()
)


def wall_offsets(track: Track, runoff: float) -> tuple[FloatArray, FloatArray]:
    """Distances (N,) m from the centre line to the left and right walls (cached per track).

    ``width + runoff`` wherever that is clear of the road, shorter where it is not
    (:meth:`tracks.Track.wall_offsets`); identical to ``width + runoff`` on the built-in tracks.
    """
    per_track = _OFFSETS.setdefault(track, {})
    if runoff not in per_track:
        per_track[runoff] = track.wall_offsets(runoff)
    return per_track[runoff]


WALL_SPACING = 0.5  # m between wall polyline points (chord error < 2 cm at 1.5 m radius)


@dataclass(frozen=True)
class Walls:
    """Inner faces of the left and right walls.

    Attributes:
        left: (W, 2) m, closed polyline on the left of the driving direction.
        right: (W, 2) m, closed polyline on the right.
        stride: centre-line points per wall point: wall point ``k`` sits beside centre point
            ``k * stride``, so a car's centre-line segment index locates nearby walls.
    """

    left: FloatArray
    right: FloatArray
    stride: int

    @classmethod
    def around(cls, track: Track, runoff: float = DEFAULT_RUNOFF) -> Walls:
        """Walls ``runoff`` m outside both road edges of ``track`` (less where that is road).

        Where the full run-off would put a wall on another part of the road (the infield of
        a tight hairpin on an imported track) it is shortened: see :func:`wall_offsets`.
        """
        stride = max(1, round(WALL_SPACING / float(np.mean(track.segment_lengths))))
        idx = np.arange(0, track.n_points, stride)
        c, n = track.centre[idx], track.normals[idx]
        to_left, to_right = wall_offsets(track, runoff)
        left = c + to_left[idx, None] * n
        right = c - to_right[idx, None] * n
        return cls(left=left, right=right, stride=stride)

    @property
    def n_points(self) -> int:
        """Points W per wall polyline."""
        return len(self.left)

    def window(self, segment: IntArray, half_width: int) -> IntArray:
        """Wall-point indices (n, 2*half_width+1) around centre-line segment indices (n,)."""
        base = np.asarray(segment, dtype=np.int64) // self.stride
        return (base[:, None] + np.arange(-half_width, half_width + 1)) % self.n_points

    def segments(self) -> tuple[FloatArray, FloatArray]:
        """All wall segments: starts and ends (2W, 2) m, left wall first."""
        starts = np.vstack([self.left, self.right])
        ends = np.vstack([np.roll(self.left, -1, axis=0), np.roll(self.right, -1, axis=0)])
        return starts, ends
