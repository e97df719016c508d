"""What the intervals of issue 15 cost: the analysis with and without them, and a run under 3 seeds vs 1.

1. `analyse_run` on a synthetic run of the default size (16 families x 5 severities, 204 frames, 1000
   resamples) with and without the joint bootstrap (median of several runs, and the ratio).
2. `pytest --drivedegrade PLANNER` on a small run (--drivedegrade-frames 24, a few families, S1 and S5) with
   --drivedegrade-seeds 3 vs 1, fresh report folders (nothing resumed): median wall time and the ratio.

    python benchmarks/intervals.py [--repeat 5] [--planner planners/camera_cnn.py] [--skip-run]
"""

from __future__ import annotations

import argparse
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
    from test_analysis import synthetic_run

    from pytest_drivedegrade.scoring.verdict import FamilyGroups, analyse_run

    recs, _ = synthetic_run(frames)
    groups = FamilyGroups.from_registry()
    analyse_run(recs, groups=groups)  # warm up imports and caches
    out = []
    for intervals in (False, True):
        times = []
        for _ in range(repeat):
            start = time.perf_counter()
            analyse_run(recs, groups=groups, intervals=intervals)
            times.append(time.perf_counter() - start)
        out.append(statistics.median(times))
    return out[0], out[1]


def run_time(planner: str, seeds: int, frames: int) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "pytest", "--drivedegrade", planner, "-q", "-p", "no:randomly",
               "--drivedegrade-report", tmp, "--drivedegrade-frames", str(frames), "--drivedegrade-families",
               FAMILIES, "--drivedegrade-severities", "1,5", "--drivedegrade-seeds", str(seeds)]
        start = time.perf_counter()
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        wall = time.perf_counter() - start
        if proc.returncode not in (0, 1):
            sys.exit(f"run failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return wall


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
    one = statistics.median(run_time(args.planner, 1, args.run_frames) for _ in range(runs))
    three = statistics.median(run_time(args.planner, 3, args.run_frames) for _ in range(runs))
    print(f"run, {args.run_frames} frames, {FAMILIES} at S1/S5 (median of {runs}): --drivedegrade-seeds 1 "
          f"{one:.1f} s, 3 {three:.1f} s, ratio {three / one:.2f}x")


if __name__ == "__main__":
    main()
