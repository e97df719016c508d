"""Transmission-group families: lossy compression and resolution loss on the link to the compute unit."""

from __future__ import annotations

import cv2
import numpy as np

from .registry import register

_IMREAD_COLOR_RGB = getattr(cv2, "IMREAD_COLOR_RGB", None)


@register("jpeg", group="transmission", axis="quality", parameter="JPEG quality", unit="quality",
          values=(75, 45, 25, 12, 6), random=False)
def jpeg(image: np.ndarray, quality: int, rng: None, scale: float) -> np.ndarray:
    """Baseline JPEG (libjpeg via OpenCV, 4:2:0 chroma) encode and decode at the given quality."""
    bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - libjpeg does not fail on a valid uint8 image
        raise RuntimeError("JPEG encoding failed")
    if _IMREAD_COLOR_RGB is not None:  # OpenCV >= 4.10 decodes straight to RGB: one pass less
        rgb = cv2.imdecode(buf, _IMREAD_COLOR_RGB)
        assert rgb is not None  # decoding the buffer imencode just wrote
        return rgb
    decoded = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    assert decoded is not None  # decoding the buffer imencode just wrote
    return cv2.cvtColor(decoded, cv2.COLOR_BGR2RGB)


@register("downscale", group="transmission", axis="quality", parameter="linear downscale factor",
          unit="x", values=(1.5, 2, 3, 4, 6), random=False)
def downscale(image: np.ndarray, factor: float, rng: None, scale: float) -> np.ndarray:
    """Area downsampling by `factor`, then bilinear upsampling back to the original size."""
    h, w = image.shape[:2]
    small = (max(1, round(w / factor)), max(1, round(h / factor)))
    reduced = cv2.resize(image, small, interpolation=cv2.INTER_AREA)
    return cv2.resize(reduced, (w, h), interpolation=cv2.INTER_LINEAR)
