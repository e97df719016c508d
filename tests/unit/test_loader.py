"""The loader delivers exactly what the public injector API computes, decodes only what the planner reads,
and hands out read-only arrays."""

from __future__ import annotations

import numpy as np
import pytest

from pytest_drivedegrade import FAMILIES, corrupt_sample
from pytest_drivedegrade.constants import CAMERAS, HORIZON_STEPS
from pytest_drivedegrade.data.frame import CameraInfo, Command, EgoStatus, Frame
from pytest_drivedegrade.loader import samples

H, W = 36, 64


def make_frames(n: int, scenes: int = 1) -> list[Frame]:
    cams = {c: CameraInfo(c, f"{c}.jpg", W, H, np.eye(3), (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0)) for c in CAMERAS}
    return [Frame(f"tok{k}", f"scene{k * scenes // n}", k, cams, EgoStatus((5.0, 0.0), (0.0, 0.0), 0.0),
                  Command.STRAIGHT, np.zeros((HORIZON_STEPS, 2)), np.ones(HORIZON_STEPS, bool)) for k in range(n)]


class Decoder:
    """Deterministic synthetic images per (frame, camera), counting decodes."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, str]] = []

    def image(self, token: str, camera: str) -> np.ndarray:
        seed = (int(token[3:]) * 31 + CAMERAS.index(camera)) % 2**32
        return np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8)

    def __call__(self, frame: Frame, camera: str) -> np.ndarray:
        self.calls.append((frame.token, camera))
        return self.image(frame.token, camera)


@pytest.mark.parametrize("family", [f for f in FAMILIES if f != "frame_dropout"])
def test_cell_sample_equals_corrupt_sample(family):
    decode = Decoder()
    frames = make_frames(2)
    for sample in samples(frames, family, 3, seed=5, decode=decode):
        clean = {c: decode.image(sample.frame.token, c) for c in CAMERAS}
        expected = corrupt_sample(clean, family, 3, seed=5, frame=sample.frame.token)
        for cam in CAMERAS:
            np.testing.assert_array_equal(sample[cam], expected[cam])


def test_frame_dropout_runs_along_the_cell_and_resets_per_scene():
    decode = Decoder()
    frames = make_frames(24, scenes=2)
    previous: dict[str, np.ndarray] | None = None
    scene = None
    held = 0
    for sample in samples(frames, "frame_dropout", 5, seed=0, decode=decode):
        if sample.frame.scene_token != scene:
            scene, previous = sample.frame.scene_token, None
        clean = {c: decode.image(sample.frame.token, c) for c in CAMERAS}
        expected = corrupt_sample(clean, "frame_dropout", 5, frame=sample.frame.token, previous=previous)
        delivered = {c: sample[c] for c in CAMERAS}
        for cam in CAMERAS:
            np.testing.assert_array_equal(delivered[cam], expected[cam])
            held += previous is not None and np.array_equal(delivered[cam], previous[cam])
        previous = delivered
    assert held > 0


def test_only_read_cameras_are_decoded_and_arrays_are_read_only():
    decode = Decoder()
    sample = next(samples(make_frames(1), "jpeg", 2, seed=0, decode=decode))
    image = sample["CAM_FRONT"]
    assert sample["CAM_FRONT"] is image and decode.calls == [("tok0", "CAM_FRONT")]
    assert not image.flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        image[0, 0, 0] = 1
    with pytest.raises(TypeError):
        sample["CAM_FRONT"] = image  # type: ignore[index]
    assert list(sample) == list(CAMERAS) and len(sample) == 6
    assert set(sample.delivered) == {"CAM_FRONT"}


def test_null_blind_and_clean_cells():
    decode = Decoder()
    frame = make_frames(1)
    null = next(samples(frame, "null", 0, seed=0, decode=decode, unread=("CAM_BACK", "CAM_BACK_LEFT")))
    assert not null["CAM_BACK"].any() and not null["CAM_BACK_LEFT"].any()
    np.testing.assert_array_equal(null["CAM_FRONT"], decode.image("tok0", "CAM_FRONT"))
    blind = next(samples(frame, "blind", 0, seed=0, decode=decode))
    assert all(not blind[c].any() and blind[c].shape == (H, W, 3) for c in CAMERAS)
    clean = next(samples(frame, "clean", 0, seed=0, decode=decode))
    np.testing.assert_array_equal(clean["CAM_BACK"], decode.image("tok0", "CAM_BACK"))
