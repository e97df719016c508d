"""The pre-flight check (SPEC section 20), on the controller before any cell: the planner's declared needs
(cameras, poses, ``context``, LiDAR, ``predict_batch``, ``reset``, device) against what the data serve; one clean
frame predicted and validated (shape, dtype, finiteness, cameras read that are not declared); the run's predictions
counted and its wall time estimated, in one line. A mismatch is one usage error naming every problem, and no cell
runs; ``--drivedegrade-dry-run`` stops after the check.

The planner is built here from its file as a Ray actor builds it (`actors.PlannerFile`, with the module the
session imported) and torn down after the check; a fixture that requests what only pytest's test run provides
(``request``, a conftest fixture) leaves the frame unchecked until the first cell, and the line says so.
"""

from __future__ import annotations

import inspect
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from ..constants import HORIZON_STEPS
from ..data.frame import Frame
from ..errors import DataError, DriveDegradeError, PlannerOutputError
from ..loader import planner_view
from ..pacing import opencv_share
from ..planning import (
    CallStyle,
    Planner,
    call_style,
    horizon_problem,
    planner_cameras,
    planner_poses,
    to_numpy,
    validate_output,
)
from ..run import RunContext
from ..store import ResultStore
from ..stream import describe_failure, time_limit
from .options import RunOptions

#: The optional planner attributes the check reads besides ``cameras``: the number of 0.5 s poses it plans
#: (SPEC section 19: 6, or NAVSIM's 8) and whether it reads LIDAR_TOP through ``context.lidar_points()``.
POSES_ATTR, LIDAR_ATTR = "poses", "lidar"
#: Frames tried, in run order, for one whose declared cameras decode (a broken image is the data's, not the
#: planner's: the cells report it).
PROBE_FRAMES = 8
HEAD = "drivedegrade pre-flight"


@dataclass(frozen=True)
class Probe:
    """One clean frame predicted: which, the planner's seconds on its second (warm) call, the cameras read."""

    token: str
    seconds: float
    read: tuple[str, ...]
    name: str = ""  #: the planner's name (its report folder), "" where it is not usable


def declared_problems(planner: Planner, context: RunContext) -> tuple[list[str], list[str]]:
    """(problems, notes): what the planner declares it needs that the data or the run do not serve."""
    problems: list[str] = []
    notes: list[str] = []
    try:
        cameras = planner_cameras(planner)
        style = call_style(planner)
    except DriveDegradeError as exc:
        return [str(exc)], notes
    frames = context.frames
    missing = sorted({c for f in frames for c in cameras if c not in f.cameras})
    if missing:
        problems.append(f"planner.cameras declares {', '.join(missing)}, which some scored frames do not have")
    root = getattr(getattr(context, "reader", None), "root", None)
    problems += _horizon(planner, frames, "the data" if root is None else f"the data at {root}")
    lidar = getattr(planner, LIDAR_ATTR, False)
    if lidar and not style.takes_context:
        problems.append(f"planner.{LIDAR_ATTR} is set but predict() takes no `context` parameter, the one way "
                        "LiDAR points are served (context.lidar_points()): add `context=None` to predict()")
    without = sum(1 for f in frames if not f.lidar_file)
    if lidar and without:
        problems.append(f"planner.{LIDAR_ATTR} is set but {without} of {len(frames)} scored frames have no "
                        "LIDAR_TOP sweep in this data set")
    reset: Callable[..., object] = getattr(planner, "reset") if style.resets else (lambda token: None)  # noqa: B009
    try:
        inspect.signature(reset).bind("scene-token")
    except (TypeError, ValueError):
        problems.append("planner.reset must take one argument, the scene token (reset(scene_token)); "
                        f"its signature is reset{_signature(reset)}")
    if style.resets and getattr(context.settings, "two_stage", False):
        problems.append("--drivedegrade-two-stage cannot score a planner with reset(): its stage two starts from "
                        "poses the car never drove, where NAVSIM gives the planner the stage-one history; the suite "
                        "does not replay that history into a stateful planner before each start. Run it without "
                        "--drivedegrade-two-stage")
    batch = context.settings.batch
    if batch > 1 and not callable(getattr(planner, "predict_batch", None)):
        notes.append(f"--drivedegrade-batch {batch} has no effect: the planner has no predict_batch()")
    elif batch > 1 and style.resets:
        notes.append(f"--drivedegrade-batch {batch} has no effect: a planner with reset() is called frame by frame")
    problems += _device(planner, context.settings.device)
    return problems, notes


def _signature(function: Callable[..., object]) -> str:
    try:
        return str(inspect.signature(function))
    except (TypeError, ValueError):
        return "(...)"


def _horizon(planner: Planner, frames: Sequence[Frame], where: str = "the data") -> list[str]:
    """The planner's declared poses against the future every scored frame of the data holds
    (`planning.horizon_problem`, the rule the start-up check applies too)."""
    future = min((getattr(f, "future_needed", len(f.gt_future)) for f in frames), default=HORIZON_STEPS)
    problem = horizon_problem(planner, future, where)
    return [problem] if problem else []


def _device(planner: Planner, device: str) -> list[str]:
    """The planner's weights on another device than --drivedegrade-device: its plans would be computed elsewhere
    than the run key says."""
    for owner in (planner, getattr(planner, "model", None), getattr(planner, "net", None)):
        parameters = getattr(owner, "parameters", None)
        if owner is None or not callable(parameters):
            continue
        try:
            first = next(iter(parameters()), None)
        except (TypeError, StopIteration):
            return []
        found = str(getattr(first, "device", "") or "")
        wanted = device if ":" in device or device == "cpu" else f"{device}:"
        if found and not (found == wanted or found.startswith(wanted)):
            return [f"the run asks for --drivedegrade-device {device} but the planner's weights are on {found}: "
                    "build it on planner_device() (or drivedegrade_context.device)"]
        return []
    return []


def _frame(context: RunContext, cameras: Sequence[str]) -> tuple[Frame | None, dict[str, np.ndarray]]:
    """The first of `PROBE_FRAMES` run frames whose declared cameras all decode, with their images. A frame with
    a non-finite planner input (`Frame.input_fault`) is skipped: it is the data set's fault in every cell, and a
    planner that passes the NaN on into its plan is not in breach of its contract (issue 37)."""
    for frame in context.frames[:PROBE_FRAMES]:
        if frame.input_fault:
            continue
        try:
            return frame, {c: _readonly(context.decode(frame, c)) for c in cameras}
        except DataError:
            continue
    return None, {}


def _readonly(image: np.ndarray) -> np.ndarray:
    if image.flags.writeable:
        image = image.copy()
        image.setflags(write=False)
    return image


def _call(planner: Planner, context: RunContext, frame: Frame, images: Mapping[str, np.ndarray], style: CallStyle,
          read: list[str]) -> tuple[object, float]:
    """One clean predict() as the cells call it; returns (raw output, seconds)."""
    def load(camera: str) -> np.ndarray:
        read.append(camera)
        found = images.get(camera)
        return found if found is not None else _readonly(context.decode(frame, camera))

    ego = replace(frame.ego, past_xy=_readonly(np.array(frame.ego.past_xy, dtype=np.float64)))
    if style.resets:
        getattr(planner, "reset")(frame.scene_token)  # noqa: B009 - optional: not in the Planner protocol
    predict: Callable[..., object] = planner.predict
    start = time.perf_counter()
    with time_limit(context.settings.timeout):
        if style.takes_context:
            raw = predict(planner_view(load), ego, frame.command, context=context.context_of(frame).private())
        else:
            raw = predict(planner_view(load), ego, frame.command)
    return raw, time.perf_counter() - start


def probe_first_frame(planner: Planner, context: RunContext) -> tuple[Probe | None, list[str], list[str]]:
    """(probe, problems, notes) of one clean frame predicted twice (the second timed) and validated."""
    cameras, style = planner_cameras(planner), call_style(planner)
    frame, images = _frame(context, cameras)
    if frame is None:
        return None, [], [f"no clean frame checked: the declared cameras of the first {PROBE_FRAMES} frames do "
                          "not decode or hold a non-finite input (the cells report the data errors)"]
    read: list[str] = []
    try:
        with opencv_share():  # as the cells call it: OpenCV's thread count the run's, and put back after
            _call(planner, context, frame, images, style, read)
            raw, seconds = _call(planner, context, frame, images, style, read)
        plan = validate_output(to_numpy(raw), frame.token, planner_poses(planner))
    except PlannerOutputError as exc:
        return None, [str(exc)], []
    except Exception as exc:  # noqa: BLE001 - the planner's failure on a clean frame: named, no traceback
        return None, [describe_failure(exc, frame.token)], []
    probe = Probe(frame.token, seconds, tuple(dict.fromkeys(read)), _usable_name(planner))
    undeclared = [c for c in probe.read if c not in cameras]
    if not undeclared:
        return probe, [], []
    black = {**images, **{c: _readonly(np.zeros_like(context.decode(frame, c))) for c in undeclared}}
    try:
        with opencv_share():
            again = validate_output(to_numpy(_call(planner, context, frame, black, style, [])[0]), frame.token,
                                    planner_poses(planner))
    except Exception as exc:  # noqa: BLE001 - failing on a black camera it does not declare is relying on it
        again = np.full_like(plan, np.nan) if not isinstance(exc, KeyboardInterrupt) else plan
    if style.deterministic and not np.array_equal(again, plan):
        return probe, [f"predict() reads {', '.join(undeclared)}, which planner.cameras ({', '.join(cameras)}) "
                       f"does not declare, and its plan on frame {frame.token!r} changes when they are black: add "
                       "them to planner.cameras (or stop reading them); the null control would fail"], []
    return probe, [], [f"predict() reads {', '.join(undeclared)} without declaring it; the plan does not change "
                       "when it is black"]


def _usable_name(planner: Planner) -> str:
    from ..planning import planner_name

    try:
        return planner_name(planner, "")
    except DriveDegradeError:
        return ""


def _name(probe: Probe | None, options: RunOptions) -> str:
    """The report folder's name: the planner's, where the pre-flight built it, else the file's stem."""
    if probe is not None and probe.name:
        return probe.name
    return options.planner_path.stem if options.planner_path else "planner"


def build_planner(config: pytest.Config, options: RunOptions, context: RunContext, collect_path: Path,
                  module: ModuleType | None) -> tuple[Planner, Callable[[], list[str]]] | str:
    """The planner built from its fixture outside pytest's test run, with its teardown; or why it cannot be
    (a fixture that requests ``request`` or a conftest fixture). A fixture that raises is a usage error."""
    from .actors import FixtureUnavailable, PlannerFile

    if module is None:  # conftest mode: the conftest module pytest loaded
        module = next((p for p in config.pluginmanager.get_plugins()
                       if Path(getattr(p, "__file__", "") or ".") == collect_path), None)
    try:
        return PlannerFile(collect_path, loaded=module)(context)
    except FixtureUnavailable as exc:
        return str(exc).split(", which a ")[0]
    except DriveDegradeError as exc:
        raise pytest.UsageError(f"{HEAD}: building the planner failed, so no cell ran: {exc}") from None


def _processes(config: pytest.Config, options: RunOptions) -> int:
    """The processes that run cells: the xdist workers (-n), the Ray actors, or this one."""
    if options.ray is not None:
        return options.ray.actors or 2
    workers = config.getoption("numprocesses", default=None)
    return workers if isinstance(workers, int) and workers > 0 else 1


def rootdir_note(invocation: Path, rootdir: Path, planner: Path | None, inifile: Path | None) -> str:
    """Why a planner file outside the current folder matters ("" when it does not): pytest derives its rootdir
    from the paths on the command line, so the run's cache (the world, the floor) and the settings it reads move
    with the file, silently (a second world build, a retrained floor, the project's ini options dropped)."""
    if planner is None or planner.is_relative_to(invocation) or rootdir == invocation:
        return ""
    ini = f"the settings of {inifile}" if inifile else "no ini file's settings"
    return (f"the planner file lies outside {invocation}, so pytest took {rootdir} as its rootdir: the cache (the "
            f"world, the floor) is {rootdir / '.pytest_cache'} and {ini} apply; pass --rootdir {invocation} (and "
            "-c pyproject.toml) to keep this folder's")


def replaced_note(folder: Path, frames: int, cells: int) -> str:
    """A line when `folder` holds a certificate of a run of another size (the quick recipe's 48 frames over the
    full run's 204): this run replaces it; "" when there is none or it is of the same size."""
    import json

    try:
        cert = json.loads((folder / "certificate.json").read_text())
        theirs = (int(cert["dataset"]["frames"]), len(cert["cells"]))
    except (OSError, ValueError, KeyError, TypeError):
        return ""
    if theirs == (frames, cells):
        return ""
    return (f"{folder} holds the certificate of another run ({theirs[0]} frames, {theirs[1]} cells); this run "
            f"({frames} frames, {cells} cells) replaces it: pass another --drivedegrade-report to keep both")


def _others() -> float:
    """The runnable processes of other jobs: the 1-minute load average less this one (0 where unknown)."""
    try:
        return max(0.0, os.getloadavg()[0] - 1.0)
    except (AttributeError, OSError):  # pragma: no cover - a platform without a load average
        return 0.0


@dataclass(frozen=True)
class Checked:
    """What the check found: the probe (None: no frame checked, `why`), notes, and the cells a stored result
    with this run's key will stand for (a rerun computes only the others)."""

    probe: Probe | None
    why: str = ""
    notes: tuple[str, ...] = ()
    stored: frozenset[str] = frozenset()


def _stored(planner: Planner, context: RunContext, store: ResultStore | None,
            cells: Sequence[tuple[str, int]]) -> frozenset[str]:
    """The cells of `cells` a stored result of this run key will stand for (`checks.stored_reader`)."""
    if store is None or not store.resume:
        return frozenset()
    from ..cells import cell_id
    from .checks import stored_reader

    try:
        read = stored_reader(context, planner, store)
        return frozenset(c for c in (cell_id(f, s) for f, s in cells) if read(c) is not None)
    except DriveDegradeError:  # a bad name or cameras: the cells report it
        return frozenset()


@dataclass(frozen=True)
class Found:
    """What checking a built planner found: the problems (a usage error), notes, the probe and the stored cells."""

    problems: tuple[str, ...]
    notes: tuple[str, ...]
    probe: Probe | None
    stored: frozenset[str]


def inspect_planner(planner: Planner, context: RunContext, store: ResultStore | None,
                    cells: Sequence[tuple[str, int]]) -> Found:
    """The declared needs against the data, one clean frame predicted and validated, the stored cells: what the
    controller runs under -n 0 and `isolated` runs in a process of its own under -n N."""
    problems, notes = declared_problems(planner, context)
    probe = None
    if not problems:
        probe, problems, more = probe_first_frame(planner, context)
        notes += more
    stored = _stored(planner, context, store, cells) if not problems else frozenset()
    return Found(tuple(problems), tuple(notes), probe, stored)


#: The check run in a process of its own (`isolated.check_in_child`, its digest folder bound): the planner built
#: and `inspect_planner` run there, or why no frame could be checked.
ChildCheck = Callable[[RunOptions, RunContext, Path, "ModuleType | None", "ResultStore | None",
                       Sequence[tuple[str, int]]], "Found | str"]


def _check(config: pytest.Config, options: RunOptions, context: RunContext, collect_path: Path,
           module: ModuleType | None, store: ResultStore | None = None,
           cells: Sequence[tuple[str, int]] = (), child: ChildCheck | None = None) -> Checked:
    """What the check found; a usage error naming every problem. With `child` (under -n N: `isolated`) the
    planner is built and checked in a process of its own: the controller, which decides the exit status, never
    runs planner code."""
    if options.ray is not None:
        return Checked(None, "the planner is built in the Ray actors")
    if child is not None:
        found: Found | str = child(options, context, collect_path, module, store, cells)
    else:
        built = build_planner(config, options, context, collect_path, module)
        if isinstance(built, str):
            return Checked(None, built)
        planner, close = built
        try:
            found = inspect_planner(planner, context, store, cells)
        finally:
            close()
            del planner
    if isinstance(found, str):
        return Checked(None, found)
    if found.problems:
        listed = "\n".join(f"  - {p}" for p in found.problems)
        raise pytest.UsageError(f"{HEAD}: the planner and the data disagree, so no cell ran:\n{listed}")
    return Checked(found.probe, "", found.notes, found.stored)


def preflight_lines(config: pytest.Config, options: RunOptions, context: RunContext, collect_path: Path,
                    module: ModuleType | None, cells: Sequence[tuple[str, int]], closed: int,
                    store: ResultStore | None = None, child: ChildCheck | None = None) -> list[str]:
    """The pre-flight check's lines (the estimate first); pytest.UsageError on a mismatch, before any cell."""
    from ..cells import cell_id
    from ..certificate.estimate import count_predictions, estimate_line, run_wall_seconds
    from ..metrics.pdms.two_stage import STAGE_TWO_STARTS

    checked = _check(config, options, context, collect_path, module, store, cells, child)
    probe, why, notes = checked.probe, checked.why, list(checked.notes)
    todo = [(f, s) for f, s in cells if cell_id(f, s) not in checked.stored]
    if checked.stored:
        notes.append(f"{len(checked.stored)} of {len(cells)} cells are stored with this run's key and are reused "
                     "(--drivedegrade-no-resume recomputes them): the estimate counts the other cells")
    replaced = replaced_note(options.report_dir / _name(probe, options), context.frames_total,
                             len(cells) + closed) if options.settings.shard is None else ""
    notes += [replaced] if replaced else []
    processes = _processes(config, options)
    per_frame = 1 + (len(STAGE_TWO_STARTS) if options.settings.two_stage else 0)  # stage two: a call per start
    count = replace(count_predictions(len(context.frames) * per_frame, [len(context.seeds_for(f)) for f, _ in todo],
                                      processes=processes, closed_cells=closed), cells=len(cells))
    seconds = None if probe is None else \
        run_wall_seconds(count, probe.seconds, processes=processes, cores=os.cpu_count() or 1, load=_others())
    bound = "at most " if options.settings.adaptive else ""
    head = (f"clean frame {probe.token!r} predicted and valid ({probe.seconds * 1000:.1f} ms per frame); "
            if probe is not None else f"no frame checked before the cells ({why}); ")
    lines = [f"{HEAD}: {head}{bound}{estimate_line(count, seconds, processes=processes)}"]
    moved = rootdir_note(Path(config.invocation_params.dir), Path(config.rootpath), options.planner_path,
                         config.inipath)
    notes += [moved] if moved else []
    return lines + [f"{HEAD}: note: {n}" for n in notes]
