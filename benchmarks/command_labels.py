"""The reference planners' command labels on a world's junction split (issue 40): each planner certified by the
plugin on the junction scenes with the command_swap cell, its `command` section read back.

    python benchmarks/command_labels.py                # 20 junction scenes; floor, constant_velocity, the
                                                       # privileged expert, camera_cnn, temporal_cnn, closed_driver
    python benchmarks/command_labels.py --quick        # 4 junction scenes; floor, constant_velocity, the expert
    python benchmarks/command_labels.py --world DIR    # a world already built with --junction-scenes
    python benchmarks/command_labels.py --planners closed_driver   # some of the planners only (names below)

Each run is `pytest --drivedegrade PLANNER --drivedegrade-data WORLD --drivedegrade-split junction
--drivedegrade-families command_swap --drivedegrade-severities 5 -n 0` (4 cells: clean, null, blind, command_swap).
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
PLANNERS = {"ego_mlp (floor)": "planners/ego_mlp.py", "constant_velocity": "planners/constant_velocity.py",
            "privileged expert": "benchmarks/command_expert.py", "camera_cnn": "planners/camera_cnn.py",
            "temporal_cnn": "planners/temporal_cnn.py", "closed_driver": "planners/closed_driver.py"}
QUICK = ("ego_mlp (floor)", "constant_velocity", "privileged expert")


def certify(planner: str, world: Path, report: Path) -> dict:
    """The planner's certificate's `command` section from a plugin run on the junction split."""
    cmd = [sys.executable, "-m", "pytest", "--drivedegrade", str(ROOT / planner), "--drivedegrade-data", str(world),
           "--drivedegrade-split", "junction", "--drivedegrade-families", "command_swap",
           "--drivedegrade-severities", "5", "--drivedegrade-report", str(report), "--drivedegrade-report-overwrite",
           "-n", "0", "-q", "-p", "no:randomly"]
    start = time.perf_counter()
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{planner}: the run failed (exit {done.returncode}):\n{done.stdout[-2000:]}")
    found = sorted(report.glob("*/certificate.json"), key=lambda p: p.stat().st_mtime)[-1]
    section = json.loads(found.read_text())["command"]
    section["seconds"] = round(time.perf_counter() - start, 1)
    return section


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--world", type=Path)
    parser.add_argument("--json")
    parser.add_argument("--planners", help="comma-separated names among: " + ", ".join(PLANNERS))
    args = parser.parse_args()
    chosen = args.planners.split(",") if args.planners else list(PLANNERS)
    unknown = sorted(set(chosen) - set(PLANNERS))
    if unknown:
        parser.error(f"unknown planner(s) {', '.join(unknown)}: the names are {', '.join(PLANNERS)}")
    work = Path(tempfile.mkdtemp(prefix="command-labels-"))
    world = args.world
    if world is None:
        from pytest_drivedegrade.data.world import write_world

        start = time.perf_counter()
        world = write_world(work / "world", junction_scenes=4 if args.quick else 20)
        print(f"world with junction scenes built in {time.perf_counter() - start:.1f} s: {world}")
    rows = {}
    for name, planner in PLANNERS.items():
        if (args.quick and name not in QUICK) or name not in chosen:
            continue
        got = certify(planner, world, work / "rep")
        rows[name] = got
        print(f"{name:20s} following {got['following']:.3f} [{got['low']:.3f} .. {got['high']:.3f}] "
              f"{got['label']:20s} {got['frames']} junction frames, {got.get('basis', '')} ({got['seconds']} s)")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
