"""Build a world on disk: scenes -> tables, CAN bus, JPEGs, manifest; and the cached default world."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType
from typing import Any

from ...errors import DataError
from ...progress import Progress, Sink
from ..nuscenes import WORLD_MANIFEST, official_scene_names
from . import export, tasks
from .junctionscenes import JUNCTION_SPLIT, junction_indices, junction_names
from .rig import Rig
from .scene import KEYFRAMES, scene_keyframes
from .tasks import SceneTask

GENERATOR_VERSION = "3.1.1"  # 3.1: the lane-level map layers; 3.1.1: their polygons share edges exactly
#: The version folder: the name the converters of planner code bases accept (mmdet3d, UniAD, VAD).
WORLD_VERSION = "v1.0-trainval"
MANIFEST = WORLD_MANIFEST  # the file the reader looks for
DEFAULT_SCENES = 100  # 94 train scenes (3196 scorable frames) and 6 val scenes (204 scorable frames)
MAX_VAL_SCENES = 6  # val is what a certification scores (91 cells x its frames): enough, and bounded
SCORABLE_PER_SCENE = KEYFRAMES - 6
#: Scene numbers nuscenes-devkit's `NuScenesCanBus.get_messages` refuses (its `can_blacklist`).
CAN_BLACKLIST = frozenset((*range(161, 169), *range(170, 177), *range(309, 315)))

def split_names(n: int) -> tuple[list[str], list[str]]:
    """Scene names of the train and val splits: the last tenth (at least one, at most MAX_VAL_SCENES) is val.

    Names are the official nuScenes split's (`nuscenes.utils.splits`), in scene-number order: train scenes take
    the first names of the official train list, val scenes the first of the official val list, so a converter
    that selects scenes by the official lists (mmdet3d's, UniAD's, VAD's `create_nuscenes_infos`) puts every
    world scene in the split the suite scores it in. Train scenes beyond the official list's 700 are
    `ddworld-NNNN`, which no official list names (the manifest's `splits` still does). Scene numbers the devkit's
    `NuScenesCanBus` refuses (`CAN_BLACKLIST`: real logs without CAN bus data) are skipped, so UniAD's and VAD's
    converters read every world scene's `can_bus/<scene>_pose.json`.
    """
    n_val = min(max(1, -(-n // 10)), MAX_VAL_SCENES)
    official = [s for s in official_scene_names("train") if int(s[-4:]) not in CAN_BLACKLIST]
    train = [official[i] if i < len(official) else f"ddworld-{i + 1:04d}" for i in range(n - n_val)]
    return train, [s for s in official_scene_names("val") if int(s[-4:]) not in CAN_BLACKLIST][:n_val]


def write_world(out_dir, *, scenes: int | None = None, seed: int = 0, full_size: bool = False,
                train_images: bool = False, progress: Sink | None = None, val_images: bool = True,
                workers: int | None = None, future_s: int = 3, junction_scenes: int = 0) -> Path:
    """Generate a world of `scenes` scenes into `out_dir` (the nuScenes data root) and return it.

    Val images are rendered (unless `val_images` is False, for table-only checks); train images only with
    `train_images` (the tables are complete either way). Scenes are generated on `workers` processes (None:
    `tasks.default_workers`, from the cores available); the files are the same for any number.
    The manifest is written last, so a world without one is incomplete. `future_s` 4: every scored frame holds
    4 s of future (NAVSIM's eight poses), each scene exporting two keyframes more (`scene.scene_keyframes`) and
    scoring the same frames as the default world's; the manifest then names it (``future_s``).
    `junction_scenes` N > 0 adds N scenes in a split of their own, ``junction`` (`junctionscenes`: each turns at
    a junction the ego reaches), rendered and fingerprinted as val; with 0 the world is the one without it.
    """
    n = DEFAULT_SCENES if scenes is None else int(scenes)
    try:
        keyframes = scene_keyframes(future_s)
    except ValueError:
        raise DataError(f"a world's future is 3 or 4 seconds per scored frame; got {future_s!r}") from None
    if n < 2:
        raise DataError(f"a world needs at least 2 scenes (one train, one val); got {n}")
    if not isinstance(junction_scenes, int) or isinstance(junction_scenes, bool) or junction_scenes < 0:
        raise DataError(f"junction_scenes is a count of scenes (0 or more); got {junction_scenes!r}")
    root = Path(out_dir)
    root.mkdir(parents=True, exist_ok=True)
    train, val = split_names(n)
    todo = [SceneTask(str(root), seed, i, name, full_size, render=(name in val and val_images)
                      or (name not in val and train_images), fingerprint_images=name in val, keyframes=keyframes)
            for i, name in enumerate(train + val)]
    junction = junction_names(junction_scenes)
    todo += [SceneTask(str(root), seed, index, name, full_size, render=val_images, fingerprint_images=True,
                       keyframes=keyframes) for index, name in zip(junction_indices(seed, junction_scenes), junction)]
    with Progress("drivedegrade world", len(todo), unit="scenes", sink=progress or Sink.silent()) as bar:
        outputs = tasks.run_tasks(todo, workers, lambda t: bar.advance(note=f"{t.name}{' rendered' * t.render}"))
    longer = f"|future{future_s}" if future_s != 3 else ""  # only then: the default world keeps its fingerprint
    longer += f"|junction{junction_scenes}" if junction_scenes else ""
    digest = hashlib.blake2b(f"{GENERATOR_VERSION}|{seed}|{n}|{full_size}{longer}".encode(), digest_size=16)
    for out in outputs:
        digest.update(out.fingerprint)
    static = export.static_tables(seed, Rig.nuscenes_like(full_size))
    static["map"] = [{"token": export.token(seed, "map"), "log_tokens": [out.log_token for out in outputs],
                      "category": "semantic_prior", "filename": ""}]
    tables = {name: [export.items_json(records)] for name, records in static.items()}
    tables.update({name: [out.tables[name] for out in outputs] for name in tasks.SCENE_TABLES})
    for name, items in sorted(tables.items()):
        digest.update(export.dump_items(root / WORLD_VERSION / f"{name}.json", items))
    of = {name: split for split, names in (("train", train), ("val", val), (JUNCTION_SPLIT, junction))
          for name in names}
    events = {split: [e for out, t in zip(outputs, todo) if of[t.name] == split
                      for e in out.events[:SCORABLE_PER_SCENE]]
              for split in ("train", "val", *((JUNCTION_SPLIT,) if junction else ()))}
    manifest = {"generator": "pytest-drivedegrade world", "generator_version": GENERATOR_VERSION,
                "version": WORLD_VERSION, "seed": seed, "scenes": n, "full_size": full_size,
                "train_images": bool(train_images),
                "splits": {"train": train, "val": val, **({JUNCTION_SPLIT: junction} if junction else {})},
                "fingerprint": digest.hexdigest(), "events": {s: _event_stats(e) for s, e in events.items()}}
    if future_s != 3:  # only then: the default world's manifest keeps its bytes
        manifest["future_s"] = future_s
    export.dump(root / MANIFEST, manifest)
    return root


EVENT_DEFINITION = ("keyframes whose ground-truth position at 3 s lies more than 1 m from the constant-acceleration, "
                    "constant-yaw-rate extrapolation of the ego status")


def _event_stats(kinds: list[str]) -> dict:
    n = max(len(kinds), 1)
    out: dict[str, Any] = {"frames": len(kinds), "fraction": round(sum(1 for k in kinds if k) / n, 4)}
    out.update({k: sum(1 for x in kinds if x == k) for k in ("brake", "vru", "bend", "other")})
    out["definition"] = EVENT_DEFINITION
    return out


def add_train_images(root: Path, progress: Sink | None = None, workers: int | None = None) -> None:
    """Render the train split's images into an existing world (same seed and options as its manifest)."""
    manifest = json.loads((root / MANIFEST).read_text())
    names = manifest["splits"]["train"]
    keyframes = scene_keyframes(manifest.get("future_s", 3))
    todo = [SceneTask(str(root), manifest["seed"], i, name, manifest["full_size"], tables=False, render=True,
                      keyframes=keyframes) for i, name in enumerate(names)]
    with Progress("drivedegrade world: train images", len(todo), unit="scenes",
                  sink=progress or Sink.silent()) as bar:
        tasks.run_tasks(todo, workers, lambda t: bar.advance(note=t.name))
    manifest["train_images"] = True
    tmp = root / (MANIFEST + ".tmp")
    export.dump(tmp, manifest)
    os.replace(tmp, root / MANIFEST)


@contextmanager
def _locked(path: Path):
    """An exclusive inter-process lock on `path` (fcntl where available; else an O_EXCL lock file)."""
    fcntl: ModuleType | None  # the module, or None where it does not exist
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        fcntl = None
    if fcntl is not None:
        with open(path, "a+") as fh:
            fcntl.flock(fh, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)
        return
    while True:  # pragma: no cover - Windows
        try:
            fd = os.open(str(path) + ".excl", os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            break
        except FileExistsError:
            time.sleep(0.5)
    try:  # pragma: no cover
        yield
    finally:  # pragma: no cover
        os.close(fd)
        os.unlink(str(path) + ".excl")


def default_world_dir(cache_root) -> Path:
    """Where `ensure_default_world` keeps the default world under `cache_root` (ready when it holds MANIFEST)."""
    return Path(cache_root) / f"world-{GENERATOR_VERSION}-seed0"


def ensure_default_world(cache_root, *, train_images: bool = False, progress: Sink | None = None) -> Path:
    """The default world in `cache_root`, generated on first use (into a temporary folder, then renamed), its
    progress on `progress` (None: one line on stderr). A build worker re-running a script's unguarded
    ``pytest.main`` stops before the lock, saying why (`tasks.stop_starting_worker`), rather than wait there for
    ever; a world already built is returned to any process, as before."""
    if progress is not None and not isinstance(progress, Sink):  # e.g. progress=print: fail before any work
        raise TypeError(f"ensure_default_world(progress=...) takes a pytest_drivedegrade.progress.Sink (Sink() for "
                        f"stderr, Sink.silent() for nothing), got {progress!r}")
    cache_root = Path(cache_root)
    cache_root.mkdir(parents=True, exist_ok=True)
    target = default_world_dir(cache_root)
    say = progress if progress is not None else Sink()

    def ready() -> bool:
        if not (target / MANIFEST).is_file():
            return False
        return not train_images or json.loads((target / MANIFEST).read_text()).get("train_images", False)

    if ready():
        return target
    tasks.stop_starting_worker()  # the lock below is held by the parent building the world: it would never come
    with _locked(cache_root / ".world.lock"):
        if ready():
            return target
        if not (target / MANIFEST).is_file():
            tmp = cache_root / f".world-tmp-{os.getpid()}"
            shutil.rmtree(tmp, ignore_errors=True)
            shutil.rmtree(target, ignore_errors=True)  # an incomplete world from an older crash
            try:
                write_world(tmp, train_images=train_images, progress=say)
                os.replace(tmp, target)
            except BaseException:  # an interrupted or failed build leaves no half-written folder behind
                shutil.rmtree(tmp, ignore_errors=True)
                raise
        if train_images and not ready():
            add_train_images(target, say)
    return target


def cli_world(args) -> int:
    """`drivedegrade world --out DIR [--scenes N] [--seed S] [--full-size] [--train-images] [--future 3|4]`."""
    start = time.perf_counter()
    root = write_world(args.out, scenes=args.scenes, seed=args.seed, full_size=args.full_size,
                       train_images=args.train_images, progress=Sink(), future_s=getattr(args, "future", 3),
                       junction_scenes=getattr(args, "junction_scenes", 0))
    manifest = json.loads((root / MANIFEST).read_text())
    ev = manifest["events"]["val"]
    junction = len(manifest["splits"].get(JUNCTION_SPLIT, []))
    also = f" and {junction} junction scenes" if junction else ""
    print(f"wrote {root} ({manifest['scenes']} scenes{also}, fingerprint {manifest['fingerprint']}) in "
          f"{time.perf_counter() - start:.1f} s; val frames with a camera-only event: {ev['fraction']:.0%}",
          file=sys.stderr)
    return 0
