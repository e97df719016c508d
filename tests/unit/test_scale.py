"""Batches, the cost ledger and the wall-time estimate (SPEC section 9)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from pytest_drivedegrade.certificate.estimate import estimate, overhead_per_prediction
from pytest_drivedegrade.run import RunContext
from pytest_drivedegrade.scoring.records import cost_ledger
from pytest_drivedegrade.settings import RunSettings
from pytest_drivedegrade.stream import REUSE_CONTROL_EVERY

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def world(eleven_scene_world: Path) -> Path:
    """The shared 11-scene world (`conftest.eleven_scene_world`), read only."""
    return eleven_scene_world


@pytest.fixture(scope="module")
def camera_cnn():
    sys.path.insert(0, str(ROOT / "planners"))
    import camera_cnn

    return camera_cnn.CameraCNNPlanner()


def context(world: Path, batch: int) -> RunContext:
    return RunContext.open(RunSettings(data=world, timeout=0.0, batch=batch))


@pytest.mark.parametrize("batch", [4, 16])
def test_batched_plans_equal_per_frame_plans(world, camera_cnn, batch):
    one, many = context(world, 1), context(world, batch)
    assert len(one.frames) > 2 * batch  # several batches and a last partial one
    for family, severity in (("clean", 0), ("fog", 3), ("frame_dropout", 5)):
        a, b = one.run_cell(camera_cnn, family, severity), many.run_cell(camera_cnn, family, severity)
        assert not a.errors and not b.errors
        # float32 sums in another order (mkldnn's batched 1x1 convolution, gemm for gemv): within 1e-5 m
        np.testing.assert_allclose(b.plans, a.plans, rtol=0, atol=1e-5)
    assert many.run_key(camera_cnn)["batch"] == batch and "batch" not in one.run_key(camera_cnn)


def test_a_cell_joined_from_its_scene_groups_is_the_cell_run_at_once(world, camera_cnn):
    """What Ray actors return and the controller joins (`CellRecord.concat`): the same record, bit for bit, but
    for the cost seconds (summed); frame_dropout's state restarts per scene, so whole-scene groups lose nothing."""
    from pytest_drivedegrade.cells import CellRecord
    from pytest_drivedegrade.shards import scene_runs

    ctx = context(world, 1)
    sizes = [len(run) for run in scene_runs(ctx.frames)]
    assert len(sizes) >= 2
    spans = [(sum(sizes[:i]), sum(sizes[:i + 1])) for i in range(len(sizes))]
    for family, severity in (("clean", 0), ("frame_dropout", 5), ("ego_noise", 3)):
        whole = ctx.run_cell(camera_cnn, family, severity).to_builtins()
        parts = [ctx.run_cell(camera_cnn, family, severity, span=s) for s in spans]
        joined = CellRecord.concat(parts).to_builtins()
        assert joined.pop("seconds")["total"] == pytest.approx(sum(p.seconds["total"] for p in parts))
        whole.pop("seconds")
        assert json.dumps(joined, sort_keys=True) == json.dumps(whole, sort_keys=True)  # NaN equal to NaN too
        assert len(joined["frames"]) == sum(sizes)
    parts = [ctx.run_cell(camera_cnn, "clean", 0, span=s) for s in spans[:2]]
    parts[0].errors, parts[1].data_errors = ["frame 'a': planner"], ["frame 'b': data"]
    joined_record = CellRecord.concat(parts)  # failures travel apart: a data fault is never the planner's
    assert (joined_record.errors, joined_record.data_errors) == (["frame 'a': planner"], ["frame 'b': data"])
    with pytest.raises(ValueError, match="only single-seed records of one cell"):
        CellRecord.concat([ctx.run_cell(camera_cnn, "clean", 0, span=spans[0]),
                           ctx.run_cell(camera_cnn, "jpeg", 1, span=spans[1])])


def test_one_ray_actor_runs_each_cell_whole_and_more_actors_split_it_into_scene_groups(world):
    """`RayPool.spans`: with one actor there is no other to balance against, so a cell is one group (each group
    pays its own first frame's loading and last frames' scoring beside no planner call); with two, up to
    GROUPS_PER_ACTOR groups per actor of whole scenes, in frame order, covering the span exactly."""
    from pytest_drivedegrade.raypool import GROUPS_PER_ACTOR, RayOptions, RayPool
    from pytest_drivedegrade.shards import scene_runs

    frames = RunContext.open(RunSettings(data=world)).frames
    scenes = len(scene_runs(frames))
    assert scenes >= 2
    pool = RayPool(None, RayOptions("local"), None, None, None, "p", frames)  # type: ignore[arg-type]
    pool.slots = [object()]  # type: ignore[list-item]
    assert pool.spans((0, len(frames))) == [(0, len(frames))]
    assert pool.spans((2, 9)) == [(2, 9)]
    pool.slots = [object(), object()]  # type: ignore[list-item]
    groups = pool.spans((0, len(frames)))
    assert len(groups) == min(scenes, 2 * GROUPS_PER_ACTOR)
    assert groups[0][0] == 0 and groups[-1][1] == len(frames)
    assert all(a[1] == b[0] for a, b in zip(groups, groups[1:]))  # contiguous, in order
    starts = {frames[a].scene_token for a, _ in groups}
    assert all(frames[a - 1].scene_token != frames[a].scene_token for a, _ in groups[1:])  # whole scenes
    assert len(starts) == len(groups)


class Faulty:
    """A stateless planner whose batch call fails, or returns too few plans, or one bad plan."""

    cameras = ()

    def __init__(self, how: str) -> None:
        self.how = how

    def predict(self, images, ego, cmd):
        return np.zeros((6, 2))

    def predict_batch(self, images, egos, cmds, contexts):
        if self.how == "raise":
            raise RuntimeError("cuda out of memory")
        out = np.zeros((len(images), 6, 2))
        if self.how == "short":
            return out[:-1]
        out[1, 2, 0] = np.nan
        return out


def test_batch_failures_are_named_per_frame(world):
    ctx = context(world, 4)
    n = len(ctx.frames)
    raised = ctx.run_cell(Faulty("raise"), "clean", 0)
    assert len(raised.errors) == n and "predict() raised RuntimeError: cuda out of memory (in a batch of 4)" \
        in raised.errors[0]
    short = ctx.run_cell(Faulty("short"), "clean", 0)
    assert len(short.errors) == n and "predict_batch() returned 3 plans for 4 frames" in short.errors[0]
    nan = ctx.run_cell(Faulty("nan"), "clean", 0)
    assert len(nan.errors) == -(-n // 4) and "is not finite (first at step 2, coordinate 0)" in nan.errors[0]


class Stateful(Faulty):
    def reset(self, scene_token: str) -> None:
        pass

    def predict_batch(self, images, egos, cmds, contexts):
        raise AssertionError("a planner with reset() is never batched")


def test_a_planner_with_reset_is_never_batched(world):
    record = context(world, 8).run_cell(Stateful("none"), "clean", 0)
    assert not record.errors


def test_cost_ledger_counts_predictions_and_seconds(world, camera_cnn):
    ctx = context(world, 1)
    records = [ctx.run_cell(camera_cnn, "clean", 0), ctx.run_cell(camera_cnn, "jpeg", 5)]
    cost = cost_ledger(records)
    n = len(ctx.frames)
    assert cost["predictions"] == 2 * n and cost["reused"] == 0
    assert cost["cells"]["jpeg-s5"]["predictions"] == n and cost["cells"]["jpeg-s5"]["inject"] > 0
    assert cost["cells"]["clean"]["inject"] == 0  # clean injects nothing
    assert cost["seconds"]["planner"] == pytest.approx(sum(c["planner"] for c in cost["cells"].values()))
    assert cost["planner_frames_per_second"] == pytest.approx(2 * n / cost["seconds"]["planner"])


def test_estimate_known_answers():
    from pytest_drivedegrade import FAMILIES
    from pytest_drivedegrade.cells import run_order
    from pytest_drivedegrade.certificate.estimate import DEFAULT_CELLS

    assert DEFAULT_CELLS == len(run_order(FAMILIES, (1, 2, 3, 4, 5))) == 91  # the default run's cells
    rows = estimate(1.8, 6019, [1, 8, 64])
    assert rows[0].predictions == 91 * 6019
    assert rows[0].wall_hours == pytest.approx(91 * 6019 / 1.8 / 3600)  # 84.5 h, as `drivedegrade estimate` prints
    assert rows[1].wall_hours == pytest.approx(rows[0].wall_hours / 8)
    over = overhead_per_prediction({"predictions": 100, "seconds": {"decode": 1.0, "inject": 2.0, "metrics": 0.5,
                                                                    "pdms": 0.5, "check": 1.0, "planner": 50.0}})
    assert over == pytest.approx(0.05)
    with_overhead = estimate(45, 6019, [1], cells=89, overhead=over)[0]
    assert with_overhead.wall_hours == pytest.approx(89 * 6019 * (1 / 45 + 0.05) / 3600)
    with pytest.raises(ValueError):
        estimate(0, 10, [1])


def test_report_shows_the_cost_panel():
    from test_analysis import synthetic_run

    from pytest_drivedegrade.certificate.seal import Provenance
    from pytest_drivedegrade.report.html import render_report
    from pytest_drivedegrade.scoring.analyse import analyse_run

    recs, _ = synthetic_run(8)
    cost = {"predictions": 1234, "reused": 16, "planner_frames_per_second": 50.0,
            "seconds": {"planner": 6.0, "inject": 3.0, "decode": 1.0, "metrics": 0.0, "pdms": 0.0, "check": 0.0},
            "cells": {"clean": {"predictions": 8, "reused": 0}, "blackout-s1": {"predictions": 0, "reused": 8},
                      "frame_dropout-s2": {"predictions": 0, "reused": 8}}}
    html = render_report(analyse_run(recs, n_resamples=20), Provenance("p", "f", "d", "val", "3.0.0"), cost=cost)
    assert "<h2>Cost</h2>" in html and "1234 predictions, and 16 frames that reused the clean plan" in html
    assert "camera the planner reads): blackout-s1 8, frame_dropout-s2 8;" in html and "50.0" in html
    assert "planner (predict)</td><td class=\"n\">6.0</td><td class=\"n\">60.0 %" in html
    assert "<h2>Cost</h2>" not in render_report(analyse_run(recs, n_resamples=20),
                                                 Provenance("p", "f", "d", "val", "3.0.0"))


class Counting:
    """camera_cnn behind a counter of the frames it is asked to plan (predict and predict_batch)."""

    cameras = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT")

    def __init__(self, inner, **attrs) -> None:
        self.inner, self.calls, self.batches = inner, 0, []
        self.__dict__.update(attrs)

    def predict(self, images, ego, cmd):
        self.calls += 1
        return self.inner.predict(images, ego, cmd)

    def predict_batch(self, images, egos, cmds, contexts):
        self.batches.append(len(images))
        return self.inner.predict_batch(images, egos, cmds, contexts)


SAME_FIELDS = ("plans", "l2", "collision", "collision_vru", "jerk", "bit1", "nc", "dac", "ttc", "ep", "comfort",
               "pdms", "map_scored")


def assert_same_record(a, b):
    from pytest_drivedegrade.cells import identical_plans

    for name in SAME_FIELDS:
        assert identical_plans(getattr(a, name), getattr(b, name)), name
    assert a.errors == b.errors and a.frames == b.frames


def test_reuse_skips_predict_where_inputs_equal_clean_and_changes_nothing(world, camera_cnn):
    ctx, planner = context(world, 1), Counting(camera_cnn)
    n = len(ctx.frames)
    clean = ctx.run_cell(planner, "clean", 0)
    assert planner.calls == n and clean.reused == 0
    # blackout S3 blacks out exactly this front planner's unread cameras: it is the rear null control, never reused
    for (family, severity), known in {("blackout", 1): n, ("blackout", 2): n, ("blackout", 3): 0,
                                      ("blackout", 4): 0, ("blackout", 5): 0, ("jpeg", 3): 0,
                                      ("frame_dropout", 3): None}.items():
        assert ctx.reuses_clean(planner, family, severity) is (known != 0)
        planner.calls = 0
        reused = ctx.run_cell(planner, family, severity, clean=clean)
        made = planner.calls
        full = ctx.run_cell(planner, family, severity)
        assert planner.calls - made == n and full.reused == 0  # without the clean record: every frame predicted
        assert_same_record(reused, full)
        controls = (reused.reused + REUSE_CONTROL_EVERY - 2) // REUSE_CONTROL_EVERY  # the reuse control's calls
        assert reused.reused + made - controls == n, family
        if known is None:  # frame_dropout S3: the frames where none of the three front cameras was dropped
            assert 0 < reused.reused < n
        else:
            assert reused.reused == known, (family, severity)
    cost = cost_ledger([clean, ctx.run_cell(planner, "blackout", 1, clean=clean)])
    assert (cost["predictions"], cost["reused"]) == (n, n)
    assert cost["cells"]["blackout-s1"]["predictions"] == 0 and cost["cells"]["blackout-s1"]["reused"] == n


def test_no_reuse_for_nondeterministic_or_stateful_planners_or_when_turned_off(world, camera_cnn):
    ctx = context(world, 1)
    n = len(ctx.frames)
    clean = ctx.run_cell(Counting(camera_cnn), "clean", 0)

    class WithReset(Counting):
        def reset(self, scene_token):
            pass

    for planner in (Counting(camera_cnn, deterministic=False), WithReset(camera_cnn)):
        assert not ctx.reuses_clean(planner, "blackout", 1)
        record = ctx.run_cell(planner, "blackout", 1, clean=clean)
        assert record.reused == 0 and planner.calls == n
    off = RunContext.open(RunSettings(data=world, timeout=0.0, reuse=False))
    planner = Counting(camera_cnn)
    assert not off.reuses_clean(planner, "blackout", 1)
    assert off.run_cell(planner, "blackout", 1, clean=clean).reused == 0 and planner.calls == n
    with pytest.raises(Exception, match="must be True or False"):
        ctx.run_cell(Counting(camera_cnn, deterministic="no"), "blackout", 1, clean=clean)


def test_reused_frames_skip_the_batch(world, camera_cnn):
    ctx, planner = context(world, 4), Counting(camera_cnn)
    n = len(ctx.frames)
    clean = ctx.run_cell(planner, "clean", 0)
    planner.batches = []
    record = ctx.run_cell(planner, "frame_dropout", 3, clean=clean)
    assert planner.calls == 0 and not record.errors
    assert sum(planner.batches) == n - record.reused and 0 < record.reused < n
    assert all(b == 4 for b in planner.batches[:-1]) and 0 < planner.batches[-1] <= 4  # B counts predicted frames
    full = ctx.run_cell(planner, "frame_dropout", 3)
    np.testing.assert_allclose(record.plans, full.plans, rtol=0, atol=1e-5)  # other batch companions: rounding
    planner.batches = []
    blackout = ctx.run_cell(planner, "blackout", 2, clean=clean)
    assert planner.batches == [] and blackout.reused == n
    assert_same_record(blackout, ctx.run_cell(planner, "blackout", 2))


def test_the_device_and_batched_no_reuse_enter_the_run_key(world, camera_cnn):
    def key(**kw):
        ctx = RunContext.open(RunSettings(data=world, frames=4, timeout=0.0, **kw))
        return ctx.run_key(camera_cnn)

    plain = key()
    assert "device" not in plain and "reuse" not in plain  # a CPU run keeps the key (and stored cells) it had
    assert key(device="cuda:0")["device"] == "cuda:0"
    assert key(reuse=False) == plain  # at batch 1 reuse changes no bit
    assert key(batch=8, reuse=False)["reuse"] is False and "reuse" not in key(batch=8)


@pytest.mark.parametrize(("processes", "memory", "budget"), [
    (2, 24 * 2**30, 2 * 2**30),  # this machine under -n 2: capped at 2 GiB
    (1, 4 * 2**30, 2**30),  # a quarter of 4 GiB
    (4, 4 * 2**30, 512 * 2**20),  # a small machine keeps the old 512 MiB floor
    (1, 0, 512 * 2**20),  # memory unknown
])
def test_the_decode_budget_is_a_quarter_of_memory_per_process_within_bounds(processes, memory, budget):
    from pytest_drivedegrade.run import decode_cache_bytes

    assert decode_cache_bytes(processes, memory) == budget


def test_decoded_images_are_kept_up_to_the_budget_and_the_pixels_do_not_depend_on_it(world):
    """A budget of one image keeps one; the next frame's image is decoded again each time, to the same pixels."""
    ctx = RunContext.open(RunSettings(data=world, timeout=0.0))
    one = ctx.frames[0].cameras["CAM_FRONT"]
    ctx._decode_budget = one.width * one.height * 3
    first, second = ctx.decode(ctx.frames[0], "CAM_FRONT"), ctx.decode(ctx.frames[1], "CAM_FRONT")
    assert ctx.decode(ctx.frames[0], "CAM_FRONT") is first  # kept
    again = ctx.decode(ctx.frames[1], "CAM_FRONT")
    assert again is not second and np.array_equal(again, second)  # over budget: decoded again, same pixels
    assert ctx._decoded_bytes == first.nbytes


def test_an_adaptive_runs_key_holds_its_stopping_rule_and_a_full_runs_key_does_not(world, camera_cnn):
    """A changed stopping rule must not reuse cells a former rule stopped; a full run keeps its key."""
    from pytest_drivedegrade.scoring.sequential import METHOD

    full = RunContext.open(RunSettings(data=world, timeout=0.0)).run_key(camera_cnn)
    adaptive = RunContext.open(RunSettings(data=world, timeout=0.0, adaptive=True)).run_key(camera_cnn)
    assert "adaptive_method" not in full and adaptive["adaptive_method"] == METHOD == "betting"
