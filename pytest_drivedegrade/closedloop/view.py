"""What the planner's `images` argument holds at one route step: the six cameras as the open loop's read-only
view (`loader.planner_view`). The cameras the planner declares are rendered and corrupted up front, as one
sample; any other camera is rendered only if the planner reads it (then corrupted alone, which gives the same
pixels: each camera's randomness is keyed by its own name). So undeclared cameras cost nothing, and a planner
that secretly reads one sees it, clean in `closed-clean` and black in `closed-blackout-s3`: the null control
catches it.

With a thread pool (``--drivedegrade-prefetch`` above 0) each declared camera renders and is corrupted on a
thread of its own: the same pixels, since each camera's randomness is keyed by its own name (OpenCV and most of
numpy let go of the GIL while they work)."""

from __future__ import annotations

import time
from collections.abc import Mapping
from concurrent.futures import Executor
from typing import TYPE_CHECKING

import numpy as np

from ..corruptions.api import corrupt_sample
from ..loader import planner_view
from .camera import RouteCameras

if TYPE_CHECKING:
    from .simulate import Corruption, Timings


class StepImages:
    """The route's camera stream under one corruption and seed (frame key ``<route>/<step>``)."""

    def __init__(self, cameras: RouteCameras, corruption: Corruption, seed: int, timings: Timings,
                 pool: Executor | None = None) -> None:
        self.cameras, self.corruption, self.seed, self.timings = cameras, corruption, seed, timings
        self.pool = pool
        self._others: dict[str, RouteCameras] = {}  # an undeclared camera's renderer, built on its first read
        self._previous: dict[str, np.ndarray] = {}  # the last delivered image per camera (frame_dropout holds it)

    def _corrupt(self, images: dict[str, np.ndarray], k: int) -> dict[str, np.ndarray]:
        if not images or self.corruption.family == "clean":
            return images
        previous = {c: self._previous[c] for c in images if c in self._previous} or None
        return corrupt_sample(images, self.corruption.family, self.corruption.severity, seed=self.seed,
                              frame=f"{self.cameras.route.name}/{k}", previous=previous)

    def _made(self, pose: tuple[float, float, float], t: int, k: int) -> dict[str, np.ndarray]:
        """The declared cameras at `pose`, corrupted: on the pool's threads a camera each, or here."""
        cams = self.cameras
        if self.pool is None or len(cams.cameras) < 2:
            return self._corrupt(cams.images(pose, t), k)
        parts = cams.parts(pose, t)

        def one(cam: str) -> np.ndarray:
            return self._corrupt({cam: cams.one(cam, parts, pose, t)}, k)[cam]

        futures = [(cam, self.pool.submit(one, cam)) for cam in cams.cameras]
        return {cam: f.result() for cam, f in futures}

    def at(self, pose: tuple[float, float, float], t: int, k: int) -> Mapping[str, np.ndarray]:
        """The planner's images at route step `k` (log step `t`, world `pose`)."""
        t0 = time.perf_counter()
        made = self._made(pose, t, k)
        self.timings.render += time.perf_counter() - t0
        delivered = dict(made)

        def read(camera: str) -> np.ndarray:
            if camera not in delivered:
                start = time.perf_counter()
                other = self._others.get(camera)
                if other is None:
                    other = self._others[camera] = RouteCameras(self.cameras.route, (camera,))
                delivered[camera] = self._corrupt(other.images(pose, t), k)[camera]
                self.timings.render += time.perf_counter() - start
            return delivered[camera]

        self._previous = delivered  # read lazily: a camera read at this step is there by the next one
        return planner_view(read)
