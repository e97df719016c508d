"""Loader hooks: put the same injector inside code bases this plugin does not drive.

A planner repository usually loads its camera images with `cv2.imread`, `mmcv.imread` or `PIL.Image.open`.
`Injection` wraps such a callable so that every image it returns is corrupted after decoding and before the
code base's own normalisation, exactly as the plugin's loader does (the paper's "one injector, fifteen
policies")::

    import cv2
    from pytest_drivedegrade import patch_loader

    # every cv2.imread in the planner's data pipeline now returns JPEG-q12 images (BGR stays BGR)
    with patch_loader(cv2, "imread", "jpeg", 4, channel_order="BGR"):
        run_planner_evaluation()

    # or as a decorator on a loader of your own that returns RGB arrays
    @inject_loader("gaussian_blur", 3)
    def load_rgb(path): ...

The frame key and camera of each image come from its path: nuScenes file names carry both
(`<log>__CAM_FRONT__<timestamp>.jpg`); a path without a camera name counts as CAM_FRONT. Stream-level
families work per image too: blackout zeroes the images of its cameras, frame_dropout holds the last image
this hook delivered for that camera. Images that are not 8-bit 3-channel (depth maps, masks) pass through
unchanged and are counted in `skipped`.
"""

from __future__ import annotations

import functools
import os
import re
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import PurePath
from typing import Any

import numpy as np

from ..constants import CAMERAS
from .api import check_family, check_severity, corrupt_sample

_ORDERS = ("RGB", "BGR")
_CAMERA_IN_NAME = re.compile(r"(CAM_(?:FRONT|BACK)(?:_LEFT|_RIGHT)?)")


def camera_of(path: str | os.PathLike[str]) -> str:
    """The nuScenes camera named in a file path (`..__CAM_FRONT__..` or `samples/CAM_FRONT/`), else CAM_FRONT."""
    found = _CAMERA_IN_NAME.findall(os.fspath(path))
    return found[-1] if found and found[-1] in CAMERAS else "CAM_FRONT"


def frame_key(path: object) -> tuple[str, str]:
    """(frame, camera) for an image path: the file stem and the nuScenes camera in the path."""
    text = os.fspath(path) if isinstance(path, (str, os.PathLike)) else str(path)
    return PurePath(text).stem, camera_of(text)


class Injection:
    """Corrupt every image a wrapped loader returns with one family at one severity.

    Use it as a decorator (`Injection(...)(loader)`) or through `inject_loader` / `patch_loader`.
    `channel_order` says how the loader's arrays are ordered ("BGR" for OpenCV, "RGB" otherwise); PIL
    images are recognised and converted back to PIL after corruption.
    """

    def __init__(self, family: str, severity: int, *, seed: int = 0, channel_order: str = "RGB",
                 key: Callable[[object], tuple[str, str]] = frame_key) -> None:
        self.family = check_family(family)
        self.severity = check_severity(severity)
        if channel_order not in _ORDERS:
            raise ValueError(f"channel_order must be one of {_ORDERS}, got {channel_order!r}")
        self.seed, self.channel_order, self.key = int(seed), channel_order, key
        self.delivered: dict[str, np.ndarray] = {}  # last image per camera, for frame_dropout
        self.corrupted = 0
        self.skipped = 0

    def apply(self, image: Any, source: object) -> Any:
        """Corrupt one loaded image (ndarray or PIL image) that came from `source`."""
        is_pil = hasattr(image, "mode") and hasattr(image, "size") and not isinstance(image, np.ndarray)
        array = np.asarray(image.convert("RGB") if is_pil else image)
        if array.dtype != np.uint8 or array.ndim != 3 or array.shape[2] != 3:
            self.skipped += 1
            return image
        if self.channel_order == "BGR" and not is_pil:
            array = array[..., ::-1]
        frame, camera = self.key(source)
        out = corrupt_sample({camera: np.ascontiguousarray(array)}, self.family, self.severity, seed=self.seed,
                             frame=frame, previous=self.delivered)[camera]
        self.delivered[camera] = out
        self.corrupted += 1
        if is_pil:
            return _to_pil(image, out)
        return np.ascontiguousarray(out[..., ::-1]) if self.channel_order == "BGR" else out

    def __call__(self, loader: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(loader)
        def wrapped(source: object, *args: Any, **kwargs: Any) -> Any:
            image = loader(source, *args, **kwargs)
            return image if image is None else self.apply(image, source)

        wrapped.__drivedegrade_injection__ = self  # type: ignore[attr-defined]
        return wrapped


def _to_pil(original: Any, array: np.ndarray) -> Any:
    """Back to a PIL image of the original's mode, using the original's own module (no PIL import here)."""
    import PIL.Image

    return PIL.Image.fromarray(array, "RGB").convert(original.mode)


def inject_loader(family: str, severity: int, **options: Any) -> Injection:
    """Decorator form: `@inject_loader("fog", 3)` above a loader that returns RGB arrays."""
    return Injection(family, severity, **options)


@contextmanager
def patch_loader(owner: Any, name: str, family: str, severity: int, **options: Any) -> Iterator[Injection]:
    """Replace `owner.name` (a module or class attribute such as `cv2.imread`) with an injecting wrapper for
    the duration of the block; restored on exit, also on error. Yields the `Injection` (its counters)."""
    original = getattr(owner, name)
    injection = Injection(family, severity, **options)
    setattr(owner, name, injection(original))
    try:
        yield injection
    finally:
        setattr(owner, name, original)
