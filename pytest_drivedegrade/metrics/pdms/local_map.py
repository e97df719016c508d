"""The drivable area near the ego: the map cut to the polygons around one point, so that a frame's many plans
are each tested against a few rings (all edges at once) rather than the whole location's map."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ...data.maps import DrivableArea, RingSet
from .constants import LOCAL_MAP_M


class LocalDrivable:
    """A drivable-area query restricted to the polygons near one point (in the map's frame): points inside the
    window are tested against the rings of the polygons whose bounding box meets it (no other polygon can hold
    them), all edges at once with `maps.points_in_ring`'s crossing rule; a point outside the window goes to
    the whole map's query."""

    def __init__(self, drivable: DrivableArea, center: npt.ArrayLike, half: float = LOCAL_MAP_M) -> None:
        self.full = drivable
        c = np.asarray(center, dtype=np.float64).reshape(2)
        self.lo, self.hi = c - half, c + half
        polygons = [p for p in drivable.polygons if len(p.exterior) >= 3
                    and (p.exterior.min(0) <= self.hi).all() and (p.exterior.max(0) >= self.lo).all()]
        rings = [(k, False, p.exterior) for k, p in enumerate(polygons)]
        rings += [(k, True, h) for k, p in enumerate(polygons) for h in p.holes if len(h) >= 3]
        self.ring_polygon = np.array([r[0] for r in rings], dtype=np.int64)
        self.ring_hole = np.array([r[1] for r in rings], dtype=bool)
        self.rings = RingSet([r[2] for r in rings])

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if not ((pts >= self.lo) & (pts <= self.hi)).all():
            return np.asarray(self.full(pts), dtype=bool).reshape(-1)
        if not self.rings.count or not len(pts):
            return np.zeros(len(pts), dtype=bool)
        odd = self.rings.parity(pts)  # (P, rings), every ring's edges in one crossing test
        in_exterior = odd[:, ~self.ring_hole]  # (P, polygons): exterior rings come first, one per polygon
        in_hole = np.zeros_like(in_exterior)
        if self.ring_hole.any():
            holes = np.flatnonzero(self.ring_hole)
            np.logical_or.at(in_hole.T, self.ring_polygon[holes], odd[:, holes].T)
        return np.asarray((in_exterior & ~in_hole).any(axis=1), dtype=bool)
