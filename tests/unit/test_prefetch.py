"""--drivedegrade-prefetch: `loader.ahead` makes at most N frames ahead of the one handed out, in order; a sample
made ahead delivers, faults and counts exactly as one made lazily; the default depth follows the machine's cores."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from test_loader import Decoder, make_frames

from pytest_drivedegrade.constants import CAMERAS
from pytest_drivedegrade.errors import DataError
from pytest_drivedegrade.loader import ahead, samples
from pytest_drivedegrade.metrics.trajectory import bit1_density
from pytest_drivedegrade.pacing import auto_prefetch, prefetch_depth
from pytest_drivedegrade.settings import RunSettings


class Counted:
    """A stand-in sample: `produce` records that frame `index` was made (slowly, on the prefetch thread)."""

    made: list[int]
    lock = threading.Lock()

    def __init__(self, index: int, made: list[int]) -> None:
        self.index, self.made = index, made

    def produce(self, cameras: tuple[str, ...]) -> None:
        time.sleep(0.002)
        with self.lock:
            self.made.append(self.index)


@pytest.mark.parametrize("depth", [1, 2, 3, 5])
def test_never_more_than_n_frames_are_made_ahead_of_the_one_handed_out(depth):
    made: list[int] = []
    asked: list[int] = []

    def items():
        for k in range(20):
            asked.append(k)
            yield Counted(k, made), k

    got = []
    for _sample, k in ahead(items(), CAMERAS, depth, wanted=lambda k: True):  # type: ignore[arg-type]
        with Counted.lock:
            ahead_now = [m for m in made if m > k]
        assert max(asked) <= k + depth  # drawn (and so submitted) at most N ahead
        assert len(ahead_now) <= depth
        assert k in made  # the frame handed out is made before the caller gets it
        got.append(k)
        time.sleep(0.003)  # the planner's call: the next frames are made meanwhile
    assert got == list(range(20))
    assert sorted(made) == list(range(20))


def test_depth_zero_is_the_lazy_serial_path_and_unwanted_frames_are_not_made():
    made: list[int] = []
    items = [(Counted(k, made), k) for k in range(6)]
    assert [k for _, k in ahead(iter(items), CAMERAS, 0, wanted=lambda k: True)] == list(range(6))  # type: ignore[arg-type]
    assert made == []
    assert [k for _, k in ahead(iter(items), CAMERAS, 2, wanted=lambda k: k % 2 == 0)] == list(range(6))  # type: ignore[arg-type]
    assert sorted(made) == [0, 2, 4]


@pytest.mark.parametrize("family", ["jpeg", "frame_dropout", "null", "fog"])
def test_a_sample_made_ahead_delivers_and_counts_as_a_lazy_one(family):
    frames = make_frames(6, scenes=2)
    lazy = list(samples(frames, family, 4, seed=3, decode=Decoder(), unread=("CAM_BACK",)))
    early = list(samples(frames, family, 4, seed=3, decode=Decoder(), unread=("CAM_BACK",)))
    for a, b in zip(lazy, early):
        b.produce(CAMERAS)
        for cam in ("CAM_FRONT", "CAM_BACK"):  # the planner reads two of the six made
            np.testing.assert_array_equal(a[cam], b[cam])
            assert not b[cam].flags.writeable
        assert sorted(b.delivered) == sorted(a.delivered) == ["CAM_BACK", "CAM_FRONT"]  # the energy: what was read
        assert bit1_density(b.delivered) == bit1_density(a.delivered)
        assert b.written() == [] and b.ahead == 4  # the four unread images are never delivered


def test_a_data_fault_met_ahead_is_raised_and_counted_only_when_read():
    def decode(frame, camera):
        if camera == "CAM_BACK":
            raise DataError(f"truncated JPEG {camera}.jpg")
        return np.zeros((36, 64, 3), np.uint8)

    sample = next(samples(make_frames(1), "jpeg", 2, seed=0, decode=decode))
    sample.produce(CAMERAS)
    assert sample.data_errors == []  # a camera the planner never reads is no fault of the frame
    sample["CAM_FRONT"]
    with pytest.raises(DataError, match="truncated JPEG CAM_BACK.jpg"):
        sample["CAM_BACK"]
    with pytest.raises(DataError):  # read again: raised and counted again, as the lazy path does
        sample["CAM_BACK"]
    assert sample.data_errors == ["truncated JPEG CAM_BACK.jpg"] * 2


@pytest.mark.parametrize(("processes", "cpus", "depth"), [(1, 2, 2), (2, 2, 0), (3, 2, 0), (1, 1, 0), (7, 8, 2)])
def test_the_default_depth_needs_a_core_to_spare(processes, cpus, depth):
    assert auto_prefetch(processes, cpus) == depth


def test_a_given_depth_wins_and_none_follows_the_xdist_workers(monkeypatch):
    assert prefetch_depth(RunSettings(prefetch=3)) == 3
    assert prefetch_depth(RunSettings(prefetch=0)) == 0
    monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", "512")
    assert prefetch_depth(RunSettings()) == 0


def test_the_cost_ledger_gives_each_process_wall_time_and_planner_busy():
    from pytest_drivedegrade.cells import CellRecord, RecordBuilder
    from pytest_drivedegrade.certificate.estimate import overhead_per_prediction
    from pytest_drivedegrade.scoring.records import cost_ledger

    def record(cell, seconds):
        return RecordBuilder(cell, "jpeg", 1, ["a", "b"]).build(seconds)

    first = record("jpeg-s1", {"planner": 3.0, "decode": 1.0, "total": 4.0, "wall@aa": 4.0, "planner@aa": 3.0})
    parts = [record("jpeg-s2", {"planner": 1.0, "total": 2.0, "wall@aa": 2.0, "planner@aa": 1.0}),
             record("jpeg-s2", {"planner": 2.0, "total": 2.0, "wall@bb": 2.0, "planner@bb": 2.0})]
    joined = CellRecord.concat(parts)  # a cell whose scene groups ran in two processes (Ray actors)
    cost = cost_ledger([first, record("jpeg-s3", {"planner": 0.5, "total": 1.0}), joined])
    assert cost["wall"] == 8.0  # the record without wall@ keys (stored before them) adds no process
    assert cost["processes"] == [{"wall": 6.0, "planner_busy": 4.0 / 6.0}, {"wall": 2.0, "planner_busy": 1.0}]
    assert cost["planner_busy"] == pytest.approx(6.0 / 8.0)
    assert cost["cells"]["jpeg-s2"]["wall"] == 4.0
    # estimate: the planner waited wall x (1 - busy) = 2 s over 8 predictions (2 + 2 frames, the joined cell 4)
    assert cost["predictions"] == 8 and overhead_per_prediction(cost) == pytest.approx(2.0 / 8)
    old = cost_ledger([record("jpeg-s3", {"planner": 0.5, "decode": 0.25, "total": 1.0})])
    assert old["wall"] is None and old["planner_busy"] is None and old["processes"] == []
    assert overhead_per_prediction(old) == pytest.approx(0.25 / 2)


class _Prepared:
    """`run.RunContext.pdms_frame` over a world, without a run: each frame prepared once."""

    def __init__(self, reader):
        self.reader, self.cache = reader, {}

    def pdms_frame(self, frame, poses=6):
        from pytest_drivedegrade.metrics.pdms import PreparedFrame

        assert poses == 6  # these plans are six-pose; an 8-pose preparation is `run.RunContext`'s
        if frame.token not in self.cache:
            self.cache[frame.token] = PreparedFrame.of(frame, self.reader.drivable_area(frame),
                                                       lane_map=self.reader.lane_map(frame))
        return self.cache[frame.token]


def _cell_rows(frames, plans):
    from pytest_drivedegrade.cells import RecordBuilder

    rows = RecordBuilder("jpeg-s3", "jpeg", 3, [f.token for f in frames])
    for i, plan in enumerate(plans):
        if np.isfinite(plan).all():
            rows.put(i, plans=plan)
        else:
            rows.fail(f"frame {frames[i].token!r}: failed")
    return rows


def test_a_cells_pdms_scored_in_spans_beside_the_planner_equals_one_batch_at_its_end(small_world):
    """`CellPdms`: spans of any length (the overlap path) give the serial path's PDMS and EPDMS arrays bit for bit,
    EC across a span's edge and a failed frame included; and a plan judged twice (the memo) the same again."""
    from pytest_drivedegrade.cells import PDMS_FIELDS
    from pytest_drivedegrade.data.nuscenes import NuScenesReader
    from pytest_drivedegrade.pacing import CellPdms

    reader = NuScenesReader(small_world, split="all")
    frames = reader.scorable_frames()[:14]
    rng = np.random.default_rng(3)
    plans = np.stack([f.gt_future + rng.normal(0.0, 0.6, (6, 2)) for f in frames])
    plans[5] = np.nan  # a failed frame: no PDMS, and frame 6 has no previous plan for its EC
    names = (*PDMS_FIELDS, "ddc", "lk", "hc", "ec", "epdms")
    results = {}
    for span in (None, 1, 3, 4, 32):
        rows = _cell_rows(frames, plans)
        pdms = CellPdms(_Prepared(reader), rows, frames, span)
        spans_scored = sum(pdms.ready(i) for i in range(len(frames)))
        pdms.finish()
        assert spans_scored == (0 if span is None else len(frames) // span)
        results[span] = {n: rows.arrays[n].tobytes() for n in names}
        if span is not None:  # each frame prepared as its row filled, the failed one too: none left for a span
            assert len(pdms.source.cache) == len(frames)
    assert all(results[span] == results[None] for span in results)
    serial = _cell_rows(frames, plans)
    CellPdms(_Prepared(reader), serial, frames, None).finish()
    assert np.isnan(serial.arrays["pdms"][5]) and np.isfinite(serial.arrays["pdms"][[4, 6]]).all()
    assert np.isnan(serial.arrays["ec"][6]) and np.isfinite(serial.arrays["ec"][7])  # EC needs frame i - 1's plan
    assert len(set(serial.arrays["pdms"].round(6).tolist())) > 3  # the noisy plans score differently


def test_a_plan_judged_again_on_its_frame_comes_from_the_memo_with_the_same_figures(small_world):
    from pytest_drivedegrade.data.nuscenes import NuScenesReader
    from pytest_drivedegrade.metrics.pdms import PreparedFrame, tracked_states

    reader = NuScenesReader(small_world, split="all")
    frame = reader.scorable_frames()[2]
    prepared = PreparedFrame.of(frame, reader.drivable_area(frame), lane_map=reader.lane_map(frame))
    plan = frame.gt_future + np.random.default_rng(0).normal(0.0, 0.5, (6, 2))
    states = tracked_states(plan[None], [prepared.initial])[0]
    first = prepared.judged(plan, states)
    assert prepared.judged(plan.copy(), states) is first  # the same bytes: judged once
    fresh = PreparedFrame.of(frame, reader.drivable_area(frame), lane_map=reader.lane_map(frame))
    result = fresh.score_tracked(plan, states)
    assert (result, fresh.extended(states, result)).__repr__() == first.__repr__()
    other = plan + 1e-9
    assert prepared.judged(other, tracked_states(other[None], [prepared.initial])[0]) is not first


class _Config:
    """The options `plugin.options._prefetch` reads, as a worker's config holds them."""

    def __init__(self, **options: object) -> None:
        self.options = options

    def getoption(self, dest: str, default: object = None) -> object:
        return self.options.get(dest, default)

    def getini(self, dest: str) -> object:
        return None


@pytest.mark.parametrize(("workers_env", "cpus", "depth"), [("2", 2, 0), ("", 2, 2), ("2", 4, 2), ("4", 4, 0)])
def test_an_xdist_worker_counts_its_siblings_though_its_n_reads_none(monkeypatch, workers_env, cpus, depth):
    """xdist hands a worker -n as None: the default depth is read from PYTEST_XDIST_WORKER_COUNT there, so the two
    workers of `-n 2` on two cores run no loading or scoring threads beside their planners."""
    from pytest_drivedegrade.plugin import options

    monkeypatch.setattr("pytest_drivedegrade.pacing.cores", lambda: cpus)
    if workers_env:
        monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", workers_env)
    else:
        monkeypatch.delenv("PYTEST_XDIST_WORKER_COUNT", raising=False)
    assert options._prefetch(_Config(numprocesses=None)) == depth
    assert options._prefetch(_Config(numprocesses=None, drivedegrade_prefetch="3")) == 3
    monkeypatch.delenv("PYTEST_XDIST_WORKER_COUNT", raising=False)
    assert options._prefetch(_Config(numprocesses=cpus)) == 0  # the controller of -n <cores>


def test_the_scorer_keeps_frame_order_and_holds_at_most_its_depth_beside_the_planner():
    """`Scorer`: frames scored on one thread in submission order; `submit` returns while fewer than
    SCORER_DEPTH frames wait and blocks past that (the memory bound); a failure is raised by a later call."""
    from pytest_drivedegrade.pacing import SCORER_DEPTH, Scorer

    gate, done, order = threading.Event(), [], []

    def score(i):
        def run():
            gate.wait(5)
            order.append(i)
        return run

    with Scorer(True) as scorer:
        for i in range(SCORER_DEPTH):
            scorer.submit(score(i))
        assert order == [] and len(scorer.waiting) == SCORER_DEPTH  # nothing scored yet, the caller not held
        threading.Timer(0.2, gate.set).start()
        start = time.perf_counter()
        scorer.submit(score(SCORER_DEPTH))  # one too many: waits for the oldest
        assert time.perf_counter() - start >= 0.15 and order[0] == 0
    assert order == list(range(SCORER_DEPTH + 1))

    def fail():
        raise ValueError("scoring broke")

    with pytest.raises(ValueError, match="scoring broke"), Scorer(True) as scorer:
        scorer.submit(fail)
        for _ in range(SCORER_DEPTH + 1):
            scorer.submit(done.clear)
    with Scorer(False) as serial:  # the serial path scores at once, in the caller's thread
        serial.submit(lambda: done.append(threading.current_thread().name))
    assert done == [threading.current_thread().name]


@pytest.mark.parametrize(("workers_env", "cpus", "threads"),
                         [("2", 2, 1), ("", 2, 2), ("", 16, 16), ("8", 16, 2), ("3", 2, 1), ("", 1, 1), ("2", 5, 2)])
def test_opencv_gets_the_cores_a_process_has_to_itself(monkeypatch, workers_env, cpus, threads):
    """OpenCV's threads in a process running cells: its share of the cores among the xdist workers, at least one:
    the two workers of -n 2 on two cores get one each, one process keeps them all."""
    from pytest_drivedegrade.pacing import opencv_threads

    if workers_env:
        monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", workers_env)
    else:
        monkeypatch.delenv("PYTEST_XDIST_WORKER_COUNT", raising=False)
    assert opencv_threads(cpus) == threads


def test_the_cores_counted_are_those_this_process_may_run_on(monkeypatch):
    """A container or CI job pinned to 2 of a machine's 16 cores: the prefetch depth, OpenCV's share and the world
    build's processes all count the 2 (`settings.cores`), not the 16 `os.cpu_count` reports (which gave two -n 2
    workers 8 OpenCV threads each and a prefetch depth of 2 on cores they did not have)."""
    from pytest_drivedegrade.data.world.tasks import default_workers
    from pytest_drivedegrade.pacing import opencv_threads
    from pytest_drivedegrade.settings import cores

    monkeypatch.setattr("os.cpu_count", lambda: 16)
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: {3, 7}, raising=False)
    monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", "2")
    assert cores() == 2
    assert opencv_threads() == 1 and auto_prefetch(2) == 0 and auto_prefetch(1) == 2
    assert default_workers(100) == 2
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: set(), raising=False)
    assert cores() == 1  # never 0


def test_a_cell_sets_opencv_threads_while_it_runs_and_puts_them_back(monkeypatch):
    """`opencv_share` sets the count for the cell's span only; where the user set $OPENCV_FOR_THREADS_NUM it is
    left as the user made it."""
    import cv2

    from pytest_drivedegrade.pacing import OPENCV_THREADS_ENV, opencv_share

    monkeypatch.delenv(OPENCV_THREADS_ENV, raising=False)
    monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", "2")
    monkeypatch.setattr("pytest_drivedegrade.pacing.cores", lambda: 2)
    before = cv2.getNumThreads()
    try:
        cv2.setNumThreads(3)
        with opencv_share():
            assert cv2.getNumThreads() == 1
        assert cv2.getNumThreads() == 3
        with pytest.raises(RuntimeError), opencv_share():  # put back when the cell raises, too
            raise RuntimeError
        assert cv2.getNumThreads() == 3
        with opencv_share():  # overlapping cells (the floor's on a thread beside one): the last one out restores
            inner = opencv_share()
            inner.__enter__()
        assert cv2.getNumThreads() == 1
        inner.__exit__(None, None, None)
        assert cv2.getNumThreads() == 3
        monkeypatch.setenv(OPENCV_THREADS_ENV, "3")
        with opencv_share():
            assert cv2.getNumThreads() == 3
    finally:
        cv2.setNumThreads(before)


def test_every_family_gives_the_same_bytes_whatever_opencv_threads():
    """What makes `opencv_share` free of consequence for the results: every family at every severity, on a real
    1600 x 900 nuScenes image and at the world's 800 x 450, delivers the same bytes with OpenCV on one thread as
    on four (its parallel loops split rows, never a pixel's arithmetic)."""
    from pathlib import Path

    import cv2

    from pytest_drivedegrade.corruptions.api import corrupt_sample
    from pytest_drivedegrade.corruptions.ladder import FAMILIES
    from pytest_drivedegrade.corruptions.preview import read_rgb

    path = next((Path(__file__).resolve().parents[1] / "data" / "nuscenes").glob("*__CAM_FRONT__*.jpg"))
    full = read_rgb(path)
    images = {"CAM_FRONT": full, "CAM_BACK": cv2.resize(full, (800, 450), interpolation=cv2.INTER_AREA)}
    before = cv2.getNumThreads()
    got: dict[int, dict[tuple[str, int, str], bytes]] = {}
    try:
        for threads in (1, 4):
            cv2.setNumThreads(threads)
            got[threads] = {(family, severity, cam): image.tobytes()
                            for family in FAMILIES for severity in range(1, 6)
                            for cam, image in corrupt_sample(images, family, severity, seed=3, frame="f").items()}
    finally:
        cv2.setNumThreads(before)
    assert len(got[1]) == len(FAMILIES) * 5 * 2
    assert [k for k in got[1] if got[1][k] != got[4][k]] == []
