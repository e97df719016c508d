"""The ladder means what it says: every family's physical parameter, measured from outside.

Each test feeds a synthetic image through the public API (`corrupt`, `corrupt_sample`; `FAMILIES[...].op`
only where a random draw must be forced) and measures the parameter the ladder declares, at the 1600 px
reference width and at 800 px (spatial parameters scale with width / 1600). Every tolerance is tighter
than a 25 % error in the parameter: an operator that realises 0.75x or 1.25x its declared value fails.
A known gap between an operator and its declared value is marked `xfail(strict=True)` with the defect
named, so a fix turns it into a failure that asks for the marker to go; spec 4.0.0 has none (its two,
gaussian_blur below 0.4 px and raindrop's coverage at S1-S3, were fixed).

Run this file as a script from the repository root (`PYTHONPATH=. python tests/unit/test_ladder_physics.py`)
to print the declared-versus-measured table.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from pytest_drivedegrade import FAMILIES, corrupt, corrupt_sample
from pytest_drivedegrade.constants import CAMERAS

WIDTHS = (1600, 800)
SEVERITIES = (1, 2, 3, 4, 5)


def declared(family: str, severity: int, width: int = 1600) -> float:
    """The ladder's value, scaled to `width` when the parameter is spatial."""
    fam = FAMILIES[family]
    return fam.value(severity) * (width / 1600) if fam.spatial else fam.value(severity)


def srgb_to_linear(code) -> np.ndarray:
    """The sRGB electro-optical transfer (IEC 61966-2-1), 8-bit code -> linear light."""
    c = np.asarray(code, dtype=np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def normal_cdf(x: float) -> float:
    return 0.5 * (1.0 + math.erf(x / math.sqrt(2.0)))


# --- measurements ---------------------------------------------------------------------------------------------


def noise_sigma(width: int, severity: int) -> tuple[float, float]:
    """(measured std of output - 128 on a mid-grey frame, the std that clip(128 + round(sigma z)) has)."""
    grey = np.full((width * 9 // 16, width, 3), 128, np.uint8)
    residual = corrupt(grey, "gaussian_noise", severity, frame="physics").astype(np.float64) - 128.0
    sigma = declared("gaussian_noise", severity)
    values = np.arange(-128, 128)  # round(sigma z) after clipping to the 8-bit range
    upper = [normal_cdf((v + 0.5) / sigma) if v < 127 else 1.0 for v in values]
    pmf = np.diff([0.0, *upper])
    mean = float((pmf * values).sum())
    expected = math.sqrt(float((pmf * (values - mean) ** 2).sum()))
    return float(residual.std()), expected


def _step_profile(out: np.ndarray, axis: int) -> np.ndarray:
    """The middle line of a step-edge image across the edge, one channel, as float."""
    h, w = out.shape[:2]
    return (out[h // 2, :, 1] if axis == 1 else out[:, w // 2, 1]).astype(np.float64)


def _spread(profile: np.ndarray) -> float:
    """Standard deviation of the line spread function (the derivative of an edge profile, as weights)."""
    d = np.diff(profile)
    w = d / d.sum()
    x = np.arange(len(d))
    mu = (w * x).sum()
    return float(np.sqrt((w * (x - mu) ** 2).sum()))


def _rise_10_90(profile: np.ndarray) -> float:
    """Distance (px) between the 10 % and 90 % crossings of a rising edge profile (linear interpolation)."""
    p = (profile - profile.min()) / (profile.max() - profile.min())
    x = np.arange(len(p))
    return float(np.interp(0.9, p, x) - np.interp(0.1, p, x))


def blur_sigma(width: int, severity: int) -> tuple[float, float]:
    """(sigma from the line spread's second moment, sigma from the 10-90 % rise / 2.563) of a bar's two
    edges, one at an even column and one at an odd one (the half-resolution path has two phases)."""
    image = np.zeros((32, width, 3), np.uint8)
    a, b = width // 4, 3 * width // 4 + 1
    image[:, a:b] = 255
    line = _step_profile(corrupt(image, "gaussian_blur", severity), axis=1)
    reach = 60
    edges = (line[a - reach:a + reach], line[b - reach:b + reach][::-1])  # both rising
    moment = float(np.mean([_spread(e) for e in edges]))
    rise = float(np.mean([_rise_10_90(e) for e in edges])) / 2.563
    return moment, rise


class ForcedAngle:
    """A stand-in generator whose single uniform draw (motion_blur's direction) is the given angle."""

    def __init__(self, degrees: float) -> None:
        self.angle = math.radians(degrees)

    def uniform(self, low: float, high: float) -> float:
        assert (low, high) == (0.0, math.pi)  # the operator draws its direction this way
        return self.angle


def _edge_extent(profile: np.ndarray) -> float:
    """Length (px) of a uniform smear from its edge profile: the total rise over the rise per pixel of the
    fully covered pixels (their run around the steepest step, telescoped so that 8-bit rounding enters
    only at its two ends). A uniform segment of length L gives L; a partly covered end pixel is a fraction."""
    d = np.diff(profile)
    full = d >= d.max() - 3.0
    a = b = int(np.argmax(d))
    while a > 0 and full[a - 1]:
        a -= 1
    while b < len(d) - 1 and full[b + 1]:
        b += 1
    per_pixel = (profile[b + 1] - profile[a]) / (b + 1 - a)
    return float((profile[-1] - profile[0]) / per_pixel)


def smear(width: int, blur) -> dict[str, float]:
    """A motion blur measured on two step edges (vertical: profile along x; horizontal: along y).

    Returns the extent along x and y (`_edge_extent`), the spread (std) along x and y, and the Euclidean
    length from the second moment, sqrt(12 (var_x + var_y)) (a uniform segment of length L has variance
    L^2 / 12 along itself)."""
    height = 128
    vertical = np.zeros((height, width, 3), np.uint8)
    vertical[:, width // 2:] = 255
    horizontal = np.zeros((height, width, 3), np.uint8)
    horizontal[height // 2:] = 255
    px = _step_profile(blur(vertical), axis=1)[width // 2 - 48:width // 2 + 48]
    py = _step_profile(blur(horizontal), axis=0)[height // 2 - 48:height // 2 + 48]
    sx, sy = _spread(px), _spread(py)
    return {"extent_x": _edge_extent(px), "extent_y": _edge_extent(py), "std_x": sx, "std_y": sy,
            "moment_length": math.sqrt(12.0 * (sx * sx + sy * sy))}


def motion_length_at(width: int, severity: int, degrees: float) -> tuple[float, float]:
    """(Euclidean length from the extent along the major axis, from the second moment) at a forced angle.

    Along its major axis a segment at angle a advances max(|cos a|, |sin a|) px per px of its length, so
    the Euclidean length is the major-axis extent divided by that."""
    op = FAMILIES["motion_blur"].op
    s = smear(width, lambda im: op(im, FAMILIES["motion_blur"].value(severity), ForcedAngle(degrees), width / 1600))
    a = math.radians(degrees)
    major = "extent_x" if abs(math.cos(a)) >= abs(math.sin(a)) else "extent_y"
    return s[major] / max(abs(math.cos(a)), abs(math.sin(a))), s["moment_length"]


def low_light_response(width: int, severity: int) -> tuple[float, float]:
    """(exposure: mean linear light out over in, pooled over a ramp of codes 64..255; photon-noise variance
    over the variance a Poisson count with 1200 photo-electrons at white times the exposure has)."""
    exposure = declared("low_light", severity)
    ramp = (64 + np.arange(width) * 192 // width).astype(np.uint8)
    image = np.repeat(np.repeat(ramp[None, :, None], 48, axis=0), 3, axis=2)
    out = srgb_to_linear(corrupt(image, "low_light", severity, frame="physics"))
    measured_exposure = float(out.mean() / srgb_to_linear(image).mean())
    # per input code: the variance of the photo-electron count, pooled against Poisson's (= its mean)
    counts = out.transpose(1, 0, 2).reshape(len(ramp), -1) * 1200.0  # one row per column of the ramp
    codes = ramp.astype(np.int64)
    var_sum = lam_sum = 0.0
    for code in np.unique(codes):
        sample = counts[codes == code].ravel()
        var_sum += sample.var() * sample.size
        lam_sum += exposure * float(srgb_to_linear(code)) * 1200.0 * sample.size
    return measured_exposure, var_sum / lam_sum


def jpeg_reference(image: np.ndarray, quality: int, sampling: int) -> np.ndarray:
    """A libjpeg round trip through OpenCV at `quality` with the given chroma sampling, RGB in and out."""
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, int(quality), cv2.IMWRITE_JPEG_SAMPLING_FACTOR, sampling])
    assert ok
    return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def textured(width: int, seed: int = 0) -> np.ndarray:
    noise = np.random.default_rng(seed).integers(0, 256, (width * 9 // 16, width, 3), dtype=np.uint8)
    return cv2.GaussianBlur(noise, (0, 0), 1.5)


def jpeg_quality(width: int, severity: int) -> int | None:
    """The quality q in 1..100 whose 4:2:0 libjpeg round trip equals the operator's output (None if none)."""
    image = textured(width)[:96]
    out = corrupt(image, "jpeg", severity)
    q = int(declared("jpeg", severity))
    for candidate in [q, *range(1, 101)]:  # the declared value first: one encode when it matches
        if np.array_equal(out, jpeg_reference(image, candidate, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420)):
            return candidate
    return None


def downscale_reference(image: np.ndarray, factor: float) -> np.ndarray:
    h, w = image.shape[:2]
    small = cv2.resize(image, (max(1, round(w / factor)), max(1, round(h / factor))), interpolation=cv2.INTER_AREA)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)


def downscale_factor(width: int, severity: int) -> float | None:
    """The factor (on a 0.05 grid from 1 to 8) whose INTER_AREA down / INTER_LINEAR up round trip equals
    the operator's output: the reduced image's width is round(W / factor), so the grid finds the factor."""
    image = textured(width)[:90]
    out = corrupt(image, "downscale", severity)
    value = float(declared("downscale", severity))
    for candidate in [value, *np.round(np.arange(1.0, 8.0001, 0.05), 2)]:
        if np.array_equal(out, downscale_reference(image, float(candidate))):
            return float(candidate)
    return None


def colour_levels(width: int, severity: int) -> list[int]:
    """Distinct output values per channel of a frame holding every 8-bit code."""
    ramp = (np.arange(width) * 256 // width).astype(np.uint8)
    image = np.stack([np.tile(ramp, (8, 1)), np.tile(ramp[::-1], (8, 1)), np.tile(np.roll(ramp, 77), (8, 1))], -1)
    out = corrupt(image, "color_quant", severity)
    return [len(np.unique(out[..., c])) for c in range(3)]


#: The fog depth prior of spec/README.md: a level camera 1.5 m up with f = 1266 px at 1600 px, the horizon
#: at mid-height, a ceiling plane 8 m up above it, depths capped at 1000 m.
def depth_prior(height: int, width: int) -> np.ndarray:
    focal = 1266.0 * width / 1600.0
    rows = np.arange(height) + 0.5 - height / 2.0
    with np.errstate(divide="ignore"):
        depth = np.where(rows > 0, 1.5 * focal / rows, 8.0 * focal / -rows)
    return np.minimum(np.abs(depth), 1000.0)


def fog_visibility(width: int, severity: int) -> tuple[float, float]:
    """(visibility fitted per row from the contrast a black | white frame keeps, Koschmieder:
    C(d) / C(0) = exp(-3.912 d / V) in linear light, median over rows with 5-95 % contrast; airlight)."""
    height = width * 9 // 16
    image = np.zeros((height, width, 3), np.uint8)
    image[:, width // 2:] = 255
    out = srgb_to_linear(corrupt(image, "fog", severity))
    contrast = out[:, -1, 1] - out[:, 0, 1]
    depth = depth_prior(height, width)
    usable = (contrast > 0.05) & (contrast < 0.95)
    visibility = -3.912 * depth[usable] / np.log(contrast[usable])
    airlight = out[usable, 0, 1] / (1.0 - contrast[usable])
    return float(np.median(visibility)), float(np.median(airlight))


def _checker(width: int) -> np.ndarray:
    h = width * 9 // 16
    y, x = np.mgrid[0:h, 0:width]
    return np.repeat((((x + y) % 2) * 255).astype(np.uint8)[..., None], 3, axis=2)


def raindrop_coverage(width: int, severity: int, frames: str = "abcdefgh") -> float:
    """Mean share of the frame under drops (drop opacity >= 1/2) on a 1-px checkerboard: a drop shows a
    defocused view, the same behind a black and a white square, so in each 2 x 2 block the white-minus-black
    difference falls to 255 (1 - alpha)."""
    checker = _checker(width)
    h, w = checker.shape[:2]
    shares = []
    for frame in frames:
        out = corrupt(checker, "raindrop", severity, frame=frame)[: h // 2 * 2, : w // 2 * 2, 1].astype(np.int32)
        # in each 2 x 2 block the white squares are (row, column) (0, 1) and (1, 0): the frame is (x + y) % 2 * 255
        white = out[0::2, 1::2] + out[1::2, 0::2]
        black = out[0::2, 0::2] + out[1::2, 1::2]
        shares.append(float((white - black <= 255).mean()))  # 255 (1 - alpha) <= 255 / 2, in sums of two
    return float(np.mean(shares))


def occlusion_coverage(width: int, severity: int) -> list[float]:
    grey = np.full((width * 9 // 16, width, 3), 128, np.uint8)
    return [float((corrupt(grey, "occlusion", severity, frame=f).max(axis=2) == 0).mean()) for f in "abc"]


_MUD_GREEN = (255 + 68) / 2  # halfway between the green frame and the mud's mean green


def mud_coverage(width: int, severity: int) -> list[float]:
    """Share of a pure green frame whose green falls past halfway to the mud's (opacity >= 1/2)."""
    green = np.zeros((width * 9 // 16, width, 3), np.uint8)
    green[..., 1] = 255
    return [float((corrupt(green, "mud_splash", severity, frame=f)[..., 1] < _MUD_GREEN).mean()) for f in "abc"]


def dirt_coverage(width: int, severity: int) -> list[tuple[float, float]]:
    """(dirty share, veil opacity) per frame on a pure blue frame. The veil is measured on the clean part:
    red = 215 x opacity (spec: 0.5 x fraction); the dirt is where red moves from the veiled background by
    more than half the weakest dirt opacity (0.35) would move it towards the dirt's red (150)."""
    blue = np.zeros((width * 9 // 16, width, 3), np.uint8)
    blue[..., 2] = 255
    out = []
    for frame in "abc":
        red = corrupt(blue, "lens_dirt", severity, frame=frame)[..., 0].astype(np.float64)
        veil = float(np.median(red)) / 215.0
        background = 215.0 * veil
        dirty = np.abs(red - background) > 0.5 * 0.35 * (150.0 * (1 - veil) + 215.0 * veil - background)
        out.append((float(dirty.mean()), veil))
    return out


def snow_share(width: int, level: int) -> float:
    """Share of a dark frame whitened by flakes beyond the veil (40 levels above the frame's median, which
    the veil sets), over two frames."""
    grey = np.full((width * 9 // 16, width, 3), 60, np.uint8)
    shares = []
    for frame in "ab":
        out = corrupt(grey, "snow", level, frame=frame).astype(np.float64).mean(axis=2)
        shares.append(float((out > np.median(out) + 40).mean()))
    return float(np.mean(shares))


def dropout_rate(width: int, severity: int, frames: int) -> tuple[int, int]:
    """(frames lost, frames offered) over `frames` samples of six cameras (a lost frame with nothing to
    hold is black)."""
    images = {cam: np.full((2, width, 3), 9, np.uint8) for cam in CAMERAS}
    lost = sum(not out.any() for k in range(frames)
               for out in corrupt_sample(images, "frame_dropout", severity, frame=f"k{k}").values())
    return lost, frames * len(CAMERAS)


def bit_flips(width: int, severity: int, expected_flips: float = 1000.0) -> tuple[int, int]:
    """(bits flipped, bits offered) over enough black 16:9 frames to expect `expected_flips` flips."""
    image = np.zeros((width * 9 // 16, width, 3), np.uint8)
    bits = image.size * 8
    rate = declared("bit_error", severity)
    count = max(1, math.ceil(expected_flips / (rate * bits)))
    flipped = 0
    for k in range(count):
        out = corrupt(image, "bit_error", severity, frame=f"b{k}")  # the frame was black: count its 1 bits
        flipped += int(np.bitwise_count(out.reshape(-1).view(np.uint64)).sum(dtype=np.int64))
    return flipped, count * bits


# --- tests ------------------------------------------------------------------------------------------------------


def within(measured: float, expected: float, rel: float) -> bool:
    return abs(measured / expected - 1.0) <= rel


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("severity", SEVERITIES)
def test_gaussian_noise_sigma(width, severity):
    """std(out - 128) on mid-grey equals that of clip(128 + round(sigma z)) within 1 % (sigma x 1.25 is off
    by 25 %; the sampling error of 4 M samples is 0.04 %)."""
    measured, expected = noise_sigma(width, severity)
    assert within(measured, expected, 0.01), (declared("gaussian_noise", severity), measured, expected)


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("severity", SEVERITIES)
def test_gaussian_blur_sigma(width, severity):
    """The line spread of a step edge has the declared sigma within 10 % (measured 0.98-1.02 x, S1 at 800 px
    too: sigma 0.25, which a Gaussian sampled at whole pixels realised as 0.026 before spec 4.0.0); from
    sigma 1 px the 10-90 % rise is 2.563 sigma within 10 %."""
    sigma = declared("gaussian_blur", severity, width)
    moment, rise = blur_sigma(width, severity)
    assert within(moment, sigma, 0.10), (sigma, moment)
    if sigma >= 1.0:
        assert within(rise, sigma, 0.10), (sigma, rise)


ANGLES = (0.0, 22.5, 45.0, 67.5, 112.5, 135.0, 157.5)


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("degrees", ANGLES)
def test_motion_blur_length_at_every_angle(width, degrees):
    """The smear is a segment of the declared Euclidean length in the drawn direction: its extent along the
    major axis over max(|cos|, |sin|) within 5 % at every severity (the old digital line of L samples was
    1.41 L long at 45 degrees), and from 7 px up its second moment, sqrt(12 var), within 10 %."""
    for severity in SEVERITIES:
        length = declared("motion_blur", severity, width)
        extent, moment = motion_length_at(width, severity, degrees)
        assert within(extent, length, 0.05), (severity, length, extent)
        if length >= 7:
            assert within(moment, length, 0.10), (severity, length, moment)


@pytest.mark.parametrize("width", WIDTHS)
def test_motion_blur_length_through_the_public_api(width):
    """With the seeded direction (unknown to the test) the second-moment length is the declared one within
    10 % from 7 px up, in three realisations per severity, and the realisations point different ways."""
    directions = set()
    for severity in SEVERITIES:
        length = declared("motion_blur", severity, width)
        if length < 7:
            continue
        for frame in ("a", "b", "c"):
            s = smear(width, lambda im, sev=severity, fr=frame: corrupt(im, "motion_blur", sev, frame=fr))
            assert within(s["moment_length"], length, 0.10), (severity, frame, length, s)
            directions.add(round(math.degrees(math.atan2(s["std_y"], s["std_x"]))))
    assert len(directions) > 3


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("severity", SEVERITIES)
def test_low_light_exposure_and_photon_noise(width, severity):
    """In linear light the mean falls to the exposure within 3 %, and the photo-electron count's variance is
    Poisson's (1200 e- at white x exposure) within 10 % (the Anscombe grid adds 1 %, 8-bit output 1-2 %)."""
    exposure, variance_ratio = low_light_response(width, severity)
    assert within(exposure, declared("low_light", severity), 0.03), exposure
    assert abs(variance_ratio - 1.0) <= 0.10, variance_ratio


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("severity", SEVERITIES)
def test_jpeg_is_a_libjpeg_round_trip_at_the_declared_quality(width, severity):
    """Bit-identical to OpenCV's libjpeg at the declared quality with 4:2:0 chroma, and to no other quality;
    a 4:4:4 round trip differs (the chroma really is subsampled)."""
    quality = int(declared("jpeg", severity))
    assert jpeg_quality(width, severity) == quality
    image = textured(width)[:96]
    out = corrupt(image, "jpeg", severity)
    assert not np.array_equal(out, jpeg_reference(image, quality, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444))


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("severity", SEVERITIES)
def test_downscale_factor(width, severity):
    """Equal to INTER_AREA down by the declared factor and INTER_LINEAR back; the first factor on a 0.05
    grid that reproduces it is the declared one."""
    assert downscale_factor(width, severity) == pytest.approx(declared("downscale", severity))


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("severity", SEVERITIES)
def test_color_quant_levels_are_exactly_two_to_the_bits(width, severity):
    bits = int(declared("color_quant", severity))
    assert colour_levels(width, severity) == [2**bits] * 3


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("severity", SEVERITIES)
def test_fog_follows_koschmieder_on_the_depth_prior(width, severity):
    """The visibility fitted row by row from the contrast kept is the declared one within 5 %, the airlight
    0.78 (linear) within 0.01."""
    visibility, airlight = fog_visibility(width, severity)
    assert within(visibility, declared("fog", severity), 0.05), visibility
    assert airlight == pytest.approx(0.78, abs=0.01)


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("severity", SEVERITIES)
def test_raindrop_coverage(width, severity):
    """The share of the frame under drops (opacity >= 1/2), over eight realisations, is the declared
    fraction within 5 % (measured 0.995-1.005 x; 1.11-1.21 x at S1-S3 before spec 4.0.0)."""
    coverage = raindrop_coverage(width, severity)
    assert within(coverage, declared("raindrop", severity), 0.05), coverage


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("severity", SEVERITIES)
def test_occlusion_coverage(width, severity):
    fraction = declared("occlusion", severity)
    assert all(within(c, fraction, 0.02) for c in occlusion_coverage(width, severity))


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("severity", SEVERITIES)
def test_mud_splash_coverage(width, severity):
    fraction = declared("mud_splash", severity)
    assert all(within(c, fraction, 0.05) for c in mud_coverage(width, severity))


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("severity", SEVERITIES)
def test_lens_dirt_coverage_and_veil(width, severity):
    """The dirty share within 12 % of the fraction; the veil over the clean part is 0.5 x fraction within the
    8-bit rounding of 215 x veil (S1: 0.0233 for 0.025; a quarter of it is 0.006)."""
    fraction = declared("lens_dirt", severity)
    for share, veil in dirt_coverage(width, severity):
        assert within(share, fraction, 0.12), share
        assert abs(veil - 0.5 * fraction) <= 0.5 / 215 + 1e-9, veil


@pytest.mark.parametrize("width", WIDTHS)
def test_snow_level_is_ordinal(width):
    """Snow has no outside measurement (its level is ordinal, spec/README.md): the whitened share grows
    strictly with the level."""
    shares = [snow_share(width, level) for level in SEVERITIES]
    assert all(a < b for a, b in zip(shares, shares[1:])), shares


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("severity", SEVERITIES)
def test_frame_dropout_loss_rate(width, severity):
    """Lost frames over 1000 six-camera samples within 4 binomial standard errors of p (S1: 0.016, a
    quarter of p is 0.025)."""
    p = declared("frame_dropout", severity)
    lost, offered = dropout_rate(width, severity, 1000)
    assert abs(lost - p * offered) <= 4 * math.sqrt(offered * p * (1 - p)), (lost / offered, p)


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("severity", SEVERITIES)
def test_bit_error_rate(width, severity):
    """Flipped bits within 4 binomial standard errors of the rate, over enough frames to expect 1000 flips
    (4 standard errors are 13 % of the rate there, a 25 % error is 7.9)."""
    rate = declared("bit_error", severity)
    flipped, bits = bit_flips(width, severity)
    assert abs(flipped - rate * bits) <= 4 * math.sqrt(bits * rate * (1 - rate)), (flipped / bits, rate)


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("severity", SEVERITIES)
def test_blackout_zeroes_exactly_the_declared_cameras(width, severity):
    images = {cam: np.full((9, width, 3), 40 + i, np.uint8) for i, cam in enumerate(CAMERAS)}
    out = corrupt_sample(images, "blackout", severity)
    black = {cam for cam, img in out.items() if not img.any()}
    assert black == set(declared("blackout", severity))
    assert all(np.array_equal(out[c], images[c]) for c in CAMERAS if c not in black)


# --- the table ----------------------------------------------------------------------------------------------


def _table_row(family: str, width: int) -> list[str]:
    cells = []
    for severity in SEVERITIES:
        if family == "gaussian_noise":
            value = noise_sigma(width, severity)[0]
        elif family == "gaussian_blur":
            value = blur_sigma(width, severity)[0]
        elif family == "motion_blur":
            lengths = [motion_length_at(width, severity, d)[0] for d in ANGLES]
            cells.append(f"{min(lengths):.3g}-{max(lengths):.3g}")
            continue
        elif family == "low_light":
            exposure, variance = low_light_response(width, severity)
            cells.append(f"{exposure:.3f} (var x{variance:.3f})")
            continue
        elif family == "jpeg":
            value = jpeg_quality(width, severity)
        elif family == "downscale":
            value = downscale_factor(width, severity)
        elif family == "color_quant":
            value = colour_levels(width, severity)[0]
        elif family == "fog":
            value = fog_visibility(width, severity)[0]
        elif family == "snow":
            value = snow_share(width, severity)
        elif family == "frame_dropout":
            lost, offered = dropout_rate(width, severity, 1000)
            value = lost / offered
        elif family == "bit_error":
            flipped, bits = bit_flips(width, severity)
            value = flipped / bits
        elif family == "raindrop":
            value = raindrop_coverage(width, severity)
        elif family == "occlusion":
            value = float(np.mean(occlusion_coverage(width, severity)))
        elif family == "mud_splash":
            value = float(np.mean(mud_coverage(width, severity)))
        elif family == "lens_dirt":
            share = dirt_coverage(width, severity)
            cells.append(f"{np.mean([s for s, _ in share]):.4f} (veil {np.mean([v for _, v in share]):.4f})")
            continue
        elif family == "blackout":
            images = {cam: np.full((2, width, 3), 40, np.uint8) for cam in CAMERAS}
            out = corrupt_sample(images, family, severity)
            value = "+".join(c.replace("CAM_", "") for c in CAMERAS if not out[c].any())
        cells.append(f"{value:.4g}" if isinstance(value, float) else str(value))
    return cells


if __name__ == "__main__":  # pragma: no cover - prints the declared-versus-measured table
    for name, fam in FAMILIES.items():
        values = ", ".join("+".join(c.replace("CAM_", "") for c in v) if isinstance(v, tuple) else f"{v:g}"
                           for v in fam.values)
        print(f"| {name} | {values} | " + " / ".join(_table_row(name, 1600)) + " | "
              + " / ".join(_table_row(name, 800)) + " |")
