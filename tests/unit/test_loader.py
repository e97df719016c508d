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


def test_frame_dropout_span_with_its_scene_history_delivers_the_full_runs_images():
    """A span that starts mid-scene (an adaptive unit, a replay), given the scene's frames before it, delivers
    the images a run from the scene's start delivers, bit for bit, without decoding the history; without it,
    a frame held from before the span is black instead (so the test sees the case it guards)."""
    frames = make_frames(30, scenes=2)
    full = {s.frame.token: {c: s[c] for c in CAMERAS} for s in samples(frames, "frame_dropout", 5, seed=3,
                                                                        decode=Decoder())}
    differ = 0
    for start in range(len(frames)):
        first = next(i for i, f in enumerate(frames) if f.scene_token == frames[start].scene_token)
        decode = Decoder()
        got = next(samples(frames[start:start + 1], "frame_dropout", 5, seed=3, decode=decode,
                           history=frames[first:start]))
        for cam in CAMERAS:
            assert np.array_equal(got[cam], full[got.frame.token][cam]), (start, cam)
        assert len(decode.calls) <= len(CAMERAS)  # the history's frames are never decoded
        alone = next(samples(frames[start:start + 1], "frame_dropout", 5, seed=3, decode=Decoder()))
        differ += any(not np.array_equal(alone[c], full[alone.frame.token][c]) for c in CAMERAS)
    assert differ > 0


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


FRONT3 = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT")


def _equals_clean_by_pixels(sample, cameras) -> bool:
    """The ground truth the structural predicate must match: every read camera's delivered image is the clean one
    (the synthetic images differ between frames and cameras, so equal pixels mean the same source)."""
    return all(np.array_equal(sample[c], Decoder().image(sample.frame.token, c)) for c in cameras)


@pytest.mark.parametrize(("cameras", "reusable"), [
    (FRONT3, {1: True, 2: True, 3: True, 4: False, 5: False}),  # S1-S3 black out rear cameras only
    (CAMERAS, dict.fromkeys(range(1, 6), False)),  # every severity blacks out a camera it reads
    (("CAM_BACK",), {1: False, 2: True, 3: False, 4: True, 5: True}),
    ((), dict.fromkeys(range(1, 6), True)),  # reads nothing: every sample equals clean on what it reads
])
def test_blackout_equals_clean_per_severity_without_decoding(cameras, reusable):
    for severity, expected in reusable.items():
        decode = Decoder()
        for sample in samples(make_frames(3), "blackout", severity, seed=0, decode=decode):
            calls = len(decode.calls)
            assert sample.equals_clean(cameras) is expected, (cameras, severity)
            assert len(decode.calls) == calls  # decided from the cell alone: nothing decoded, no pixel compared
            assert _equals_clean_by_pixels(sample, cameras) is expected


@pytest.mark.parametrize("cameras", [FRONT3, CAMERAS, ("CAM_FRONT",)])
def test_frame_dropout_equals_clean_exactly_where_no_read_camera_was_dropped(cameras):
    decode = Decoder()
    seen = []
    for sample in samples(make_frames(40, scenes=2), "frame_dropout", 3, seed=1, decode=decode):
        calls = len(decode.calls)
        got = sample.equals_clean(cameras)
        assert len(decode.calls) == calls  # from the dropout state (source frames) alone: nothing decoded
        seen.append((got, _equals_clean_by_pixels(sample, cameras)))
    assert all(got == truth for got, truth in seen)
    assert {got for got, _ in seen} == {True, False}  # at S3 (p = 0.3) both happen in 40 frames


@pytest.mark.parametrize("family", ["clean", "null", "blind", "ego_noise", "ego_blind", "jpeg", "occlusion",
                                    "mud_splash"])
def test_other_cells_never_equal_clean_for_a_planner_that_reads_cameras(family):
    from pytest_drivedegrade.loader import may_equal_clean

    severity = 0 if family in ("clean", "null", "blind", "ego_blind") else 2
    for sample in samples(make_frames(2), family, severity, seed=0, decode=Decoder()):
        assert not sample.equals_clean(FRONT3)
    assert not may_equal_clean(family, severity, FRONT3)
    # a camera-less planner reads nothing a ladder family changes; the controls and ego cells stay excluded
    assert may_equal_clean(family, severity, ()) is (family in ("jpeg", "occlusion", "mud_splash"))
