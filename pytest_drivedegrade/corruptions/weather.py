"""Weather-group families: fog by Koschmieder's law on a ground-plane depth prior, and falling snow."""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from .kernels import blend, linear_to_srgb, scaled, srgb_to_linear_table, to_alpha8, veiled
from .registry import register

#: Depth prior: camera height over the ground plane (nuScenes cameras sit about 1.5 m up), the height of
#: the "ceiling" plane that stands in for buildings and trees above the horizon, and the far cap.
CAMERA_HEIGHT_M = 1.5
CEILING_HEIGHT_M = 8.0
MAX_DEPTH_M = 1000.0
#: Focal length of the nuScenes cameras at the 1600 px reference width.
FOCAL_PX_AT_REFERENCE = 1266.0
#: Airlight (the fog's own luminance), linear light.
AIRLIGHT = 0.78
_T_STEPS = 512  # transmission is quantised to 1/512 so rows share lookup tables


def depth_prior(height: int, width: int) -> np.ndarray:
    """Per-row depth (m) for a level camera with the horizon at mid-height: the ground plane below,
    a ceiling plane above, infinite at the horizon, capped at MAX_DEPTH_M."""
    focal = FOCAL_PX_AT_REFERENCE * width / 1600.0
    rows = np.arange(height) + 0.5 - height / 2.0
    with np.errstate(divide="ignore"):
        depth = np.where(rows > 0, CAMERA_HEIGHT_M * focal / rows, CEILING_HEIGHT_M * focal / -rows)
    return np.minimum(np.abs(depth), MAX_DEPTH_M)


@lru_cache(maxsize=64)
def _fog_luts(visibility: float, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(row index of each run start, one 256-entry LUT per run) for this visibility and image size."""
    beta = 3.912 / visibility  # Koschmieder: 2% contrast threshold at the visibility distance
    t = np.exp(-beta * depth_prior(height, width))
    tq = np.round(t * _T_STEPS) / _T_STEPS
    starts = np.flatnonzero(np.r_[True, tq[1:] != tq[:-1]])
    lin = srgb_to_linear_table().astype(np.float64)
    runs_t = tq[starts][:, None]
    luts = linear_to_srgb(lin[None, :] * runs_t + AIRLIGHT * (1.0 - runs_t))
    return starts, luts


@register("fog", group="weather", axis="quality", parameter="meteorological visibility", unit="m",
          values=(500, 250, 120, 70, 35), random=False)
def fog(image: np.ndarray, visibility: float, rng: None, scale: float) -> np.ndarray:
    """I = J t + A (1 - t), t = exp(-3.912 d / V), in linear light, d from the depth prior."""
    h, w = image.shape[:2]
    starts, luts = _fog_luts(float(visibility), h, w)
    out = np.empty_like(image)
    ends = np.r_[starts[1:], h]
    for start, end, lut in zip(starts, ends, luts):
        cv2.LUT(image[start:end], lut, dst=out[start:end])  # written in place: no temporary per run of rows
    return out


#: Snow level -> (far flakes per reference megapixel, far-flake sigma px at 1600 px, veil opacity).
_SNOW = {1: (500, 0.9, 0.04), 2: (1000, 1.1, 0.08), 3: (1800, 1.4, 0.12), 4: (2800, 1.7, 0.17),
         5: (4200, 2.0, 0.23)}
_SNOW_WHITE = 245.0
_NEAR_SHARE, _NEAR_SIZE = 0.12, 3.0  # near flakes: fewer, larger, out of focus and fainter


def _flake_layer(rng: np.random.Generator, shape: tuple[int, int], count: int, sigma: float,
                 brightness: tuple[float, float]) -> np.ndarray:
    """Sparse impulses of random brightness, blurred into soft flakes elongated by their fall; the blur
    is normalised so a flake's peak opacity equals its drawn brightness."""
    h, w = shape
    layer = np.zeros(shape, np.float32)
    layer[rng.integers(0, h, count), rng.integers(0, w, count)] = rng.uniform(*brightness, count)
    sx, sy = max(sigma, 0.35), max(1.8 * sigma, 0.5)
    k = (2 * int(np.ceil(3 * sx)) + 1, 2 * int(np.ceil(3 * sy)) + 1)
    return cv2.GaussianBlur(layer, k, sigmaX=sx, sigmaY=sy) * float(2 * np.pi * sx * sy)


@register("snow", group="weather", axis="quality", parameter="snow level", unit="level",
          values=(1, 2, 3, 4, 5), random=True, spatial=True)
def snow(image: np.ndarray, level: int, rng: np.random.Generator, scale: float) -> np.ndarray:
    """Falling snow: far (small, many) and near (large, few, defocused) flakes whose density and size grow
    with the level, over a whitening veil of snow-filled air. Flakes are rendered at half resolution."""
    per_mp, sigma, veil = _SNOW[int(level)]
    h, w = image.shape[:2]
    hh, hw = max(1, h // 2), max(1, w // 2)
    # per reference megapixel: the same number of flakes in the same field of view at any resolution (each
    # flake's size scales with the width), so the snow covers the same share of the frame at 800 and 1600 px
    count = per_mp * (w / scale) * (h / scale) / 1e6
    far = _flake_layer(rng, (hh, hw), int(count), scaled(sigma, scale) / 2, (0.55, 1.0))
    near = _flake_layer(rng, (hh, hw), int(count * _NEAR_SHARE), scaled(_NEAR_SIZE * sigma, scale) / 2,
                        (0.35, 0.7))
    alpha = cv2.resize(to_alpha8(np.minimum(far + near, 1.0)), (w, h), interpolation=cv2.INTER_LINEAR)
    return blend(veiled(image, veil, _SNOW_WHITE), int(_SNOW_WHITE), alpha)
