"""Injector properties (hypothesis) and known answers on synthetic images."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pytest_drivedegrade import FAMILIES, corrupt, corrupt_sample
from pytest_drivedegrade.constants import CAMERAS
from pytest_drivedegrade.corruptions.kernels import (
    _discrete_normal_tables,
    add_discrete_normal,
    discrete_gaussian_kernel,
    discrete_normal,
)
from pytest_drivedegrade.corruptions.memory import flip_positions
from pytest_drivedegrade.corruptions.sensor import _line_blur

IMAGE_FAMILIES = [n for n, f in FAMILIES.items() if f.scope == "image"]
RANDOM_IMAGE = [n for n in IMAGE_FAMILIES if FAMILIES[n].random]
DETERMINISTIC_IMAGE = [n for n in IMAGE_FAMILIES if not FAMILIES[n].random]

images = st.tuples(st.integers(8, 72), st.integers(8, 96)).flatmap(
    lambda hw: arrays(np.uint8, (hw[0], hw[1], 3), elements=st.integers(0, 255)))
fast = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def textured(h: int = 64, w: int = 96, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


@fast
@given(image=images, family=st.sampled_from(IMAGE_FAMILIES), severity=st.integers(1, 5))
def test_shape_dtype_and_input_untouched(image, family, severity):
    before = image.copy()
    image.setflags(write=False)
    out = corrupt(image, family, severity, frame="f", camera="CAM_BACK")
    assert out.shape == image.shape and out.dtype == np.uint8
    assert out.flags.writeable and out.flags.c_contiguous
    np.testing.assert_array_equal(image, before)
    assert not np.shares_memory(out, image)


@fast
@given(image=images, family=st.sampled_from(IMAGE_FAMILIES))
def test_severity_zero_is_an_equal_copy(image, family):
    out = corrupt(image, family, 0)
    np.testing.assert_array_equal(out, image)
    assert not np.shares_memory(out, image)


@fast
@given(image=images, family=st.sampled_from(IMAGE_FAMILIES), severity=st.integers(1, 5),
       seed=st.integers(0, 2**31), frame=st.text(max_size=12))
def test_same_key_is_bit_identical(image, family, severity, seed, frame):
    a = corrupt(image, family, severity, seed=seed, frame=frame, camera="CAM_FRONT_LEFT")
    b = corrupt(image.copy(), family, severity, seed=seed, frame=frame, camera="CAM_FRONT_LEFT")
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("family", RANDOM_IMAGE)
def test_random_family_differs_across_frames_and_cameras(family):
    image = textured()
    base = corrupt(image, family, 5, frame="a", camera="CAM_FRONT")
    assert not np.array_equal(base, corrupt(image, family, 5, frame="b", camera="CAM_FRONT"))
    assert not np.array_equal(base, corrupt(image, family, 5, frame="a", camera="CAM_BACK"))
    assert not np.array_equal(base, corrupt(image, family, 5, frame="a", camera="CAM_FRONT", seed=1))


@fast
@given(image=images, family=st.sampled_from(DETERMINISTIC_IMAGE), severity=st.integers(1, 5),
       seed=st.integers(1, 2**31))
def test_deterministic_family_ignores_seed_frame_and_camera(image, family, severity, seed):
    a = corrupt(image, family, severity, seed=0, frame="x", camera="CAM_FRONT")
    b = corrupt(image, family, severity, seed=seed, frame="y", camera="CAM_BACK")
    np.testing.assert_array_equal(a, b)


def sample(h: int = 24, w: int = 40) -> dict[str, np.ndarray]:
    return {cam: textured(h, w, seed=i) for i, cam in enumerate(CAMERAS)}


@pytest.mark.parametrize("severity", [1, 2, 3, 4, 5])
def test_blackout_zeroes_exactly_the_spec_cameras(severity):
    spec = {1: {"CAM_BACK"}, 2: {"CAM_BACK_LEFT", "CAM_BACK_RIGHT"},
            3: {"CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT"}, 4: {"CAM_FRONT_LEFT", "CAM_FRONT_RIGHT"},
            5: {"CAM_FRONT"}}[severity]
    images = sample()
    out = corrupt_sample(images, "blackout", severity)
    for cam in CAMERAS:
        if cam in spec:
            assert not out[cam].any()
        else:
            np.testing.assert_array_equal(out[cam], images[cam])


def test_blind_and_clean_cells():
    images = sample()
    assert all(not v.any() for v in corrupt_sample(images, "blind", 0).values())
    clean = corrupt_sample(images, "clean", 0)
    assert all(np.array_equal(clean[c], images[c]) and clean[c] is not images[c] for c in CAMERAS)


def test_frame_dropout_holds_the_last_delivered_frame_or_black():
    images, previous = sample(), {cam: textured(24, 40, seed=99) for cam in CAMERAS}
    lost_seen = kept_seen = 0
    for k in range(30):
        out = corrupt_sample(images, "frame_dropout", 3, frame=f"f{k}", previous=previous)
        black = corrupt_sample(images, "frame_dropout", 3, frame=f"f{k}")
        for cam in CAMERAS:
            if np.array_equal(out[cam], previous[cam]):
                lost_seen += 1
                assert not black[cam].any()
            else:
                kept_seen += 1
                np.testing.assert_array_equal(out[cam], images[cam])
                np.testing.assert_array_equal(black[cam], images[cam])
    assert lost_seen and kept_seen


def test_frame_dropout_loss_rate_follows_the_ladder():
    images = {cam: np.full((2, 2, 3), 7, np.uint8) for cam in CAMERAS}
    rates = []
    for severity in range(1, 6):
        lost = sum(not out.any() for k in range(150)
                   for out in corrupt_sample(images, "frame_dropout", severity, frame=str(k)).values())
        rates.append(lost / 900)
    nominal = FAMILIES["frame_dropout"].values
    for rate, p in zip(rates, nominal):
        assert abs(rate - p) < 4 * np.sqrt(p * (1 - p) / 900), (rates, nominal)


@pytest.mark.parametrize("severity", [1, 2, 3, 4, 5])
def test_color_quant_levels(severity):
    bits = FAMILIES["color_quant"].value(severity)
    out = corrupt(textured(128, 128), "color_quant", severity)  # 16k draws: every code 0..255 is there
    levels = sorted({round(q * 255 / (2**bits - 1)) for q in range(2**bits)})  # spread over 0..255
    for c in range(3):
        assert np.unique(out[..., c]).tolist() == levels


@pytest.mark.parametrize("severity", [3, 4, 5])
def test_bit_error_rate_within_binomial_interval(severity):
    rate = FAMILIES["bit_error"].value(severity)
    image = textured(450, 800)
    out = corrupt(image, "bit_error", severity, frame="x")
    flipped = int(np.unpackbits(np.bitwise_xor(image, out)).sum())
    n = image.size * 8
    assert abs(flipped - n * rate) <= 4 * np.sqrt(n * rate * (1 - rate)) + 1, (flipped, n * rate)


def test_flip_positions_are_distinct_and_in_range():
    pos = flip_positions(np.random.default_rng(3), 10_000, 0.2)
    assert len(np.unique(pos)) == len(pos) and pos.min() >= 0 and pos.max() < 10_000
    assert abs(len(pos) - 2000) < 4 * np.sqrt(10_000 * 0.2 * 0.8)


@pytest.mark.parametrize("severity", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("shape", [(900, 1600), (450, 800), (120, 200)])
def test_occlusion_covers_the_nominal_fraction(severity, shape):
    fraction = FAMILIES["occlusion"].value(severity)
    image = np.full((*shape, 3), 128, np.uint8)
    for frame in ("a", "b", "c"):
        out = corrupt(image, "occlusion", severity, frame=frame)
        covered = (out.sum(axis=2) == 0).mean()
        assert abs(covered - fraction) <= 0.01, (covered, fraction)


@pytest.mark.parametrize("family, blobs, bias", [("mud_splash", 3, 0.35), ("lens_dirt", 6, 0.0)])
@pytest.mark.parametrize("shape", [(900, 1600), (450, 800)])
def test_deposits_cover_the_nominal_fraction(family, blobs, bias, shape):
    """Mud and dirt cover their severity's frame fraction (alpha >= 0.5) within 0.5 % of the frame."""
    from pytest_drivedegrade.corruptions.contamination import _deposit_alpha

    h, w = shape
    for severity in range(1, 6):
        fraction = FAMILIES[family].value(severity)
        for seed in range(4):
            alpha, box = _deposit_alpha(np.random.default_rng(seed), h, w, fraction, blobs, bias)
            covered = np.count_nonzero(cv2.resize(alpha, (box[1].stop - box[1].start, box[0].stop - box[0].start))
                                       >= 0.5) / (h * w)
            assert abs(covered - fraction) < 0.005, (severity, seed, covered)


def test_snow_covers_the_same_share_of_the_frame_at_any_width():
    """A spatial family is defined at 1600 px and scales with the width: the share of a grey frame that the
    flakes whiten (beyond the veil) is the same at 1600 and 800 px, level by level, within 10 % (level 1's
    far flakes are at the half-resolution layer's smallest blur at 800 px, so it is left out)."""
    from pytest_drivedegrade.corruptions.kernels import veiled
    from pytest_drivedegrade.corruptions.weather import _SNOW, _SNOW_WHITE

    def share(width: int, level: int) -> float:
        image = np.full((width * 9 // 16, width, 3), 60, np.uint8)
        base = veiled(image, _SNOW[level][2], _SNOW_WHITE).astype(int)
        return float(np.mean([((corrupt(image, "snow", level, frame=f) - base).mean(axis=2) > 40).mean()
                              for f in "abcd"]))

    for level in (2, 3, 5):
        full, half = share(1600, level), share(800, level)
        assert abs(half / full - 1) < 0.10, (level, full, half)


@pytest.mark.parametrize("sigma", [4, 16, 45])
def test_discrete_normal_matches_rounded_gaussian(sigma):
    x = discrete_normal(np.random.default_rng(0), (400_000,), sigma)
    assert abs(x.mean()) < 4 * sigma / np.sqrt(x.size)
    # variance of round(sigma z) is sigma^2 + 1/12 (Sheppard's correction)
    assert abs(x.var() / (sigma**2 + 1 / 12) - 1) < 0.01
    # the mass at 0 equals P(|sigma z| < 0.5)
    from math import erf, sqrt

    p0 = erf(0.5 / sigma / sqrt(2))
    assert abs((x == 0).mean() - p0) < 4 * np.sqrt(p0 * (1 - p0) / x.size)


def test_discrete_normal_follows_the_exact_pmf():
    """Chi-square of one million draws against the pmf of round(sigma z), bins with >= 20 expected."""
    from math import erf, sqrt

    sigma, count = 5.5, 1_000_000
    x = discrete_normal(np.random.default_rng(1), (count,), sigma)
    values, counts = np.unique(x, return_counts=True)
    observed = dict(zip(values.tolist(), counts.tolist()))
    cdf = lambda v: 0.5 * (1 + erf((v + 0.5) / sigma / sqrt(2)))  # noqa: E731
    chi2, bins = 0.0, 0
    for v in range(-40, 41):
        expected = count * (cdf(v) - cdf(v - 1))
        if expected >= 20:
            chi2 += (observed.get(v, 0) - expected) ** 2 / expected
            bins += 1
    # 99.9% quantile of chi-square with ~40 degrees of freedom is ~73.4
    assert bins > 30 and chi2 < 73.4, (chi2, bins)


@settings(max_examples=20, deadline=None)
@given(h=st.integers(1, 300), w=st.integers(1, 700), sigma=st.sampled_from([3.0, 4.0, 16.0, 45.0]),
       seed=st.integers(0, 2**32))
def test_fused_noise_equals_clipped_sum(h, w, sigma, seed):
    """The chunked, fused noise adder is clip(base + discrete_normal) for the same random stream,
    across chunk boundaries (up to 630k samples)."""
    base = np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)
    noise = discrete_normal(np.random.default_rng(seed + 1), base.shape, sigma)
    fused = add_discrete_normal(base, np.random.default_rng(seed + 1), sigma)
    assert fused.dtype == np.uint8 and fused.shape == base.shape
    np.testing.assert_array_equal(fused, np.clip(base.astype(int) + noise, 0, 255))


@settings(max_examples=15, deadline=None)
@given(h=st.integers(1, 300), w=st.integers(1, 700), seed=st.integers(0, 2**32))
def test_shifted_noise_is_the_unclipped_sum_plus_the_margin(h, w, seed):
    """With headroom (base <= 255 - 2 limit) the 8-bit shifted adder gives base + noise + limit exactly."""
    limit = 18
    base = np.random.default_rng(seed).integers(0, 256 - 2 * limit, (h, w, 3), dtype=np.uint8)
    noise = discrete_normal(np.random.default_rng(seed + 1), base.shape, 3.0, limit)
    shifted = add_discrete_normal(base, np.random.default_rng(seed + 1), 3.0, limit, shifted=True)
    np.testing.assert_array_equal(shifted, base.astype(int) + noise + limit)


@pytest.mark.parametrize("sigma, limit", [(3.0, 18), (4.0, 255), (16.0, 255), (45.0, 255)])
def test_refinement_equals_a_search_of_the_32_bit_thresholds(sigma, limit):
    """The per-bucket step table gives the value a binary search of the 32-bit thresholds gives, for
    every ambiguous bucket (single- and multi-step) and random low halves, including both ends."""
    from pytest_drivedegrade.corruptions.kernels import _resolve

    tables = _discrete_normal_tables(sigma, limit)
    ambiguous = np.flatnonzero(tables.bucket == -32768).astype(np.uint16)
    assert (tables.steps[ambiguous] > 1).any()  # the far tails are cut by several steps
    rng = np.random.default_rng(0)
    high = np.concatenate([np.repeat(ambiguous, 2), rng.choice(ambiguous, 50_000)])
    low = np.concatenate([np.tile(np.array([0, 65535], np.uint16), ambiguous.size),
                          rng.integers(0, 2**16, 50_000, dtype=np.uint16)])
    u32 = (high.astype(np.uint64) << np.uint64(16)) | low.astype(np.uint64)
    expected = tables.values[np.searchsorted(tables.thresholds, u32, side="right")]
    np.testing.assert_array_equal(_resolve(tables, high, low), expected)


def test_noise_tables_resolve_almost_every_draw_in_16_bits():
    """The bucket table leaves at most ~1% of the probability to the 32-bit refinement."""
    for sigma in (4.0, 16.0, 45.0):
        assert (_discrete_normal_tables(sigma, 255).bucket == -32768).mean() < 0.01


def test_discrete_gaussian_kernel_known_values():
    """exp(-t) I_n(t) at t = 1 (Abramowitz and Stegun 9.8: e^-1 I_0(1) = 0.4657596, e^-1 I_1(1) = 0.2079104,
    e^-1 I_2(1) = 0.0499387), and for small t the three-tap limit [t/2, 1 - t, t/2]."""
    k = discrete_gaussian_kernel(1.0)
    c = len(k) // 2
    np.testing.assert_allclose(k[c:c + 3], [0.4657596, 0.2079104, 0.0499387], rtol=1e-4)
    small = discrete_gaussian_kernel(0.1)
    c = len(small) // 2
    np.testing.assert_allclose(small[c - 1:c + 2], [0.005, 0.99, 0.005], rtol=0.01)


@settings(max_examples=60, deadline=None)
@given(sigma=st.floats(0.05, 20.0))
def test_discrete_gaussian_kernel_has_variance_sigma_squared(sigma):
    """Symmetric, sums to 1, standard deviation sigma within 0.1 % at any sigma (a Gaussian sampled at whole
    pixels has 0.026 for 0.25)."""
    k = discrete_gaussian_kernel(sigma)
    x = np.arange(len(k)) - len(k) // 2
    np.testing.assert_array_equal(k, k[::-1])
    assert k.sum() == pytest.approx(1.0, abs=1e-12) and (k > 0).all()
    assert np.sqrt((k * x * x).sum()) == pytest.approx(sigma, rel=1e-3)


@settings(max_examples=30, deadline=None)
@given(a=st.floats(0.1, 4.0), b=st.floats(0.1, 4.0))
def test_discrete_gaussians_compose_like_gaussians(a, b):
    """The semigroup property that makes it the discrete analogue of the Gaussian: blurring by sigma a
    then b is blurring by sqrt(a^2 + b^2), exactly up to the kernels' truncation."""
    both = np.convolve(discrete_gaussian_kernel(a), discrete_gaussian_kernel(b))
    one = discrete_gaussian_kernel(float(np.hypot(a, b)))
    pad = (len(both) - len(one)) // 2
    if pad >= 0:
        one = np.pad(one, pad)
    else:
        both = np.pad(both, -pad)
    assert np.abs(both - one).max() < 2e-4


@pytest.mark.parametrize("severity, scale", [(1, 0.5), (1, 1.0), (2, 1.0), (3, 0.5), (3, 1.0)])
def test_gaussian_blur_below_the_pyramid_is_the_discrete_gaussian(severity, scale):
    """Below sigma 3 px the operator is the discrete Gaussian along x and y with reflected edges, rounded
    once (within a level of the exact float result, and on average within 0.01)."""
    image = textured(40, 70, seed=severity)
    sigma = FAMILIES["gaussian_blur"].value(severity) * scale
    out = FAMILIES["gaussian_blur"].op(image, FAMILIES["gaussian_blur"].value(severity), None, scale)
    k = discrete_gaussian_kernel(sigma)
    exact = cv2.sepFilter2D(image.astype(np.float64), cv2.CV_64F, k, k, borderType=cv2.BORDER_REFLECT_101)
    assert np.abs(out - exact).max() <= 1.0
    assert abs((out - exact).mean()) < 0.01


def test_mean_drop_area_is_that_of_a_log_uniform_radius():
    """pi x aspect x E[r^2] for r log-uniform on [14, 55] px (quadrature), 1.34 x the r_lo r_hi that sized
    raindrop's batches before spec 4.0.0; and a fixed radius where the range is one point."""
    from pytest_drivedegrade.corruptions.contamination import _DROP_ASPECT, _mean_drop_area

    lo, hi = np.log(14.0), np.log(55.0)
    u = np.linspace(lo, hi, 200_001)
    mean_r2 = np.exp(2 * u).mean()  # E[r^2] = E[exp(2 U)], U uniform on [lo, hi]
    assert _mean_drop_area(lo, hi) == pytest.approx(np.pi * _DROP_ASPECT * mean_r2, rel=1e-4)
    assert _mean_drop_area(lo, hi) / (np.pi * _DROP_ASPECT * 14.0 * 55.0) == pytest.approx(1.34, abs=0.01)
    assert _mean_drop_area(lo, lo) == pytest.approx(np.pi * _DROP_ASPECT * 14.0**2)


@pytest.mark.parametrize("severity", [1, 3, 5])
def test_raindrop_realisations_each_cover_the_fraction(severity):
    """Each realisation, not only their mean, covers the declared share of the drop grid at opacity >= 1/2
    within half the largest drop (the drop that reaches the fraction is kept only if that lands nearer)."""
    from pytest_drivedegrade.corruptions.contamination import _DROP_ASPECT, _covered, _drop_params

    fraction = FAMILIES["raindrop"].value(severity)
    for seed in range(4):
        params = _drop_params(np.random.default_rng(seed), 900, 1600, fraction, 1.0, 4.0)
        cells = params.shape[0] * params.shape[1]
        share = _covered(params, slice(0, params.shape[0]), slice(0, params.shape[1])).sum() / cells
        half_drop = 0.5 * np.pi * 55.0**2 * _DROP_ASPECT / 16.0 / cells  # grid cells of 4 x 4 px
        assert abs(share - fraction) <= half_drop, (seed, share)


def _covered_before(params: np.ndarray, rows: slice, cols: slice) -> np.ndarray:
    """`contamination._covered` as it was written before issue 23's second pass."""
    box = params[rows, cols]
    dx = np.arange(cols.start, cols.stop, dtype=np.float32) + 0.5 - box[..., 0]
    dy = np.arange(rows.start, rows.stop, dtype=np.float32)[:, None] + 0.5 - box[..., 1]
    rx2, ry2 = np.square(box[..., 2]), np.square(box[..., 3])
    return (dx * dx * ry2 + dy * dy * rx2 <= (1.0 - 0.5 / 12.0) ** 2 * rx2 * ry2) & (rx2 > 0)


def _drops_one_by_one(rng: np.random.Generator, h: int, w: int, fraction: float, scale: float,
                      step: float) -> np.ndarray:
    """`contamination._drop_params` as the suite computed it before issue 23's second pass: every drop painted,
    then its box's covered cells recounted, one at a time."""
    from pytest_drivedegrade.corruptions import contamination as C  # noqa: N812 - C for the module

    gh, gw = max(1, round(h / step)), max(1, round(w / step))
    params, covered, area = np.zeros((gh, gw, 4), np.float32), np.zeros((gh, gw), bool), 0
    target = fraction * gh * gw
    lo, hi = np.log(C.scaled(C._DROP_RADIUS[0], scale)), np.log(C.scaled(C._DROP_RADIUS[1], scale))
    drop_cells, count = C._mean_drop_area(lo, hi) / (step * step), 0
    while count < 5000:
        batch = max(1, int((target - area) / drop_cells))
        rx = np.maximum(1.0, np.exp(rng.uniform(lo, hi, batch)))
        new = np.stack([rng.uniform(0, w, batch), rng.uniform(0, h, batch), rx, rx * C._DROP_ASPECT], axis=1) / step
        for drop in new:
            count += 1
            cx, cy, ax, ay = (float(v) for v in drop)
            centre, axes = (round(cx), round(cy)), (max(1, round(ax)), max(1, round(ay)))
            box = (slice(max(0, centre[1] - axes[1] - 1), min(gh, centre[1] + axes[1] + 2)),
                   slice(max(0, centre[0] - axes[0] - 1), min(gw, centre[0] + axes[0] + 2)))
            held = params[box].copy()
            cv2.ellipse(params, centre, axes, 0, 0, 360, (cx, cy, ax, ay), -1)
            now = _covered_before(params, *box)
            gain = int(np.count_nonzero(now)) - int(np.count_nonzero(covered[box]))
            if area + gain < target:
                covered[box], area = now, area + gain
                continue
            if area + gain - target > target - area:
                params[box] = held
            return params
    return params


@pytest.mark.parametrize("shape", [(450, 800), (900, 1600), (37, 61), (3, 500)])
def test_raindrops_painted_in_bulk_are_the_drops_painted_one_by_one(shape):
    """The drops that cannot reach the fraction painted at once (`_DropGrid.paint_short`) leave the grid that
    painting each and recounting its box leaves, bit for bit, at every severity's fraction and beyond."""
    from pytest_drivedegrade.corruptions.contamination import _drop_params

    h, w = shape
    scale = w / 1600
    step = max(1.0, 4.0 * scale)
    for fraction in (*FAMILIES["raindrop"].values, 0.0, 0.5, 0.9):
        for seed in range(3):
            got = _drop_params(np.random.default_rng(seed), h, w, fraction, scale, step)
            want = _drops_one_by_one(np.random.default_rng(seed), h, w, fraction, scale, step)
            assert got.view(np.uint32).tobytes() == want.view(np.uint32).tobytes(), (fraction, seed)


@settings(max_examples=300, deadline=None)
@given(cx=st.floats(-3.0, 43.0), cy=st.floats(-3.0, 33.0), rx=st.floats(0.25, 14.0), aspect=st.floats(0.5, 2.0),
       under=st.integers(0, 3), seed=st.integers(0, 1000))
def test_a_drops_gain_bound_is_never_below_what_it_adds(cx, cy, rx, aspect, under, seed):
    """`_Drops.gain` is an upper bound on how many covered cells painting the drop adds, whatever it is painted
    over (`paint_short` relies on it to paint in bulk only drops that cannot reach the fraction): drops of any
    size and place, edges and other drops under it included. A bound without the lattice's margin fails here
    (a drop of radius 1 centred on a cell corner covers four cells, more than pi)."""
    from pytest_drivedegrade.corruptions.contamination import _DropGrid, _Drops

    gh, gw = 30, 40
    rng = np.random.default_rng(seed)
    grid = _DropGrid(gh, gw)
    others = np.stack([rng.uniform(0, gw, under), rng.uniform(0, gh, under), rng.uniform(1, 9, under),
                       rng.uniform(1, 9, under)], axis=1) if under else np.zeros((0, 4))
    drops = _Drops(np.vstack([others, [[cx, cy, rx, rx * aspect]]]).astype(np.float64), gh, gw)
    for k in range(under):
        grid.paint(drops, k, np.inf)  # never reaches an infinite target: painted and counted
    before = grid.area
    grid.paint(drops, under, np.inf)
    assert grid.area - before <= drops.gain[under], (grid.area - before, drops.gain[under])


def _line_mean(image: np.ndarray, length: float, slope: float) -> np.ndarray:
    """Brute force: the area-sampled segment `length` rows long on the digital line through each pixel,
    advancing along axis 0: n = floor(length) whole samples (window [i - n//2, i + n - 1 - n//2]) and the
    next one weighted by length - n, the line's column shifted by round(slope * i), both clamped."""
    rows, cols = image.shape[:2]
    n = int(length + 1e-9)  # a length within 1e-9 of a whole number is that number, as the operator takes it
    i = np.arange(rows)[:, None]
    j = np.arange(cols)[None, :]
    total = np.zeros(image.shape, float)
    taps = [(k, 1.0) for k in range(-(n // 2), n - n // 2)] + [(n - n // 2, max(length - n, 0.0))]
    for k, weight in taps:
        q = np.clip(i + k, 0, rows - 1)
        col = np.clip(j - np.round(slope * i) + np.round(slope * q), 0, cols - 1).astype(int)
        total += weight * image[q, col]
    return total / length


@settings(max_examples=40, deadline=None)
@given(rows=st.integers(1, 420), cols=st.integers(1, 90), n=st.integers(2, 40),
       slope=st.floats(-1.0, 1.0), seed=st.integers(0, 1000))
def test_line_blur_is_the_mean_along_the_digital_line(rows, cols, n, slope, seed):
    """Exact up to rounding, across the filter's row blocks and at every edge. OpenCV's 8-bit box filter
    rounds through fixed point (up to 0.75 of a level off for n = 4); two taps are rounded exactly."""
    image = np.random.default_rng(seed).integers(0, 256, (rows, cols, 3), dtype=np.uint8)
    error = np.abs(_line_blur(image, n, slope) - _line_mean(image, n, slope)).max()
    assert error <= 0.5 + 1e-9 if n == 2 else error < 1.0


@settings(max_examples=40, deadline=None)
@given(rows=st.integers(1, 420), cols=st.integers(1, 90), length=st.floats(1.0, 40.0),
       slope=st.floats(-1.0, 1.0), seed=st.integers(0, 1000), transposed=st.booleans())
def test_line_blur_of_a_real_length_is_the_area_sampled_segment(rows, cols, length, slope, seed, transposed):
    """A real length adds the partial sample: within 1.25 levels of the weighted mean (the box filter's
    rounding, at most 0.75 of a level, scaled by n / length, plus the final rounding), on either axis."""
    image = np.random.default_rng(seed).integers(0, 256, (rows, cols, 3), dtype=np.uint8)
    expected = _line_mean(image, length, slope)
    if transposed:
        got = _line_blur(np.ascontiguousarray(image.transpose(1, 0, 2)), length, slope, transposed=True)
        got = got.transpose(1, 0, 2)
    else:
        got = _line_blur(image, length, slope)
    assert np.abs(got - expected).max() < 1.25


def test_motion_blur_work_buffers_are_per_thread():
    """motion_blur reuses its work buffers within a thread: threads blurring different images and sizes
    at once get exactly what one thread gets, and a result never aliases a buffer the next call reuses."""
    from concurrent.futures import ThreadPoolExecutor

    jobs = [(textured(225 + 9 * k, 400 + 16 * k, seed=k), 1 + k % 5, f"t{k}") for k in range(12)]
    alone = [corrupt(image, "motion_blur", severity, frame=frame) for image, severity, frame in jobs]
    with ThreadPoolExecutor(4) as pool:
        together = list(pool.map(lambda job: corrupt(job[0], "motion_blur", job[1], frame=job[2]), jobs * 3))
    for k, out in enumerate(together):
        np.testing.assert_array_equal(out, alone[k % len(jobs)])
    np.testing.assert_array_equal(alone[0], corrupt(jobs[0][0], "motion_blur", jobs[0][1], frame=jobs[0][2]))


@pytest.mark.parametrize("width", [1600, 800, 400, 200])
def test_motion_blur_keeps_a_flat_image_flat(width):
    """A constant image is a fixed point of every blur length (OpenCV 5.0's 2-tap box filter is not)."""
    image = np.full((width * 9 // 16, width, 3), 97, np.uint8)
    for severity in range(1, 6):
        for frame in ("a", "b"):
            assert np.unique(corrupt(image, "motion_blur", severity, frame=frame)).tolist() == [97]


@pytest.mark.parametrize("bad, match", [
    (np.zeros((4, 4, 3), np.float32), "dtype uint8"),
    (np.zeros((4, 4), np.uint8), "H x W x 3"),
    (np.zeros((4, 4, 4), np.uint8), "H x W x 3"),
    (np.zeros((0, 4, 3), np.uint8), "empty"),
    ([[1, 2, 3]], "numpy array"),
])
def test_bad_images_are_named(bad, match):
    with pytest.raises(ValueError, match=match):
        corrupt(bad, "jpeg", 1)


def test_bad_family_severity_camera_list_the_valid_choices():
    image = textured(8, 8)
    with pytest.raises(ValueError, match="unknown corruption family 'haze'.*gaussian_blur.*lens_dirt"):
        corrupt(image, "haze", 1)
    for severity in (6, -1, 2.5, True, "3"):
        with pytest.raises(ValueError, match=r"severity must be an integer 0\.\.5"):
            corrupt(image, "jpeg", severity)
    with pytest.raises(ValueError, match="unknown camera 'CAM_TOP'.*CAM_FRONT.*CAM_BACK_RIGHT"):
        corrupt(image, "jpeg", 1, camera="CAM_TOP")
    with pytest.raises(ValueError, match="corrupt_sample"):
        corrupt(image, "blackout", 1)
    with pytest.raises(ValueError, match="unknown camera 'front'"):
        corrupt_sample({"front": image}, "jpeg", 1)
    with pytest.raises(ValueError, match=r"images\['CAM_BACK'\].*dtype uint8"):
        corrupt_sample({"CAM_BACK": image.astype(float)}, "jpeg", 1)
