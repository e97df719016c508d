"""The one description of a run: `RunSettings`, and `TABLE`, which says per setting what it means outside the run.

A setting enters the run key (`RunSettings.run_key_fields`, the stored cells a rerun may reuse), the certificate
(`certificate_settings`, `from_certificate`), a shard manifest and a Ray actor's payload (`to_builtins`,
`from_builtins`), the command line a rerun needs (`rerun_argv`), and the comparisons of shards (`same_run`) and of
a run with its baseline (`baseline_differences`), all read off one row of `TABLE`. Adding a setting is a field of
`RunSettings` (its default there) and a row of `TABLE`; a test checks that every field has its row.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from enum import Enum
from pathlib import Path

from .constants import DEFAULT_FLAT
from .errors import DriveDegradeError, InvalidInput

#: What `dataset.source` of a certificate says for the suite's own rendered world (`RunSettings.data` None).
EMBEDDED_WORLD = "embedded world"
_SHARD = re.compile(r"^\s*(\d+)\s*/\s*(\d+)\s*$")

def shown_path(path: str | Path, root: Path) -> str:
    """A path as a published output records it (issue 20): relative to `root` (pytest's rootdir, or the folder
    `drivedegrade merge` runs in) when inside it, else ``.../<its name>``, so a certificate or report never
    reveals the user's file system. A relative path is kept as given."""
    given = Path(path)
    if not given.is_absolute():
        return given.as_posix()
    try:
        return given.resolve().relative_to(Path(root).resolve()).as_posix()
    except (ValueError, OSError):
        return f".../{given.name}"


def shown_arg(arg: str, root: Path) -> str:
    """A command-line argument with an absolute path in it (``/p`` or ``--option=/p``) shown by `shown_path`."""
    head, sep, tail = arg.partition("=") if arg.startswith("-") else ("", "", arg)
    return head + sep + shown_path(tail, root) if tail.startswith("/") else arg


#: A setting's value as builtins: what JSON, xdist and Ray carry.
Builtin = str | int | float | bool | None


@dataclass(frozen=True)
class Shard:
    """Shard `index` (1-based) of `count` (`--drivedegrade-shard I/N`; `shards.partition` says which frames)."""

    index: int
    count: int

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"

    @property
    def label(self) -> str:
        """A folder-safe name, e.g. ``shard-2-of-8``."""
        return f"shard-{self.index}-of-{self.count}"

    @classmethod
    def parse(cls, text: str) -> Shard:
        """``I/N`` with 1 <= I <= N; DriveDegradeError saying what is wrong otherwise."""
        found = _SHARD.match(str(text))
        if not found:
            raise DriveDegradeError(f"expected I/N (e.g. 2/8), got {text!r}")
        index, count = int(found.group(1)), int(found.group(2))
        if count < 1 or not 1 <= index <= count:
            raise DriveDegradeError(f"shard {index}/{count}: I must be between 1 and N (1-based)")
        return cls(index, count)


@dataclass(frozen=True)
class RunSettings:
    """Everything a run's numbers depend on besides the planner, the data's content and the tool: the options a
    rerun must repeat. Defaults are the options' defaults (`DEFAULTS`)."""

    data: Path | None = None  #: --drivedegrade-data; None: the embedded world
    split: str = "val"
    frames: int | None = None  #: --drivedegrade-frames as asked for (None: every scorable frame)
    seed: int = 0
    seeds: int = 1  #: random families run under seed .. seed + seeds - 1
    batch: int = 1  #: frames per predict_batch() call (stateless planners only)
    reuse: bool = True  #: not --drivedegrade-no-reuse: frames whose inputs equal clean take the clean plan
    device: str = "cpu"  #: where a planner that supports it runs (`planning.planner_device`)
    timeout: float = 60.0  #: seconds one predict() may take (0: no limit)
    metric: str = "l2"  #: the retention the verdict is put on (l2, pdms, epdms or epdms2)
    flat: float = DEFAULT_FLAT  #: retention at or above which an axis counts as flat
    ego_box: str = "nuscenes"  #: the ego box the PDMS and EPDMS score with (`metrics.pdms.constants.EGO_BOXES`)
    #: --drivedegrade-two-stage: each cell also scored by NAVSIM v2's two-stage pseudo-simulation
    #: (`closedloop.twostage`)
    two_stage: bool = False
    shard: Shard | None = None  #: the part of the run's scenes this process scores (None: all of them)
    prefetch: int | None = None  #: frames decoded and corrupted ahead of the planner (None: `pacing.prefetch_depth`)
    adaptive: bool = False  #: cells stop when their anytime-valid interval settles their decisions (spec 14)
    alpha: float = 0.05  #: --drivedegrade-alpha: the adaptive run's error level (the whole certificate's)
    isolate: bool = False  #: --drivedegrade-isolate: every planner call in a child process given only its inputs
    # The closed loop (SPEC section 13): held in the certificate's closed_loop section and the closed cells' key.
    loop: str = "open"  #: --drivedegrade-loop: open (the replayed frames), closed (the simulator), both
    closed_cells: str = "slice"  #: --drivedegrade-closed-cells: slice, all or a list of cells
    closed_seeds: int = 2  #: corruption seeds each route runs under
    closed_hz: int = 2  #: planner calls per simulated second
    closed_routes: int | None = None  #: the first N routes only (None: every route)
    closed_steps: int | None = None  #: at most N planner calls per run (None: to the route's end)
    closed_agents: str = "log"  #: the other agents: log (replayed) or reactive (IDM along their paths)
    closed_collisions: str = "all"  #: which collisions the DS counts: all (the leaderboard) or at_fault (NAVSIM)
    closed_scenarios: int = 18  #: scenario routes after the val routes (`data.world.scenarios`)
    closed_lights: int = 6  #: light routes after the scenario routes (`data.world.scenarios.light_scene`)

    @property
    def data_source(self) -> str:
        """The data set as the certificate's ``dataset.source`` names it."""
        return EMBEDDED_WORLD if self.data is None else str(self.data)

    def shown_source(self, root: Path | None) -> str:
        """`data_source` as a published output records it: by `shown_path` under `root` (None: as is)."""
        return self.data_source if self.data is None or root is None else shown_path(self.data, root)

    def value(self, name: str) -> object:
        return getattr(self, name)

    # --- builtins ----------------------------------------------------------------------------------------------

    def to_builtins(self) -> dict[str, Builtin]:
        """Every setting as JSON builtins, by field name (a shard manifest's ``settings``, a Ray actor's payload)."""
        return {row.name: _encode(self.value(row.name)) for row in TABLE}

    @classmethod
    def from_builtins(cls, data: Mapping[str, object]) -> RunSettings:
        """Inverse of `to_builtins`; a setting the mapping lacks takes its default."""
        return _settings({row.name: _decode(row.name, data[row.name]) for row in TABLE if row.name in data})

    def certificate_settings(self) -> dict[str, Builtin]:
        """The settings the certificate's ``settings`` section records, by their key there."""
        return {row.where[0][1]: _encode(self.value(row.name)) for row in TABLE
                if row.where and row.where[0][0] == "settings"}

    def closed_loop_settings(self) -> dict[str, Builtin]:
        """The settings the certificate's ``closed_loop`` section records (SPEC section 13), by their key there."""
        return {row.where[0][1]: _encode(self.value(row.name)) for row in TABLE
                if row.where and row.where[0][0] == "closed_loop"}

    @classmethod
    def from_certificate(cls, cert: Mapping[str, object]) -> RunSettings:
        """The settings a certificate records (its first location that has it; a certificate written before a
        setting existed has that setting's default). The shard is never recorded: a certificate is a whole run."""
        found: dict[str, object] = {}
        for row in TABLE:
            for section, key in row.where:
                part = cert.get(section)
                if isinstance(part, Mapping) and key in part:
                    found[row.name] = _decode(row.name, part[key])
                    break
        return _settings(found)

    # --- what the run key, a rerun and the comparisons see -----------------------------------------------------

    def run_key_fields(self) -> dict[str, Builtin]:
        """The settings a stored cell's run key holds, in table order (each only where it changes a plan, so a
        run at the defaults keeps the key, and the stored cells, of runs before the setting existed)."""
        return {row.name: _encode(self.value(row.name)) for row in TABLE if row.keyed is not None and row.keyed(self)}

    def rerun_argv(self) -> list[str]:
        """The ``--drivedegrade-*`` options that repeat these settings (`Setting.rerun` says which are given)."""
        out: list[str] = []
        for row in TABLE:
            got = self.value(row.name)
            if row.rerun == "never" or got is None or (row.rerun == "changed" and got == row.default):
                continue
            out += [row.flag] if isinstance(row.default, bool) else [row.flag, _text(got)]
        return out

    def differences(self, other: RunSettings) -> list[Difference]:
        """Every setting in which `other` differs from this run's, in table order."""
        return [Difference(row, self.value(row.name), other.value(row.name)) for row in TABLE
                if self.value(row.name) != other.value(row.name)]

    def same_run(self, other: RunSettings) -> list[Difference]:
        """The differences that make `other` another run's (shards of one run differ only where `Setting.per_shard`)."""
        return [d for d in self.differences(other) if not d.setting.per_shard]

    def baseline_differences(self, baseline: RunSettings) -> list[Difference]:
        """The differences that make `baseline` another quantity than this run (`Setting.gate`), as the gate
        refuses them: a KEYED setting only where either run key holds it."""
        out = []
        for d in self.differences(baseline):
            gate = d.setting.gate
            if gate is Gate.SAME or (gate is Gate.KEYED and self.keyed(d.setting) != baseline.keyed(d.setting)):
                out.append(d)
        return out

    def keyed(self, row: Setting) -> Builtin:
        """The setting's value as the run key holds it (None where the key leaves it out)."""
        return _encode(self.value(row.name)) if row.keyed is not None and row.keyed(self) else None


#: The options' defaults.
DEFAULTS = RunSettings()


class Gate(Enum):
    """What the baseline gate asks of a setting (`Setting.gate`; its reason in `Setting.reason`)."""

    SAME = "must equal the baseline's"
    KEYED = "must equal the baseline's where either run key holds it"
    FREE = "may differ from the baseline's"


@dataclass(frozen=True)
class Setting:
    """One row of `TABLE`: a field of `RunSettings` and what it means outside the run.

    `where`: its places in a certificate, (section, key), the first found wins (); none: not recorded.
    `keyed`: when the run key holds it (None: never; the frames key and the dataset fingerprint hold what it
    changes). `gate` and `reason`: whether it may differ between a run and its baseline, and why. `rerun`:
    whether a rerun's command line gives it "always", when "changed" from the default, or "never" (where the data
    lies is this machine's; a certificate is of a whole run, no shard). `per_shard`: shards of one run may
    differ in it.
    """

    name: str
    label: str
    flag: str
    where: tuple[tuple[str, str], ...]
    gate: Gate
    reason: str
    keyed: Callable[[RunSettings], bool] | None = None
    rerun: str = "changed"
    per_shard: bool = False

    @property
    def default(self) -> object:
        return DEFAULTS.value(self.name)


@dataclass(frozen=True)
class Difference:
    """One setting in which two runs differ: this run's value and the other's."""

    setting: Setting
    mine: object
    theirs: object

    @property
    def name(self) -> str:
        return self.setting.name

    def against_baseline(self) -> str:
        """``label: baseline X, this run Y (flag)``, as the gate names it."""
        row = self.setting
        return f"{row.label}: baseline {_shown(self.theirs)}, this run {_shown(self.mine)} ({row.flag})"


def _always(settings: RunSettings) -> bool:
    return True


_S, _K, _F = Gate.SAME, Gate.KEYED, Gate.FREE
TABLE: tuple[Setting, ...] = (
    Setting("data", "data set", "--drivedegrade-data", (("dataset", "source"),), _F, "where the data lies is not "
            "what it holds: the dataset fingerprint compares the scored frames' content", rerun="never",
            per_shard=True),
    Setting("split", "split", "--drivedegrade-split", (("dataset", "split"),), _S, "another split scores other "
            "frames", rerun="always"),
    Setting("frames", "frames asked for", "--drivedegrade-frames", (("dataset", "frames_requested"),
            ("dataset", "frames")), _F, "the gate compares the frames scored (their count and the dataset "
            "fingerprint), not how many were asked for"),
    Setting("seed", "corruption seed", "--drivedegrade-seed", (("settings", "seed"),), _S, "another seed draws "
            "other corruptions", keyed=_always, rerun="always"),
    Setting("seeds", "corruption seeds", "--drivedegrade-seeds", (("settings", "seeds"),), _S, "a retention "
            "averaged over several seeds is another quantity than one seed's", keyed=lambda s: s.seeds > 1),
    Setting("batch", "batch", "--drivedegrade-batch", (("settings", "batch"),), _K, "batched float sums round "
            "differently (within 1e-5 m); the run key holds it above 1", keyed=lambda s: s.batch > 1),
    Setting("reuse", "reuse", "--drivedegrade-no-reuse", (("settings", "reuse"),), _K, "a reused plan is the "
            "call's bit for bit; only with batches (where the run key holds it) does reuse change which frames "
            "share a call", keyed=lambda s: s.batch > 1 and not s.reuse),
    Setting("device", "device", "--drivedegrade-device", (("settings", "device"),), _K, "another device's kernels "
            "round differently, as batches do; the run key holds it off cpu", keyed=lambda s: s.device != "cpu"),
    Setting("timeout", "timeout", "--drivedegrade-timeout", (("settings", "timeout"),), _F, "it changes no plan a "
            "frame got: a frame it stops is a conformance failure the certificate reports", rerun="always"),
    Setting("metric", "verdict metric", "--drivedegrade-metric", (("settings", "verdict_metric"),), _S, "the "
            "verdict is put on another retention"),
    Setting("flat", "flat line", "--drivedegrade-flat", (("settings", "flat"),), _F, "the gate compares "
            "retentions, which the flat line only labels"),
    Setting("ego_box", "ego box", "--drivedegrade-ego-box", (("settings", "ego_box"),), _S, "another ego box "
            "scores other collisions, TTC and drivable-area verdicts", keyed=lambda s: s.ego_box != "nuscenes"),
    Setting("two_stage", "two-stage", "--drivedegrade-two-stage", (("settings", "two_stage"),), _S, "a two-stage "
            "run adds the stage-two EPDMS its verdict may be put on; the run key holds it, so neither run reuses the "
            "other's stored cells", keyed=lambda s: s.two_stage),
    Setting("shard", "shard", "--drivedegrade-shard", (), _F, "each shard scores its own part of a run; a "
            "certificate is of a whole run", rerun="never", per_shard=True),
    Setting("prefetch", "prefetch", "--drivedegrade-prefetch", (), _F, "it changes when a frame is decoded, "
            "corrupted and scored, never what: every output is the serial path's bit for bit", rerun="never",
            per_shard=True),
    Setting("adaptive", "adaptive", "--drivedegrade-adaptive", (("adaptive", "enabled"),), _F, "the gate compares "
            "retentions: an adaptive run estimates the same retention on the units it drew, and the sequential "
            "gate pairs it unit by unit with a full baseline's frames (and a full run is gated on an adaptive "
            "baseline's intervals); the run key holds it, so neither reuses the other's stored cells",
            keyed=lambda s: s.adaptive),
    Setting("alpha", "alpha", "--drivedegrade-alpha", (("adaptive", "alpha"),), _F, "it sets how sure an adaptive "
            "cell is when it stops, not what it estimates; the run key holds it in an adaptive run",
            keyed=lambda s: s.adaptive),
    Setting("isolate", "isolated planner", "--drivedegrade-isolate", (("settings", "planner_isolated"),), _F,
            "it changes where the planner runs, never a plan (the cells are the in-process run's bit for bit); "
            "the run key holds it, so an isolated run never reuses a cell computed beside the stream",
            keyed=lambda s: s.isolate),
    *(Setting(name, label, flag, (("closed_loop", name),), _F, "the closed loop is certified in its own section, "
              "beside the open-loop cells the gate compares") for name, label, flag in (
        ("loop", "loop", "--drivedegrade-loop"), ("closed_cells", "closed-loop cells", "--drivedegrade-closed-cells"),
        ("closed_seeds", "closed-loop seeds", "--drivedegrade-closed-seeds"),
        ("closed_hz", "closed-loop plan rate", "--drivedegrade-closed-hz"),
        ("closed_routes", "closed-loop routes", "--drivedegrade-closed-routes"),
        ("closed_steps", "closed-loop steps", "--drivedegrade-closed-steps"),
        ("closed_agents", "closed-loop agents", "--drivedegrade-closed-agents"),
        ("closed_collisions", "closed-loop collisions", "--drivedegrade-closed-collisions"),
        ("closed_scenarios", "closed-loop scenario routes", "--drivedegrade-closed-scenarios"),
        ("closed_lights", "closed-loop light routes", "--drivedegrade-closed-lights"))),
)
_BY_NAME = {row.name: row for row in TABLE}


def setting(name: str) -> Setting:
    """The row of `TABLE` for a field of `RunSettings`."""
    return _BY_NAME[name]


def check_table() -> list[str]:
    """What is wrong with `TABLE` against `RunSettings` (empty: every field has exactly one row, in field order)."""
    names = [f.name for f in fields(RunSettings)]
    rows = [row.name for row in TABLE]
    return [] if names == rows else [f"RunSettings fields {names} but TABLE rows {rows}"]


def _encode(value: object) -> Builtin:
    if isinstance(value, (Path, Shard)):
        return str(value)
    assert value is None or isinstance(value, (str, int, float, bool)), value
    return value


def _decode(name: str, raw: object) -> object:
    """A builtin back into the field's type; InvalidInput naming the setting when it cannot be."""
    default = DEFAULTS.value(name)
    if raw is None:
        return default
    try:
        if not isinstance(raw, (str, int, float)):
            raise ValueError(f"expected a number, a string or true / false, got {type(raw).__name__}")
        if name == "data":
            return None if raw == EMBEDDED_WORLD else Path(str(raw))
        if name == "shard":
            return Shard.parse(str(raw))
        if isinstance(default, bool) or isinstance(raw, bool):
            if not (isinstance(default, bool) and isinstance(raw, bool)):
                raise ValueError(f"expected {type(default).__name__}, got {raw!r}")
            return raw
        if isinstance(default, float):
            return float(raw)
        return int(raw) if name in ("frames", "prefetch", "closed_routes", "closed_steps", "closed_scenarios",
                                   "closed_lights") or \
            isinstance(default, int) else str(raw)
    except (ValueError, DriveDegradeError) as exc:
        raise InvalidInput(f"setting {name!r}: {exc}") from None


def _settings(found: Mapping[str, object]) -> RunSettings:
    """RunSettings from decoded values by field name (each of the field's type: `_decode` made it so)."""
    return RunSettings(**found)  # type: ignore[arg-type]


def _text(value: object) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def _shown(value: object) -> str:
    return repr(_encode(value))


def cores() -> int:
    """The cores this process may run on: its CPU affinity where the platform has one (a container or a CI job
    pinned to some of a machine's cores sees only those), else the machine's count; at least 1. The one count
    behind the default prefetch depth and OpenCV's share (`pacing`) and the world build's processes
    (`data.world.tasks`)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - macOS, Windows
        return max(1, os.cpu_count() or 1)
