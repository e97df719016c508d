"""Run options: one table of `--drivedegrade-*` flags, each also settable in `[tool.pytest.ini_options]`.

Values are parsed and checked once, at start-up, into a `RunOptions`; a bad value is a usage error that
names the option, never a traceback later in the run. Light: no heavy imports at module level.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

from ..constants import COMMAND_BLIND, COMMAND_SWAP, DEFAULT_TOLERANCE, EGO_BLIND, EGO_NOISE
from ..errors import DriveDegradeError
from ..settings import DEFAULTS, RunSettings, Shard
from .optiontable import ENABLE, OPTIONS
from .pathcheck import check_utf8_paths

if TYPE_CHECKING:
    from ..raypool import RayOptions

#: the input cells besides the cameras: ego status, command
EGO_FAMILIES = (EGO_NOISE, EGO_BLIND, COMMAND_BLIND, COMMAND_SWAP)


_BY_DEST = {spec.dest: spec for spec in OPTIONS}


def value(config: pytest.Config, dest: str) -> Any:
    """The command-line value, else the ini value, else None."""
    got = config.getoption(dest, default=None)
    if got is None:
        got = config.getini(dest) or None
    return got


def _fail(dest: str, text: str) -> pytest.UsageError:
    return pytest.UsageError(f"{_BY_DEST[dest].flag}: {text}")


def _number(config: pytest.Config, dest: str, kind: type[int] | type[float], default: Any, low: float,
            high: float | None) -> Any:
    """A number option within [low, high]; NaN and infinities are usage errors (a NaN tolerance would turn
    the gate off, a NaN flat line would seal a wrong verdict)."""
    raw = value(config, dest)
    if raw is None:
        return default
    try:
        got = kind(str(raw).strip())
    except ValueError:
        raise _fail(dest, f"expected {'an integer' if kind is int else 'a number'}, got {raw!r}") from None
    if not math.isfinite(got):
        raise _fail(dest, f"must be a finite number, got {raw!r}")
    if got < low or (high is not None and got > high):
        bound = f"between {low} and {high}" if high is not None else f"at least {low}"
        raise _fail(dest, f"must be {bound}, got {got}")
    return got


#: The shortest --drivedegrade-timeout but 0 (no limit): below a millisecond every predict() call would fail.
MIN_TIMEOUT = 1e-3


def _timeout(config: pytest.Config) -> float:
    got = float(_number(config, "drivedegrade_timeout", float, DEFAULTS.timeout, 0.0, None))
    if 0 < got < MIN_TIMEOUT:
        raise _fail("drivedegrade_timeout", f"must be 0 (no limit) or at least {MIN_TIMEOUT:g} s, got {got:g}: "
                    "every predict() call would time out")
    return got


def _flag(config: pytest.Config, dest: str) -> bool:
    """An on/off option: the flag on the command line, or true / false in the ini file."""
    raw = value(config, dest)
    if raw is None or isinstance(raw, bool):
        return bool(raw)
    text = str(raw).strip().lower()
    if text not in ("1", "true", "yes", "on", "0", "false", "no", "off"):
        raise _fail(dest, f"expected true or false, got {raw!r}")
    return text in ("1", "true", "yes", "on")


def _list(config: pytest.Config, dest: str) -> list[str] | None:
    raw = value(config, dest)
    if raw is None:
        return None
    items = [p.strip() for p in str(raw).replace(" ", ",").split(",") if p.strip()]
    if not items:
        raise _fail(dest, "is empty")
    return items


@dataclass(frozen=True)
class RunOptions:
    """Everything a run depends on, checked: its `settings` and how this session runs and reports it.
    `planner_path` is None for a conftest planner fixture."""

    planner_path: Path | None
    settings: RunSettings  #: what the run's numbers depend on (data, split, frames, seed(s), batch, ...), checked
    families: tuple[str, ...]
    severities: tuple[int, ...]
    report_dir: Path
    baseline_path: Path | None
    tolerance: float
    ego: tuple[str, ...] = ("ego_noise", "ego_blind")  #: the ego cells to run (SPEC section 10)
    baseline_partial: bool = False  #: --drivedegrade-baseline-partial: gate on what the baseline covers
    baseline_any_planner: bool = False  #: --drivedegrade-baseline-any-planner: another planner's baseline is fine
    baseline_public_key: Path | None = None  #: --drivedegrade-baseline-public-key: the baseline must be signed by it
    report_overwrite: bool = False  #: --drivedegrade-report-overwrite: replace another planner's outputs
    resume: bool = True  #: not --drivedegrade-no-resume: reuse stored cells of the same run key (results unchanged)
    ray: RayOptions | None = None  #: --drivedegrade-ray: the planner actors (None: the planner runs in-process)
    dry_run: bool = False  #: --drivedegrade-dry-run: stop after the pre-flight check


def _ray(config: pytest.Config) -> RayOptions | None:
    """--drivedegrade-ray ADDRESS and its actors and GPUs, checked: Ray importable, no -n (the actors are the
    run's parallelism and the controller their only driver: xdist workers would each start a pool)."""
    address = value(config, "drivedegrade_ray")
    actors = _number(config, "drivedegrade_ray_actors", int, None, 1, None)
    gpus = _number(config, "drivedegrade_ray_gpus", float, 0.0, 0.0, None)
    if address is None:
        for dest in ("drivedegrade_ray_actors", "drivedegrade_ray_gpus"):
            if value(config, dest) is not None:
                raise _fail(dest, "needs --drivedegrade-ray ADDRESS (local, auto or a cluster address)")
        return None
    address = str(address).strip()
    if address not in ("local", "auto") and ":" not in address:
        raise _fail("drivedegrade_ray", f"expected local, auto, ray://HOST:PORT or HOST:PORT, got {address!r}")
    workers = getattr(config.option, "numprocesses", None)
    if workers:
        raise _fail("drivedegrade_ray", f"cannot be combined with -n {workers} (xdist): the Ray actors run the cells' "
                    "frames in parallel and the controller must be their only driver; drop -n (or give -n 0)")
    from ..raypool import RayOptions, import_ray

    try:
        import_ray()
    except DriveDegradeError as exc:
        raise _fail("drivedegrade_ray", str(exc)) from None
    return RayOptions(address, actors, gpus)


def _device(config: pytest.Config) -> str:
    """cpu, cuda or cuda:N; CUDA only where torch sees that device, so a GPU run never silently runs on CPU."""
    raw = value(config, "drivedegrade_device")
    device = str(raw or DEFAULTS.device).strip().lower()
    if device == "cpu":
        return device
    head, _, index = device.partition(":")
    if head != "cuda" or (index and not index.isdigit()):
        raise _fail("drivedegrade_device", f"unknown device {raw!r}; valid devices: cpu, cuda, cuda:N")
    try:
        import torch
    except ImportError:
        raise _fail("drivedegrade_device", f"{device} needs PyTorch with CUDA, and torch is not installed; "
                    "run on cpu or install a CUDA build of torch") from None
    if not torch.cuda.is_available():
        raise _fail("drivedegrade_device", f"{device} asked for, but this machine has no CUDA device torch can use "
                    f"(torch {torch.__version__}, built with CUDA {torch.version.cuda or 'none'}); run on cpu, or "
                    "on a machine with a GPU")
    count = torch.cuda.device_count()
    if index and int(index) >= count:
        raise _fail("drivedegrade_device", f"{device}: this machine has {count} CUDA device(s), numbered 0 to "
                    f"{count - 1}")
    return device


def _settings(config: pytest.Config, here: Path) -> RunSettings:
    """The run's settings (`RunSettings`), each checked."""
    from ..data.nuscenes import SPLITS
    from ..metrics.pdms.constants import EGO_BOXES

    data = value(config, "drivedegrade_data")
    split = str(value(config, "drivedegrade_split") or DEFAULTS.split)
    if split not in SPLITS:
        raise _fail("drivedegrade_split", f"unknown split {split!r}; valid splits: {', '.join(SPLITS)}")
    shard_text = value(config, "drivedegrade_shard")
    try:
        shard = Shard.parse(str(shard_text)) if shard_text is not None else None
    except DriveDegradeError as exc:
        raise _fail("drivedegrade_shard", str(exc)) from None
    metric = str(value(config, "drivedegrade_metric") or DEFAULTS.metric).strip().lower()
    if metric not in ("l2", "pdms", "epdms", "epdms2"):
        raise _fail("drivedegrade_metric", f"unknown metric {metric!r}; valid metrics: l2, pdms, epdms, epdms2")
    two_stage = _two_stage(config)
    if metric == "epdms2" and not two_stage:
        raise _fail("drivedegrade_metric", "epdms2 is the two-stage EPDMS: it needs --drivedegrade-two-stage")
    ego_box = str(value(config, "drivedegrade_ego_box") or DEFAULTS.ego_box).strip().lower()
    if ego_box not in EGO_BOXES:
        raise _fail("drivedegrade_ego_box", f"unknown ego box {ego_box!r}; valid boxes: {', '.join(EGO_BOXES)}")
    return _closed(config, RunSettings(
        data=(here / data).resolve() if data else None,
        split=split,
        frames=_number(config, "drivedegrade_frames", int, DEFAULTS.frames, 1, None),
        seed=_number(config, "drivedegrade_seed", int, DEFAULTS.seed, 0, None),
        seeds=_number(config, "drivedegrade_seeds", int, DEFAULTS.seeds, 1, None),
        batch=_number(config, "drivedegrade_batch", int, DEFAULTS.batch, 1, 4096),
        reuse=not _flag(config, "drivedegrade_no_reuse"),
        device=_device(config),
        timeout=_timeout(config),
        metric=metric,
        flat=_number(config, "drivedegrade_flat", float, DEFAULTS.flat, 0.0, 1.0),
        ego_box=ego_box,
        two_stage=two_stage,
        shard=shard,
        prefetch=_prefetch(config),
        adaptive=_adaptive(config),
        alpha=_number(config, "drivedegrade_alpha", float, DEFAULTS.alpha, 1e-9, 0.5),
        isolate=_flag(config, "drivedegrade_isolate"),
    ))


def _closed(config: pytest.Config, settings: RunSettings) -> RunSettings:
    """The closed-loop settings (SPEC section 13), each checked."""
    from ..closedloop.agents import AGENT_MODES
    from ..closedloop.cells import HZ_CHOICES, selection
    from ..closedloop.leaderboard import COLLISION_RULES

    loop = str(value(config, "drivedegrade_loop") or DEFAULTS.loop).strip().lower()
    if loop not in ("open", "closed", "both"):
        raise _fail("drivedegrade_loop", f"expected open, closed or both, got {loop!r}")
    cells = str(value(config, "drivedegrade_closed_cells") or DEFAULTS.closed_cells).strip()
    try:
        chosen = selection(cells)
    except DriveDegradeError as exc:
        raise _fail("drivedegrade_closed_cells", str(exc)) from None
    if cells not in ("slice", "all"):
        from ..closedloop.cells import closed_id

        cells = ",".join(closed_id(f, s)[len("closed-"):] for f, s in chosen)
    hz = _number(config, "drivedegrade_closed_hz", int, DEFAULTS.closed_hz, 1, 10)
    if hz not in HZ_CHOICES:
        raise _fail("drivedegrade_closed_hz", f"must be one of {', '.join(map(str, HZ_CHOICES))} (a whole number of "
                    f"10 Hz steps per call), got {hz}")
    return replace(settings, loop=loop, closed_cells=cells, closed_hz=hz,
                   closed_seeds=_number(config, "drivedegrade_closed_seeds", int, DEFAULTS.closed_seeds, 1, None),
                   closed_routes=_number(config, "drivedegrade_closed_routes", int, None, 1, None),
                   closed_steps=_number(config, "drivedegrade_closed_steps", int, None, 1, None),
                   closed_agents=_one_of(config, "drivedegrade_closed_agents", DEFAULTS.closed_agents, AGENT_MODES),
                   closed_collisions=_one_of(config, "drivedegrade_closed_collisions", DEFAULTS.closed_collisions,
                                             COLLISION_RULES),
                   closed_scenarios=_number(config, "drivedegrade_closed_scenarios", int, DEFAULTS.closed_scenarios, 0,
                                            None),
                   closed_lights=_number(config, "drivedegrade_closed_lights", int, DEFAULTS.closed_lights, 0, None))


def _one_of(config: pytest.Config, name: str, default: str, allowed: tuple[str, ...]) -> str:
    """A closed-loop choice option (--drivedegrade-closed-agents, --drivedegrade-closed-collisions), checked."""
    got = str(value(config, name) or default).strip().lower()
    if got not in allowed:
        raise _fail(name, f"expected {' or '.join(allowed)}, got {got!r}")
    return got


def _two_stage(config: pytest.Config) -> bool:
    """--drivedegrade-two-stage, checked: not with what runs a cell in parts or elsewhere (the stage two of a frame
    is run beside its stage one, in the process that ran the cell), nor with several seeds (one run per cell)."""
    if not _flag(config, "drivedegrade_two_stage"):
        return False
    for dest, why in (("drivedegrade_ray", "its planner actors run the cells' frames elsewhere"),
                      ("drivedegrade_adaptive", "an adaptive cell runs in units and stops early")):
        if value(config, dest):
            raise _fail("drivedegrade_two_stage", f"cannot be combined with {_BY_DEST[dest].flag}: {why}, and the "
                        "stage two of each frame runs beside the whole cell's stage one in one process")
    if (_number(config, "drivedegrade_seeds", int, DEFAULTS.seeds, 1, None) or 1) > 1:
        raise _fail("drivedegrade_two_stage", "cannot be combined with --drivedegrade-seeds above 1: the two-stage "
                    "EPDMS is scored on one run of each cell")
    return True


def _adaptive(config: pytest.Config) -> bool:
    """--drivedegrade-adaptive (its --drivedegrade-alpha in (0, 0.5]), checked: not with several seeds (the
    stopping rule pairs one run of a cell with clean). With a shard, a shard owns whole families (`parse`)."""
    if not _flag(config, "drivedegrade_adaptive"):
        if value(config, "drivedegrade_alpha") is not None:
            raise _fail("drivedegrade_alpha", "needs --drivedegrade-adaptive (a full run stops no cell early)")
        return False
    if (_number(config, "drivedegrade_seeds", int, DEFAULTS.seeds, 1, None) or 1) > 1:
        raise _fail("drivedegrade_adaptive", "cannot be combined with --drivedegrade-seeds above 1: the stopping "
                    "rule pairs one run of each cell with clean, unit by unit")
    return True


#: The deepest --drivedegrade-prefetch: each frame ahead holds up to six decoded and corrupted images.
MAX_PREFETCH = 64


def _prefetch(config: pytest.Config) -> int:
    """--drivedegrade-prefetch N, or the machine's default (`pacing.prefetch_depth`): the processes that run cells
    here are the xdist workers, or a local Ray cluster's actors (default 2); a remote cluster's actors have
    their own machines, counted as one process each. The workers are counted from -n on the controller and from
    PYTEST_XDIST_WORKER_COUNT in a worker: xdist resets a worker's -n to None, which once gave every worker of
    `-n 2` on two cores its loading and scoring threads (12 % slower on the main job)."""
    from ..pacing import auto_prefetch, processes_here

    given = _number(config, "drivedegrade_prefetch", int, None, 0, MAX_PREFETCH)
    if given is not None:
        return int(given)
    workers = config.getoption("numprocesses", default=None)  # -n, an int once xdist has read "auto"
    processes = max(workers if isinstance(workers, int) and workers > 0 else 1, processes_here())
    if value(config, "drivedegrade_ray") == "local":
        processes = int(_number(config, "drivedegrade_ray_actors", int, 2, 1, None))
    return auto_prefetch(processes)


#: The options that take a path (and the planner file, ENABLE's value): valid UTF-8 (`pathcheck`).
PATH_OPTIONS = ("drivedegrade_data", "drivedegrade_report", "drivedegrade_baseline",
                "drivedegrade_baseline_public_key")


def parse(config: pytest.Config) -> RunOptions:
    """Read and check every option; raise pytest.UsageError naming the first bad one."""
    from ..corruptions.ladder import FAMILIES, SEVERITIES

    here = Path(config.invocation_params.dir)
    check_utf8_paths(here, {_BY_DEST[d].flag: value(config, d) for d in (ENABLE, *PATH_OPTIONS)})
    path = value(config, ENABLE)
    planner_path = (here / path).resolve() if path else None
    listed = _list(config, "drivedegrade_families")
    families = listed or [*FAMILIES, *EGO_FAMILIES]
    unknown = [f for f in families if f not in FAMILIES and f not in EGO_FAMILIES]
    if unknown:
        raise _fail("drivedegrade_families", f"unknown famil{'y' if len(unknown) == 1 else 'ies'} "
                    f"{', '.join(map(repr, unknown))}; valid families: {', '.join([*FAMILIES, *EGO_FAMILIES])}")
    severities = []
    for s in _list(config, "drivedegrade_severities") or [str(s) for s in SEVERITIES]:
        if not s.isdigit() or int(s) not in SEVERITIES:
            raise _fail("drivedegrade_severities", f"severity {s!r} is not one of 1, 2, 3, 4, 5")
        severities.append(int(s))
    baseline, public_key = value(config, "drivedegrade_baseline"), value(config, "drivedegrade_baseline_public_key")
    if public_key and not baseline:
        raise _fail("drivedegrade_baseline_public_key", "a public key to check the baseline with, but no "
                    "--drivedegrade-baseline: pass the baseline certificate too, or drop the key")
    settings = _settings(config, here)
    if baseline and settings.shard is not None:  # issue 20 M6: a shard's frames are not the baseline's run
        raise _fail("drivedegrade_baseline", "a shard cannot be gated: the baseline covers the whole run, a shard "
                    f"only its part of the frames ({settings.shard}). Run the shards without "
                    "--drivedegrade-baseline and gate the merge: drivedegrade merge SHARD_DIRS --out DIR "
                    "--baseline BASE (--tolerance X), or gate the whole run unsharded")
    options = RunOptions(
        planner_path=planner_path,
        settings=settings,
        families=tuple(f for f in FAMILIES if f in families),
        severities=tuple(sorted(set(severities))),
        report_dir=(here / str(value(config, "drivedegrade_report") or "reports")).resolve(),
        baseline_path=(here / baseline).resolve() if baseline else None,
        tolerance=_number(config, "drivedegrade_tolerance", float, DEFAULT_TOLERANCE, 0.0, 1.0),
        ego=tuple(f for f in EGO_FAMILIES if f in families),
        baseline_partial=_flag(config, "drivedegrade_baseline_partial"),
        baseline_any_planner=_flag(config, "drivedegrade_baseline_any_planner"),
        baseline_public_key=(here / str(public_key)).resolve() if public_key else None,
        report_overwrite=_flag(config, "drivedegrade_report_overwrite"),
        resume=not _flag(config, "drivedegrade_no_resume"),
        ray=_ray(config),
        dry_run=_flag(config, "drivedegrade_dry_run"),
    )
    if settings.isolate and (planner_path is None or options.ray is not None):
        raise _fail("drivedegrade_isolate", "needs the planner as a file (pytest --drivedegrade PLANNER.py): a "
                    "conftest.py is imported by pytest itself in every process" if planner_path is None else
                    "cannot be combined with --drivedegrade-ray: the actors run each cell's stream beside the "
                    "planner; isolate it with -n N instead")
    if settings.adaptive and settings.shard is not None:  # an adaptive shard owns whole families' cells
        from ..cells import run_order
        from ..shards import adaptive_owned

        try:
            adaptive_owned(run_order(options.families, options.severities, ego=options.ego), settings.shard)
        except DriveDegradeError as exc:
            raise _fail("drivedegrade_shard", str(exc)) from None
    return options
