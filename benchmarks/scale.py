"""Scale: sharding overhead, batch throughput, and what a full nuScenes-val certification would take.

Prints, in one run on this machine:
- the certification with `-n 2` against shards 1/2 and 2/2 run one after the other plus `drivedegrade merge`
  (wall seconds, ratio, and whether the merged cells.csv equals the unsharded one);
- the certification on a local Ray cluster with 2 planner actors (`--drivedegrade-ray local`) against `-n 2`
  (wall seconds, ratio, and whether the two cells.csv are equal);
- camera_cnn's frames/s at batch 1 against batch 16 on CPU (predict / predict_batch over the same val frames,
  median of 5 passes), the network alone on preprocessed views beside the whole call (OpenCV's INTER_AREA
  preprocessing is per frame in both), and the largest plan difference between the two;
- predictions saved by reuse: the full ladder for camera_cnn with `-n 2`, with and without
  `--drivedegrade-no-reuse`: predict() calls counted in the planner (a worker that has not run clean computes
  it once for itself: counted), the ledger's predictions and reused frames, wall seconds, and whether the two
  runs' cells.csv are identical;
- the extrapolated wall time of a full nuScenes-val certification for a 1.8 and a 45 frames/s planner on 1, 8
  and 64 GPUs (`drivedegrade estimate`).

    python benchmarks/scale.py [--families jpeg,blackout,...] [--frames N] [--skip-sharding] [--skip-ray]
                               [--skip-batches] [--skip-reuse]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def certify(report: Path, extra: list[str], planner: str = "planners/camera_cnn.py") -> float:
    cmd = [sys.executable, "-m", "pytest", "--drivedegrade", planner, "-q", "-p", "no:randomly",
           "--drivedegrade-report", str(report), *extra]
    start = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if proc.returncode not in (0, 1):
        sys.exit(f"run failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return time.perf_counter() - start


def sharding(extra: list[str]) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        whole = certify(base / "whole", ["-n", "2", *extra])
        parts = [certify(base / "sh", ["-n", "2", "--drivedegrade-shard", f"{i}/2", *extra]) for i in (1, 2)]
        start = time.perf_counter()
        shards = sorted((base / "sh" / "camera_cnn").glob("shard-*-of-2"))
        subprocess.run([sys.executable, "-m", "pytest_drivedegrade.cli", "merge", *map(str, shards), "--out",
                        str(base / "merged")], cwd=ROOT, check=True, capture_output=True)
        merge = time.perf_counter() - start
        same = (base / "whole" / "camera_cnn" / "cells.csv").read_text() == \
            (base / "merged" / "camera_cnn" / "cells.csv").read_text()
    sharded = sum(parts) + merge
    print(f"-n 2: {whole:.1f} s; shards 1/2 + 2/2 one after the other ({parts[0]:.1f} + {parts[1]:.1f} s) + merge "
          f"{merge:.1f} s = {sharded:.1f} s; ratio {sharded / whole:.2f}; merged cells.csv identical: {same}")


def ray_actors(extra: list[str]) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        xdist = certify(base / "n2", ["-n", "2", *extra])
        ray = certify(base / "ray", ["--drivedegrade-ray", "local", "--drivedegrade-ray-actors", "2", *extra])
        same = (base / "n2" / "camera_cnn" / "cells.csv").read_text() == \
            (base / "ray" / "camera_cnn" / "cells.csv").read_text()
    print(f"-n 2: {xdist:.1f} s; Ray local cluster, 2 actors: {ray:.1f} s; ratio {ray / xdist:.2f}; cells.csv "
          f"identical: {same}")


def batches(frames: int | None) -> None:
    sys.path.insert(0, str(ROOT / "planners"))
    import camera_cnn
    import torch

    from pytest_drivedegrade.data.world import ensure_default_world
    from pytest_drivedegrade.run import RunContext
    from pytest_drivedegrade.settings import RunSettings

    torch.set_num_threads(1)
    root = ensure_default_world(ROOT / ".pytest_cache" / "d" / "drivedegrade")
    ctx = RunContext.open(RunSettings(data=root, frames=frames, timeout=0.0))
    planner = camera_cnn.CameraCNNPlanner()
    from pytest_drivedegrade.loader import samples

    images = [dict(s.items()) for s in samples(ctx.frames, "clean", 0, seed=0, decode=ctx.decode,
                                               unread=("CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT"))]
    egos, cmds = [f.ego for f in ctx.frames], [f.command for f in ctx.frames]

    from pytest_drivedegrade.floor import ego_features

    pix = np.stack([camera_cnn.preprocess(im) for im in images])
    feats = np.stack([ego_features(e, c) for e, c in zip(egos, cmds)])
    n = len(images)

    def one() -> np.ndarray:
        return np.stack([planner.predict(im, e, c) for im, e, c in zip(images, egos, cmds)])

    def sixteen() -> np.ndarray:
        return np.concatenate([planner.predict_batch(images[i:i + 16], egos[i:i + 16], cmds[i:i + 16], [])
                               for i in range(0, n, 16)])

    def network(b: int) -> Callable[[], np.ndarray]:
        return lambda: np.concatenate([planner.predict_many(pix[i:i + b], feats[i:i + b]) for i in range(0, n, b)])

    def preprocess() -> np.ndarray:
        return np.stack([camera_cnn.preprocess(im) for im in images])

    times = {}
    for name, fn in (("batch 1", one), ("batch 16", sixteen), ("network 1", network(1)),
                     ("network 16", network(16)), ("preprocess", preprocess)):
        fn()  # warm-up
        runs = []
        for _ in range(5):
            start = time.perf_counter()
            out = fn()
            runs.append(time.perf_counter() - start)
        times[name] = (n / statistics.median(runs), out)
    diff = float(np.abs(times["batch 1"][1] - times["batch 16"][1]).max())
    print(f"camera_cnn on CPU, one thread, {n} val frames (decoded images cached): batch 1 "
          f"{times['batch 1'][0]:.0f} frames/s, batch 16 {times['batch 16'][0]:.0f} frames/s, ratio "
          f"{times['batch 16'][0] / times['batch 1'][0]:.2f}; largest plan difference {diff:.2e} m; the network "
          f"alone {times['network 1'][0]:.0f} vs {times['network 16'][0]:.0f} frames/s (ratio "
          f"{times['network 16'][0] / times['network 1'][0]:.2f}), OpenCV preprocessing alone "
          f"{times['preprocess'][0]:.0f} frames/s")


COUNTED = '''
import sys

import pytest
import torch

sys.path.insert(0, {planners!r})
from camera_cnn import CameraCNNPlanner  # noqa: E402


class Counted(CameraCNNPlanner):
    """camera_cnn, appending one line per predict() call to a file (every worker process)."""

    def predict(self, images, ego, cmd):
        with open({count!r}, "a") as f:
            f.write("1\\n")
        return super().predict(images, ego, cmd)


@pytest.fixture(scope="session")
def planner():
    torch.set_num_threads(1)
    return Counted()
'''


def reuse(frames: int | None) -> None:
    """The full ladder with and without reuse under -n 2: predict() calls, the ledger, wall seconds."""
    import json

    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        # the repository's pytest cache (its rendered world and trained floor), not one beside the temporary
        # planner file: else the first run renders the world and trains the floor and looks slower
        extra = ["-n", "2", "-o", f"cache_dir={ROOT / '.pytest_cache'}"] + \
            (["--drivedegrade-frames", str(frames)] if frames else [])
        rows = {}
        count, planner = base / "count.txt", base / "counted.py"  # one file: one fingerprint, comparable cells
        planner.write_text(COUNTED.format(planners=str(ROOT / "planners"), count=str(count)))
        # warm-up (one small cell set): imports, the world's files and the floor in the OS and pytest caches, so
        # that neither timed run pays them
        certify(base / "warm", [*extra, "--drivedegrade-families", "jpeg", "--drivedegrade-severities", "1"],
                planner=str(planner))
        count.unlink()
        for label, flags in (("with reuse", []), ("--drivedegrade-no-reuse", ["--drivedegrade-no-reuse"])):
            report = base / f"rep{len(rows)}"
            wall = certify(report, [*extra, *flags], planner=str(planner))
            cost = json.loads((report / "camera_cnn" / "certificate.json").read_text())["cost"]
            calls = len(count.read_text().splitlines())
            count.unlink()
            rows[label] = (wall, calls, cost["predictions"], cost["reused"],
                           (report / "camera_cnn" / "cells.csv").read_text())
        n_frames = frames or "all"
        for label, (wall, calls, made, reused, _) in rows.items():
            print(f"camera_cnn full ladder, -n 2, {n_frames} frames, {label}: {calls} predict() calls (ledger: "
                  f"{made} predictions, {reused} reused), {wall:.1f} s wall")
        on, off = rows["with reuse"], rows["--drivedegrade-no-reuse"]
        print(f"reuse saves {off[1] - on[1]} predict() calls ({100 * (off[1] - on[1]) / off[1]:.1f} %, the clean "
              f"cell a worker computed for itself included) and {off[0] - on[0]:.1f} s; cells.csv identical: "
              f"{on[4] == off[4]}")


def estimates() -> None:
    from pytest_drivedegrade.certificate.estimate import DEFAULT_CELLS, estimate

    for fps in (1.8, 45.0):
        rows = estimate(fps, 6019, [1, 8, 64])
        print(f"nuScenes val ({DEFAULT_CELLS} cells x 6019 frames) at {fps:g} frames/s: " +
              ", ".join(f"{r.gpus} GPU(s) {r.wall_hours:.1f} h" for r in rows))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", help="families for the sharding comparison (default: all)")
    parser.add_argument("--frames", type=int, help="frames for the batch comparison (default: all val frames)")
    parser.add_argument("--skip-sharding", action="store_true")
    parser.add_argument("--skip-ray", action="store_true")
    parser.add_argument("--skip-batches", action="store_true", help="skip the batch comparison and the estimates")
    parser.add_argument("--skip-reuse", action="store_true")
    args = parser.parse_args()
    families = ["--drivedegrade-families", args.families] if args.families else []
    if not args.skip_sharding:
        sharding(families)
    if not args.skip_ray:
        ray_actors(families)
    if not args.skip_batches:
        batches(args.frames)
    if not args.skip_reuse:
        reuse(args.frames)
    if not args.skip_batches:
        estimates()


if __name__ == "__main__":
    main()
