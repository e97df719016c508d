"""Sensor-group families: defocus and motion blur, read noise, low light with photon noise, colour depth."""

from __future__ import annotations

from functools import lru_cache
from math import ceil

import cv2
import numpy as np

from .kernels import add_noise, discrete_normal, linear_to_srgb, scaled, srgb_to_linear_table
from .registry import register


#: From this defocus sigma up, the blur runs at half resolution (see `gaussian_blur`).
_PYRAMID_SIGMA = 3.0
#: Per-axis variance (full-resolution px^2) that a 2x area downsampling and a 2x bilinear upsampling add.
_PYRAMID_VARIANCE = (2**2 - 1) / 12 + 2**2 / 6


def _gaussian(image: np.ndarray, sigma: float) -> np.ndarray:
    k = 2 * ceil(3 * sigma) + 1
    return cv2.GaussianBlur(image, (k, k), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT_101)


@register("gaussian_blur", group="sensor", axis="quality", parameter="defocus sigma", unit="px",
          values=(0.5, 1.0, 2.0, 3.5, 6.0), random=False, spatial=True)
def gaussian_blur(image: np.ndarray, sigma: float, rng: None, scale: float) -> np.ndarray:
    """Defocus as a Gaussian point spread function (separable, truncated at 3 sigma).

    From sigma 3 px up the image is already smooth at half resolution, so the blur runs there: 2x area
    downsampling, a Gaussian whose variance is sigma^2 less what the resampling adds, bilinear upsampling.
    The point spread function keeps its variance and is Gaussian to within the resampling kernels' tails.
    """
    s = scaled(sigma, scale)
    h, w = image.shape[:2]
    if s < _PYRAMID_SIGMA or min(h, w) < 16:
        return _gaussian(image, s)
    half = cv2.resize(image, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    blurred = _gaussian(half, float(np.sqrt(s * s - _PYRAMID_VARIANCE)) / 2)
    return cv2.resize(blurred, (w, h), interpolation=cv2.INTER_LINEAR)


def _line_blur_x_major(image: np.ndarray, n: int, slope: float) -> np.ndarray:
    """Average n pixels along the digital lines y = c + round(slope * x), |slope| <= 1.

    Every pixel lies on exactly one such line. Shearing column x by round(slope * x) rows lays each line
    out as a row of a taller canvas; a box filter averages along the rows in O(1) per pixel, and the
    inverse shear (the same integer offsets) puts every pixel back. Exact, no 2-D kernel.
    """
    h, w = image.shape[:2]
    offset = np.round(slope * np.arange(w)).astype(np.int16)
    top, bottom = int(offset.max()), int(offset.min())
    canvas = cv2.remap(image, _shear_map(h + top - bottom, w, offset - top), None, cv2.INTER_NEAREST,
                       borderMode=cv2.BORDER_REPLICATE)
    blurred = cv2.blur(canvas, (n, 1), borderType=cv2.BORDER_REPLICATE)
    return cv2.remap(blurred, _shear_map(h, w, top - offset), None, cv2.INTER_NEAREST)


def _shear_map(rows: int, w: int, shift: np.ndarray) -> np.ndarray:
    """A CV_16SC2 remap table reading row r of column x from row r + shift[x] (integer, exact)."""
    table = np.empty((rows, w, 2), np.int16)
    table[..., 0] = np.arange(w, dtype=np.int16)[None, :]
    table[..., 1] = np.arange(rows, dtype=np.int16)[:, None] + shift[None, :]
    return table


@register("motion_blur", group="sensor", axis="quality", parameter="blur length", unit="px",
          values=(4, 8, 14, 22, 34), random=True, spatial=True)
def motion_blur(image: np.ndarray, length: float, rng: np.random.Generator, scale: float) -> np.ndarray:
    """Linear motion blur of the given length in a random direction.

    Each output pixel averages the pixels on a rasterised line through it (see `_line_blur_x_major`);
    mostly vertical motion is handled on the transposed image. No large 2-D kernel is convolved.
    """
    n = max(1, int(round(scaled(length, scale))))
    angle = rng.uniform(0.0, np.pi)
    if n == 1:
        return image.copy()
    c, s = np.cos(angle), np.sin(angle)
    if abs(c) >= abs(s):
        return _line_blur_x_major(image, n, s / c)
    return cv2.transpose(_line_blur_x_major(cv2.transpose(image), n, c / s))


@register("gaussian_noise", group="sensor", axis="quality", parameter="noise sigma", unit="8-bit levels",
          values=(4, 8, 16, 28, 45), random=True)
def gaussian_noise(image: np.ndarray, sigma: float, rng: np.random.Generator, scale: float) -> np.ndarray:
    """Additive white Gaussian read noise, per pixel and channel: clip(round(v + sigma * z))."""
    return add_noise(image, discrete_normal(rng, image.shape, sigma))


#: Photo-electrons collected by a pixel at nominal exposure for a white (linear 1.0) scene point.
PHOTONS_AT_WHITE = 1200.0
#: Resolution of the variance-stabilised domain: grid steps per noise standard deviation. Three steps keep
#: every grid coordinate within one byte (so both look-ups are 8-bit LUTs) at an added quantisation
#: variance of 1/108 of the shot noise.
_ANSCOMBE_STEPS = 3
_NOISE_LIMIT = 6 * _ANSCOMBE_STEPS  # the unit-variance noise is clipped at 6 sigma


@lru_cache(maxsize=8)
def _low_light_tables(exposure: float) -> tuple[np.ndarray, np.ndarray]:
    """(encode, decode): encode[v] is the Anscombe grid coordinate (+ the noise margin) of input code v
    at this exposure; decode maps a noisy grid coordinate back to an sRGB code. Both are 8-bit LUTs."""
    photons = srgb_to_linear_table().astype(np.float64) * exposure * PHOTONS_AT_WHITE
    encode = np.round(_ANSCOMBE_STEPS * 2.0 * np.sqrt(photons + 3.0 / 8.0)) + _NOISE_LIMIT
    if encode.max() + _NOISE_LIMIT > 255:  # pragma: no cover - guarded by the ladder's exposures
        raise AssertionError(f"exposure {exposure} exceeds the 8-bit Anscombe grid")
    y = (np.arange(256) - _NOISE_LIMIT) / _ANSCOMBE_STEPS
    counts = np.maximum((y / 2.0) ** 2 - 3.0 / 8.0, 0.0)
    return encode.astype(np.uint8), linear_to_srgb(counts / PHOTONS_AT_WHITE)


@register("low_light", group="sensor", axis="quality", parameter="exposure",
          unit="fraction of nominal, linear light", values=(0.6, 0.4, 0.25, 0.15, 0.08), random=True)
def low_light(image: np.ndarray, exposure: float, rng: np.random.Generator, scale: float) -> np.ndarray:
    """Under-exposure in linear light with the photon (shot) noise a sensor adds at that exposure.

    Each pixel's photon count is Poisson with mean exposure * linear(v) * PHOTONS_AT_WHITE; the count is
    sampled in the Anscombe domain (2 sqrt(n + 3/8), where Poisson noise has unit variance) on a grid of
    sigma/3, then decoded to sRGB. No auto-gain: the image darkens as a fixed-exposure camera's would.
    """
    encode, decode = _low_light_tables(float(exposure))
    noise = discrete_normal(rng, image.shape, _ANSCOMBE_STEPS, limit=_NOISE_LIMIT)
    noisy = cv2.add(cv2.LUT(image, encode), noise, dtype=cv2.CV_8U)
    return cv2.LUT(noisy, decode)


@register("color_quant", group="sensor", axis="quality", parameter="bits per channel", unit="bits",
          values=(6, 5, 4, 3, 2), random=False)
def color_quant(image: np.ndarray, bits: int, rng: None, scale: float) -> np.ndarray:
    """Reduced colour depth: keep the top `bits` bits, reconstructed over the full 0..255 range."""
    levels = (1 << bits) - 1
    q = np.arange(256) >> (8 - bits)
    table = np.round(q * (255.0 / levels)).astype(np.uint8)
    return cv2.LUT(image, table)
