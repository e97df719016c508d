"""Decode camera images: RGB uint8, with a clear DataError naming the file and the frame for a missing, empty,
truncated, undecodable or wrong-size file (a data fault, counted apart from the planner's contract failures)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import DataError


def decode_rgb(path: str | Path, frame_token: str = "", size: tuple[int, int] | None = None) -> np.ndarray:
    """Read and decode an image file to H x W x 3 uint8 RGB. JPEGs must end with the EOI marker; with `size`
    (width, height: what the calibration and sample_data say), the decoded image must have exactly that size."""
    where = f" (frame {frame_token})" if frame_token else ""
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise DataError(f"missing image {p}{where}: the data set is incomplete; re-extract or regenerate it") \
            from None
    except OSError as exc:
        raise DataError(f"unreadable image {p}{where}: {exc}") from exc
    if not data:
        raise DataError(f"empty image file {p}{where} (0 bytes): re-extract or regenerate the data set")
    is_jpeg = data[:2] == b"\xff\xd8"
    if is_jpeg and not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
        raise DataError(f"truncated JPEG {p}{where}: no end-of-image marker ({len(data)} bytes); "
                        f"re-extract or regenerate the data set")
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    except cv2.error as exc:  # OpenCV asserts on some malformed buffers instead of returning None
        raise DataError(f"undecodable image {p}{where} ({len(data)} bytes): {' '.join(str(exc).split())}") \
            from None
    if img is None:
        raise DataError(f"undecodable image {p}{where} ({len(data)} bytes): the file is corrupt")
    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        raise DataError(f"wrong-size image {p}{where}: {img.shape[1]} x {img.shape[0]} pixels, but sample_data "
                        f"and the calibration say {size[0]} x {size[1]}; the intrinsics would not match it, so it "
                        "is not scored: re-extract or regenerate the data set")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
