"""How a planner is called on one cell: frames in scene order through the loader, ``reset`` at each scene, the
context when ``predict`` takes it, batches, reuse of the clean plan, timeouts, and each failure named per frame
(the planner's, or the data's: `DataFault`). `run_cell` scores what comes out into the cell's record.

`run.RunContext` is what a run is (its settings, frames and caches) and hands itself in as the `Source`.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import replace
from functools import partial
from typing import Protocol

import numpy as np

from .cells import REAR_BLACKOUT_SEVERITY, CellRecord, RecordBuilder, cell_id, is_ego
from .constants import CAMERAS, COMMAND_SWAP, HORIZON_STEPS
from .data.context import FrameContext
from .data.frame import Command, EgoStatus, Frame
from .data.junctions import Alternative
from .errors import DataError, DriveDegradeError, PlannerOutputError
from .loader import CellSample, ahead, may_equal_clean, samples
from .metrics.pdms import PreparedFrame
from .metrics.trajectory import FrameTruth, bit1_density, frame_metrics
from .pacing import PDMS_SPAN, CellPdms, Scorer, opencv_share, prefetch_depth, process_key
from .planning import CallStyle, Planner, call_style, planner_cameras, planner_poses, to_numpy, validate_output
from .settings import RunSettings
from .timelimit import PlannerTimeout, time_limit


class DataFault(str):
    """Why a frame failed when the fault is the data's (a missing, empty, truncated, undecodable or wrong-size
    image), not the planner's: counted in `CellRecord.data_errors`, apart from the contract failures."""


#: One frame's outcome in a stream: its sample and the validated plan, or why the frame failed (a `DataFault`
#: when the data is to blame).
FrameResult = tuple[CellSample, "np.ndarray | str"]
#: A sample -> the clean plan to reuse for it, or None to call the planner.
Reuser = Callable[[CellSample], "np.ndarray | None"]


class Source(Protocol):
    """What a stream reads from its run (`run.RunContext`): the settings and the per-process caches."""

    @property
    def settings(self) -> RunSettings: ...

    def decode(self, frame: Frame, camera: str) -> np.ndarray: ...

    def context_of(self, frame: Frame) -> FrameContext: ...

    def pdms_frame(self, frame: Frame, poses: int = ...) -> PreparedFrame: ...

    def frame_truth(self, frame: Frame) -> FrameTruth: ...

    def alternative_of(self, frame: Frame) -> Alternative | None: ...


#: The reuse control: the second reused frame of a cell (the first with a skipped call before it, where a planner
#: that keeps state would show it) and every this-many-th after it are also predicted, and the plan must equal the
#: reused clean plan bit for bit (frame-by-frame calls only: a batch of one may round differently from the batch
#: that computed clean). A cell that reuses r frames makes (r + 6) // 8 such calls.
REUSE_CONTROL_EVERY = 8


def may_reuse(settings: RunSettings, planner: Planner, family: str, severity: int) -> bool:
    """Whether frames of this cell may reuse the clean plans: reuse is on (not --drivedegrade-no-reuse), the
    planner is deterministic and has no ``reset`` (`CallStyle.reuses`), it cannot see the stream (its
    ``predict`` takes no ``context``, so no scene token to track scenes by) or it declares ``deterministic =
    True`` itself, and some frame of the cell may deliver the clean images on every camera the planner declares
    (`loader.may_equal_clean`). Never blackout S3 (`REAR_BLACKOUT_SEVERITY`): when it blacks out only cameras the
    planner does not read, it is the rear cameras' null control and must call the planner to catch an undeclared
    read. The reuse control (`stream`) checks the rest: a planner that keeps state without a context."""
    if (family, severity) == ("blackout", REAR_BLACKOUT_SEVERITY):
        return False
    style = call_style(planner)
    blind_to_stream = not style.takes_context or getattr(planner, "deterministic", None) is not None
    return settings.reuse and style.reuses and blind_to_stream and \
        may_equal_clean(family, severity, planner_cameras(planner))


def _reuse_control(source: Source, planner: Planner, sample: CellSample, style: CallStyle,
                   reused: np.ndarray) -> np.ndarray | str:
    """A reused frame predicted anyway: the reused plan when the call returns it bit for bit, else the frame's
    failure saying that reuse does not hold for this planner (or why the call failed)."""
    got = _predict(source, planner, sample, style)
    if isinstance(got, str):  # the call itself failed: that failure is the frame's
        return got
    if np.array_equal(got, reused):
        return reused
    diff = float(np.nanmax(np.abs(got - reused))) if np.isfinite(got).any() else float("nan")
    return (f"frame {sample.frame.token!r}: reuse control failed: predict() on inputs equal to the clean cell's "
            f"returned another plan than clean's (max abs difference {diff:.6g} m), so its clean plans cannot "
            "stand for its calls: its plans depend on call history; give it a reset(), declare deterministic = "
            "False, or run with --drivedegrade-no-reuse")


def reuser(clean: CellRecord, unread: tuple[str, ...]) -> Reuser:
    """A sample -> the clean plan to reuse for it, or None to predict (see `stream`), in a cell that may reuse."""
    if clean.family != "clean":
        raise DriveDegradeError(f"the plans to reuse must be the clean cell's, not {clean.cell!r}'s")
    cameras = tuple(c for c in CAMERAS if c not in unread)
    index = {token: i for i, token in enumerate(clean.frames)}

    def reuse(sample: CellSample) -> np.ndarray | None:
        i = index.get(sample.frame.token)
        if i is None or not sample.equals_clean(cameras) or not np.isfinite(clean.plans[i]).all():
            return None
        sample.reused_from = i
        return np.array(clean.plans[i], dtype=np.float64, copy=True)

    return reuse


def stream(source: Source, planner: Planner, family: str, severity: int, frames: list[Frame], *,
           unread: tuple[str, ...], seed: int, clean: CellRecord | None = None,
           history: Sequence[Frame] = ()) -> Iterator[FrameResult]:
    """Feed `frames` (scene by scene, in order) through the planner under one cell's corruption: for each frame
    its sample and the validated plan, or the one-line reason the frame failed.

    ``reset(scene_token)`` runs before the first frame of each scene, so no state crosses a scene or a cell; the
    context goes in when ``predict`` takes it; each call gets private copies of its inputs, and a write into an
    input image fails the frame naming the camera.

    With `clean` (the run's clean cell), a deterministic planner without ``reset`` is not called on a frame whose
    sample equals clean on every camera it reads (`CellSample.equals_clean`, decided structurally): the clean
    plan is yielded instead (bit for bit what the call would return) and the sample is marked (``reused_from``:
    its index in clean). A frame that failed in clean is called again. On frame-by-frame calls, the second
    reused frame and every `REUSE_CONTROL_EVERY`-th after it are predicted as well (the reuse control): a plan
    that is not the reused one bit for bit fails the frame, naming why. `history`: see `loader.samples`.
    """
    style = call_style(planner)
    reuse = reuser(clean, unread) if clean is not None and may_reuse(source.settings, planner, family, severity) \
        else _predict_every_frame
    feed = ((s, reuse(s)) for s in samples(frames, family, severity, seed=seed, decode=source.decode, unread=unread,
                                           history=history))
    pairs = ahead(feed, _declared(planner), prefetch_depth(source.settings), wanted=_is_none)
    if source.settings.batch > 1 and not style.resets and callable(getattr(planner, "predict_batch", None)):
        yield from _stream_batched(source, planner, pairs)
        return
    scene, reuses = None, 0
    for sample, reused in pairs:
        frame = sample.frame
        if reused is not None:  # a reusing planner has no reset, so no scene is skipped
            reuses += 1
            controlled = reuses % REUSE_CONTROL_EVERY == 2
            yield sample, _reuse_control(source, planner, sample, style, reused) if controlled else reused
            continue
        if style.resets and frame.scene_token != scene:
            try:
                with _calling([sample]):
                    getattr(planner, "reset")(frame.scene_token)  # noqa: B009 - optional: not in the protocol
            except Exception as exc:  # noqa: BLE001 - the planner's failure, named, never a crash
                scene = None
                yield sample, (f"frame {frame.token!r}: reset({frame.scene_token!r}) raised "
                               f"{type(exc).__name__}: {exc}")
                continue
        scene = frame.scene_token
        yield sample, _predict(source, planner, sample, style)


def _stream_batched(source: Source, planner: Planner,
                    pairs: Iterator[tuple[CellSample, np.ndarray | None]]) -> Iterator[FrameResult]:
    """`--drivedegrade-batch B`: B frames per ``predict_batch(images, egos, cmds, contexts)`` call, in order; each
    frame's output is checked (and its inputs for writes) as a single prediction's would be. A frame that reuses
    the clean plan skips the batch (B counts the frames predicted) and keeps its place."""
    pending: list[tuple[CellSample, np.ndarray | None]] = []
    todo = 0
    for sample, reused in pairs:
        pending.append((sample, reused))
        todo += reused is None
        if todo == source.settings.batch:
            yield from _flush(source, planner, pending)
            pending, todo = [], 0
    if pending:
        yield from _flush(source, planner, pending)


def _flush(source: Source, planner: Planner,
           pending: list[tuple[CellSample, np.ndarray | None]]) -> Iterator[FrameResult]:
    """The pending frames in order: the reused ones as they are, the others from one batch call."""
    todo = [s for s, reused in pending if reused is None]
    predicted = iter(_predict_batch(source, planner, todo) if todo else ())
    for sample, reused in pending:
        yield (sample, reused) if reused is not None else next(predicted)


def _predict_batch(source: Source, planner: Planner, batch: list[CellSample]) -> Iterator[FrameResult]:
    inputs = [_inputs(source, s, CallStyle(True, False)) for s in batch]
    egos, contexts = [e for e, _ in inputs], [c for _, c in inputs]
    try:
        with _calling(batch), time_limit(source.settings.timeout * len(batch)):
            call = getattr(planner, "predict_batch")  # noqa: B009 - optional: not in the Planner protocol
            raw = call([s.view for s in batch], egos, [command_of(s, source) for s in batch], contexts)
        raw = to_numpy(raw)
        if len(raw) != len(batch):
            raise PlannerOutputError(f"predict_batch() returned {len(raw)} plans for {len(batch)} frames")
    except PlannerOutputError as exc:
        for s in batch:
            yield s, _data_fault(s) or f"frame {s.frame.token!r}: {exc}"
        return
    except Exception as exc:  # noqa: BLE001 - the planner's failure, on every frame of the batch
        for s in batch:
            yield s, _data_fault(s, exc) or describe_failure(exc, s.frame.token) + f" (in a batch of {len(batch)})"
        return
    for s, plan in zip(batch, raw):
        yield s, _checked(s, plan, planner_poses(planner))


def _inputs(source: Source, sample: CellSample, style: CallStyle) -> tuple[EgoStatus, FrameContext | None]:
    """The call's ego status and context (perturbed in the ego cells): every array in them read-only and a copy
    private to this call, so nothing the planner does to them reaches another frame or cell."""
    frame = sample.frame
    ego = replace(frame.ego, past_xy=_readonly(frame.ego.past_xy))  # private to the call
    context = source.context_of(frame).private() if style.takes_context else None
    if is_ego(sample.family):  # the ego cells: the ego status and the context's CAN bus, perturbed or zeroed
        from .corruptions.ego import perturb

        ego, bus = perturb(ego, None if context is None else context.can_bus, sample.family, sample.severity,
                           seed=source.settings.seed, frame=frame.token)
        context = None if context is None else replace(context, can_bus=bus)
    return ego, context


def command_of(sample: CellSample, source: Source) -> Command:
    """The command the planner is given: the frame's, or in the command cells the one the cell gives
    (`corruptions.command.command_for`; command_swap: the frame's alternative, `Source.alternative_of`)."""
    from .corruptions.command import command_for

    if sample.family == COMMAND_SWAP:
        alt = source.alternative_of(sample.frame)
        return sample.frame.command if alt is None else alt.command
    return command_for(sample.frame.command, sample.family)


def _predict(source: Source, planner: Planner, sample: CellSample, style: CallStyle) -> np.ndarray | str:
    frame = sample.frame
    ego, context = _inputs(source, sample, style)
    command = command_of(sample, source)
    predict: Callable[..., object] = planner.predict
    try:
        with _calling([sample]), time_limit(source.settings.timeout):
            if style.takes_context:
                raw = predict(sample.view, ego, command, context=context)
            else:
                raw = predict(sample.view, ego, command)
    except Exception as exc:  # noqa: BLE001 - any planner failure is this frame's conformance failure
        return _data_fault(sample, exc) or (f"frame {frame.token!r}: {exc}" if isinstance(exc, DataError) else
                                            describe_failure(exc, frame.token))
    return _checked(sample, raw, style.poses)


def _checked(sample: CellSample, raw: object, poses: int = HORIZON_STEPS) -> np.ndarray | str:
    """A returned plan, validated; or the frame's data fault (one the planner caught and planned around is still
    the data's), or the write into an input image, or what is wrong with the plan."""
    fault = _data_fault(sample)
    if fault:
        return fault
    written = sample.written()
    if written:
        return _written_message(sample.frame.token, written)
    try:
        return validate_output(raw, sample.frame.token, poses)
    except PlannerOutputError as exc:
        return str(exc)


class _Clock:
    """Where a cell's seconds go: decode, inject and the input check as the loader measured them (on whichever
    thread made the image), the planner its calls (`CellSample.called`), metrics and pdms the scoring, and the
    cell's wall time in this process, also under this process's own key (`process_key`) for the cost ledger."""

    def __init__(self) -> None:
        self.spent = {"decode": 0.0, "inject": 0.0, "planner": 0.0, "metrics": 0.0, "pdms": 0.0, "check": 0.0}
        self.scoring = {"metrics": 0.0, "pdms": 0.0}  # added to by the scoring thread only
        self.start = time.perf_counter()

    def delivered(self, sample: CellSample) -> None:
        for part in ("decode", "inject", "check"):
            self.spent[part] += sample.seconds[part]
        self.spent["planner"] += sample.called

    def total(self) -> dict[str, float]:
        wall = time.perf_counter() - self.start
        spent = {**self.spent, **{k: self.spent[k] + v for k, v in self.scoring.items()}}
        key = process_key()
        return {**spent, "total": wall, f"wall@{key}": wall, f"planner@{key}": spent["planner"]}


def run_cell(source: Source, planner: Planner, family: str, severity: int, frames: list[Frame], *,
             unread: tuple[str, ...], seed: int, clean: CellRecord | None = None,
             history: Sequence[Frame] = (), pdms: bool = True) -> CellRecord:
    """Every frame of `frames` through the planner under one cell (`stream`), scored into the cell's record;
    per-frame failures become NaN rows plus a message. A frame that reused clean's plan takes clean's whole row
    (the bit-1 density too: what the planner would have read is clean's images), so nothing is scored twice.
    With --drivedegrade-prefetch above 0 a frame is scored on a thread beside the planner's next call, and the
    PDMS of every PDMS_SPAN frames' plans there too; without, the PDMS of the cell's plans at its end, their
    tracking in one batch (`CellPdms`: the same figures either way). `pdms` False leaves the PDMS and EPDMS
    columns NaN (the ego-only floor, whose L2 alone the report reads)."""
    rows = RecordBuilder(cell_id(family, severity), family, severity, [f.token for f in frames],
                         poses=call_style(planner).poses)
    clock = _Clock()
    overlap = prefetch_depth(source.settings) > 0
    cell_pdms = CellPdms(source, rows, frames, PDMS_SPAN if overlap else None, enabled=pdms)
    with opencv_share(), Scorer(overlap) as scorer:
        for i, (sample, result) in enumerate(stream(source, planner, family, severity, frames, unread=unread,
                                                    seed=seed, clean=clean, history=history)):
            clock.delivered(sample)
            scorer.submit(partial(_record, source, rows, i, sample, result, clean, clock, cell_pdms))
    start = time.perf_counter()
    cell_pdms.finish()
    clock.spent["pdms"] += time.perf_counter() - start
    return rows.build(clock.total())


def _record(source: Source, rows: RecordBuilder, i: int, sample: CellSample, result: np.ndarray | str,
            clean: CellRecord | None, clock: _Clock, pdms: CellPdms) -> None:
    """Frame `i`'s row: its failure, clean's row (a reused plan) or its scores; then its PDMS with its span's."""
    if isinstance(result, str):
        rows.fail(str(result), data=isinstance(result, DataFault))
    elif sample.reused_from is not None and clean is not None:
        rows.copy_row(i, clean, sample.reused_from)
    else:
        _score(source, rows, i, sample, result, clock)
    start = time.perf_counter()
    pdms.ready(i)
    clock.scoring["pdms"] += time.perf_counter() - start


def _score(source: Source, rows: RecordBuilder, i: int, sample: CellSample, plan: np.ndarray, clock: _Clock) -> None:
    """Frame `i`'s figures of a validated plan: L2, collisions, jerk, the bit-1 density of what it read."""
    start = time.perf_counter()
    m = frame_metrics(plan[:HORIZON_STEPS], sample.frame, source.frame_truth(sample.frame))  # L2: nuScenes' 3 s
    rows.put(i, plans=plan, l2=m["l2"], collision=m["collision"], collision_vru=m["collision_vru"], jerk=m["jerk"],
             bit1=bit1_density(sample.delivered) if sample.delivered else np.nan)
    if sample.family == COMMAND_SWAP:  # what the following measure needs: the expert's change of path
        alt = source.alternative_of(sample.frame)
        if alt is not None:
            rows.put(i, command_target=alt.path - np.asarray(sample.frame.gt_future, dtype=np.float64))
    clock.scoring["metrics"] += time.perf_counter() - start


@contextlib.contextmanager
def _calling(batch: list[CellSample]) -> Iterator[None]:
    """Time the planner's call on `batch` into `CellSample.called`, net of the images made lazily inside it."""
    made = sum(sum(s.seconds.values()) for s in batch)
    start = time.perf_counter()
    try:
        yield
    finally:
        took = time.perf_counter() - start - (sum(sum(s.seconds.values()) for s in batch) - made)
        for s in batch:
            s.called += took / len(batch)


def _declared(planner: Planner) -> tuple[str, ...]:
    """The cameras to make ahead: the planner's declared ones (none where the declaration is invalid: the cells
    report that)."""
    try:
        return planner_cameras(planner)
    except DriveDegradeError:
        return ()


def _is_none(reused: np.ndarray | None) -> bool:
    return reused is None


def _data_fault(sample: CellSample, exc: BaseException | None = None) -> DataFault | None:
    """The frame's data fault, naming the frame, or None: the first image that could not be produced, a
    non-finite planner input of the data set (`Frame.input_fault`), or, for a call that failed with `exc`, a
    DataError the frame's LiDAR sweep raises when read again here (so a planner cannot pass its own failure off
    as the data's)."""
    token = sample.frame.token
    if sample.data_errors:
        return DataFault(f"frame {token!r}: {sample.data_errors[0]}")
    if sample.frame.input_fault:
        return DataFault(f"frame {token!r}: {sample.frame.input_fault}")
    if isinstance(exc, DataError) and sample.frame.lidar_file:
        from .data.context import load_points

        try:
            load_points(sample.frame.lidar_file)
        except DataError as again:
            return DataFault(f"frame {token!r}: {again}")
    return None


def _predict_every_frame(sample: CellSample) -> None:
    """The reuser of a cell that does not reuse: every frame is predicted."""
    return None


def _written_message(token: str, cameras: list[str]) -> str:
    return (f"frame {token!r}: predict() wrote into its input image of {', '.join(cameras)}; inputs are read-only: "
            "copy before modifying (np.array(img), or tensor.clone() after torch.from_numpy)")


def _readonly(array: np.ndarray) -> np.ndarray:
    out = np.array(array, dtype=np.float64, copy=True)
    out.setflags(write=False)
    return out


def describe_failure(exc: BaseException, frame_token: str) -> str:
    """One line naming the frame and what the planner did wrong."""
    if isinstance(exc, PlannerTimeout):
        return f"frame {frame_token!r}: {exc} (raise --drivedegrade-timeout if this planner is legitimately slow)"
    if isinstance(exc, ValueError) and "read-only" in str(exc):
        return (f"frame {frame_token!r}: predict() wrote to its input image ({exc}); the images are read-only: "
                "copy before modifying (np.array(img))")
    if isinstance(exc, TypeError) and "does not support item assignment" in str(exc):
        return f"frame {frame_token!r}: predict() tried to modify the images mapping ({exc}); it is read-only"
    return f"frame {frame_token!r}: predict() raised {type(exc).__name__}: {exc}"
