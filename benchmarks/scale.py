"""Scale: sharding overhead, batch throughput, and what a full nuScenes-val certification would take.

Prints, in one run on this machine:
- the certification with `-n 2` against shards 1/2 and 2/2 run one after the other plus `drivedegrade merge`
  (wall seconds, ratio, and whether the merged cells.csv equals the unsharded one);
- the certification on a local Ray cluster with 2 planner actors (`--drivedegrade-ray local`) against `-n 2`
  (wall seconds, ratio, and whether the two cells.csv are equal);
- camera_cnn's frames/s at batch 1 against batch 16 on CPU (predict / predict_batch over the same val frames,
  median of 5 passes), and the largest plan difference between the two;
- the extrapolated wall time of a full nuScenes-val certification for a 1.8 and a 45 frames/s planner on 1, 8
  and 64 GPUs (`drivedegrade estimate`).

    python benchmarks/scale.py [--families jpeg,blackout,...] [--frames N] [--skip-sharding] [--skip-ray]
                               [--skip-batches]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def certify(report: Path, extra: list[str]) -> float:
    cmd = [sys.executable, "-m", "pytest", "--drivedegrade", "planners/camera_cnn.py", "-q", "-p", "no:randomly",
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

    torch.set_num_threads(1)
    root = ensure_default_world(ROOT / ".pytest_cache" / "d" / "drivedegrade")
    ctx = RunContext.open(data_root=root, split="val", frames=frames, seed=0, timeout=0.0, planner_path=None)
    planner = camera_cnn.CameraCNNPlanner()
    from pytest_drivedegrade.loader import samples

    images = [dict(s.items()) for s in samples(ctx.frames, "clean", 0, seed=0, decode=ctx.decode,
                                               unread=("CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT"))]
    egos, cmds = [f.ego for f in ctx.frames], [f.command for f in ctx.frames]

    def one() -> np.ndarray:
        return np.stack([planner.predict(im, e, c) for im, e, c in zip(images, egos, cmds)])

    def sixteen() -> np.ndarray:
        return np.concatenate([planner.predict_batch(images[i:i + 16], egos[i:i + 16], cmds[i:i + 16], [])
                               for i in range(0, len(images), 16)])

    times = {}
    for name, fn in (("batch 1", one), ("batch 16", sixteen)):
        runs = []
        for _ in range(5):
            start = time.perf_counter()
            out = fn()
            runs.append(time.perf_counter() - start)
        times[name] = (len(images) / statistics.median(runs), out)
    diff = float(np.abs(times["batch 1"][1] - times["batch 16"][1]).max())
    print(f"camera_cnn on CPU, one thread, {len(images)} val frames (decoded images cached): batch 1 "
          f"{times['batch 1'][0]:.0f} frames/s, batch 16 {times['batch 16'][0]:.0f} frames/s, ratio "
          f"{times['batch 16'][0] / times['batch 1'][0]:.2f}; largest plan difference {diff:.2e} m")


def estimates() -> None:
    from pytest_drivedegrade.report.estimate import estimate

    for fps in (1.8, 45.0):
        rows = estimate(fps, 6019, [1, 8, 64])
        print(f"nuScenes val (89 cells x 6019 frames) at {fps:g} frames/s: " +
              ", ".join(f"{r.gpus} GPU(s) {r.wall_hours:.1f} h" for r in rows))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", help="families for the sharding comparison (default: all)")
    parser.add_argument("--frames", type=int, help="frames for the batch comparison (default: all val frames)")
    parser.add_argument("--skip-sharding", action="store_true")
    parser.add_argument("--skip-ray", action="store_true")
    parser.add_argument("--skip-batches", action="store_true", help="skip the batch comparison and the estimates")
    args = parser.parse_args()
    families = ["--drivedegrade-families", args.families] if args.families else []
    if not args.skip_sharding:
        sharding(families)
    if not args.skip_ray:
        ray_actors(families)
    if not args.skip_batches:
        batches(args.frames)
        estimates()


if __name__ == "__main__":
    main()
