"""Stream-level families, which act on the six-camera sample rather than one image: frame dropout
(temporal) and camera blackout (multi-camera)."""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np

from .registry import register

RngFor = Callable[[str], np.random.Generator]


def frame_lost(rng: np.random.Generator, probability: float) -> bool:
    """One draw: is this camera's frame lost? The first number of the camera's own generator."""
    return bool(rng.random() < probability)


@register("frame_dropout", group="temporal", axis="removal", parameter="frame loss probability",
          unit="probability", values=(0.1, 0.2, 0.3, 0.5, 0.7), random=True, scope="sample")
def frame_dropout(images: Mapping[str, np.ndarray], probability: float, rng_for: RngFor,
                  previous: Mapping[str, np.ndarray] | None) -> dict[str, np.ndarray]:
    """Each camera's frame is lost with `probability`, independently; a lost frame is held at the last
    delivered frame of that camera (`previous`), or black when there is none."""
    out = {}
    for camera, image in images.items():
        if frame_lost(rng_for(camera), probability):
            held = None if previous is None else previous.get(camera)
            out[camera] = np.zeros_like(image) if held is None or held.shape != image.shape else held.copy()
        else:
            out[camera] = image.copy()
    return out


@register("blackout", group="multi-camera", axis="removal", parameter="cameras set to zero", unit="cameras",
          values=(("CAM_BACK",), ("CAM_BACK_LEFT", "CAM_BACK_RIGHT"),
                  ("CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT"), ("CAM_FRONT_LEFT", "CAM_FRONT_RIGHT"),
                  ("CAM_FRONT",)), random=False, scope="sample")
def blackout(images: Mapping[str, np.ndarray], cameras: tuple[str, ...], rng_for: RngFor,
             previous: Mapping[str, np.ndarray] | None) -> dict[str, np.ndarray]:
    """The named cameras deliver all-zero images; the others are untouched."""
    return {cam: (np.zeros_like(img) if cam in cameras else img.copy()) for cam, img in images.items()}
