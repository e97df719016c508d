"""Loader hooks reach foreign loaders: cv2.imread-like (BGR) and PIL-like callables."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from pytest_drivedegrade import corrupt, corrupt_sample, inject_loader, patch_loader


def test_patch_cv2_imread_corrupts_in_rgb_and_restores(nuscenes_frames):
    path, rgb = nuscenes_frames["CAM_BACK"]
    original = cv2.imread
    with patch_loader(cv2, "imread", "gaussian_noise", 3, seed=5, channel_order="BGR") as injection:
        bgr = cv2.imread(str(path))
        assert cv2.imread(str(path) + ".missing") is None  # a failed read passes through
    assert cv2.imread is original
    expected = corrupt(rgb, "gaussian_noise", 3, seed=5, frame=path.stem, camera="CAM_BACK")
    np.testing.assert_array_equal(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), expected)
    assert injection.corrupted == 1


def test_patch_is_restored_on_error():
    class Loader:
        @staticmethod
        def load(path):
            return np.zeros((4, 4, 3), np.uint8)

    original = Loader.load
    with pytest.raises(RuntimeError):
        with patch_loader(Loader, "load", "jpeg", 1):
            raise RuntimeError("boom")
    assert Loader.load is original


def test_decorator_blackout_and_dropout_per_camera():
    @inject_loader("blackout", 5)
    def load(path):
        return np.full((6, 8, 3), 200, np.uint8)

    assert not load("samples/CAM_FRONT/x.jpg").any()
    assert load("samples/CAM_BACK/x.jpg").all()

    images = {f"n__CAM_FRONT__{k}.jpg": np.full((6, 8, 3), k + 1, np.uint8) for k in range(40)}
    injection = inject_loader("frame_dropout", 5)
    loader = injection(lambda p: images[p])
    delivered, previous = [], None
    for name, img in images.items():
        out = loader(name)
        expected = corrupt_sample({"CAM_FRONT": img}, "frame_dropout", 5, frame=name[:-4],
                                  previous=None if previous is None else {"CAM_FRONT": previous})
        np.testing.assert_array_equal(out, expected["CAM_FRONT"])
        delivered.append(out)
        previous = out
    assert any(np.array_equal(a, b) for a, b in zip(delivered, delivered[1:]))  # some frames held


def test_pil_images_round_trip(nuscenes_frames):
    pil = pytest.importorskip("PIL.Image")
    path, rgb = nuscenes_frames["CAM_FRONT"]
    opened = inject_loader("fog", 4)(pil.open)(str(path))
    assert isinstance(opened, pil.Image) and opened.mode == "RGB"
    np.testing.assert_array_equal(np.asarray(opened), corrupt(rgb, "fog", 4))


def test_non_rgb_images_pass_through_and_are_counted():
    injection = inject_loader("jpeg", 3)
    depth = np.zeros((5, 5), np.float32)
    assert injection(lambda p: depth)("d.png") is depth
    assert injection.skipped == 1 and injection.corrupted == 0
    with pytest.raises(ValueError, match="channel_order"):
        inject_loader("jpeg", 3, channel_order="RGBA")
