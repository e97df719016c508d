"""Frictions a newcomer met in the first hour (issue 41), each fixed where it bit."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from pytest_drivedegrade.data.world import build
from pytest_drivedegrade.progress import Sink

ROOT = Path(__file__).resolve().parents[2]


def test_a_progress_that_is_not_a_sink_fails_before_any_work(tmp_path):
    """planners/train_camera_cnn.py passed progress=print: it crashed mid-build, leaving .world-tmp-<pid>."""
    with pytest.raises(TypeError, match=r"takes a pytest_drivedegrade\.progress\.Sink .*got <built-in function print>"):
        build.ensure_default_world(tmp_path, progress=print)  # type: ignore[arg-type]
    assert list(tmp_path.iterdir()) == []


def test_a_failed_world_build_leaves_no_temporary_folder(tmp_path, monkeypatch):
    def broken(out, **kwargs):
        Path(out).mkdir(parents=True)
        (Path(out) / "half").write_text("x")
        raise RuntimeError("the build broke")

    monkeypatch.setattr(build, "write_world", broken)
    with pytest.raises(RuntimeError, match="the build broke"):
        build.ensure_default_world(tmp_path, progress=Sink.silent())
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".world-tmp-")]


def test_the_camera_cnn_training_script_passes_a_sink(tmp_path, monkeypatch):
    import pytest_drivedegrade.data.world as world

    seen = []

    def record(cache_root, *, train_images=False, progress=None):
        seen.append(progress)
        raise SystemExit(0)

    monkeypatch.setattr(world, "ensure_default_world", record)
    spec = importlib.util.spec_from_file_location("train_camera_cnn", ROOT / "planners" / "train_camera_cnn.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    with pytest.raises(SystemExit):
        module.main(["--cache-root", str(tmp_path)])
    assert len(seen) == 1 and isinstance(seen[0], Sink)


def test_a_planner_file_outside_the_folder_says_where_the_rootdir_and_cache_went(tmp_path):
    from pytest_drivedegrade.plugin.plannercheck import rootdir_note

    clone, elsewhere = tmp_path / "clone", tmp_path / "law"
    note = rootdir_note(clone, elsewhere, elsewhere / "law_planner.py", None)
    assert note.startswith(f"the planner file lies outside {clone}, so pytest took {elsewhere} as its rootdir")
    assert f"the cache (the world, the floor) is {elsewhere / '.pytest_cache'} and no ini file's settings" in note
    assert f"--rootdir {clone}" in note
    assert rootdir_note(clone, clone, elsewhere / "p.py", clone / "pyproject.toml") == ""  # pinned: nothing moved
    assert rootdir_note(clone, clone / "planners", clone / "planners" / "p.py", None) == ""
    assert rootdir_note(clone, elsewhere, None, None) == ""  # conftest mode


def test_a_label_names_a_unit_once():
    from pytest_drivedegrade.corruptions.ladder import FAMILIES

    assert FAMILIES["jpeg"].describe(4) == "JPEG quality = 12"  # was "JPEG quality = 12 quality"
    assert FAMILIES["color_quant"].describe(4) == "bits per channel = 3"
    assert FAMILIES["raindrop"].describe(4) == "frame fraction under drops = 0.16"
    assert FAMILIES["gaussian_blur"].describe(4) == "defocus sigma = 3.5 px"  # a unit the name lacks stays
    for fam in FAMILIES.values():
        parameter, _, rest = fam.describe(4).partition(" = ")
        words = rest.split()[1:]
        assert not words or words[0].strip(",") not in parameter.split(), fam.describe(4)


def test_the_s4_montage_has_no_unlabelled_black_tile():
    import numpy as np

    from pytest_drivedegrade.corruptions.ladder import FAMILIES
    from pytest_drivedegrade.corruptions.preview import montage

    image = np.full((90, 160, 3), 200, np.uint8)
    grid = montage(image, severity=4, frame="f", width=160)
    tile_h, tile_w = grid.shape[0] // 3, grid.shape[1] // 6
    assert (len(FAMILIES) + 1) < 18  # one place of the 6 x 3 grid is left over
    last = grid[2 * tile_h:, 5 * tile_w:]
    bar = 2 * 18 + 6
    assert (last[bar:] == 128).all()  # grey, not black (which reads as a blacked-out camera)
    assert (last[:bar] > 200).any()  # and labelled


def test_a_retention_above_the_top_is_shown_not_clipped():
    from pytest_drivedegrade.report.plots import RETENTION_TOP, upper_limit

    assert upper_limit([0.4, 0.95, 1.02, None, float("nan")]) == RETENTION_TOP
    assert upper_limit([1.110]) == 1.15  # occlusion S1 of camera_cnn on 24 frames was cut off at 1.08
    assert upper_limit([0.9, 1.379]) == 1.45  # an interval's high end too
    assert upper_limit([]) == RETENTION_TOP


def test_a_run_of_another_size_says_it_replaces_the_certificate_in_its_folder(tmp_path):
    import json

    from pytest_drivedegrade.plugin.plannercheck import replaced_note

    folder = tmp_path / "camera_cnn"
    assert replaced_note(folder, 48, 17) == ""  # nothing there
    folder.mkdir()
    (folder / "certificate.json").write_text(json.dumps({"dataset": {"frames": 204}, "cells": [{}] * 89}))
    assert replaced_note(folder, 204, 89) == ""  # the same run again
    assert replaced_note(folder, 48, 17) == (
        f"{folder} holds the certificate of another run (204 frames, 89 cells); this run (48 frames, 17 cells) "
        "replaces it: pass another --drivedegrade-report to keep both")


def test_the_training_how_to_example_trains_and_its_planner_meets_the_contract(small_world, tmp_path):
    """planners/examples/tiny_camera.py, as the how-to runs it (on the small world's val images, which are
    rendered; the how-to trains on the embedded world's train split)."""
    import numpy as np

    from pytest_drivedegrade.data.nuscenes import NuScenesReader
    from pytest_drivedegrade.planning import validate_output

    spec = importlib.util.spec_from_file_location("tiny_camera", ROOT / "planners" / "examples" / "tiny_camera.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    out = tmp_path / "tiny.pt"
    assert module.main(["--data", str(small_world), "--split", "val", "--steps", "3", "--out", str(out)]) == 0
    import torch

    model = module.TinyCamera()
    model.load_state_dict(torch.load(out, weights_only=True))
    planner = module.TinyCameraPlanner(model)
    reader = NuScenesReader(small_world, split="val")
    frame = reader.scorable_frames(limit=1)[0]
    plan = planner.predict({"CAM_FRONT": reader.load_image(frame.cameras["CAM_FRONT"])}, frame.ego, frame.command)
    assert validate_output(plan, frame.token).shape == (6, 2) and np.isfinite(plan).all()


def test_no_property_test_has_a_deadline():
    """A property test judged by the clock fails on a busy machine (issue 41): the suite's profile has none."""
    from hypothesis import settings

    assert settings().deadline is None
