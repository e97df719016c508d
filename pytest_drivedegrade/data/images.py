"""Decode camera images: RGB uint8, with a clear DataError for a missing, truncated or undecodable file."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import DataError


def decode_rgb(path: str | Path, frame_token: str = "") -> np.ndarray:
    """Read and decode an image file to H x W x 3 uint8 RGB. JPEGs must end with the EOI marker."""
    where = f" (frame {frame_token})" if frame_token else ""
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise DataError(f"missing image {p}{where}: the data set is incomplete; re-extract or regenerate it") \
            from None
    except OSError as exc:
        raise DataError(f"unreadable image {p}{where}: {exc}") from exc
    is_jpeg = data[:2] == b"\xff\xd8"
    if is_jpeg and not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
        raise DataError(f"truncated JPEG {p}{where}: no end-of-image marker ({len(data)} bytes); "
                        f"re-extract or regenerate the data set")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise DataError(f"undecodable image {p}{where} ({len(data)} bytes): the file is corrupt")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
