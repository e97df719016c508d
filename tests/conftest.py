"""Shared test fixtures: the six real nuScenes frames shipped in tests/data/nuscenes (see its README)."""

from __future__ import annotations

from pathlib import Path

import pytest

DATA = Path(__file__).parent / "data" / "nuscenes"


@pytest.fixture(scope="session")
def nuscenes_frames():
    """camera name -> (path, RGB uint8 1600x900 image) for the one real keyframe."""
    from pytest_drivedegrade.corruptions.preview import camera_of, read_rgb

    frames = {camera_of(p): (p, read_rgb(p)) for p in sorted(DATA.glob("*.jpg"))}
    assert len(frames) == 6, f"expected six camera frames in {DATA}"
    return frames
