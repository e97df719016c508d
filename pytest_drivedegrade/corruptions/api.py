"""The public injector API: `corrupt` for one image, `corrupt_sample` for a six-camera sample.

Both validate their input and raise `InvalidInput` (a `ValueError`) naming the problem and the valid
choices; neither ever modifies its input, and both return new, writeable uint8 arrays.
"""

from __future__ import annotations

from collections.abc import Mapping
from numbers import Integral

import numpy as np

from ..constants import CAMERAS, REFERENCE_WIDTH
from ..errors import InvalidInput
from .ladder import FAMILIES, Family
from .seeding import rng_for

#: Cells that are not on the ladder: the clean image (severity 0) and all six cameras black.
DIAGNOSTIC = ("clean", "blind")


def check_image(image: object, where: str = "image") -> np.ndarray:
    """An H x W x 3 uint8 array, or InvalidInput saying what it is instead."""
    if not isinstance(image, np.ndarray):
        raise InvalidInput(f"{where}: expected a numpy array (H x W x 3 uint8 RGB), got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise InvalidInput(f"{where}: expected dtype uint8, got {image.dtype}; convert with "
                           "np.clip(x, 0, 255).astype(np.uint8) or load 8-bit images")
    if image.ndim != 3 or image.shape[2] != 3:
        raise InvalidInput(f"{where}: expected shape H x W x 3 (RGB), got {image.shape}; "
                           "grey or RGBA images must be converted to 3-channel RGB first")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise InvalidInput(f"{where}: the image is empty (shape {image.shape})")
    return image


def check_family(family: object, *, allow_diagnostic: bool = False) -> str:
    valid = list(FAMILIES) + (list(DIAGNOSTIC) if allow_diagnostic else [])
    if not isinstance(family, str) or family not in valid:
        raise InvalidInput(f"unknown corruption family {family!r}; valid families: {', '.join(valid)}")
    return family


def check_severity(severity: object) -> int:
    if isinstance(severity, bool) or not isinstance(severity, Integral) or not 0 <= int(severity) <= 5:
        raise InvalidInput(f"severity must be an integer 0..5 (0 = clean, 1..5 = S1..S5), got {severity!r}")
    return int(severity)


def check_camera(camera: object) -> str:
    if camera not in CAMERAS:
        raise InvalidInput(f"unknown camera {camera!r}; valid cameras: {', '.join(CAMERAS)}")
    return str(camera)


def _apply_image(family: Family, image: np.ndarray, severity: int, seed: int, frame: str,
                 camera: str) -> np.ndarray:
    rng = rng_for(seed, frame, camera, family.name, severity) if family.random else None
    out = family.op(image, family.value(severity), rng, image.shape[1] / REFERENCE_WIDTH)
    return np.ascontiguousarray(out, dtype=np.uint8)


def corrupt(image: np.ndarray, family: str, severity: int, *, seed: int = 0, frame: str = "",
            camera: str = "CAM_FRONT") -> np.ndarray:
    """Apply a single-image family at severity 0..5 to an H x W x 3 uint8 RGB image.

    The realisation of a random family is keyed by (seed, frame, camera, family, severity). Severity 0
    returns an equal copy. Stream-level families (frame_dropout, blackout) need the whole sample: use
    `corrupt_sample`.
    """
    image = check_image(image)
    fam = FAMILIES[check_family(family)]
    severity = check_severity(severity)
    camera = check_camera(camera)
    if fam.scope != "image":
        raise InvalidInput(f"{family!r} acts on the six-camera sample, not one image; use "
                           f"corrupt_sample(images, {family!r}, {severity})")
    if severity == 0:
        return image.copy()
    return _apply_image(fam, image, severity, int(seed), str(frame), camera)


def corrupt_sample(images: Mapping[str, np.ndarray], family: str, severity: int, *, seed: int = 0,
                   frame: str = "", previous: Mapping[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Apply any family to a sample (camera name -> image); also the diagnostic cells "clean" and "blind".

    `previous` holds the last delivered image per camera, for frame_dropout's hold-last-frame. Each
    camera's randomness is keyed by its own name, so a camera's result does not depend on which other
    cameras are in the sample.
    """
    if not isinstance(images, Mapping) or not images:
        raise InvalidInput("images: expected a non-empty mapping camera name -> H x W x 3 uint8 array")
    for camera, image in images.items():
        check_camera(camera)
        check_image(image, where=f"images[{camera!r}]")
    name = check_family(family, allow_diagnostic=True)
    severity = check_severity(severity)
    if name == "clean" or severity == 0 and name != "blind":
        return {cam: img.copy() for cam, img in images.items()}
    if name == "blind":
        return {cam: np.zeros_like(img) for cam, img in images.items()}
    fam = FAMILIES[name]
    if fam.scope == "sample":
        return fam.op(images, fam.value(severity),
                      lambda cam: rng_for(int(seed), str(frame), cam, name, severity), previous)
    return {cam: _apply_image(fam, img, severity, int(seed), str(frame), cam) for cam, img in images.items()}
