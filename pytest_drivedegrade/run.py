"""What a run is: `RunContext`, built once per process (the controller, or each xdist worker), holds the run's
settings, the data and its scored frames, and the per-process caches (decoded images, frame contexts, PDMS
preparations, the clean cell). How a planner is called on a cell's frames is `stream`'s; `run_cell` dispatches a
cell to it, or to a planner that runs elsewhere (`PlannerElsewhere`: Ray actors), and returns a `CellRecord`.
"""

from __future__ import annotations

import hashlib
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol, Union

import numpy as np

from . import stream
from .cells import RECORD_VERSION, CellRecord
from .constants import ADAPTIVE_METHOD, CAMERAS, HORIZON_STEPS
from .corruptions.derived import register as register_stable
from .corruptions.ladder import FAMILIES, SPEC_VERSION
from .data.content import content_fingerprint
from .data.context import FrameContext
from .data.frame import Frame
from .data.junctions import Alternative, alternative
from .data.nuscenes import UNSCORED, NuScenesReader
from .errors import DataError, DriveDegradeError
from .metrics.pdms import EgoStates, PreparedFrame, tracked_experts
from .metrics.pdms.constants import EGO_BOXES
from .metrics.trajectory import FrameTruth
from .pacing import processes_here
from .planning import CallStyle, Planner, call_style, planner_cameras, planner_fingerprint
from .settings import Builtin, RunSettings
from .shards import shard_frames

MAX_MESSAGES = 5  # per cell, the first few per-frame failures are spelled out
#: Decoded clean images kept per process for reuse by later cells: a fixed budget, so memory is flat in the
#: number of frames. At least this (about 500 images at 800 x 450) ...
DECODE_CACHE_MIN_BYTES = 512 * 2**20
#: ... and at most this (the embedded world's 204 frames x 3 cameras take 0.66 GB; a camera decoded again in
#: every cell costs about 3 ms, issue 23's "decode work shared").
DECODE_CACHE_MAX_BYTES = 2 * 2**30


def decode_cache_bytes(processes: int, memory: int | None = None) -> int:
    """The decoded-image budget of one process: a quarter of the machine's memory shared among the `processes`
    running cells on it, within [DECODE_CACHE_MIN_BYTES, DECODE_CACHE_MAX_BYTES] (the minimum where the memory
    cannot be read). Only speed depends on it: a frame outside the cache is decoded again, to the same pixels."""
    if memory is None:
        try:
            memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (AttributeError, ValueError, OSError):  # pragma: no cover - a platform without sysconf
            memory = 0
    share = memory // (4 * max(1, processes))
    return max(DECODE_CACHE_MIN_BYTES, min(DECODE_CACHE_MAX_BYTES, share))


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


class StageTwoStep(Protocol):
    """`RunContext.stage_two`: a whole cell's record with its stage two added (`closedloop.twostage`)."""

    def __call__(self, context: RunContext, planner: Planner, record: CellRecord, *, seed: int,
                 unread: tuple[str, ...]) -> CellRecord: ...


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


class PlannerApart:
    """A planner called from this process but built and run in a child (`plugin.childplanner`, under
    --drivedegrade-isolate): the suite calls it as a planner here; its fingerprint is the one the child computed
    of the planner itself (`apart_fingerprint`)."""

    apart_fingerprint: str


#: A planner the run calls: one in this process, or one that runs elsewhere (Ray actors).
AnyPlanner = Union[Planner, "PlannerElsewhere"]


def style_of(planner: AnyPlanner) -> CallStyle:
    """How the suite calls `planner` (`planning.call_style`), also for a planner that runs elsewhere."""
    return planner.style if isinstance(planner, PlannerElsewhere) else call_style(planner)


def checked_frames(frames: list[Frame]) -> list[Frame]:
    """`frames` with each one's non-finite planner inputs noted (`Frame.input_fault`); a frame whose scoring truth
    is not finite is a DataError naming it (issue 37: it failed every cell with a traceback)."""
    from dataclasses import replace

    from .data.faults import input_fault, truth_fault

    out = []
    for frame in frames:
        truth = truth_fault(frame)
        if truth is not None:
            raise DataError(truth)
        fault = input_fault(frame)
        out.append(replace(frame, input_fault=fault) if fault else frame)
    return out


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
    #: `decode_cache_bytes` for this process among the xdist workers it knows of
    _decode_budget: int = field(default_factory=lambda: decode_cache_bytes(processes_here()))
    #: the prefetch thread (`loader.ahead`) and the planner's thread may decode at once: one fills the cache
    _decode_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _clean: dict[int, CellRecord] = field(default_factory=dict)
    _primed: set[int] = field(default_factory=set)  #: the planners that planned clean in this process
    _contexts: dict[str, FrameContext] = field(default_factory=dict)
    _pdms: dict[str, PreparedFrame] = field(default_factory=dict)
    #: the run frames' experts tracked (`tracked_experts`), by the horizon scored (6 or 8 poses)
    _experts: dict[int, dict[str, EgoStates]] = field(default_factory=dict)
    _truth: dict[str, FrameTruth] = field(default_factory=dict)
    _alternatives: dict[str, Alternative | None] = field(default_factory=dict)
    #: --drivedegrade-two-stage: the step that adds stage two to a whole open-loop cell's record (the plugin sets
    #: `closedloop.twostage.add_stage_two`: the run sits below the closed loop's renderer), and what it keeps per
    #: process (its routes and renders)
    stage_two: StageTwoStep | None = None
    stage_two_cache: object = None

    @classmethod
    def open(cls, settings: RunSettings, *, root: Path | None = None, planner_path: Path | None = None,
             digest_cache: Path | None = None) -> RunContext:
        """Index the data at `root` (default ``settings.data``) and pick the scored frames (of one shard, with
        ``settings.shard``; every frame for an adaptive shard, which owns cells); a data problem raises DataError
        naming the file or token. The dataset fingerprint covers the content of the files every scored frame of
        the run (all shards) is read from (`data.content`), with file digests cached in `digest_cache` (a folder)
        when given."""
        root = root if root is not None else settings.data
        if root is None:
            raise DriveDegradeError("no data root: the settings name none and none was given")
        reader = NuScenesReader(root, split=settings.split)
        chosen = reader.scorable_frames(limit=settings.frames)
        if not chosen:
            raise DriveDegradeError(f"{root}: split {settings.split!r} has no scorable frames (frames need six "
                                    f"future keyframes); skipped: {dict(reader.skipped)}")
        chosen = checked_frames(chosen)
        total = len(chosen)
        fingerprint = content_fingerprint(reader, chosen, digest_cache)
        if settings.shard is not None and not settings.adaptive:  # an adaptive shard owns cells, on every frame
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

    def planner_info(self, planner: AnyPlanner) -> PlannerInfo:
        if isinstance(planner, PlannerElsewhere):
            return planner.info
        key = id(planner)
        if key not in self._planner:
            fingerprint = planner.apart_fingerprint if isinstance(planner, PlannerApart) else \
                planner_fingerprint(planner, self.planner_path)
            self._planner[key] = PlannerInfo(planner_cameras(planner), fingerprint)
        return self._planner[key]

    def run_key(self, planner: AnyPlanner) -> dict[str, Builtin]:
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
        if self.settings.adaptive:  # where a cell stops depends on the stopping rule
            key["adaptive_method"] = ADAPTIVE_METHOD
        return {**key, **self.settings.run_key_fields()}

    def seeds_for(self, family: str) -> list[int]:
        """The corruption seeds a cell of `family` runs under: seed .. seed + seeds - 1 for a random family,
        the run's seed alone for a deterministic one (it would repeat itself) and for the diagnostic cells."""
        if self.settings.seeds > 1 and family in FAMILIES and FAMILIES[family].random:
            return [self.seed + k for k in range(self.settings.seeds)]
        return [self.seed]

    def run_seeded_cell(self, planner: AnyPlanner, family: str, severity: int, *,
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
        """The clean image; the first `decode_cache_bytes` of decoded images stay in memory for the next cells.

        Fill-once, never evict: every cell reads the frames in the same order, so an LRU would miss every
        time, while a fixed set hits every time. Memory stays bounded whatever the number of frames. Cached
        arrays are read-only, so no cell can change what another one reads.
        """
        key = (frame.token, camera)
        image = self._decoded.get(key)
        if image is not None:
            return image
        image = self.reader.load_image(frame.cameras[camera])
        with self._decode_lock:  # another thread may have decoded it meanwhile: keep one copy, count it once
            cached = self._decoded.get(key)
            if cached is not None:
                return cached
            if self._decoded_bytes + image.nbytes <= self._decode_budget:
                image.setflags(write=False)
                self._decoded[key] = image
                register_stable(image)  # kept read-only and never handed out: what is derived from it holds
                self._decoded_bytes += image.nbytes
        return image

    def reuses_clean(self, planner: AnyPlanner, family: str, severity: int) -> bool:
        """Whether frames of this cell may reuse the clean plans (`stream.may_reuse`). Never the clean, null, blind
        or ego cells, nor on planner actors (`PlannerElsewhere`: each predicts every frame it is sent). The one
        decision: `stream` asks it once per cell."""
        return not isinstance(planner, PlannerElsewhere) and stream.may_reuse(self.settings, planner, family, severity)

    def clean_record(self, planner: AnyPlanner, stored: Callable[[], CellRecord | None] = lambda: None) -> CellRecord:
        """The clean cell, once per process: the clean item's result and the reference of the null control and
        the baseline gate. `stored` is asked first (a reusable stored result), then it is computed."""
        key = id(planner)
        if key not in self._clean:
            found = stored()
            if found is None:
                found = self.run_cell(planner, "clean", 0)
                self._primed.add(key)
            self._clean[key] = found
        return self._clean[key]

    def prime_clean(self, planner: AnyPlanner) -> None:
        """Have the planner plan the clean cell in this process before any other cell (M12): a planner that keeps
        a plan per frame across calls (a memo) then holds clean's plans in every process (each xdist worker, each
        Ray actor), so its blind cell equals clean wherever it runs and `scoring.verdict.blind_equals_clean` finds
        it; a planner that plans each call from its inputs plans the same either way. The clean cell computed here
        is this process's (`clean_record`) unless it has one. Nothing for a planner that runs elsewhere (each
        actor primes its own) or one that already planned clean here."""
        key = id(planner)
        if isinstance(planner, PlannerElsewhere) or key in self._primed:
            return
        self._primed.add(key)
        record = self.run_cell(planner, "clean", 0)
        self._clean.setdefault(key, record)

    def context_of(self, frame: Frame) -> FrameContext:
        """The frame's read-only context, built once per process (it is the same in every cell)."""
        found = self._contexts.get(frame.token)
        if found is None:
            found = self._contexts[frame.token] = FrameContext.of(frame)
        return found

    def pdms_frame(self, frame: Frame, poses: int = HORIZON_STEPS) -> PreparedFrame:
        """The frame's PDMS preparation (expert states, agent tracks, the map around the ego) for plans of `poses`
        waypoints (6, or NAVSIM's 8 over 4 s), built once per process and shared by every cell: a cell then pays
        only for its own plans."""
        key = frame.token if poses == HORIZON_STEPS else f"{frame.token}|{poses}"
        found = self._pdms.get(key)
        if found is None:
            if poses not in self._experts:  # every run frame's expert tracked at the first, in one batch
                self._experts[poses] = tracked_experts(self.frames, poses)
            found = self._pdms[key] = PreparedFrame.of(frame, self.reader.drivable_area(frame),
                                                       lane_map=self.reader.lane_map(frame),
                                                       expert_states=self._experts[poses].get(frame.token),
                                                       ego_size=EGO_BOXES[self.settings.ego_box], poses=poses)
        return found

    def frame_truth(self, frame: Frame) -> FrameTruth:
        """What the L2 and collision metrics derive from the frame alone (`FrameTruth`), once per process."""
        found = self._truth.get(frame.token)
        if found is None:
            found = self._truth[frame.token] = FrameTruth.of(frame)
        return found

    def alternative_of(self, frame: Frame) -> Alternative | None:
        """The frame's alternative command and the expert's path for it (`data.junctions.alternative`), or None
        away from junctions; once per process."""
        if frame.token not in self._alternatives:
            self._alternatives[frame.token] = alternative(self.reader.lane_map(frame), frame.pose, frame.gt_future,
                                                          frame.command)
        return self._alternatives[frame.token]

    def run_cell(self, planner: AnyPlanner, family: str, severity: int, *, unread: tuple[str, ...] | None = None,
                 seed: int | None = None, span: Span | None = None, clean: CellRecord | None = None,
                 pdms: bool = True) -> CellRecord:
        """Every frame of one cell through the planner (`stream.run_cell`); per-frame failures become NaN rows
        plus a message. `seed` overrides the run's seed (one of `seeds_for`); `span` runs only
        ``frames[start:stop]`` (a replay, an adaptive unit, or one group of a cell run by planner actors), streamed
        as a run of those frames alone would be, except that frame_dropout's held frames are those of a run from
        the scene's start (`scene_history`); with `clean`, frames whose inputs equal clean's reuse its plans and the
        record counts them (``reused``). Planner actors do not reuse: each predicts every frame it is sent.
        `pdms` False skips the PDMS and EPDMS (NaN columns: the floor's cells, of which the report reads L2)."""
        if unread is None:  # the cameras only: the floor model needs no fingerprint
            unread = unread_cameras(planner_cameras(planner))
        start, stop = span or (0, len(self.frames))
        seed = self.seed if seed is None else seed
        if isinstance(planner, PlannerElsewhere):
            return planner.run_cell(self, family, severity, unread=unread, seed=seed, span=(start, stop))
        record = stream.run_cell(self, planner, family, severity, self.frames[start:stop], unread=unread, seed=seed,
                                 clean=clean, history=self.scene_history(start), pdms=pdms)
        if self.settings.two_stage and pdms and span is None:  # the two-stage mode: every whole open-loop cell
            if self.stage_two is None:
                raise DriveDegradeError("--drivedegrade-two-stage: this run has no stage-two step (set "
                                        "RunContext.stage_two to closedloop.twostage.add_stage_two)")
            record = self.stage_two(self, planner, record, seed=seed, unread=unread)
        return record

    def scene_history(self, start: int) -> list[Frame]:
        """The run's frames of frame `start`'s scene before it (none at a scene's start)."""
        if start >= len(self.frames):
            return []
        first, scene = start, self.frames[start].scene_token
        while first > 0 and self.frames[first - 1].scene_token == scene:
            first -= 1
        return self.frames[first:start]
