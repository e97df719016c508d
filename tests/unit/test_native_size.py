"""Native geometry (SPEC section 8): every family, at every severity, delivers each camera at its stored size, so
a planner's calibration stays valid; also for odd sizes that no scale factor divides evenly."""

from __future__ import annotations

import numpy as np
import pytest

from pytest_drivedegrade import FAMILIES, corrupt_sample
from pytest_drivedegrade.constants import CAMERAS

SIZES = {cam: ((450, 800), (900, 1600), (201, 357), (450, 800), (97, 161), (450, 800))[i]
         for i, cam in enumerate(CAMERAS)}


@pytest.fixture(scope="module")
def sample() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(3)
    return {cam: rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for cam, (h, w) in SIZES.items()}


@pytest.mark.parametrize("family", list(FAMILIES))
@pytest.mark.parametrize("severity", [1, 2, 3, 4, 5])
def test_every_family_keeps_each_cameras_stored_size(sample, family, severity):
    previous = {cam: np.zeros_like(img) for cam, img in sample.items()}
    out = corrupt_sample(sample, family, severity, seed=1, frame="tok", previous=previous)
    assert set(out) == set(sample)
    for cam, img in out.items():
        assert img.shape == sample[cam].shape and img.dtype == np.uint8, (family, severity, cam, img.shape)
