"""Running one cell: stream the frames through the loader into the planner, check conformance, score.

`RunContext` is built once per process (the controller, or each xdist worker): the data, the frame list,
the result store. `run_cell` is the whole of a cell's work and returns a `CellRecord` whose per-frame
failures are NaN rows with a message naming the frame.
"""

from __future__ import annotations

import contextlib
import hashlib
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from .cells import PDMS_FIELDS, REAR_BLACKOUT_SEVERITY, RECORD_VERSION, CellRecord, cell_id, is_ego
from .constants import CAMERAS, HORIZON_STEPS
from .corruptions.ladder import FAMILIES, SPEC_VERSION
from .data.content import content_fingerprint
from .data.context import FrameContext
from .data.frame import Frame
from .data.nuscenes import UNSCORED, NuScenesReader
from .errors import DataError, DriveDegradeError, PlannerOutputError
from .loader import CellSample, may_equal_clean, samples
from .metrics.pdms import PreparedFrame
from .metrics.trajectory import bit1_density, frame_metrics
from .planning import CallStyle, call_style, planner_cameras, planner_fingerprint, to_numpy, validate_output
from .settings import Builtin, RunSettings
from .shards import shard_frames


class DataFault(str):
    """Why a frame failed when the fault is the data's (a missing, empty, truncated, undecodable or wrong-size
    image), not the planner's: counted in `CellRecord.data_errors`, apart from the contract failures."""


#: One frame's outcome in a stream: its sample and the validated plan, or why the frame failed (a `DataFault`
#: when the data is to blame).
FrameResult = tuple[CellSample, "np.ndarray | str"]

MAX_MESSAGES = 5  # per cell, the first few per-frame failures are spelled out
#: Decoded clean images kept per process for reuse by later cells (a fixed budget, so memory is flat in the
#: number of frames): 512 MB holds about 500 images at 800 x 450.
DECODE_CACHE_BYTES = 512 * 2**20


class PlannerTimeout(Exception):
    """predict() ran past --drivedegrade-timeout on one frame."""


@contextlib.contextmanager
def time_limit(seconds: float) -> Iterator[None]:
    """Raise PlannerTimeout inside the block after `seconds` (POSIX main thread; a no-op elsewhere or at 0)."""
    usable = seconds > 0 and hasattr(signal, "setitimer") and threading.current_thread() is threading.main_thread()
    if not usable:
        yield
        return

    def expire(signum: int, frame: Any) -> None:
        raise PlannerTimeout(f"predict() took longer than {seconds:g} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


@dataclass
class PlannerInfo:
    cameras: tuple[str, ...]
    fingerprint: str

    @property
    def unread(self) -> tuple[str, ...]:
        return unread_cameras(self.cameras)


def unread_cameras(cameras: tuple[str, ...]) -> tuple[str, ...]:
    """The cameras a planner declares it does not read (blacked out by the null control, never decoded)."""
    return tuple(c for c in CAMERAS if c not in cameras)


#: The frames ``[start, stop)`` of a run's frame list (`RunContext.frames`).
Span = tuple[int, int]


class PlannerElsewhere:
    """A planner built and run in other processes (`raypool`'s actors): what the controller knows of it (its
    name, cameras, fingerprint and call style, as the processes that built it reported them) and the one thing
    it does, a cell on a span of frames. `RunContext.run_cell` hands such a planner its cells."""

    @property
    def name(self) -> str:
        raise NotImplementedError

    @property
    def cameras(self) -> tuple[str, ...]:
        raise NotImplementedError

    @property
    def info(self) -> PlannerInfo:
        raise NotImplementedError

    @property
    def style(self) -> CallStyle:
        raise NotImplementedError

    def run_cell(self, context: RunContext, family: str, severity: int, *, unread: tuple[str, ...], seed: int,
                 span: Span) -> CellRecord:
        """The cell's record on ``context.frames[span[0]:span[1]]``, in frame order."""
        raise NotImplementedError

    def prefetch(self, context: RunContext, family: str, severity: int, *, unread: tuple[str, ...], seed: int) -> None:
        """Start the cell on every frame now; a later `run_cell` with the same arguments collects it."""


def style_of(planner: Any) -> CallStyle:
    """How the suite calls `planner` (`planning.call_style`), also for a planner that runs elsewhere."""
    return planner.style if isinstance(planner, PlannerElsewhere) else call_style(planner)


@dataclass
class RunContext:
    """Per-process state of a certification run."""

    reader: NuScenesReader
    frames: list[Frame]
    settings: RunSettings
    dataset_fingerprint: str
    planner_path: Path | None
    frames_unscored: int = 0  #: keyframes of the split read but not scored (fewer than six future keyframes)
    frames_total: int = 0  #: scored frames of the whole run (all shards)
    _planner: dict[int, PlannerInfo] = field(default_factory=dict)
    _decoded: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)
    _decoded_bytes: int = 0
    _clean: dict[int, CellRecord] = field(default_factory=dict)
    _contexts: dict[str, FrameContext] = field(default_factory=dict)
    _pdms: dict[str, PreparedFrame] = field(default_factory=dict)

    @classmethod
    def open(cls, settings: RunSettings, *, root: Path | None = None, planner_path: Path | None = None,
             digest_cache: Path | None = None) -> RunContext:
        """Index the data at `root` (default ``settings.data``) and pick the scored frames (of one shard, with
        ``settings.shard``); a data problem raises DataError naming the file or token. The dataset fingerprint
        covers the content of the files every scored frame of the run (all shards) is read from (`data.content`),
        with file digests cached in `digest_cache` (a folder) when given."""
        root = root if root is not None else settings.data
        if root is None:
            raise DriveDegradeError("no data root: the settings name none and none was given")
        reader = NuScenesReader(root, split=settings.split)
        chosen = reader.scorable_frames(limit=settings.frames)
        if not chosen:
            raise DriveDegradeError(f"{root}: split {settings.split!r} has no scorable frames (frames need six "
                                    f"future keyframes); skipped: {dict(reader.skipped)}")
        total = len(chosen)
        fingerprint = content_fingerprint(reader, chosen, digest_cache)
        if settings.shard is not None:
            chosen = shard_frames(chosen, settings.shard)
        return cls(reader, chosen, settings, fingerprint, planner_path, frames_unscored=reader.skipped[UNSCORED],
                   frames_total=total)

    @property
    def seed(self) -> int:
        """The run's corruption seed (``settings.seed``)."""
        return self.settings.seed

    @property
    def device(self) -> str:
        """--drivedegrade-device: where the planner should run (``settings.device``; planner fixtures read it)."""
        return self.settings.device

    @property
    def frames_key(self) -> str:
        """Which frames are scored (the --drivedegrade-frames subset changes results)."""
        return hashlib.sha256("|".join(f.token for f in self.frames).encode()).hexdigest()[:16]

    def planner_info(self, planner: Any) -> PlannerInfo:
        if isinstance(planner, PlannerElsewhere):
            return planner.info
        key = id(planner)
        if key not in self._planner:
            self._planner[key] = PlannerInfo(planner_cameras(planner), planner_fingerprint(planner, self.planner_path))
        return self._planner[key]

    def run_key(self, planner: Any) -> dict[str, Builtin]:
        """What a stored cell result must match to be reused by a rerun: the tool's and the data's identity and
        the settings the run key holds (`RunSettings.run_key_fields`: the seed, and the seed count, batch, reuse
        and device only where they change a plan, so a run at the defaults keeps the key of runs before they
        existed). The tool version is part of it: a new release may compute a cell differently, so it never
        reuses an older release's cells."""
        from . import __version__

        key: dict[str, Builtin] = {
            "spec_version": SPEC_VERSION, "tool_version": __version__, "record_version": RECORD_VERSION,
            "planner_fingerprint": self.planner_info(planner).fingerprint,
            "dataset_fingerprint": self.dataset_fingerprint, "frames_key": self.frames_key}
        return {**key, **self.settings.run_key_fields()}

    def seeds_for(self, family: str) -> list[int]:
        """The corruption seeds a cell of `family` runs under: seed .. seed + seeds - 1 for a random family,
        the run's seed alone for a deterministic one (it would repeat itself) and for the diagnostic cells."""
        if self.settings.seeds > 1 and family in FAMILIES and FAMILIES[family].random:
            return [self.seed + k for k in range(self.settings.seeds)]
        return [self.seed]

    def run_seeded_cell(self, planner: Any, family: str, severity: int, *,
                        clean: CellRecord | None = None) -> CellRecord:
        """A ladder cell under every seed of `seeds_for`: the first seed's record carrying the others' runs.
        `clean` is the run's clean cell, whose plans frames with inputs equal to clean's reuse (`stream`)."""
        seeds = self.seeds_for(family)
        if isinstance(planner, PlannerElsewhere):  # every seed's frames queued at once, then collected in order
            unread = unread_cameras(planner_cameras(planner))
            for s in seeds:
                planner.prefetch(self, family, severity, unread=unread, seed=s)
        first = self.run_cell(planner, family, severity, seed=seeds[0], clean=clean)
        if len(seeds) > 1:
            first.seed_runs = [self.run_cell(planner, family, severity, seed=s, clean=clean) for s in seeds[1:]]
            first.seeds = seeds
        return first

    def decode(self, frame: Frame, camera: str) -> np.ndarray:
        """The clean image; the first DECODE_CACHE_BYTES of decoded images stay in memory for the next cells.

        Fill-once, never evict: every cell reads the frames in the same order, so an LRU would miss every
        time, while a fixed set hits every time. Memory stays bounded whatever the number of frames. Cached
        arrays are read-only, so no cell can change what another one reads.
        """
        key = (frame.token, camera)
        image = self._decoded.get(key)
        if image is None:
            image = self.reader.load_image(frame.cameras[camera])
            if self._decoded_bytes + image.nbytes <= DECODE_CACHE_BYTES:
                image.setflags(write=False)
                self._decoded[key] = image
                self._decoded_bytes += image.nbytes
        return image

    def reuses_clean(self, planner: Any, family: str, severity: int) -> bool:
        """Whether frames of this cell may reuse the clean plans: reuse is on (not --drivedegrade-no-reuse), the
        planner is deterministic and has no ``reset`` (`CallStyle.reuses`), and some frame of the cell may
        deliver the clean images on every camera the planner declares (`loader.may_equal_clean`). Never the
        clean, null, blind or ego cells, nor blackout S3 (`REAR_BLACKOUT_SEVERITY`): when it blacks out only
        cameras the planner does not read, it is the rear cameras' null control and must call the planner to
        catch an undeclared read. Never on planner actors (`PlannerElsewhere`: each predicts every frame it is
        sent). The one decision: `stream` asks it once per cell."""
        if isinstance(planner, PlannerElsewhere) or (family, severity) == ("blackout", REAR_BLACKOUT_SEVERITY):
            return False
        return self.settings.reuse and call_style(planner).reuses and \
            may_equal_clean(family, severity, planner_cameras(planner))

    def clean_record(self, planner: Any, stored: Callable[[], CellRecord | None] = lambda: None) -> CellRecord:
        """The clean cell, once per process: the clean item's result and the reference of the null control and
        the baseline gate. `stored` is asked first (a reusable stored result), then it is computed."""
        key = id(planner)
        if key not in self._clean:
            self._clean[key] = stored() or self.run_cell(planner, "clean", 0)
        return self._clean[key]

    def context_of(self, frame: Frame) -> FrameContext:
        """The frame's read-only context, built once per process (it is the same in every cell)."""
        found = self._contexts.get(frame.token)
        if found is None:
            found = self._contexts[frame.token] = FrameContext.of(frame)
        return found

    def pdms_frame(self, frame: Frame) -> PreparedFrame:
        """The frame's PDMS preparation (expert states, agent tracks, the map around the ego), built once per
        process and shared by every cell: a cell then pays only for its own plans."""
        found = self._pdms.get(frame.token)
        if found is None:
            found = self._pdms[frame.token] = PreparedFrame.of(frame, self.reader.drivable_area(frame))
        return found

    def stream(self, planner: Any, family: str, severity: int, frames: list[Frame], *,
               unread: tuple[str, ...], seed: int | None = None,
               clean: CellRecord | None = None) -> Iterator[FrameResult]:
        """Feed `frames` (scene by scene, in order) through the planner under one cell's corruption: for each
        frame its sample and the validated plan, or the one-line reason the frame failed.

        ``reset(scene_token)`` runs before the first frame of each scene, so no state crosses a scene or a
        cell; the context goes in when ``predict`` takes it; each call gets private copies of its inputs, and a
        write into an input image fails the frame naming the camera.

        With `clean` (the run's clean cell), a deterministic planner without ``reset`` is not called on a frame
        whose sample equals clean on every camera it reads (`CellSample.equals_clean`, decided structurally):
        the clean plan is yielded instead (bit for bit what the call would return) and the sample is marked
        (``reused_from``: its index in clean). A frame that failed in clean is called again.
        """
        style = call_style(planner)
        scene = None
        seed = self.seed if seed is None else seed
        reuse = self._reuser(clean, unread) if clean is not None and self.reuses_clean(planner, family, severity) \
            else _predict_every_frame
        if self.settings.batch > 1 and not style.resets and callable(getattr(planner, "predict_batch", None)):
            yield from self._stream_batched(planner, samples(frames, family, severity, seed=seed,
                                                             decode=self.decode, unread=unread), reuse)
            return
        for sample in samples(frames, family, severity, seed=seed, decode=self.decode, unread=unread):
            frame = sample.frame
            reused = reuse(sample)
            if reused is not None:  # a reusing planner has no reset, so no scene is skipped
                yield sample, reused
                continue
            if style.resets and frame.scene_token != scene:
                try:
                    planner.reset(frame.scene_token)
                except Exception as exc:  # noqa: BLE001 - the planner's failure, named, never a crash
                    scene = None
                    yield sample, (f"frame {frame.token!r}: reset({frame.scene_token!r}) raised "
                                   f"{type(exc).__name__}: {exc}")
                    continue
            scene = frame.scene_token
            yield sample, self._predict(planner, sample, style)

    def _reuser(self, clean: CellRecord, unread: tuple[str, ...]) -> Callable[[CellSample], np.ndarray | None]:
        """A sample -> the clean plan to reuse for it, or None to predict (see `stream`), in a cell that may
        reuse (`reuses_clean`)."""
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

    def _stream_batched(self, planner: Any, stream: Iterator[CellSample],
                        reuse: Callable[[CellSample], np.ndarray | None]) -> Iterator[FrameResult]:
        """`--drivedegrade-batch B`: B frames per ``predict_batch(images, egos, cmds, contexts)`` call, in order;
        each frame's output is checked (and its inputs for writes) as a single prediction's would be. A frame
        that reuses the clean plan skips the batch (B counts the frames predicted) and keeps its place."""
        pending: list[tuple[CellSample, np.ndarray | None]] = []
        todo = 0
        for sample in stream:
            reused = reuse(sample)
            pending.append((sample, reused))
            todo += reused is None
            if todo == self.settings.batch:
                yield from self._flush(planner, pending)
                pending, todo = [], 0
        if pending:
            yield from self._flush(planner, pending)

    def _flush(self, planner: Any, pending: list[tuple[CellSample, np.ndarray | None]]) -> Iterator[FrameResult]:
        """The pending frames in order: the reused ones as they are, the others from one batch call."""
        todo = [s for s, reused in pending if reused is None]
        predicted = iter(self._predict_batch(planner, todo) if todo else ())
        for sample, reused in pending:
            yield (sample, reused) if reused is not None else next(predicted)

    def _predict_batch(self, planner: Any, batch: list[CellSample]) -> Iterator[FrameResult]:
        inputs = [self._inputs(planner, s, CallStyle(True, False)) for s in batch]
        egos, contexts = [e for e, _ in inputs], [c for _, c in inputs]
        try:
            with time_limit(self.settings.timeout * len(batch)):
                raw = planner.predict_batch([s.view for s in batch], egos, [s.frame.command for s in batch],
                                            contexts)
            raw = to_numpy(raw)
            if len(raw) != len(batch):
                raise PlannerOutputError(f"predict_batch() returned {len(raw)} plans for {len(batch)} frames")
        except PlannerOutputError as exc:
            for s in batch:
                yield s, _data_fault(s) or f"frame {s.frame.token!r}: {exc}"
            return
        except Exception as exc:  # noqa: BLE001 - the planner's failure, on every frame of the batch
            for s in batch:
                yield s, _data_fault(s) or describe_failure(exc, s.frame.token) + f" (in a batch of {len(batch)})"
            return
        for s, plan in zip(batch, raw):
            fault = _data_fault(s)
            if fault:
                yield s, fault
                continue
            written = s.written()
            if written:
                yield s, _written_message(s.frame.token, written)
                continue
            try:
                yield s, validate_output(plan, s.frame.token)
            except PlannerOutputError as exc:
                yield s, str(exc)

    def _inputs(self, planner: Any, sample: CellSample, style: CallStyle) -> tuple[Any, FrameContext | None]:
        """The call's ego status and context (perturbed in the ego cells): every array in them read-only and a
        copy private to this call, so nothing the planner does to them reaches another frame or cell."""
        frame = sample.frame
        ego = replace(frame.ego, past_xy=_readonly(frame.ego.past_xy))  # private to the call
        context = self.context_of(frame).private() if style.takes_context else None
        if is_ego(sample.family):  # the ego cells: the ego status and the context's CAN bus, perturbed or zeroed
            from .corruptions.ego import perturb

            ego, bus = perturb(ego, None if context is None else context.can_bus, sample.family, sample.severity,
                               seed=self.seed, frame=frame.token)
            context = None if context is None else replace(context, can_bus=bus)
        return ego, context

    def _predict(self, planner: Any, sample: CellSample, style: CallStyle) -> np.ndarray | str:
        frame = sample.frame
        ego, context = self._inputs(planner, sample, style)
        try:
            with time_limit(self.settings.timeout):
                if style.takes_context:
                    raw = planner.predict(sample.view, ego, frame.command, context=context)
                else:
                    raw = planner.predict(sample.view, ego, frame.command)
        except Exception as exc:  # noqa: BLE001 - any planner failure is this frame's conformance failure
            return _data_fault(sample) or (f"frame {frame.token!r}: {exc}" if isinstance(exc, DataError) else
                                           describe_failure(exc, frame.token))
        fault = _data_fault(sample)  # a data fault the planner caught and planned around: still the data's
        if fault:
            return fault
        written = sample.written()
        if written:
            return _written_message(frame.token, written)
        try:
            return validate_output(raw, frame.token)
        except PlannerOutputError as exc:
            return str(exc)

    def run_cell(self, planner: Any, family: str, severity: int, *, unread: tuple[str, ...] | None = None,
                 seed: int | None = None, span: Span | None = None, clean: CellRecord | None = None) -> CellRecord:
        """Every frame of one cell through the planner; per-frame failures become NaN rows plus a message.
        `seed` overrides the run's seed (one of `seeds_for`); `span` runs only ``frames[start:stop]`` (a replay,
        or one group of a cell run by planner actors), streamed as a run of those frames alone would be; with
        `clean`, frames whose inputs equal clean's reuse its plans (`stream`) and the record counts them
        (``reused``). Planner actors do not reuse: each predicts every frame it is sent."""
        if unread is None:  # the cameras only: the floor model needs no fingerprint
            unread = unread_cameras(planner_cameras(planner))
        span = span or (0, len(self.frames))
        if isinstance(planner, PlannerElsewhere):
            return planner.run_cell(self, family, severity, unread=unread, seed=self.seed if seed is None else seed,
                                    span=span)
        frames = self.frames[span[0]:span[1]]
        n = len(frames)
        plans = np.full((n, HORIZON_STEPS, 2), np.nan)
        l2, col, vru = (np.full((n, HORIZON_STEPS), np.nan) for _ in range(3))
        jerk, bit1 = np.full(n, np.nan), np.full(n, np.nan)
        pdms = {k: np.full(n, np.nan) for k in (*PDMS_FIELDS, "map_scored")}
        errors: list[str] = []
        data_errors: list[str] = []
        spent = {"decode": 0.0, "inject": 0.0, "planner": 0.0, "metrics": 0.0, "pdms": 0.0, "check": 0.0}
        reused = 0
        start = last = time.perf_counter()
        for i, (sample, result) in enumerate(self.stream(planner, family, severity, frames, unread=unread, seed=seed,
                                                         clean=clean)):
            elapsed = time.perf_counter() - last  # predict() plus the lazy decode, injection and input check
            for part in ("decode", "inject", "check"):
                spent[part] += sample.seconds[part]
            spent["planner"] += elapsed - sum(sample.seconds.values())
            t1 = time.perf_counter()
            if isinstance(result, DataFault):
                data_errors.append(str(result))
            elif isinstance(result, str):
                errors.append(result)
            elif sample.reused_from is not None and clean is not None:
                # clean's plan for this very frame: every figure of the frame is clean's row (the bit-1 density
                # too: what the planner would have read is clean's images), so nothing is scored twice
                j = sample.reused_from
                reused += 1
                plans[i], l2[i], col[i], vru[i] = result, clean.l2[j], clean.collision[j], clean.collision_vru[j]
                jerk[i], bit1[i] = clean.jerk[j], clean.bit1[j]
                for k in (*PDMS_FIELDS, "map_scored"):
                    pdms[k][i] = getattr(clean, k)[j]
            else:
                m = frame_metrics(result, sample.frame)
                plans[i], l2[i], col[i], vru[i] = result, m["l2"], m["collision"], m["collision_vru"]
                jerk[i] = m["jerk"]
                bit1[i] = bit1_density(sample.delivered) if sample.delivered else np.nan
                t2 = time.perf_counter()
                scored = self.pdms_frame(sample.frame).score(result)
                for k in PDMS_FIELDS:
                    pdms[k][i] = getattr(scored, k)
                pdms["map_scored"][i] = float(scored.map_scored)
                took = time.perf_counter() - t2
                spent["pdms"] += took
                spent["metrics"] -= took  # metrics is the rest
            last = time.perf_counter()
            spent["metrics"] += last - t1
        spent["total"] = time.perf_counter() - start
        return CellRecord(cell_id(family, severity), family, severity, [f.token for f in frames], plans, l2,
                          col, vru, jerk, bit1, seconds=spent, errors=errors, nc=pdms["nc"], dac=pdms["dac"],
                          ttc=pdms["ttc"], ep=pdms["ep"], comfort=pdms["comfort"], pdms=pdms["pdms"],
                          map_scored=pdms["map_scored"], data_errors=data_errors, reused=reused)


def _data_fault(sample: CellSample) -> DataFault | None:
    """The frame's data fault (the first image that could not be produced), naming the frame, or None."""
    if not sample.data_errors:
        return None
    return DataFault(f"frame {sample.frame.token!r}: {sample.data_errors[0]}")


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
