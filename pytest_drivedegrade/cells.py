"""Which cells exist and what one cell yields: cell ids, the diagnostic cells, the run order, the per-cell
record and the one definition of bit-identical plans (`payload` carries a record to the controller and the store).

One home for "which cells exist": the plugin collects items from `run_order` (the scoring orders its summaries
with `scoring.records.report_order`), the store and the certificate key everything by `cell_id`.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .constants import COMMAND_BLIND, COMMAND_SWAP, EGO_BLIND, EGO_NOISE, HORIZON_STEPS
from .errors import InvalidInput
from .metrics.trajectory import l2_avg

#: Cells that are not ladder families, in report order: clean (severity 0), the null control (the cameras the
#: planner does not read blacked out; an untouched rerun for a planner that reads all six) and blind (all six
#: black).
DIAGNOSTIC: tuple[str, ...] = ("clean", "null", "blind")
#: The ego ladder (SPEC section 10): cells outside the camera axes that perturb (`ego_noise`, S1..S5) or zero
#: (`ego_blind`, severity 0) the ego status and the context's CAN bus, the images left clean.
EGO_FAMILIES: tuple[str, ...] = (EGO_NOISE, EGO_BLIND)
#: The command cells (spec 5): the images and the ego status clean, the command replaced (`command_blind`: the
#: same command on every frame; `command_swap`: the alternative command at junction frames).
COMMAND_FAMILIES: tuple[str, ...] = (COMMAND_BLIND, COMMAND_SWAP)
#: Every cell of an input other than the cameras, in report order: the ego cells, then the command cells.
INPUT_FAMILIES: tuple[str, ...] = (*EGO_FAMILIES, *COMMAND_FAMILIES)
#: Version of the stored per-cell record: part of the run key, so a stored cell of an older record (no PDMS
#: arrays) is recomputed rather than reused. 2: per-frame PDMS and sub-scores; the ego cells. 3: data faults
#: (`data_errors`) kept apart from the planner's contract failures (`errors`). 4: PDMS on tracked states (spec 4.1).
#: 5: the tracker's velocity fit as NAVSIM's code does it (spec 4.2). 6: the EPDMS terms and NC/TTC's side rule as
#: NAVSIM v2.2's code (issue 39). 7: ``command_target``, the expert's change of path at command_swap's junction
#: frames (issue 40).
RECORD_VERSION = 7
#: The per-frame PDMS arrays of a record (spec 3): the score and its sub-scores, each (F,), NaN where unscored.
PDMS_FIELDS: tuple[str, ...] = ("nc", "dac", "ttc", "ep", "comfort", "pdms")
#: The per-frame EPDMS arrays (spec 4.1, NAVSIM v2): its own terms (before the human filter) and the score; NaN
#: where not scored (no lanes: ddc, lk; no traffic lights: tlc; no previous plan of the scene: ec).
EPDMS_FIELDS: tuple[str, ...] = ("ddc", "tlc", "lk", "hc", "ec", "epdms")
#: The two-stage arrays (--drivedegrade-two-stage, issue 39; `closedloop.twostage`): stage two's weighted EPDMS
#: and the frame's two-stage EPDMS (stage one's times stage two's); NaN in a one-stage run, which stores neither
#: (sparse: its record keeps its form), and where a frame has no stage two.
TWO_STAGE_FIELDS: tuple[str, ...] = ("epdms_stage2", "epdms2")


@dataclass(frozen=True)
class FrameArray:
    """One per-frame array of a cell's record: its name, dtype and each frame's shape (the array is (F, *shape)),
    whether builtins carry it as 0/1 flags (ints, -1 for a failed frame's NaN), and the record version it
    appeared in (a record stored before it loads it as NaN)."""

    name: str
    shape: tuple[int, ...]
    dtype: str = "float64"
    flags: bool = False
    since: int = 1
    #: left out of the builtins when every value is NaN (the record of a cell that never fills it keeps the
    #: form it had before the array existed)
    sparse: bool = False

    def empty(self, frames: int) -> np.ndarray:
        """Every frame NaN: the row of a frame not (yet) scored."""
        return np.full((frames, *self.shape), np.nan, dtype=self.dtype)

    def to_builtins(self, array: np.ndarray) -> list[Any]:
        if self.flags:
            return [[int(v) if v == v else -1 for v in row] for row in array]
        return list(array.tolist())

    def from_builtins(self, data: object) -> np.ndarray:
        arr = np.asarray(data, dtype=self.dtype)
        return np.where(arr < 0, np.nan, arr) if self.flags else arr


#: The plans of a planner declaring NAVSIM's eight poses (`planning.planner_poses`) are (F, 8, 2): the one
#: per-frame array whose shape follows the planner; every other array (L2, collisions) reads the first six.
PLANNED_POSES = 8
#: Every per-frame array of a `CellRecord`, in the order its builtins list them: a new per-frame figure is one
#: entry here (and a `CellRecord` field), and construction, builtins, concat and the builder follow.
FRAME_ARRAYS: tuple[FrameArray, ...] = (
    FrameArray("plans", (HORIZON_STEPS, 2)), FrameArray("l2", (HORIZON_STEPS,)), FrameArray("jerk", ()),
    FrameArray("bit1", ()), *(FrameArray(k, (), since=2) for k in PDMS_FIELDS), FrameArray("map_scored", (), since=2),
    *(FrameArray(k, (), since=4) for k in EPDMS_FIELDS),
    FrameArray("collision", (HORIZON_STEPS,), flags=True), FrameArray("collision_vru", (HORIZON_STEPS,), flags=True),
    FrameArray("command_target", (HORIZON_STEPS, 2), since=7, sparse=True),
    *(FrameArray(k, (), since=7, sparse=True) for k in TWO_STAGE_FIELDS),
)
#: The blackout severity whose cameras are exactly the rear three: for a planner that does not read them,
#: that cell is the null control and is asserted bit-identical to clean too.
REAR_BLACKOUT_SEVERITY = 3

#: A JUnit property value: builtins only (xdist serialises them).
Property = tuple[str, "str | float | int"]


def cell_id(family: str, severity: int) -> str:
    """The stable id of a cell: `clean`, `null`, `blind` or `<family>-s<severity>` (e.g. `jpeg-s3`)."""
    return family if family in DIAGNOSTIC or family in (EGO_BLIND, *COMMAND_FAMILIES) else f"{family}-s{int(severity)}"


def is_ego(family: str) -> bool:
    """Whether a family is one of the ego cells (outside the camera axes)."""
    return family in EGO_FAMILIES


def is_input(family: str) -> bool:
    """Whether a family probes an input other than the cameras (an ego cell or a command cell): its images are
    clean and it is outside the camera axes."""
    return family in INPUT_FAMILIES


def is_camera_ladder(family: str) -> bool:
    """A family of the camera ladder: not a diagnostic cell (clean, null, blind), not an ego or command cell."""
    return family not in DIAGNOSTIC and not is_input(family)


def run_order(families: Iterable[str], severities: Iterable[int], *,
              ego: Iterable[str] | bool = INPUT_FAMILIES) -> list[tuple[str, int]]:
    """(family, severity) of every cell in run order: clean first, the ladder, the ego cells (`ego_noise` at the
    same severities, then `ego_blind`, then `command_blind` and `command_swap`: those of `ego` that are asked
    for; ``ego=False`` for none), blind, and the null control last, so that under xdist the clean result is
    already stored when the null control and the baseline gate compare against it, and no worker computes clean
    twice."""
    sev = list(severities)
    wanted = set(INPUT_FAMILIES if ego is True else () if ego is False else ego)
    ego_cells = [*((EGO_NOISE, s) for s in sev if EGO_NOISE in wanted),
                 *((f, 0) for f in (EGO_BLIND, *COMMAND_FAMILIES) if f in wanted)]
    return [("clean", 0), *((f, s) for f in families for s in sev), *ego_cells, ("blind", 0), ("null", 0)]


def rear_cameras() -> tuple[str, ...]:
    """The cameras blackout S3 zeroes (the rear three), read off the ladder rather than copied."""
    from .corruptions.ladder import FAMILIES

    return tuple(FAMILIES["blackout"].value(REAR_BLACKOUT_SEVERITY))


def _plans_bytes(plans: Any) -> tuple[tuple[int, ...], bytes]:
    """The shape and the float64 little-endian C-order bytes of plans (the canonical byte form)."""
    arr = np.ascontiguousarray(plans, dtype="<f8")
    return arr.shape, arr.tobytes()


#: The bit pattern every NaN takes in `plans_digest` (numpy's ``np.nan``), whatever sign or payload it carried.
CANONICAL_NAN = np.float64(np.nan)


def plans_digest(runs: Iterable[Any]) -> str:
    """SHA-256 hex of a cell's plans, one array per seed run in run order (one entry for a single seed).

    Each run contributes its shape and its float64 bytes, little-endian, C order (frames in run order), with every
    NaN replaced by ``CANONICAL_NAN``: the certificate's ``plans_digest``, so a rerun can be compared bit for bit
    (`identical_plans`) with nothing but the certificate. -0.0 and 0.0 differ, as in `identical_plans`.
    """
    digest = hashlib.sha256(b"drivedegrade-plans-v1")
    for plans in runs:
        arr = np.array(plans, dtype=np.float64)  # a copy: its NaNs are rewritten
        arr[np.isnan(arr)] = CANONICAL_NAN
        shape, data = _plans_bytes(arr)
        digest.update(("|" + ",".join(map(str, shape)) + "|").encode() + data)
    return digest.hexdigest()


def identical_plans(a: Any, b: Any) -> bool:
    """The one definition of "bit-identical" plans: same shape and the same float64 bytes.

    So ``-0.0`` differs from ``0.0``, a value one float step away differs, and NaN equals NaN only with the same
    bit pattern (every failed frame is the same canonical NaN). The null-control item and the certificate's
    ``null_control`` both use it, so a cell cannot pass while the certificate says the control failed.
    """
    return _plans_bytes(a) == _plans_bytes(b)


def planned_in_both(a: Any, b: Any) -> np.ndarray:
    """The frames (first axis) with a plan in both `a` and `b`: finite in each (a failed frame is NaN). The null
    control compares these only: a frame that failed in one cell is that cell's conformance failure, not a
    difference of plans (and not a camera's doing)."""
    x = np.asarray(a, dtype=np.float64)
    y = np.asarray(b, dtype=np.float64)
    if x.shape != y.shape:
        raise InvalidInput(f"plans have shapes {x.shape} and {y.shape}")
    if not x.size:
        return np.zeros(len(x), dtype=bool)
    return np.asarray(np.isfinite(x).reshape(len(x), -1).all(axis=1) & np.isfinite(y).reshape(len(y), -1).all(axis=1))


def differing_frames(a: Any, b: Any) -> np.ndarray:
    """Indices of the frames (first axis) whose plans are not bit-identical (see `identical_plans`)."""
    x = np.ascontiguousarray(a, dtype=np.float64)
    y = np.ascontiguousarray(b, dtype=np.float64)
    if x.shape != y.shape:
        raise InvalidInput(f"plans have shapes {x.shape} and {y.shape}")
    xb, yb = x.reshape(len(x), -1).view(np.uint64), y.reshape(len(y), -1).view(np.uint64)
    return np.flatnonzero((xb != yb).any(axis=1))


def _absent() -> np.ndarray:
    """The value of a per-frame array a record was made without (NaN for every frame, `CellRecord`)."""
    return np.empty(0)


@dataclass
class CellRecord:
    """Everything one finished cell yields, per frame; the frame order is the same in every cell of a run.

    Arrays: ``plans`` (F, 6, 2) metres; ``l2``, ``collision``, ``collision_vru`` (F, 6) per step; ``jerk`` and
    ``bit1`` (F,); the PDMS-like score and its sub-scores ``nc, dac, ttc, ep, comfort, pdms`` (F,) in [0, 1]
    (`PDMS_FIELDS`; NaN in a record stored before they existed) and ``map_scored`` (F,) 1.0 where the drivable
    area was scored (0.0: no map, dac fixed at 1). A frame that failed carries NaN and is left out of means; its
    one-line reason is in ``errors`` when the planner broke the contract, in ``data_errors`` when the data did
    (a missing, empty, truncated, undecodable or wrong-size image).
    """

    cell: str
    family: str
    severity: int
    frames: list[str]
    plans: np.ndarray
    l2: np.ndarray
    collision: np.ndarray
    collision_vru: np.ndarray
    jerk: np.ndarray
    bit1: np.ndarray
    seconds: dict[str, float] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)
    seed_runs: list[CellRecord] = field(default_factory=list)
    seeds: list[int] = field(default_factory=list)
    nc: np.ndarray = field(default_factory=_absent)  #: absent (a record from before the PDMS arrays): NaN
    dac: np.ndarray = field(default_factory=_absent)
    ttc: np.ndarray = field(default_factory=_absent)
    ep: np.ndarray = field(default_factory=_absent)
    comfort: np.ndarray = field(default_factory=_absent)
    pdms: np.ndarray = field(default_factory=_absent)
    map_scored: np.ndarray = field(default_factory=_absent)
    ddc: np.ndarray = field(default_factory=_absent)  #: the EPDMS arrays (`EPDMS_FIELDS`, record version 4)
    tlc: np.ndarray = field(default_factory=_absent)
    lk: np.ndarray = field(default_factory=_absent)
    hc: np.ndarray = field(default_factory=_absent)
    ec: np.ndarray = field(default_factory=_absent)
    epdms: np.ndarray = field(default_factory=_absent)
    #: command_swap's junction frames (record version 7): the privileged expert's path for the alternative command
    #: minus the logged future, (F, 6, 2); NaN at every other frame and in every other cell
    command_target: np.ndarray = field(default_factory=_absent)
    epdms_stage2: np.ndarray = field(default_factory=_absent)  #: the two-stage arrays (`TWO_STAGE_FIELDS`)
    epdms2: np.ndarray = field(default_factory=_absent)
    data_errors: list[str] = field(default_factory=list)
    reused: int = 0  #: frames whose plan is the clean cell's, reused rather than predicted (equal inputs)
    #: --drivedegrade-adaptive: the units of the draw order this cell ran (a prefix; 0: a skipped severity) and
    #: the forward passes they took (warm-up frames included); None in a full run, whose record keeps its form
    units: int | None = None
    passes: int | None = None

    def __post_init__(self) -> None:
        n = len(self.frames)
        self.frames = [str(f) for f in self.frames]
        self.severity = int(self.severity)
        for a in FRAME_ARRAYS:
            got = getattr(self, a.name)
            if got is None or (a.since > 1 and n and np.size(got) == 0):  # from before the array existed: unscored
                got = a.empty(n)
            arr = np.asarray(got, dtype=a.dtype)
            shape = (n, *a.shape)
            if a.name == "plans" and arr.ndim == 3 and arr.shape[1:] == (PLANNED_POSES, 2):  # a 4 s planner's
                shape = (n, PLANNED_POSES, 2)
            arr = arr.reshape(shape) if arr.size == 0 else arr
            if arr.shape != shape:
                raise InvalidInput(f"cell {self.cell!r}: {a.name} has shape {arr.shape}, expected {shape}")
            setattr(self, a.name, arr)
        self.seeds = [int(s) for s in self.seeds]
        self.errors, self.data_errors = [str(e) for e in self.errors], [str(e) for e in self.data_errors]
        self.reused = int(self.reused)
        if not 0 <= self.reused <= n:
            raise InvalidInput(f"cell {self.cell!r}: {self.reused} reused frames of {n}")
        for run in self.seed_runs:
            if run.frames != self.frames:
                raise InvalidInput(f"cell {self.cell!r}: a seed run was scored on other frames")
        if self.seed_runs and len(self.seeds) != 1 + len(self.seed_runs):
            raise InvalidInput(f"cell {self.cell!r}: {len(self.seeds)} seeds for {1 + len(self.seed_runs)} runs")

    def failed_frames(self) -> tuple[int, int]:
        """(planner contract failures, data faults) over every seed run of the cell."""
        return sum(len(r.errors) for r in self.runs()), sum(len(r.data_errors) for r in self.runs())

    def runs(self) -> list[CellRecord]:
        """Every seed's run of this cell: this record first, then ``seed_runs`` (one entry for a single seed)."""
        return [self, *self.seed_runs]

    def plans_digest(self) -> str:
        """`plans_digest` over every seed run's plans in order: the certificate's per-cell ``plans_digest``."""
        return plans_digest(run.plans for run in self.runs())

    def to_builtins(self) -> dict[str, Any]:
        """Plain lists / floats / ints / strs only: safe for xdist, JSON and ``user_properties``."""
        out: dict[str, Any] = {k: getattr(self, k) for k in ("cell", "family", "severity", "frames")}
        out.update({a.name: a.to_builtins(self.array(a.name)) for a in FRAME_ARRAYS
                    if not (a.sparse and np.isnan(self.array(a.name)).all())})
        out["seconds"] = {str(k): float(v) for k, v in self.seconds.items()}
        out["errors"] = [str(e) for e in self.errors]
        out["data_errors"] = [str(e) for e in self.data_errors]
        if self.reused:  # only then: a record without reuse keeps its earlier form (and digest) byte for byte
            out["reused"] = self.reused
        if self.units is not None:  # only in an adaptive run: a full run's record keeps its form byte for byte
            out["units"], out["passes"] = int(self.units), int(self.passes or 0)
        if self.seed_runs:  # only then: a one-seed record keeps its pre-seeds form byte for byte
            out["seeds"] = list(self.seeds)
            out["seed_runs"] = [run.to_builtins() for run in self.seed_runs]
        return out

    @classmethod
    def from_builtins(cls, data: Mapping[str, Any]) -> CellRecord:
        """Inverse of ``to_builtins``; a collision of -1 (a NaN frame) comes back as NaN. A record stored before
        the PDMS arrays existed loads with them NaN (its run key differs, so it is recomputed, never reused)."""
        if not isinstance(data, Mapping):
            raise InvalidInput(f"a cell record is a JSON object, found {type(data).__name__}")
        try:
            kw = {k: data[k] for k in ("cell", "family", "severity", "frames")}
            kw.update({a.name: a.from_builtins(data[a.name]) for a in FRAME_ARRAYS
                       if a.since == 1 or data.get(a.name) is not None})
        except KeyError as exc:
            raise InvalidInput(f"cell record lacks the field {exc.args[0]!r}") from None
        runs = [cls.from_builtins(r) for r in data.get("seed_runs", [])]
        return cls(**kw, seconds=dict(data.get("seconds", {})), errors=list(data.get("errors", [])),
                   seed_runs=runs, seeds=list(data.get("seeds", [])), data_errors=list(data.get("data_errors", [])),
                   reused=int(data.get("reused", 0)), units=_optional_int(data.get("units")),
                   passes=_optional_int(data.get("passes")))

    @classmethod
    def concat(cls, parts: Sequence[CellRecord]) -> CellRecord:
        """One cell's record from the records of consecutive frame groups of it (in frame order): the arrays and
        errors joined in that order, the cost seconds summed. Groups of whole scenes give exactly the record of
        one sequential run (`reset` and frame_dropout's state restart at each scene)."""
        if not parts:
            raise InvalidInput("no record to concatenate")
        first = parts[0]
        if any((p.cell, p.family, p.severity) != (first.cell, first.family, first.severity) or p.seed_runs
               for p in parts):
            raise InvalidInput(f"cell {first.cell!r}: only single-seed records of one cell are concatenated")
        arrays = {a.name: np.concatenate([p.array(a.name) for p in parts]) for a in FRAME_ARRAYS}
        seconds: dict[str, float] = {}
        for p in parts:
            for k, v in p.seconds.items():
                seconds[k] = seconds.get(k, 0.0) + float(v)
        return cls.of_arrays(first.cell, first.family, first.severity, [f for p in parts for f in p.frames], arrays,
                             seconds=seconds, errors=[e for p in parts for e in p.errors],
                             data_errors=[e for p in parts for e in p.data_errors], reused=sum(p.reused for p in parts))

    @classmethod
    def of_arrays(cls, cell: str, family: str, severity: int, frames: list[str], arrays: Mapping[str, np.ndarray],
                  **rest: Any) -> CellRecord:
        """A record from its per-frame arrays by name (`FRAME_ARRAYS`) and the other fields by keyword."""
        return cls(cell, family, severity, frames, **arrays, **rest)  # type: ignore[arg-type]

    def array(self, name: str) -> np.ndarray:
        """The per-frame array `name` (one of `FRAME_ARRAYS`), (F, *shape)."""
        got = getattr(self, name)
        assert isinstance(got, np.ndarray), name
        return got

    def endpoint_shift(self, clean: CellRecord) -> np.ndarray:
        """Per frame, how far (m) the 3 s waypoint moved from clean's plan (NaN where either failed)."""
        last = HORIZON_STEPS - 1
        return np.linalg.norm(self.plans[:, last] - clean.plans[:, last], axis=-1)

    def l2_avg_per_frame(self, convention: str = "stp3") -> np.ndarray:
        """Per-frame mean of the 1/2/3 s L2 under `convention`: the M of retention, one value per frame."""
        return np.asarray(l2_avg(self.l2, convention))


def _optional_int(value: object) -> int | None:
    """An optional count of a stored record (`CellRecord.units`, ``passes``): None, or a non-negative int."""
    if value is None:
        return None
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise InvalidInput(f"a cell record's unit count must be a non-negative integer, found {value!r}")
    return value


class RecordBuilder:
    """A cell's record assembled frame by frame, outside the loop that calls the planner: every row NaN until the
    frame is scored (`put`), copied from another record (`copy_row`: a reused clean plan) or failed (`fail`)."""

    def __init__(self, cell: str, family: str, severity: int, frames: Sequence[str],
                 poses: int = HORIZON_STEPS) -> None:
        self.cell, self.family, self.severity, self.frames = cell, family, severity, list(frames)
        self.arrays = {a.name: a.empty(len(self.frames)) for a in FRAME_ARRAYS}
        if poses != HORIZON_STEPS:  # a planner of NAVSIM's 4 s: its whole plan is kept (and PDMS-scored)
            self.arrays["plans"] = np.full((len(self.frames), poses, 2), np.nan)
        self.errors: list[str] = []
        self.data_errors: list[str] = []
        self.reused = 0

    def put(self, i: int, **values: float | np.ndarray | Sequence[float]) -> None:
        """Frame `i`'s values of some arrays, by name."""
        for name, value in values.items():
            self.arrays[name][i] = value

    def copy_row(self, i: int, source: CellRecord, j: int) -> None:
        """Frame `i` takes `source`'s row `j` in every array (the same plan on the same frame): a reused frame."""
        for name, arr in self.arrays.items():
            arr[i] = source.array(name)[j]
        self.reused += 1

    def fail(self, message: str, *, data: bool = False) -> None:
        """A failed frame (its row stays NaN): the planner's contract failure, or with `data` the data's fault."""
        (self.data_errors if data else self.errors).append(message)

    def build(self, seconds: Mapping[str, float]) -> CellRecord:
        return CellRecord.of_arrays(self.cell, self.family, self.severity, self.frames, self.arrays,
                                    seconds=dict(seconds), errors=self.errors, data_errors=self.data_errors,
                                    reused=self.reused)
