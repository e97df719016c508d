"""What the intervals of issue 15 cost: the analysis with and without them, and a run under 3 seeds vs 1.

1. `analyse_run` on a synthetic run of the default size (16 families x 5 severities, 204 frames, 1000
   resamples) with and without the joint bootstrap (median of several runs, and the ratio).
2. `pytest --drivedegrade PLANNER` on a small run (--drivedegrade-frames 24, a few families, S1 and S5) with
   --drivedegrade-seeds 3 vs 1, fresh report folders (nothing resumed): median wall time and the ratio.

    python benchmarks/intervals.py [--repeat 5] [--planner planners/camera_cnn.py] [--skip-run]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests" / "unit")]
#: Two random families (run three times under seeds 3), two deterministic ones, blackout for the removal axis.
FAMILIES = "gaussian_noise,snow,jpeg,fog,blackout"


def analysis_times(repeat: int, frames: int) -> tuple[float, float]:
    """Median seconds of the analysis without and with intervals, the two interleaved so drift hits both."""
    from test_analysis import synthetic_run

    from pytest_drivedegrade.scoring.analyse import analyse_run
    from pytest_drivedegrade.scoring.verdict import FamilyGroups

    recs, _ = synthetic_run(frames)
    groups = FamilyGroups.from_registry()
    analyse_run(recs, groups=groups)  # warm up imports and caches
    times: dict[bool, list[float]] = {False: [], True: []}
    for _ in range(repeat):
        for intervals in (False, True):
            start = time.perf_counter()
            analyse_run(recs, groups=groups, intervals=intervals)
            times[intervals].append(time.perf_counter() - start)
    return statistics.median(times[False]), statistics.median(times[True])


def run_time(planner: str, seeds: int, frames: int) -> tuple[float, float]:
    """(wall seconds, summed cell seconds over every seed run) of one run in a fresh report folder."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "pytest", "--drivedegrade", planner, "-q", "-p", "no:randomly",
               "--drivedegrade-report", tmp, "--drivedegrade-frames", str(frames), "--drivedegrade-families",
               FAMILIES, "--drivedegrade-severities", "1,5", "--drivedegrade-seeds", str(seeds)]
        start = time.perf_counter()
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        wall = time.perf_counter() - start
        if proc.returncode not in (0, 1):
            sys.exit(f"run failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
        cells = 0.0
        for path in Path(tmp).glob("*/cells/*.json"):
            record = json.loads(path.read_text())["record"]
            cells += sum(r["seconds"].get("total", 0.0) for r in [record, *record.get("seed_runs", [])])
    return wall, cells


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--frames", type=int, default=204, help="frames of the synthetic analysis")
    parser.add_argument("--planner", default="planners/camera_cnn.py")
    parser.add_argument("--run-frames", type=int, default=24)
    parser.add_argument("--skip-run", action="store_true", help="time the analysis only")
    args = parser.parse_args()
    without, with_ = analysis_times(args.repeat, args.frames)
    print(f"analysis, {args.frames} frames, 16 families x 5 severities, 1000 resamples (median of {args.repeat}): "
          f"without intervals {1000 * without:.0f} ms, with {1000 * with_:.0f} ms, ratio {with_ / without:.2f}x")
    if args.skip_run:
        return
    subprocess.run([sys.executable, "-m", "pytest", "--drivedegrade", args.planner, "--co", "-q"], cwd=ROOT,
                   capture_output=True)  # render the world into the cache first, outside the timing
    runs = max(1, args.repeat // 2)
    got: dict[int, list[tuple[float, float]]] = {1: [], 3: []}
    for _ in range(runs):
        for seeds in (1, 3):
            got[seeds].append(run_time(args.planner, seeds, args.run_frames))
    (w1, c1), (w3, c3) = ((statistics.median(w for w, _ in got[s]), statistics.median(c for _, c in got[s]))
                          for s in (1, 3))
    print(f"run, {args.run_frames} frames, {FAMILIES} at S1/S5 (median of {runs}): --drivedegrade-seeds 1 "
          f"wall {w1:.1f} s (cells {c1:.2f} s), 3 wall {w3:.1f} s (cells {c3:.2f} s); ratio wall {w3 / w1:.2f}x, "
          f"cells {c3 / c1:.2f}x")


if __name__ == "__main__":
    main()
