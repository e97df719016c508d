"""The planner contract (SPEC section 2): what a planner is, what it must return, and how it is identified.

A planner is any object with ``predict(images, ego, cmd)`` returning a ``(6, 2)`` float array of waypoints at
t = 0.5 .. 3.0 s in the current ego frame (x forward, y left, metres). Four attributes are optional:

- ``poses``: 6 (the default: nuScenes' 3 s) or 8 (NAVSIM's 4 s at 0.5 s); a planner declaring 8 returns ``(8, 2)``
  and is scored with PDMS/EPDMS over 4 s on data holding 4 s of future (`check_horizon`), L2 over the first six.

- ``cameras``: the camera names it reads (default all six); a claim the null control checks.
- ``name``: the report folder name (default the planner file's stem).
- ``deterministic``: False for a planner whose plan may differ on identical inputs (default True); only then
  does the suite call it on frames whose inputs equal the clean cell's instead of reusing the clean plan.

A planner whose ``predict`` takes ``context`` gets the keyframe's `FrameContext`; a LiDAR or fusion planner
reads the keyframe's LIDAR_TOP points from it (``context.lidar_points()``, never corrupted: the suite certifies
the camera path, with clean LiDAR).

A planner file (or the user's ``conftest.py``) provides it through a pytest fixture named ``planner``. Loading
that file as a plugin module is the pytest plugin's job; this module only judges the object it yields.
"""

from __future__ import annotations

import ast
import hashlib
import inspect
import sys
import sysconfig
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from .constants import CAMERAS, HORIZON_STEPS, MAX_WAYPOINT_M, STEP_SECONDS
from .data.frame import Command, EgoStatus
from .errors import InvalidInput, PlannerOutputError

__all__ = [
    "CallStyle",
    "Command",
    "EgoStatus",
    "Planner",
    "call_style",
    "check_horizon",
    "horizon_problem",
    "planner_cameras",
    "planner_device",
    "planner_fingerprint",
    "planner_name",
    "planner_poses",
    "predict_checked",
    "to_numpy",
    "validate_output",
]

#: The fixture name a planner file or conftest.py must define.
FIXTURE_NAME = "planner"
#: The environment variable that carries --drivedegrade-device to a planner built anywhere (the planner fixture,
#: an xdist worker, a Ray actor the fixture starts): the plugin sets it for the run.
DEVICE_ENV = "DRIVEDEGRADE_DEVICE"


def planner_device(default: str = "cpu") -> str:
    """Where the run wants the planner to compute: ``$DRIVEDEGRADE_DEVICE`` (``cpu``, ``cuda``, ``cuda:N``), which
    the plugin sets from --drivedegrade-device for the whole run, else `default`. A planner that supports a GPU
    builds itself there (``CameraCNNPlanner(device=planner_device())``); the device is part of the run key."""
    import os

    return (os.environ.get(DEVICE_ENV) or default).strip().lower()


def deterministic_cuda() -> None:
    """cuDNN without autotuning (``benchmark``: the fastest kernel is chosen by timing, so it can change between
    runs), with only deterministic kernels and without TF32 (10-bit mantissa convolutions and matmuls): a CUDA
    run is then bit-reproducible run to run, and within float rounding of the CPU plans. Process-wide torch
    settings; the plugin applies them for --drivedegrade-device cuda, and a planner built elsewhere (a Ray
    actor) may call it too."""
    import torch

    torch.backends.cudnn.benchmark = False
    torch.backends.cudnn.deterministic = True
    torch.backends.cudnn.allow_tf32 = False
    torch.backends.cuda.matmul.allow_tf32 = False


#: At most this many characters of an offending value go into an error message.
_VALUE_CHARS = 400


@runtime_checkable
class Planner(Protocol):
    """What the suite drives. ``cameras`` and ``name`` are optional attributes, so they are not part of the
    runtime check; read them with ``planner_cameras`` and ``planner_name``."""

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command) -> np.ndarray:
        """Waypoints (6, 2) at 0.5 s steps, metres, current ego frame; `images` are read-only RGB uint8."""
        ...


def _show(value: Any) -> str:
    """A short, single-message rendering of an offending value."""
    try:
        text = np.array2string(np.asarray(value), precision=4, threshold=24, separator=", ")
    except Exception:  # noqa: BLE001 - any object must be showable
        text = repr(value)
    text = " ".join(text.split())
    return text if len(text) <= _VALUE_CHARS else text[:_VALUE_CHARS] + " ..."


def _fail(frame_token: str, problem: str, value: Any, poses: int = HORIZON_STEPS) -> PlannerOutputError:
    return PlannerOutputError(
        f"planner output for frame {frame_token!r} {problem}; the contract is a finite "
        f"({poses}, 2) float array of waypoints. Got {type(value).__name__}: {_show(value)}"
    )


#: The horizons a planner may declare (``poses``): nuScenes' six waypoints (3 s) and NAVSIM's eight (4 s).
POSE_COUNTS: tuple[int, ...] = (HORIZON_STEPS, 8)


def planner_poses(planner: object) -> int:
    """The waypoints a planner declares it returns (its optional ``poses``): 6 by default, or 8 (NAVSIM's 4 s at
    0.5 s). Anything else raises ``InvalidInput`` saying what to write."""
    declared = getattr(planner, "poses", None)
    if declared is None:
        return HORIZON_STEPS
    if isinstance(declared, (bool, np.bool_)) or not isinstance(declared, (int, np.integer)) \
            or int(declared) not in POSE_COUNTS:
        raise InvalidInput(f"planner.poses must be {' or '.join(map(str, POSE_COUNTS))} (waypoints at 0.5 s: "
                           f"nuScenes' 3 s or NAVSIM's 4 s), got {declared!r}")
    return int(declared)


def check_horizon(poses: int, data_poses: int, where: str = "the data") -> None:
    """A planner of `poses` waypoints on data whose scored frames hold `data_poses` future keyframes: an
    ``InvalidInput`` before any cell when the data cannot score its whole plan (an 8-pose planner on data with
    3 s of future), saying how to get data that can. Pure: the plugin's start-up and its pre-flight call it."""
    if poses > data_poses:
        raise InvalidInput(
            f"the planner declares poses = {poses} ({poses * STEP_SECONDS:g} s) but {where} holds "
            f"{data_poses * STEP_SECONDS:g} s of future per scored frame ({data_poses} keyframes), so its plan "
            f"cannot be scored over its horizon; generate a world with 4 s of future (drivedegrade world --out "
            f"DIR --future 4, then --drivedegrade-data DIR) or declare poses = {HORIZON_STEPS}")


def to_numpy(value: Any) -> Any:
    """A torch tensor (any device) as a numpy array, without importing torch; anything else unchanged.

    numpy has no bfloat16, so a bfloat16 or float16 tensor (a model run under autocast) is widened to float64
    first: its values are exact in float64, and the output check then sees a float array, not a conversion error.
    """
    if not (hasattr(value, "detach") and hasattr(value, "cpu")):
        return value
    tensor = value.detach().cpu()
    if str(getattr(tensor, "dtype", "")) in ("torch.bfloat16", "torch.float16"):
        tensor = tensor.double()
    return tensor.numpy()


def horizon_problem(planner: object, data_poses: int, where: str = "the data") -> str:
    """Why `planner` cannot be scored over its declared horizon on data holding `data_poses` future keyframes per
    scored frame ("" when it can): a malformed ``poses`` or `check_horizon`'s usage error. Pure, for the start-up
    check and the pre-flight."""
    try:
        check_horizon(planner_poses(planner), data_poses, where)
    except InvalidInput as exc:
        return str(exc)
    return ""


def validate_output(traj: Any, frame_token: str, poses: int = HORIZON_STEPS) -> np.ndarray:
    """Check one planner output against the contract and return it as a fresh float64 (`poses`, 2) array.

    Accepts any float array-like (numpy, lists of floats, a torch tensor of any float dtype, bfloat16 and float16
    included); rejects a wrong shape, a non-float dtype (int, bool, complex, object), NaN / inf and a waypoint
    farther than ``MAX_WAYPOINT_M`` (1 km) from the ego, raising ``PlannerOutputError`` that names the frame
    token and shows the value.
    """
    if traj is None:
        raise _fail(frame_token, "is None (did predict() forget to return?)", traj, poses)
    traj = to_numpy(traj)
    try:
        arr = np.asarray(traj)
    except Exception as exc:  # noqa: BLE001 - ragged lists and exotic objects
        raise _fail(frame_token, f"is not an array ({exc})", traj, poses) from None
    if arr.dtype.kind != "f":
        raise _fail(frame_token, f"has dtype {arr.dtype}, not a float dtype", traj, poses)
    if arr.shape != (poses, 2):
        hint = f" (the planner declares poses = {poses})" if poses != HORIZON_STEPS else ""
        raise _fail(frame_token, f"has shape {arr.shape}, not ({poses}, 2){hint}", traj, poses)
    if not np.isfinite(arr).all():
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise _fail(frame_token, f"is not finite (first at step {bad[0]}, coordinate {bad[1]})", traj, poses)
    out = np.array(arr, dtype=np.float64, copy=True)
    with np.errstate(over="ignore"):  # 1e200 squared is inf: still beyond the bound
        far = np.hypot(out[:, 0], out[:, 1]) > MAX_WAYPOINT_M
    if far.any():
        step = int(np.argmax(far))
        raise _fail(frame_token, f"has a waypoint {np.hypot(*out[step]):.6g} m from the ego at step {step} "
                                 f"({out[step, 0]:.6g}, {out[step, 1]:.6g}), beyond the physical bound of "
                                 f"{MAX_WAYPOINT_M:g} m", traj, poses)
    return out


def predict_checked(
    planner: Any, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command, frame_token: str
) -> np.ndarray:
    """Call ``planner.predict`` and validate its output. Exceptions raised by the planner propagate unchanged."""
    return validate_output(planner.predict(images, ego, cmd), frame_token, planner_poses(planner))


@dataclass(frozen=True)
class CallStyle:
    """How the suite calls a planner (SPEC section 8): with the frame context when ``predict`` declares a
    parameter named ``context``; ``reset(scene_token)`` before each scene when the planner has a ``reset``.

    `deterministic` is the planner's optional ``deterministic`` attribute (default True: the same inputs give
    the same plan, which the null control checks). A deterministic planner without ``reset`` is not asked
    again for a frame whose inputs equal the clean cell's: the clean plan is reused (``reuses``). `poses`: the
    waypoints each call returns (`planner_poses`)."""

    takes_context: bool
    resets: bool
    deterministic: bool = True
    poses: int = HORIZON_STEPS

    @property
    def reuses(self) -> bool:
        """Whether the clean plan of a frame may stand for a prediction on inputs equal to the clean ones."""
        return self.deterministic and not self.resets


def call_style(planner: Any) -> CallStyle:
    """Read a planner's `CallStyle` off its methods (once per planner; cheap)."""
    predict = getattr(planner, "predict", None)
    if not callable(predict):
        raise InvalidInput(f"the planner ({type(planner).__name__}) has no predict() method; see planners/template.py")
    try:
        params = inspect.signature(predict).parameters
    except (TypeError, ValueError):  # a builtin or C extension without a signature: the three-argument form
        params = {}  # type: ignore[assignment]
    deterministic = getattr(planner, "deterministic", True)
    if not isinstance(deterministic, (bool, np.bool_)):
        raise InvalidInput(f"planner.deterministic must be True or False, got {deterministic!r} "
                           f"({type(deterministic).__name__})")
    return CallStyle("context" in params, callable(getattr(planner, "reset", None)), bool(deterministic),
                     planner_poses(planner))


def planner_cameras(planner: Any) -> tuple[str, ...]:
    """The cameras a planner declares it reads, in ``CAMERAS`` order; all six when it declares nothing.

    An empty declaration (``cameras = ()``) is valid: a planner that reads no camera, such as the ego-only
    floor. A bare string, a non-string entry or an unknown name raises ``InvalidInput``.
    """
    declared = getattr(planner, "cameras", None)
    if declared is None:
        return CAMERAS
    if isinstance(declared, (str, bytes)):
        raise InvalidInput(
            f"planner.cameras must be a collection of camera names, got the string {declared!r}; "
            f"write cameras = ({declared!r},)"
        )
    try:
        names = list(declared)
    except TypeError:
        raise InvalidInput(f"planner.cameras must be a collection of camera names, got {declared!r}") from None
    unknown = [n for n in names if n not in CAMERAS]
    if unknown:
        raise InvalidInput(
            f"planner.cameras names unknown camera(s) {unknown!r}; valid names are {', '.join(CAMERAS)}"
        )
    return tuple(c for c in CAMERAS if c in names)


#: The longest planner name: it names the report folder and is printed in the terminal, HTML and certificate.
MAX_NAME = 64
#: Bidirectional embedding / override / isolate controls (U+202A-U+202E, U+2066-U+2069): they make a name read
#: differently from what it is (a "Trojan Source" name in a report or a CI log).
BIDI_CONTROLS = frozenset(map(chr, (*range(0x202A, 0x202F), *range(0x2066, 0x206A))))


def planner_name(planner: Any, default: str) -> str:
    """The planner's ``name`` attribute when it is a usable folder name, else `default` (the file's stem).

    A name is at most `MAX_NAME` printable characters with no bidirectional controls and no path; otherwise
    `InvalidInput` naming the offending character and its position.
    """
    name = getattr(planner, "name", None)
    where = "planner.name"
    if name is None:
        name, where = default, "the planner's name (its file name)"
    if not isinstance(name, str) or not name.strip():
        raise InvalidInput(f"planner.name must be a non-empty string, got {name!r}")
    name = name.strip()
    rule = (f"a planner name is at most {MAX_NAME} printable characters without bidirectional controls (it "
            "names the report folder and appears in the certificate)")
    for i, ch in enumerate(name):
        if ch in BIDI_CONTROLS or not ch.isprintable():
            kind = "bidirectional control" if ch in BIDI_CONTROLS else "non-printable"
            raise InvalidInput(f"{where} {name!r} contains the {kind} character U+{ord(ch):04X} at position {i}; "
                               f"{rule}")
    if len(name) > MAX_NAME:
        raise InvalidInput(f"{where} {name[:MAX_NAME]!r}... is {len(name)} characters long; {rule}")
    if any(sep in name for sep in ("/", "\\")) or name in (".", ".."):
        raise InvalidInput(f"{where} {name!r} is used as a report folder and may not contain a path")
    return name


def _state_bytes(planner: Any) -> bytes | None:
    """Bytes of the planner's weights when it has a torch-like ``state_dict`` (itself or its ``model``)."""
    for owner in (planner, getattr(planner, "model", None), getattr(planner, "net", None)):
        state_dict = getattr(owner, "state_dict", None)
        if owner is None or not callable(state_dict):
            continue
        digest = hashlib.sha256()
        for key, tensor in sorted(state_dict().items()):
            data = tensor.detach().cpu().contiguous().numpy() if hasattr(tensor, "detach") else np.asarray(tensor)
            digest.update(f"{key}|{data.dtype}|{data.shape}|".encode())
            digest.update(np.ascontiguousarray(data).tobytes())
        return digest.digest()
    return None


def _source_bytes(planner: Any, path: str | Path | None) -> bytes:
    """The planner file's source, or, for a conftest fixture without a path, its class's source file."""
    candidates: list[Any] = [path] if path is not None else []
    try:
        candidates.append(inspect.getsourcefile(type(planner)))
    except TypeError:  # builtins have no source file
        pass
    for candidate in candidates:
        if candidate and Path(candidate).is_file():
            return Path(candidate).read_bytes()
    return f"{type(planner).__module__}.{type(planner).__qualname__}".encode()


def _outside(file: Path) -> bool:
    """Whether `file` is the standard library's, an installed package's (site-packages) or this tool's own (its
    version is in the run key): code a planner's fingerprint leaves out."""
    roots = {sysconfig.get_paths()[k] for k in ("stdlib", "platstdlib", "purelib", "platlib")}
    roots.add(str(Path(__file__).resolve().parent))
    resolved = str(file.resolve())
    return "site-packages" in file.parts or "dist-packages" in file.parts or \
        any(resolved.startswith(str(Path(r).resolve()) + "/") for r in roots)


def _module_file(name: str, near: Path) -> Path | None:
    """The source file of module `name` as the planner imports it: the loaded module's, else one beside `near`."""
    module = sys.modules.get(name)
    found = getattr(module, "__file__", None) if module is not None else None
    if found:
        return Path(found)
    for candidate in (near / f"{name.replace('.', '/')}.py", near / name.replace(".", "/") / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _imports(file: Path) -> list[tuple[str, int]]:
    """(module, relative level) of every import statement in `file`, in order (none when it does not parse)."""
    try:
        tree = ast.parse(file.read_bytes())
    except (OSError, SyntaxError, ValueError):
        return []
    out: list[tuple[str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, 0) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            out += [(node.module or "", node.level)] + \
                [(f"{node.module}.{a.name}" if node.module else a.name, node.level) for a in node.names]
    return out


def covered_modules(path: str | Path) -> list[Path]:
    """The planner file and every module it imports, transitively, from outside the standard library,
    site-packages and this tool (`_outside`), found among the loaded modules or beside the importing file:
    the sources `planner_fingerprint` folds in, in a stable order (the planner file first)."""
    start = Path(path).resolve()
    seen, queue = [start], [start]
    while queue:
        file = queue.pop(0)
        for name, level in _imports(file):
            base = file.parent
            for _ in range(max(level - 1, 0)):
                base = base.parent
            found = _module_file(name, base) if level else \
                (_module_file(name, file.parent) if name else None)
            if found is None or found.suffix != ".py" or not found.is_file() or _outside(found):
                continue
            found = found.resolve()
            if found not in seen:
                seen.append(found)
                queue.append(found)
    return [start, *sorted(seen[1:])]


def planner_fingerprint(planner: Any, path: str | Path | None = None) -> str:
    """A SHA-256 hex digest identifying a planner: its file's source, the source of every module it imports
    from outside the standard library, site-packages and this tool (`covered_modules`: a model kept in a module
    beside it), plus its weights or declared state.

    State: a ``fingerprint`` attribute (a string, or a callable returning one) and the bytes of a torch
    ``state_dict`` (on the planner or its ``model`` / ``net``), each when present: a declared fingerprint never
    hides the weights actually loaded (a constant one would let a retrained model reuse the old model's cells).
    The planner's class name and declared cameras are included too, since they change what the suite tests.
    """
    digest = hashlib.sha256(b"drivedegrade-planner-v1|")
    digest.update(_source_bytes(planner, path))
    if path is not None and Path(path).is_file():  # the modules it imports from outside installed packages
        for module in covered_modules(path)[1:]:
            digest.update(f"|module|{module.name}|".encode() + module.read_bytes())
    digest.update(f"|class|{type(planner).__module__}.{type(planner).__qualname__}".encode())
    declared = getattr(planner, "fingerprint", None)
    if callable(declared):
        declared = declared()
    if declared is not None:
        digest.update(b"|fingerprint|" + str(declared).encode())
    state = _state_bytes(planner)
    if state is not None:
        digest.update(b"|state|" + state)
    digest.update(b"|cameras|" + ",".join(planner_cameras(planner)).encode())
    poses = planner_poses(planner)
    if poses != HORIZON_STEPS:  # only then: a six-pose planner keeps its fingerprint (and its stored cells)
        digest.update(f"|poses|{poses}".encode())
    return digest.hexdigest()
