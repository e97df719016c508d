"""Shared numeric kernels of the injector: an exact, fast discrete-Gaussian sampler, the discrete Gaussian
blur kernel, sRGB transfer tables, and a smooth random field for irregular deposits. Pure numpy / OpenCV,
vectorised.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache
from math import ceil, erf, log, sqrt
from typing import NamedTuple

import cv2
import numpy as np

_U32 = float(2**32)
#: The bucket-table value of a 16-bit bucket that a CDF step cuts (resolved with 16 more bits).
_AMBIGUOUS = -32768


class _NormalTables(NamedTuple):
    """Inverse-CDF tables of n = round(sigma * z), z ~ N(0, 1), with n clipped to [-limit, limit]."""

    values: np.ndarray  #: int16, -limit..limit
    thresholds: np.ndarray  #: uint64: thresholds[i] = P(n <= values[i]) scaled to 2**32
    bucket: np.ndarray  #: int16 per 16-bit bucket b: the value if no threshold cuts it, else _AMBIGUOUS
    shifted: np.ndarray  #: int16: bucket + limit (0..2 limit), the sentinel kept
    base: np.ndarray  #: intp per bucket: the index of the value at the bucket's first 32-bit point
    cut: np.ndarray  #: uint16 per bucket: where (low 16 bits) its first step lies
    steps: np.ndarray  #: int per bucket: how many steps cut it (1 for almost every ambiguous bucket)


@lru_cache(maxsize=64)
def _discrete_normal_tables(sigma: float, limit: int) -> _NormalTables:
    """The tables of `discrete_normal`: bucket b covers the 32-bit uniforms [b * 2**16, (b + 1) * 2**16)."""
    values = np.arange(-limit, limit + 1)
    upper = (values + 0.5) / sigma
    cdf = np.array([0.5 * (1.0 + erf(u / sqrt(2.0))) for u in upper])
    cdf[-1] = 1.0  # the tail beyond +limit folds into +limit (the clip)
    thresholds = np.minimum(np.round(cdf * _U32), _U32).astype(np.uint64)
    first = np.arange(2**16, dtype=np.uint64) << np.uint64(16)
    lo = np.searchsorted(thresholds, first, side="right")
    hi = np.searchsorted(thresholds, first + np.uint64(2**16 - 1), side="right")
    bucket = np.where(lo == hi, values[np.minimum(lo, len(values) - 1)], _AMBIGUOUS).astype(np.int16)
    cut = np.where(hi > lo, thresholds[np.minimum(lo, len(values) - 1)] - first, 0).astype(np.uint16)
    shifted = np.where(bucket == _AMBIGUOUS, _AMBIGUOUS, bucket + limit).astype(np.int16)
    return _NormalTables(values.astype(np.int16), thresholds, bucket, shifted, lo.astype(np.intp), cut, hi - lo)


def _resolve(tables: _NormalTables, high: np.ndarray, low: np.ndarray) -> np.ndarray:
    """The values of the 32-bit uniforms (high << 16 | low) whose 16-bit bucket `high` is ambiguous: the
    bucket's base value, one up past its single step; the rare buckets cut by several steps (far tails)
    search the thresholds."""
    b = high.astype(np.intp)
    index = tables.base[b] + (low >= tables.cut[b])
    several = np.flatnonzero(tables.steps[b] > 1)
    if several.size:
        u32 = (high[several].astype(np.uint64) << np.uint64(16)) | low[several].astype(np.uint64)
        index[several] = np.searchsorted(tables.thresholds, u32, side="right")
    return tables.values[index]


#: Samples per chunk of the noise kernels: a chunk's random bits, indices and noise stay in cache instead
#: of making passes over image-sized temporaries (a 1600x900 RGB image is 33 chunks).
_CHUNK = 1 << 17


def _sample_chunks(rng: np.random.Generator, count: int, tables: _NormalTables,
                   consume: Callable[[int, int, np.ndarray], None],
                   table: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Draw `count` samples chunk by chunk: `consume(start, stop, noise)` receives each chunk's int16
    noise looked up in `table` (`tables.bucket` by default, or `tables.shifted`), with the ambiguous
    samples still at the sentinel. Returns their flat positions and resolved (unshifted) values. The
    random stream is consumed as by one call: every sample's 16 bits in order, then 16 more for each
    ambiguous sample in order, so neither the chunk size nor the table changes a realisation."""
    table = tables.bucket if table is None else table
    noise = np.empty(min(_CHUNK, count), np.int16)
    indices = np.empty(noise.size, np.intp)
    positions, high = [], []
    for start in range(0, count, _CHUNK):
        stop = min(start + _CHUNK, count)
        raw = rng.bit_generator.random_raw((stop - start + 3) // 4).view(np.uint16)[: stop - start]
        chunk = noise[: stop - start]
        index = indices[: stop - start]
        index[...] = raw  # widened here, once: `take` would convert the uint16 indices more slowly itself
        table.take(index, out=chunk, mode="wrap")  # always in range; "wrap" is take's fastest mode
        consume(start, stop, chunk)
        ambiguous = np.flatnonzero(chunk == _AMBIGUOUS)
        if ambiguous.size:
            positions.append(ambiguous + start)
            high.append(raw[ambiguous])
    if not positions:
        return np.empty(0, np.intp), np.empty(0, np.int16)
    high16 = np.concatenate(high)
    low16 = rng.bit_generator.random_raw((high16.size + 3) // 4).view(np.uint16)[: high16.size]
    return np.concatenate(positions), _resolve(tables, high16, low16)


def discrete_normal(rng: np.random.Generator, shape: tuple[int, ...], sigma: float, limit: int = 255) -> np.ndarray:
    """int16 samples of round(sigma * z), z standard normal, clipped to [-limit, limit].

    Exact to 32-bit probability resolution (the resolution of a float32 uniform), yet it draws only 16
    random bits for ~99.8% of samples and needs no floating-point normal: the high 16 bits index a bucket
    table; the few samples whose bucket straddles a CDF step draw 16 more bits and are resolved on the
    32-bit thresholds. For adding noise to 8-bit pixels, the clip at +-255 changes nothing.
    """
    tables = _discrete_normal_tables(float(sigma), int(limit))
    out = np.empty(int(np.prod(shape)), np.int16)

    def keep(start: int, stop: int, noise: np.ndarray) -> None:
        out[start:stop] = noise

    positions, resolved = _sample_chunks(rng, out.size, tables, keep)
    out[positions] = resolved
    return out.reshape(shape)


def add_discrete_normal(base: np.ndarray, rng: np.random.Generator, sigma: float, limit: int = 255, *,
                        shifted: bool = False) -> np.ndarray:
    """clip(base + discrete_normal(rng, base.shape, sigma, limit), 0, 255) as a new uint8 array.

    Bit-identical to adding `discrete_normal`'s samples (the same random stream), but fused chunk by
    chunk, so no image-sized int16 noise is ever materialised: about 1.8x faster.

    `shifted=True` adds the noise plus `limit` (0..2 limit) instead, for callers whose base leaves that much
    headroom (base <= 255 - 2 limit), so that nothing clips: the sum is then formed in 8-bit arithmetic,
    4x cheaper than OpenCV's mixed-type add.
    """
    tables = _discrete_normal_tables(float(sigma), int(limit))
    flat = np.ascontiguousarray(base).reshape(-1)
    out = np.empty_like(flat)
    narrow = np.empty((1, min(_CHUNK, flat.size)), np.uint8)

    def add(start: int, stop: int, noise: np.ndarray) -> None:
        # 1 x m rows: OpenCV would read a short 1-D array as a scalar
        dst = out[start:stop].reshape(1, -1)
        if shifted:  # 0..2 limit fits a byte (the sentinels' garbage is overwritten below)
            small = narrow[:, : stop - start]
            np.copyto(small, noise.reshape(1, -1), casting="unsafe")
            cv2.add(flat[start:stop].reshape(1, -1), small, dst=dst)
        else:
            cv2.add(flat[start:stop].reshape(1, -1), noise.reshape(1, -1), dst=dst, dtype=cv2.CV_8U)

    positions, resolved = _sample_chunks(rng, flat.size, tables, add, tables.shifted if shifted else None)
    out[positions] = np.clip(flat[positions] + resolved + (limit if shifted else 0), 0, 255)
    return out.reshape(base.shape)


def blend(base: np.ndarray, over: np.ndarray | int, alpha: np.ndarray) -> np.ndarray:
    """Per-pixel mix of two uint8 images: base * (1 - a) + over * a, with `alpha` a uint8 H x W map where 255
    means all `over`; `over` may be one grey level. Two saturating 8-bit multiplies (within one level of the
    exact mix), about twice as fast as a float blend; the products reuse the two alpha buffers (each fresh
    image-sized array costs as much as a pass over it in page faults)."""
    a3 = cv2.merge([alpha, alpha, alpha]) if base.ndim == 3 else alpha.copy()
    keep = cv2.bitwise_not(a3)
    cv2.multiply(base, keep, dst=keep, scale=1 / 255)
    if isinstance(over, np.ndarray):
        cv2.multiply(over, a3, dst=a3, scale=1 / 255)
    else:  # the same rounding as multiplying by a constant image, without one
        cv2.convertScaleAbs(a3, dst=a3, alpha=int(over) / 255)
    return cv2.add(keep, a3, dst=a3)


def veiled(image: np.ndarray, opacity: float, grey: float) -> np.ndarray:
    """A uniform veil of `grey` at `opacity` over the image (scattered light, snow-filled air), as a new
    array in one pass: v * (1 - opacity) + grey * opacity, rounded."""
    return cv2.convertScaleAbs(image, alpha=1.0 - opacity, beta=grey * opacity)


def to_alpha8(alpha: np.ndarray) -> np.ndarray:
    """A float coverage in [0, 1] as the uint8 alpha map `blend` takes."""
    return cv2.convertScaleAbs(alpha, alpha=255.0)


@lru_cache(maxsize=1)
def srgb_to_linear_table() -> np.ndarray:
    """float32[256]: the sRGB electro-optical transfer, 8-bit code -> linear light in [0, 1]."""
    c = np.arange(256) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Linear light in [0, 1] (any shape) -> sRGB 8-bit codes, rounded."""
    x = np.clip(linear, 0.0, 1.0)
    c = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.clip(np.round(c * 255.0), 0, 255).astype(np.uint8)


def smooth_field(rng: np.random.Generator, height: int, width: int, cells: int, octaves: int = 3) -> np.ndarray:
    """A float32 random field in ~[0, 1] with features about width/cells wide: a few octaves of bilinearly
    upsampled uniform noise (value noise). Cheap: the work is at coarse resolution plus one resize.
    """
    field = np.zeros((height, width), np.float32)
    weight = 1.0
    total = 0.0
    for octave in range(octaves):
        n = cells * (2**octave)
        coarse = rng.random((max(2, round(n * height / width)) + 1, n + 1), dtype=np.float32)
        field += weight * cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
        total += weight
        weight *= 0.5
    return field / total


def coverage_mask(field: np.ndarray, fraction: float) -> np.ndarray:
    """Boolean mask of the `fraction` of pixels where `field` is highest (exact up to ties)."""
    flat = field.reshape(-1)
    k = int(round(fraction * flat.size))
    if k <= 0:
        return np.zeros(field.shape, bool)
    threshold = np.partition(flat, flat.size - k)[flat.size - k]
    return field >= threshold


def scaled(value: float, scale: float) -> float:
    """A spatial parameter defined at 1600 px, scaled to this image's width."""
    return float(value) * scale


@lru_cache(maxsize=32)
def discrete_gaussian_kernel(sigma: float) -> np.ndarray:
    """Lindeberg's discrete Gaussian, T(n) = exp(-t) I_n(t) with t = sigma^2, as a float64 1-D kernel.

    It is the discrete analogue of the Gaussian (the kernel of diffusion on the integer grid): its variance
    is exactly sigma^2 at any sigma, where the Gaussian sampled at whole pixels loses most of it below
    about 0.5 px (sigma 0.25 sampled gives a kernel of sigma 0.026). Truncated at 4 sigma + 2 taps and
    renormalised (sigma kept within 0.1 %). I_n by its power series, summed in log space.
    """
    t = float(sigma) ** 2
    radius = ceil(4.0 * sigma) + 2
    terms = int(t / 2 + 10 * sqrt(t) + 30)  # past the series' peak at m ~ t/2 by 10 standard deviations
    log_factorial = np.concatenate([[0.0], np.cumsum(np.log(np.arange(1, terms + radius + 1)))])
    m = np.arange(terms)[:, None]
    n = np.arange(radius + 1)[None, :]
    half = np.exp(-t + (2 * m + n) * log(t / 2) - log_factorial[m] - log_factorial[m + n]).sum(axis=0)
    kernel = np.concatenate([half[:0:-1], half])
    return kernel / kernel.sum()
