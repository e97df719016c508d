"""Decode camera images: RGB uint8, with a clear DataError naming the file and the frame for a missing, empty,
truncated, undecodable or wrong-size file (a data fault, counted apart from the planner's contract failures)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import DataError

#: The most pixels an image may declare in its header when the data does not say its size (a decompression bomb:
#: a few kilobytes that decode to gigabytes). nuScenes' cameras have 1.44 million.
MAX_PIXELS = 64_000_000
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def declared_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) as a JPEG's frame header or a PNG's IHDR declares it, read without decoding; None for
    another format or a header that cannot be followed (the decoder then says what is wrong)."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR":
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    at = 2 if data[:2] == b"\xff\xd8" else len(data)
    while at + 4 <= len(data) and data[at] == 0xFF:
        marker, length = data[at + 1], int.from_bytes(data[at + 2:at + 4], "big")
        if marker in _SOF and at + 9 <= len(data):
            return int.from_bytes(data[at + 7:at + 9], "big"), int.from_bytes(data[at + 5:at + 7], "big")
        if marker == 0xDA or length < 2:  # the scan starts: no frame header before it
            return None
        at += 2 + length
    return None


def _check_header(data: bytes, where: str, size: tuple[int, int] | None) -> None:
    """Refuse an image by its header before it is decoded: another size than the data says, or (without a size)
    more than `MAX_PIXELS` pixels."""
    declared = declared_size(data)
    if declared is None:
        return
    if size is not None and declared != tuple(size):
        raise DataError(f"wrong-size image {where}: {declared[0]} x {declared[1]} pixels, but sample_data and the "
                        f"calibration say {size[0]} x {size[1]}; the intrinsics would not match it, so it is not "
                        "scored (refused by its header, not decoded): re-extract or regenerate the data set")
    if declared[0] * declared[1] > MAX_PIXELS:
        raise DataError(f"image {where} declares {declared[0]} x {declared[1]} pixels, more than {MAX_PIXELS:,} "
                        "(a decompression bomb, or not a camera image); refused by its header, not decoded")


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
    _check_header(data, f"{p}{where}", size)
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
