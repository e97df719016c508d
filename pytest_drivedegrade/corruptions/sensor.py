"""Sensor-group families: defocus and motion blur, read noise, low light with photon noise, colour depth."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from functools import lru_cache
from math import ceil

import cv2
import numpy as np
from numpy.lib.stride_tricks import as_strided

from .kernels import add_discrete_normal, discrete_gaussian_kernel, linear_to_srgb, scaled, srgb_to_linear_table
from .registry import register

#: From this defocus sigma up, the blur runs at half resolution (see `gaussian_blur`).
_PYRAMID_SIGMA = 3.0
#: Per-axis variance (full-resolution px^2) that a 2x area downsampling and a 2x bilinear upsampling add.
_PYRAMID_VARIANCE = (2**2 - 1) / 12 + 2**2 / 6


def _gaussian(image: np.ndarray, sigma: float) -> np.ndarray:
    """The discrete Gaussian of variance sigma^2 along x then y (one separable pass, rounded once)."""
    kernel = discrete_gaussian_kernel(sigma)
    return cv2.sepFilter2D(image, -1, kernel, kernel, borderType=cv2.BORDER_REFLECT_101)


@register("gaussian_blur", group="sensor", axis="quality", parameter="defocus sigma", unit="px",
          values=(0.5, 1.0, 2.0, 3.5, 6.0), random=False, spatial=True)
def gaussian_blur(image: np.ndarray, sigma: float, rng: None, scale: float) -> np.ndarray:
    """Defocus as a Gaussian point spread function of variance sigma^2 at any sigma (the discrete Gaussian, separable).

    The kernel is the discrete Gaussian (`discrete_gaussian_kernel`), whose variance is sigma^2 also below
    one pixel, where a Gaussian sampled at whole pixels hardly blurs. From sigma 3 px up the image is
    already smooth at half resolution, so the blur runs there: 2x area downsampling, a discrete Gaussian
    whose variance is sigma^2 less what the resampling adds, bilinear upsampling. The point spread
    function keeps its variance and is Gaussian to within the resampling kernels' tails.
    """
    s = scaled(sigma, scale)
    h, w = image.shape[:2]
    if s <= 0.0:
        return image.copy()
    if s < _PYRAMID_SIGMA or min(h, w) < 16:
        return _gaussian(image, s)
    half = cv2.resize(image, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    blurred = _gaussian(half, float(np.sqrt(s * s - _PYRAMID_VARIANCE)) / 2)
    return cv2.resize(blurred, (w, h), interpolation=cv2.INTER_LINEAR)


#: Rows per block of the box filter in `_line_blur`: each block filters only the band of the canvas its
#: lines occupy, so the work stays near the image size at any angle instead of growing with the shear.
_LINE_BLOCK = 192
#: A fractional tap lighter than this (a length within 1e-6 px of an integer) is left out.
_MIN_FRACTION = 1e-6
#: Up to this many taps a window is one weighted 1-D filter down the columns (one pass, one rounding);
#: longer ones are a box filter plus a weighted add of the fractional row, O(1) per pixel at any length.
_SHORT_WINDOW = 7


_SCRATCH = threading.local()


def _scratch(name: str, size: int) -> np.ndarray:
    """A flat uint8 work buffer of `size` bytes, kept per thread and reused by the next call: the fresh
    pages of new buffers would be faulted in on every call, which at 1600 x 900 costs more than the blur
    itself. Holds the largest size a thread has needed (about 17 MB for 1600 x 900)."""
    pool = getattr(_SCRATCH, "pool", None)
    if pool is None:
        pool = _SCRATCH.pool = {}
    buf = pool.get(name)
    if buf is None or buf.size < size:
        buf = pool[name] = np.empty(size, np.uint8)
    return buf[:size]


def _runs(offsets: np.ndarray) -> list[tuple[int, int, int]]:
    """(start, stop, offset) for each run of equal values in the 1-D array `offsets`."""
    change = np.flatnonzero(np.diff(offsets)) + 1
    starts = [0, *change.tolist()]
    stops = [*change.tolist(), len(offsets)]
    return [(a, b, int(offsets[a])) for a, b in zip(starts, stops)]


def _box_rows(view: np.ndarray, n: int, dst: np.ndarray | None = None) -> np.ndarray:
    """Mean of n consecutive rows (window [i - n//2, i + n - 1 - n//2], edge rows replicated), for the
    windows longer than `_SHORT_WINDOW` (n >= `_SHORT_WINDOW` with a fractional row).

    OpenCV 5.0's `blur` misreads the replicated border of a view shorter than the window, so such a view
    is padded first. (Its 2-tap window is off by one level, a zero image coming back as 1: short windows
    never come here.)"""
    if view.shape[0] < n:
        before = n // 2
        padded = cv2.copyMakeBorder(view, before, n - 1 - before, 0, 0, cv2.BORDER_REPLICATE)
        return _box_rows(padded, n)[before:before + view.shape[0]]
    return cv2.blur(view, (1, n), dst=dst, borderType=cv2.BORDER_REPLICATE | cv2.BORDER_ISOLATED)


def _weighted_rows(view: np.ndarray, weights: np.ndarray, before: int, dst: np.ndarray | None = None) -> np.ndarray:
    """sum_k weights[k] * row (i - before + k), edge rows replicated: a short 1-D filter down the columns
    (at most `_SHORT_WINDOW` taps, one column wide), accumulated in float and rounded once."""
    taps = len(weights)
    if view.shape[0] < taps:  # pad a view shorter than the window, as `_box_rows` does
        padded = cv2.copyMakeBorder(view, before, taps - 1 - before, 0, 0, cv2.BORDER_REPLICATE)
        return _weighted_rows(padded, weights, before)[before:before + view.shape[0]]
    kernel = np.asarray(weights, np.float32).reshape(taps, 1)
    border = cv2.BORDER_REPLICATE | cv2.BORDER_ISOLATED
    return cv2.filter2D(view, -1, kernel, dst=dst, anchor=(0, before), borderType=border)


@dataclass(frozen=True)
class _Window:
    """The area-sampled segment down a line: the `n` rows from `before` rows back whole, the next one by
    `fraction` when `extra`; `reach` rows in all, `weights` per row (summing to 1)."""

    length: float
    n: int
    fraction: float
    extra: bool
    reach: int
    before: int
    weights: np.ndarray


def _window(length: float) -> _Window:
    """The window of a segment `length` rows long (>= 1, any real)."""
    n = int(length + 1e-9)
    fraction = float(length) - n
    extra = fraction > _MIN_FRACTION  # the partial row at i - n//2 + n
    weights = np.array([1.0] * n + ([fraction] if extra else [])) / length
    return _Window(length, n, fraction, extra, n + 1 if extra else n, n // 2, weights)


@dataclass(frozen=True)
class _Shear:
    """Row i of the image moves `shift[i]` (>= 0) columns right on the canvas: a whole shear of `-k` columns
    per row (a stride) plus the residual `resid[i]` (>= 0, copied run by run), shift = resid - k i + c;
    `margin` columns of edge padding on each side cover a window's sideways reach."""

    k: int
    shift: np.ndarray
    resid: np.ndarray
    c: int
    margin: int


def _shear(slope: float, rows: int, reach: int) -> _Shear:
    """shift_i = -round(slope i) (made >= 0) split into a whole shear k i, k = round(slope), and a residual
    -round((slope - k) i) with |slope - k| <= 1/2, whose runs of equal values are at least two rows long:
    the residual is copied run by run, the whole shear is a stride (a view), so no angle copies row by row."""
    k = int(np.sign(slope)) if abs(slope) > 0.5 else 0
    i = np.arange(rows)
    total = -np.round(slope * i).astype(np.int64)
    shift = total - total.min()
    resid = total + k * i
    resid -= resid.min()
    c = int(shift[0] - resid[0])  # shift_i = resid_i - k i + c
    return _Shear(k, shift, resid, c, ceil(abs(slope) * reach) + 1)


@dataclass(frozen=True)
class _Canvas:
    """The sheared canvas C[i, x] = D[i, x + k i - c] over the residual canvas D held flat in `buf` from
    `slack` on, `sd` bytes a row, `px` bytes a pixel."""

    buf: np.ndarray
    slack: int
    sd: int
    k: int
    c: int
    px: int

    def view(self, lo: int, hi: int, c0: int, c1: int) -> np.ndarray:
        """Rows lo..hi - 1, columns c0..c1 - 1 of C, as a view."""
        offset = self.slack + lo * self.sd + (c0 + self.k * lo - self.c) * self.px
        return as_strided(self.buf[offset:], shape=(hi - lo, c1 - c0, self.px),
                          strides=(self.sd + self.k * self.px, self.px, 1), writeable=False)


def _sheared_canvas(image: np.ndarray, slope: float, sh: _Shear, reach: int, transposed: bool) -> _Canvas:
    """The image (transposed first when `transposed`), padded with its edge pixels by `sh.margin` on each
    side, laid out on the residual canvas D[i, resid_i + p] = padded[i, p], in a flat buffer with room on
    both sides for the sheared views (row stride one pixel longer or shorter). Its rows are at least as
    wide as a block's band, which OpenCV needs of a row stride."""
    rows, cols = image.shape[1::-1] if transposed else image.shape[:2]
    px, margin, resid = image.shape[2], sh.margin, sh.resid
    wp = cols + 2 * margin
    padded = _scratch("padded", rows * wp * px).reshape(rows, wp, px)
    if transposed:
        cv2.transpose(image, dst=padded[:, margin:margin + cols])
    else:
        padded[:, margin:margin + cols] = image
    padded[:, :margin] = padded[:, margin:margin + 1]
    padded[:, margin + cols:] = padded[:, margin + cols - 1:margin + cols]
    wd = max(wp + int(resid.max()), cols + ceil(abs(slope) * _LINE_BLOCK) + 4)
    sd = wd * px
    slack = (rows + wd + 2 * _LINE_BLOCK + 4 * (reach + margin) + 16) * px  # views reach at most a block out
    buf = _scratch("canvas", 2 * slack + rows * sd)
    canvas_d = buf[slack:slack + rows * sd].reshape(rows, wd, px)
    for a, b, r in _runs(resid):
        canvas_d[a:b, r:r + wp] = padded[a:b]
    return _Canvas(buf, slack, sd, sh.k, sh.c, px)


def _filter_block(canvas: _Canvas, sh: _Shear, win: _Window, first: int, last: int, rows: int, cols: int,
                  held_buf: tuple[np.ndarray, int]) -> tuple[int, int, int]:
    """Filter down the canvas columns of output rows first..last - 1 (and the rows their windows reach,
    lo..hi - 1) over the band their lines occupy, straight into the work buffer `held_buf` (buffer, slack),
    with room around it for the sheared view that reads it back. Returns (lo, band's left column, band
    width)."""
    bbuf, bslack = held_buf
    px = canvas.px
    hi = min(rows, last + win.reach - 1 - win.before)  # the block and its window's reach (at least n rows)
    lo = max(0, min(first - win.before, hi - win.reach))
    band = sh.shift[first:last]
    left = sh.margin + int(band.min())
    view = canvas.view(lo, hi, left, sh.margin + int(band.max()) + cols)
    wb = view.shape[1]
    held = bbuf[bslack:bslack + (hi - lo) * wb * px].reshape(hi - lo, wb, px)
    if win.reach <= _SHORT_WINDOW:
        filtered = _weighted_rows(view, win.weights, win.before, dst=held)
    else:
        filtered = _box_rows(view, win.n, dst=held)
    if filtered is not held:  # a view shorter than its window was padded first
        held[...] = filtered
    if win.extra and win.reach > _SHORT_WINDOW:
        # the partial row of output row i is canvas row i - before + n; past the last row, the last row
        blurred = held[first - lo:last - lo]
        start = first - win.before + win.n  # > first: only the image's last row can cut it short
        inside = max(0, min(last - first, rows - start))
        tail = view[start - lo:start - lo + inside]
        if inside < last - first:
            tail = np.concatenate([tail, np.repeat(view[-1:], last - first - inside, axis=0)])
        cv2.addWeighted(blurred, win.n / win.length, tail, win.fraction / win.length, 0.0, dst=blurred)
    return lo, left, wb


def _unshear_block(out: np.ndarray, held_buf: tuple[np.ndarray, int], sh: _Shear, first: int, last: int,
                   lo: int, left: int, wb: int) -> None:
    """out[i, j] = blurred[i - first, j + margin + shift_i - left] for the block's rows, the whole shear
    again a stride and the residual copied run by run."""
    bbuf, bslack = held_buf
    px = out.shape[2]
    cols = out.shape[1]
    resid = sh.resid[first:last]
    low = int(resid.min())  # the view starts at the block's least residual: inside bbuf
    offset = bslack + ((first - lo) * wb + low + sh.margin + sh.c - left - sh.k * first) * px
    unsheared = as_strided(bbuf[offset:], shape=(last - first, cols + int(resid.max()) - low, px),
                           strides=((wb - sh.k) * px, px, 1), writeable=False)
    for a, b, r in _runs(resid):
        out[first + a:first + b] = unsheared[a:b, r - low:r - low + cols]


def _line_blur(image: np.ndarray, length: float, slope: float, *, transposed: bool = False) -> np.ndarray:
    """Average along the digital lines {(i, c + round(slope * i))}, |slope| <= 1, over a segment `length`
    rows long (`length` >= 1, any real): lines advance one row per step and drift sideways by the rounded
    slope. With `transposed`, rows and columns trade places (the lines advance along x), as if the image
    were transposed before and after.

    The segment covers rows [i - n//2 - 1/2, i - n//2 - 1/2 + length] around row i, n = floor(length):
    the n rows i - n//2 .. i - n//2 + n - 1 whole and the next row by the fraction f = length - n, each
    weighted by how much of the segment its cell holds (the area-sampled box). Every pixel lies on exactly
    one such line. Shifting row i by -round(slope * i) columns lays each line out as a column of a wider
    canvas (a row shift is one contiguous copy per run of equal shifts); down the columns, a window of at
    most `_SHORT_WINDOW` rows is one weighted 1-D filter (rounded once: within half a level), a longer
    one a box filter, O(1) per pixel, plus one weighted add of the canvas shifted by n rows for the
    fractional row (within 1.25 levels: the box filter's rounding, scaled by n / length, and the add's);
    the same integer shifts put every pixel back. No 2-D kernel. Lines leaving the image continue on its
    edge pixels (the rows are padded with their end pixels as deep as a window can reach).
    """
    rows, cols = image.shape[1::-1] if transposed else image.shape[:2]
    px = image.shape[2]  # H x W x C uint8
    win = _window(length)
    sh = _shear(slope, rows, win.reach)
    canvas = _sheared_canvas(image, slope, sh, win.reach, transposed)
    # contiguous (OpenCV transposes that twice as fast); a work buffer when the result is its transpose
    out = _scratch("out", rows * cols * px).reshape(rows, cols, px) if transposed else np.empty_like(image)
    band_width = cols + min(rows, _LINE_BLOCK) + 2 * sh.margin + 2
    bslack = (2 * _LINE_BLOCK + 4 * (win.reach + sh.margin) + 16) * px
    held_buf = (_scratch("band", 2 * bslack + (_LINE_BLOCK + win.reach) * band_width * px), bslack)
    for first in range(0, rows, _LINE_BLOCK):
        last = min(rows, first + _LINE_BLOCK)
        lo, left, wb = _filter_block(canvas, sh, win, first, last, rows, cols, held_buf)
        _unshear_block(out, held_buf, sh, first, last, lo, left, wb)
    return cv2.transpose(out) if transposed else out


@register("motion_blur", group="sensor", axis="quality", parameter="blur length", unit="px",
          values=(4, 8, 14, 22, 34), random=True, spatial=True)
def motion_blur(image: np.ndarray, length: float, rng: np.random.Generator, scale: float) -> np.ndarray:
    """Linear motion blur: the mean over a segment of the given Euclidean length in a random direction.

    Along the major axis of the direction (angle a) the segment spans length * max(|cos a|, |sin a|)
    pixels, area-sampled (whole pixels plus one fractional one, see `_line_blur`), so its Euclidean extent
    is the declared length at every angle. Mostly horizontal motion is handled on the transposed image.
    No large 2-D kernel is convolved.
    """
    angle = rng.uniform(0.0, np.pi)
    c, s = np.cos(angle), np.sin(angle)
    span = scaled(length, scale) * max(abs(c), abs(s))  # rows (or columns) the segment crosses
    if span <= 1.0:  # within one pixel: the pixel itself
        return image.copy()
    if abs(c) >= abs(s):  # lines advance along x: make x the row axis
        return _line_blur(image, span, s / c, transposed=True)
    return _line_blur(image, span, c / s)


@register("gaussian_noise", group="sensor", axis="quality", parameter="noise sigma", unit="8-bit levels",
          values=(4, 8, 16, 28, 45), random=True)
def gaussian_noise(image: np.ndarray, sigma: float, rng: np.random.Generator, scale: float) -> np.ndarray:
    """Additive white Gaussian read noise, per pixel and channel: clip(round(v + sigma * z))."""
    return add_discrete_normal(image, rng, sigma)


#: Photo-electrons collected by a pixel at nominal exposure for a white (linear 1.0) scene point.
PHOTONS_AT_WHITE = 1200.0
#: Resolution of the variance-stabilised domain: grid steps per noise standard deviation. Three steps keep
#: every grid coordinate within one byte (so both look-ups are 8-bit LUTs) at an added quantisation
#: variance of 1/108 of the shot noise.
_ANSCOMBE_STEPS = 3
_NOISE_LIMIT = 6 * _ANSCOMBE_STEPS  # the unit-variance noise is clipped at 6 sigma


@lru_cache(maxsize=8)
def _low_light_tables(exposure: float) -> tuple[np.ndarray, np.ndarray]:
    """(encode, decode): encode[v] is the Anscombe grid coordinate of input code v at this exposure;
    decode maps a noisy grid coordinate plus the noise margin (the shifted noise of `add_discrete_normal`)
    back to an sRGB code. Both are 8-bit LUTs."""
    photons = srgb_to_linear_table().astype(np.float64) * exposure * PHOTONS_AT_WHITE
    encode = np.round(_ANSCOMBE_STEPS * 2.0 * np.sqrt(photons + 3.0 / 8.0))
    if encode.max() + 2 * _NOISE_LIMIT > 255:  # pragma: no cover - guarded by the ladder's exposures
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
    noisy = add_discrete_normal(cv2.LUT(image, encode), rng, _ANSCOMBE_STEPS, limit=_NOISE_LIMIT, shifted=True)
    return cv2.LUT(noisy, decode, dst=noisy)


@register("color_quant", group="sensor", axis="quality", parameter="bits per channel", unit="bits",
          values=(6, 5, 4, 3, 2), random=False)
def color_quant(image: np.ndarray, bits: int, rng: None, scale: float) -> np.ndarray:
    """Reduced colour depth: keep the top `bits` bits, reconstructed over the full 0..255 range."""
    levels = (1 << bits) - 1
    q = np.arange(256) >> (8 - bits)
    table = np.round(q * (255.0 / levels)).astype(np.uint8)
    return cv2.LUT(image, table)
