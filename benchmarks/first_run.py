"""The first run a new user makes (issue 23): the README's main command in a fresh copy of a commit, its embedded
world built from nothing, timed, and the CPU it spent.

Copies COMMIT (`git archive`: the files a clone checks out) into a temporary folder and runs there, with that
copy first on the path (the README's set-up must have been run once in this environment, for the packages),
`python -m pytest --drivedegrade PLANNER -n N`: nothing cached, nothing resumed. Prints per run the wall time,
the world's build time (from its progress line), the CPU seconds of every process (user + system: the world's
processes, the controller, the workers), the least wall time that CPU allows on this machine's cores (CPU /
cores: where the wall sits near it the run is bound by its work, not by waiting), and the cost ledger's planner
and suite seconds; with `--against CSV`, whether the run's cells.csv equals that file byte for byte.

With `--reference REV` it times REV's first run too, alternating (REV, COMMIT, REV, COMMIT, ...), and prints the
ratio of the median walls, COMMIT / REV: this machine's speed changes from day to day (the same commit's first
run took 80.4 s on 2026-11-27 and 119.4 s on 2026-11-28), so a first-run figure is compared with a reference
measured in the same session. `--reference-wall S` (REV's first run when it was the figure to beat, e.g. the
issue's 176 s, measured on the tree before this round, 718c852) also prints S x ratio: COMMIT's first run at
the machine's speed of that day.

    python benchmarks/first_run.py [--commit HEAD] [--reps 1] [-n 2] [--against reports/camera_cnn/cells.csv]
                                   [--reference 718c852 --reference-wall 176]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from suite_cost import SUITE_PARTS, _children_cpu, _env, reference_tree  # noqa: E402  (a sibling script)

WORLD_LINE = re.compile(r"drivedegrade world: \d+ scenes in ([0-9.]+) s")


def first_run(tree: Path, planner: str, workers: int) -> dict[str, float]:
    """The main command in `tree` (its own cache and reports): wall, world and CPU seconds, the ledger's parts."""
    cmd = [sys.executable, "-m", "pytest", "--drivedegrade", planner, "-n", str(workers)]  # the README's, as typed
    start, before = time.perf_counter(), _children_cpu()
    proc = subprocess.run(cmd, cwd=tree, capture_output=True, text=True, env={**_env(), "PYTHONPATH": str(tree)})
    wall, cpu = time.perf_counter() - start, _children_cpu() - before
    found = sorted(tree.glob("reports/*/certificate.json"))
    if proc.returncode not in (0, 1) or not found:
        sys.exit(f"the main command failed in {tree} ({proc.returncode}):\n{proc.stdout[-3000:]}\n"
                 f"{proc.stderr[-3000:]}")
    world = WORLD_LINE.findall(proc.stdout + proc.stderr)
    cost = json.loads(found[0].read_text())["cost"]
    seconds = cost["seconds"]
    return {"wall": wall, "world": float(world[-1]) if world else float("nan"), "cpu": cpu,
            "planner": float(seconds.get("planner", 0.0)),
            "suite": sum(float(seconds.get(p, 0.0)) for p in SUITE_PARTS),
            "predictions": float(cost.get("predictions", 0))}


def _timed(commit: str, planner: str, workers: int, against: Path | None, cores: int, label: str) -> dict[str, float]:
    """One first run of `commit` in a fresh copy, printed as it ends."""
    with tempfile.TemporaryDirectory(prefix="ddfirst-") as tmp:
        tree = reference_tree(commit, Path(tmp))
        run = first_run(tree, planner, workers)
        same = ""
        if against is not None:
            csv = next(iter(sorted(tree.glob("reports/*/cells.csv"))), None)
            same = ", cells.csv " + ("identical" if csv is not None and csv.read_bytes() ==
                                      against.read_bytes() else "DIFFERENT")
    least = run["cpu"] / cores
    print(f"{label}: wall {run['wall']:.1f} s (world {run['world']:.1f} s); CPU {run['cpu']:.1f} s, so at "
          f"least {least:.1f} s on {cores} cores (wall / that {run['wall'] / least:.2f}); "
          f"ledger: planner {run['planner']:.1f} s, suite {run['suite']:.1f} s over {int(run['predictions'])} "
          f"predictions{same}", flush=True)
    return run


def _medians(runs: list[dict[str, float]]) -> dict[str, float]:
    return {k: statistics.median(r[k] for r in runs) for k in ("wall", "world", "cpu", "planner", "suite")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--commit", default="HEAD", help="the commit whose first run is timed")
    ap.add_argument("--planner", default="planners/camera_cnn.py")
    ap.add_argument("--reps", type=int, default=1, help="fresh copies, one run each")
    ap.add_argument("-n", type=int, default=2, help="xdist workers (the README's main command: 2)")
    ap.add_argument("--against", type=Path, help="a cells.csv the run's must equal byte for byte")
    ap.add_argument("--reference", help="a commit timed the same way, alternating, for the ratio COMMIT / it")
    ap.add_argument("--reference-wall", type=float, help="the reference's first-run seconds on the day it was "
                    "measured: prints COMMIT's at that day's speed")
    args = ap.parse_args()
    if args.reference_wall is not None and args.reference is None:
        ap.error("--reference-wall needs --reference (the commit whose first run it was)")
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    runs, refs = [], []
    for rep in range(args.reps):
        if args.reference is not None:
            refs.append(_timed(args.reference, args.planner, args.n, None, cores,
                               f"run {rep + 1}, reference {args.reference}"))
        runs.append(_timed(args.commit, args.planner, args.n, args.against, cores, f"run {rep + 1}, {args.commit}"))
    mine = _medians(runs)
    if len(runs) > 1:
        print(f"medians over {len(runs)} runs of {args.commit}: "
              + ", ".join(f"{k} {v:.1f} s" for k, v in mine.items()))
    if refs:
        theirs = _medians(refs)
        ratio = mine["wall"] / theirs["wall"]
        print(f"medians of {args.reference} (the reference): " + ", ".join(f"{k} {v:.1f} s" for k, v in theirs.items()))
        print(f"first run {args.commit} / {args.reference}: wall {ratio:.3f}, CPU {mine['cpu'] / theirs['cpu']:.3f}, "
              f"world {mine['world'] / theirs['world']:.3f}")
        if args.reference_wall is not None:
            print(f"at the speed of the day {args.reference} took {args.reference_wall:.1f} s: {args.commit} would "
                  f"take {args.reference_wall * ratio:.1f} s")


if __name__ == "__main__":
    main()
