"""Lens and windshield contamination: spatially concentrated damage. Part of the frame stays pristine; the
rest is refracted (raindrop), removed (occlusion, mud) or veiled (lens dirt)."""

from __future__ import annotations

import cv2
import numpy as np

from .derived import derived
from .kernels import blend, coverage_mask, scaled, smooth_field, to_alpha8, veiled
from .registry import register

#: Raindrop radius range (px at 1600 px width), drawn log-uniform; the drop is a little taller than wide.
_DROP_RADIUS = (14.0, 55.0)
_DROP_ASPECT = 1.15
#: A drop is a fisheye lens: it shows an inverted view of a region this many times its own size.
_DROP_MAGNIFICATION = 2.6
#: Cell size of the drop layer (px at 1600 px width, at least one image pixel): a drop is a defocused
#: object on the lens, so its refraction, shade and soft edge are built on this grid and upsampled.
_DROP_GRID = 4.0
#: A drop's opacity falls from 1 to 0 over its outer 1 / _DROP_EDGE of radius (its soft, defocused rim).
_DROP_EDGE = 12.0
#: rho^2 of `_covered`'s test, in float32 as the test multiplies it.
_REACH2 = np.float32((1.0 - 0.5 / _DROP_EDGE) ** 2)
#: `_DropGrid.paint_short` paints this many drops or more at once, and no fewer than one per this many covered
#: cells (fewer go one by one, which is then cheaper than recounting the wet cells); either way the same grid.
_BULK_DROPS = 12
_BULK_CELLS_PER_DROP = 1000


def _mean_drop_area(lo: float, hi: float) -> float:
    """Mean area (px^2) of a drop whose radius is log-uniform on [e^lo, e^hi]: pi aspect E[r^2], where
    E[r^2] = (e^(2 hi) - e^(2 lo)) / (2 (hi - lo)) (1.34x e^(lo + hi) for the reference range)."""
    mean_r2 = (np.exp(2 * hi) - np.exp(2 * lo)) / (2 * (hi - lo)) if hi > lo else np.exp(2 * lo)
    return float(np.pi * mean_r2 * _DROP_ASPECT)


def _inside(dx: np.ndarray, dy: np.ndarray, rx: np.ndarray, ry: np.ndarray) -> np.ndarray:
    """float32 offsets (dx, dy) of cells from their drops' centres within the drop's ellipse (rx, ry) to rho <=
    1 - 1 / (2 _DROP_EDGE), without a division: dx^2 ry^2 + dy^2 rx^2 <= rho^2 rx^2 ry^2, and rx > 0 (a wet
    cell). `dx` and `dy` are overwritten (the same products in the same order, without temporaries)."""
    rx2, ry2 = np.square(rx), np.square(ry)
    dx *= dx
    dx *= ry2
    dy *= dy
    dy *= rx2
    dx += dy
    reach = rx2 * _REACH2
    reach *= ry2
    inside = dx <= reach
    inside &= rx2 > 0
    return inside


def _covered(params: np.ndarray, rows: slice, cols: slice) -> np.ndarray:
    """Which cells of params[rows, cols] are under a drop at opacity >= 1/2 (what the fraction counts):
    inside their drop's ellipse to rho <= 1 - 1 / (2 _DROP_EDGE), with the alpha ramp of `_drop_layer`
    (`_inside`)."""
    box = params[rows, cols]
    dx = np.arange(cols.start, cols.stop, dtype=np.float32) + 0.5 - box[..., 0]
    dy = np.arange(rows.start, rows.stop, dtype=np.float32)[:, None] + 0.5 - box[..., 1]
    return _inside(dx, dy, box[..., 2], box[..., 3])


class _Drops:
    """A batch of drops (B, 4: cx, cy, rx, ry in grid units) as `cv2.ellipse` paints them: each one's colour
    (the four values), centre and axes in whole cells (rounded half to even, as Python's round), and the cells
    it can paint: its box, one cell of margin, cut to the grid.

    `gain`: at most how many cells painting it can add to the covered ones: the cells it paints that its own
    ellipse covers (`_covered`), which are no more than its box's cells nor the cell centres inside the ellipse
    (rx, ry), at most pi rx ry + 2 (rx + ry) + 1 (the unit squares round those centres are disjoint and lie in the
    ellipse grown by half a cell each way, whose area that is; `_covered` tests the smaller ellipse of rho <=
    1 - 1 / (2 _DROP_EDGE), 8 % less area, which far outweighs float32 rounding), rounded up."""

    def __init__(self, drops: np.ndarray, gh: int, gw: int) -> None:
        centre = np.round(drops[:, :2]).astype(np.int64)
        axes = np.maximum(1, np.round(drops[:, 2:]).astype(np.int64))
        lo, hi = np.maximum(0, centre - axes - 1), np.minimum([gw, gh], centre + axes + 2)
        cells = np.prod(np.maximum(hi - lo, 0), axis=1)  # none for a box off the grid
        rx, ry = drops[:, 2].astype(np.float64), drops[:, 3].astype(np.float64)
        self.gain = np.minimum(cells, np.ceil(np.pi * rx * ry + 2.0 * (rx + ry) + 1.0).astype(np.int64))
        self.colour = [tuple(d) for d in drops.tolist()]
        self.centre, self.axes = [tuple(c) for c in centre.tolist()], [tuple(a) for a in axes.tolist()]
        self.box = [(slice(y0, y1), slice(x0, x1)) for (x0, y0), (x1, y1) in zip(lo.tolist(), hi.tolist())]


class _DropGrid:
    """The drop grid being painted: `params` (each wet cell's drop, cx, cy, rx, ry in grid units; rx = 0 where
    the lens is dry), which cells are covered (`_covered`) and how many. `covered` always equals `_covered` of
    the whole grid: a drop changes only the cells of its box, which it recounts."""

    def __init__(self, gh: int, gw: int) -> None:
        self.params = np.zeros((gh, gw, 4), np.float32)
        self.covered = np.zeros((gh, gw), bool)
        self.area = 0

    def paint(self, drops: _Drops, k: int, target: float) -> bool:
        """Paint drop `k` over what is there (a drop over another's rim can also uncover a little, so the
        covered cells are recounted in its box). True once the covered cells reach `target`; the drop that
        reaches it is taken back if stopping before it lands nearer to the target."""
        box = drops.box[k]
        held = self.params[box].copy() if self.area + drops.gain[k] >= target else None  # its gain <= .gain
        cv2.ellipse(self.params, drops.centre[k], drops.axes[k], 0, 0, 360, drops.colour[k], -1)
        now = _covered(self.params, *box)
        gain = int(np.count_nonzero(now)) - int(np.count_nonzero(self.covered[box]))
        if self.area + gain < target:
            self.covered[box] = now
            self.area += gain
            return False
        if held is not None and self.area + gain - target > target - self.area:  # further past than short
            self.params[box] = held
        return True

    def paint_short(self, drops: _Drops, target: float) -> int:
        """Paint the leading drops that cannot reach `target` whatever they cover (the covered cells plus the
        most each can add, `_Drops.gain`, stay short of it): the ellipses first, then the covered cells recounted
        once over the wet cells, which is what painting them one by one leaves. Returns how many were painted:
        none when fewer than _BULK_DROPS could be, or too few for the cells to recount (one by one is then
        cheaper)."""
        count = int(np.searchsorted(self.area + np.cumsum(drops.gain), target, side="left"))
        if count < _BULK_DROPS or count * _BULK_CELLS_PER_DROP < self.area:  # the recount would cost more
            return 0
        for k in range(count):
            cv2.ellipse(self.params, drops.centre[k], drops.axes[k], 0, 0, 360, drops.colour[k], -1)
        flat = self.params.reshape(-1, 4)
        wet = np.flatnonzero(flat[:, 2] > 0)
        row, col = np.divmod(wet, self.params.shape[1])
        cells = np.take(flat, wet, axis=0)
        self.covered[...] = False
        self.covered.reshape(-1)[wet] = _inside(col.astype(np.float32) + 0.5 - cells[:, 0],
                                                row.astype(np.float32) + 0.5 - cells[:, 1], cells[:, 2], cells[:, 3])
        self.area = int(np.count_nonzero(self.covered))
        return count


def _drop_params(rng: np.random.Generator, h: int, w: int, fraction: float, scale: float,
                 step: float) -> np.ndarray:
    """Drops added one by one until the cells they cover at opacity >= 1/2 (`_covered`) reach `fraction`
    of the frame, painted into a 4-channel float32 grid of `step` px: each covered cell holds its drop's
    (cx, cy, rx, ry) in grid units (a later drop covers an earlier one); rx = 0 where the lens is dry.

    The drops are drawn in batches sized for the area still missing with the mean drop area (overlaps make
    a batch fall short, so the batches converge from below). The drop that reaches the fraction is kept
    only if that lands nearer to it than stopping before it does, so the covered share is unbiased.
    """
    gh, gw = max(1, round(h / step)), max(1, round(w / step))
    grid = _DropGrid(gh, gw)
    target = fraction * gh * gw
    lo, hi = np.log(scaled(_DROP_RADIUS[0], scale)), np.log(scaled(_DROP_RADIUS[1], scale))
    drop_cells = _mean_drop_area(lo, hi) / (step * step)
    count = 0
    while count < 5000:
        batch = max(1, int((target - grid.area) / drop_cells))
        rx = np.maximum(1.0, np.exp(rng.uniform(lo, hi, batch)))
        new = np.stack([rng.uniform(0, w, batch), rng.uniform(0, h, batch), rx, rx * _DROP_ASPECT], axis=1) / step
        drops = _Drops(new, gh, gw)
        for k in range(grid.paint_short(drops, target), batch):
            if grid.paint(drops, k, target):
                return grid.params
        count += batch
    return grid.params


def _drop_layer(params: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(source x, source y in full-resolution px, shade, alpha) on the drop grid: each drop shows an
    inverted, magnified view of the scene above it, with a darker rim. Computed on the wet cells only
    (3-25 % of the grid); dry cells read pixel (0, 0) at alpha 0 (they are never shown, and far-off
    coordinates would make remap's border handling crawl) with the shade of a drop's outer rim."""
    gh, gw = params.shape[:2]
    cells = params.reshape(-1, 4)
    wet = np.flatnonzero(cells[:, 2] > 0)
    cx, cy, rx, ry = np.take(cells, wet, axis=0).T  # the rows gathered by take: 10x faster than cells[wet]
    row, col = np.divmod(wet, gw)
    dx = (col.astype(np.float32) + 0.5 - cx) / rx
    dy = (row.astype(np.float32) + 0.5 - cy) / ry
    rho2 = dx * dx + dy * dy
    lens = _DROP_MAGNIFICATION * (1.0 + 0.35 * rho2)  # stronger bending towards the rim
    map_x = np.zeros(gh * gw, np.float32)
    map_y = np.zeros(gh * gw, np.float32)
    shade = np.full(gh * gw, 1.0 - 0.45, np.float32)
    alpha = np.zeros(gh * gw, np.float32)
    map_x[wet] = (cx - dx * rx * lens) * step
    map_y[wet] = (cy - 1.5 * ry - dy * ry * lens) * step  # looks up, inverted
    shade[wet] = 1.0 - 0.45 * np.minimum(rho2, 1.0) ** 3
    alpha[wet] = np.clip((1.0 - np.sqrt(rho2)) * _DROP_EDGE, 0.0, 1.0)
    return map_x.reshape(gh, gw), map_y.reshape(gh, gw), shade.reshape(gh, gw), alpha.reshape(gh, gw)


def _drop_source(image: np.ndarray, scale: float) -> np.ndarray:
    """What every drop refracts: the frame at quarter resolution, defocused (the same at every severity, so a
    run's decoded frames derive it once: `corruptions.derived`)."""
    h, w = image.shape[:2]
    small = cv2.resize(image, (max(1, w // 4), max(1, h // 4)), interpolation=cv2.INTER_AREA)
    return cv2.GaussianBlur(small, (0, 0), sigmaX=max(0.5, scaled(8.0, scale) / 4))


@register("raindrop", group="contamination", axis="contamination", parameter="frame fraction under drops",
          unit="fraction", values=(0.03, 0.06, 0.10, 0.16, 0.25), random=True, spatial=True)
def raindrop(image: np.ndarray, fraction: float, rng: np.random.Generator, scale: float) -> np.ndarray:
    """Water drops on the lens, each a small inverted fisheye view of the scene behind it, out of focus
    (the drop sits far in front of the focal plane), added until the drops at opacity >= 1/2 cover the
    fraction. The drop layer is built on a grid of 4 px at the 1600 px reference width (its content and edge
    are defocused anyway) and composited over the sharp frame."""
    h, w = image.shape[:2]
    step = max(1.0, scaled(_DROP_GRID, scale))
    map_x, map_y, shade, alpha = _drop_layer(_drop_params(rng, h, w, fraction, scale, step), step)
    source = derived(image, f"raindrop-source-{scale!r}", lambda clean: _drop_source(clean, scale))
    to_source = source.shape[1] / w
    view = cv2.remap(source, map_x * to_source, map_y * to_source, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REFLECT_101)
    view = cv2.multiply(view, cv2.merge([shade, shade, shade]), dtype=cv2.CV_8U)
    view = cv2.resize(view, (w, h), interpolation=cv2.INTER_LINEAR)
    return blend(image, view, cv2.resize(to_alpha8(alpha), (w, h), interpolation=cv2.INTER_LINEAR))


@register("occlusion", group="contamination", axis="removal", parameter="frame fraction under one black box",
          unit="fraction", values=(0.1, 0.2, 0.3, 0.4, 0.5), random=True)
def occlusion(image: np.ndarray, fraction: float, rng: np.random.Generator, scale: float) -> np.ndarray:
    """One black axis-aligned rectangle of the given area fraction, random aspect (1:2 .. 2:1) and place."""
    h, w = image.shape[:2]
    area = fraction * h * w
    aspect = float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))))
    bw = min(w, max(1, round(np.sqrt(area * aspect))))
    bh = min(h, max(1, round(area / bw)))
    bw = min(w, max(1, round(area / bh)))
    x0 = int(rng.integers(0, w - bw + 1))
    y0 = int(rng.integers(0, h - bh + 1))
    out = image.copy()
    out[y0:y0 + bh, x0:x0 + bw] = 0
    return out


def _deposit_field(rng: np.random.Generator, h: int, w: int, blobs: int, bottom_bias: float) -> np.ndarray:
    """A low-resolution field whose top quantile is a set of irregular splashes: a few Gaussian bumps
    roughened by value noise. Coordinates are in units of the frame, so it is resolution-free."""
    gh, gw = max(8, h // 8), max(8, w // 8)
    yy, xx = np.mgrid[0:gh, 0:gw].astype(np.float32)
    field = np.zeros((gh, gw), np.float32)
    for _ in range(blobs):
        cx = rng.uniform(0, gw)
        cy = gh * (bottom_bias + (1 - bottom_bias) * rng.uniform(0, 1))
        r = gw * rng.uniform(0.05, 0.18)
        field += np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * r * r)).astype(np.float32)
    return field + 0.55 * smooth_field(rng, gh, gw, cells=6, octaves=3)


def _deposit_alpha(rng: np.random.Generator, h: int, w: int, fraction: float, blobs: int,
                   bottom_bias: float) -> tuple[np.ndarray, tuple[slice, slice]]:
    """Coverage in [0, 1] over about `fraction` of the frame, cropped to its bounding box, at half resolution
    (float32), and that box (row slice, column slice) in full-resolution pixels.

    The field is made at 1/8 resolution; inside the box it is interpolated (bicubic) to half resolution and
    cut at the fraction's quantile there, so the deposit's outline is smooth at any scale (cutting first
    and upsampling the cut would leave 8 px stair steps). The edge is then softened over about two
    full-resolution pixels; callers upsample what they need once."""
    field = _deposit_field(rng, h, w, blobs, bottom_bias)
    mask = coverage_mask(field, fraction)
    gh, gw = mask.shape
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return np.zeros((0, 0), np.float32), (slice(0, 0), slice(0, 0))
    threshold = float(field[mask].min())
    # one coarse cell of margin for the soft edge, mapped to full-resolution pixels
    r0, r1 = max(0, rows[0] - 1), min(gh, rows[-1] + 2)
    c0, c1 = max(0, cols[0] - 1), min(gw, cols[-1] + 2)
    box = (slice(r0 * h // gh, r1 * h // gh), slice(c0 * w // gw, c1 * w // gw))
    bh, bw = box[0].stop - box[0].start, box[1].stop - box[1].start
    fine = cv2.resize(field[r0:r1, c0:c1], (max(1, bw // 2), max(1, bh // 2)), interpolation=cv2.INTER_CUBIC)
    inside = (fine >= threshold).astype(np.float32)
    return cv2.GaussianBlur(inside, (3, 3), 0.6), box


def _up(array: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    return cv2.resize(array, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)


def _tinted(rng: np.random.Generator, shape: tuple[int, int], rgb: np.ndarray, cells: int, spread: float) -> np.ndarray:
    """A uint8 colour texture of `shape`: `rgb` modulated by value noise, made at quarter resolution."""
    h, w = shape
    grain = smooth_field(rng, max(8, h // 4), max(8, w // 4), cells=cells, octaves=2)
    small = np.clip(rgb * (1.0 - spread / 2 + spread * grain)[..., None], 0, 255).astype(np.uint8)
    return _up(small, shape)


_MUD_RGB = np.array([92.0, 68.0, 44.0], np.float32)


@register("mud_splash", group="contamination", axis="contamination", parameter="frame fraction under mud",
          unit="fraction", values=(0.02, 0.05, 0.09, 0.14, 0.20), random=True)
def mud_splash(image: np.ndarray, fraction: float, rng: np.random.Generator, scale: float) -> np.ndarray:
    """Opaque mud thrown up from the road: irregular splashes, lower frame more likely, textured brown."""
    h, w = image.shape[:2]
    alpha, box = _deposit_alpha(rng, h, w, fraction, blobs=int(rng.integers(2, 5)), bottom_bias=0.35)
    out = image.copy()
    if alpha.size:
        region = image[box]
        mud = _tinted(rng, region.shape[:2], _MUD_RGB, cells=40, spread=0.6)
        out[box] = blend(region, mud, _up(to_alpha8(alpha), region.shape[:2]))
    return out


_DIRT_RGB = np.array([150.0, 140.0, 122.0], np.float32)
_DIRT_VEIL_PER_FRACTION = 0.5  # veiling glare opacity per unit of dirty frame fraction
_VEIL_GREY = 215.0


@register("lens_dirt", group="contamination", axis="contamination", parameter="frame fraction under dirt",
          unit="fraction", values=(0.05, 0.10, 0.20, 0.30, 0.45), random=True, spatial=True)
def lens_dirt(image: np.ndarray, fraction: float, rng: np.random.Generator, scale: float) -> np.ndarray:
    """Semi-transparent dirt on the lens: under it the scene is defocused and dimmed behind a grey-brown
    film; light scattered by the dirt veils the whole frame in proportion to the dirty fraction.

    The film (defocused scene behind the dirt) is composed at quarter resolution, where it has no detail
    left to lose, and blended over the sharp frame once at full resolution.
    """
    h, w = image.shape[:2]
    alpha, box = _deposit_alpha(rng, h, w, fraction, blobs=int(rng.integers(4, 9)), bottom_bias=0.0)
    veil = _DIRT_VEIL_PER_FRACTION * fraction
    # the veil is affine and the film blend convex, so veiling both layers equals veiling the result
    out = veiled(image, veil, _VEIL_GREY)
    if alpha.size:
        region = out[box]
        rh, rw = region.shape[:2]
        qh, qw = max(1, rh // 4), max(1, rw // 4)
        # the whole 4 x 4 blocks: OpenCV's exact fast path for integer area reduction
        small = cv2.resize(region[:qh * 4, :qw * 4] if rh >= 4 and rw >= 4 else region, (qw, qh),
                           interpolation=cv2.INTER_AREA)
        blurred = cv2.GaussianBlur(small, (0, 0), max(0.5, scaled(10.0, scale) / 4))
        opacity: np.ndarray = cv2.resize(alpha, (qw, qh), interpolation=cv2.INTER_AREA)
        opacity *= 0.35 + 0.3 * smooth_field(rng, qh, qw, cells=5, octaves=2)
        dirt = np.empty_like(small)
        dirt[:] = np.round(_DIRT_RGB * (1.0 - veil) + _VEIL_GREY * veil).astype(np.uint8)
        film = _up(blend(blurred, dirt, to_alpha8(opacity)), (rh, rw))
        out[box] = blend(region, film, _up(to_alpha8(np.minimum(alpha * 2.0, 1.0)), (rh, rw)))
    return out

