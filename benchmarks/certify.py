"""The main job, timed: wall time with -n 0 and -n 2, the speedup, where the time goes, and memory.

Runs `pytest --drivedegrade PLANNER` in fresh report folders (so nothing is resumed), reads each cell's
timings from `cells/<cell>.json`, and prints: wall seconds per layout, speedup, the share of the summed
cell time spent decoding, injecting, in the planner and in metrics, the plugin's own bookkeeping (wall x
workers - cell time), and the peak resident memory of the largest process at two frame counts.

    python benchmarks/certify.py [--planner planners/camera_cnn.py] [--frames N] [--skip-serial]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: Runs the command and prints the peak RSS (kB) of the largest process in its tree, so each run is measured alone.
_MEASURE = ("import resource, subprocess, sys; rc = subprocess.run(sys.argv[1:]).returncode; "
            "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr); sys.exit(rc)")


def run(planner: str, workers: int, frames: int | None, extra: list[str]) -> dict:
    """One certification in a fresh report folder; wall time, cell timings, peak RSS of the largest child."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "pytest", "--drivedegrade", planner, "-q", "-p", "no:randomly",
               "--drivedegrade-report", tmp, "-n", str(workers), *extra]
        if frames:
            cmd += ["--drivedegrade-frames", str(frames)]
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, "-c", _MEASURE, *cmd], cwd=ROOT, capture_output=True, text=True)
        wall = time.perf_counter() - start
        if proc.returncode not in (0, 1):
            sys.exit(f"run failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
        peak = int(proc.stderr.strip().splitlines()[-1])
        shares = {"decode": 0.0, "inject": 0.0, "planner": 0.0, "metrics": 0.0, "total": 0.0}
        for path in Path(tmp).glob("*/cells/*.json"):
            seconds = json.loads(path.read_text())["record"]["seconds"]
            for k in shares:
                shares[k] += seconds.get(k, 0.0)
        summary = [line for line in proc.stdout.splitlines() if line.startswith(("verdict", "axes"))]
    return {"wall": wall, "cells": shares, "peak_mb": peak / 1024, "summary": summary}


def report(name: str, result: dict, workers: int) -> None:
    cells = result["cells"]
    busy = cells["total"]
    book = max(0.0, result["wall"] * max(1, workers) - busy)
    print(f"{name}: wall {result['wall']:.1f} s, cell time {busy:.1f} s; of the cell time: "
          + ", ".join(f"{k} {100 * cells[k] / busy:.0f}%" for k in ("decode", "inject", "planner", "metrics"))
          + f"; plugin bookkeeping (wall x workers - cell time) {100 * book / (result['wall'] * max(1, workers)):.0f}%"
          f"; peak RSS {result['peak_mb']:.0f} MB")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--planner", default="planners/camera_cnn.py")
    parser.add_argument("--frames", type=int, default=None, help="score a subset (default: the whole val split)")
    parser.add_argument("--skip-serial", action="store_true", help="time only -n 2")
    args = parser.parse_args()
    subprocess.run([sys.executable, "-m", "pytest", "--drivedegrade", args.planner, "--co", "-q"], cwd=ROOT,
                   capture_output=True)  # render the world into the cache first, outside the timing
    parallel = run(args.planner, 2, args.frames, [])
    report("-n 2", parallel, 2)
    if not args.skip_serial:
        serial = run(args.planner, 0, args.frames, [])
        report("-n 0", serial, 1)
        print(f"speedup -n 0 -> -n 2: {serial['wall'] / parallel['wall']:.2f}x")
    for line in parallel["summary"]:
        print(line)
    small = run(args.planner, 2, 40, ["--drivedegrade-families", "jpeg", "--drivedegrade-severities", "5"])
    large = run(args.planner, 2, None, ["--drivedegrade-families", "jpeg", "--drivedegrade-severities", "5"])
    print(f"peak RSS, one family: 40 frames {small['peak_mb']:.0f} MB, all frames {large['peak_mb']:.0f} MB")


if __name__ == "__main__":
    main()
