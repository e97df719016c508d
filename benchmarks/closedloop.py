"""The closed loop on the default world, timed: per-route Driving Score of the world's expert, constant velocity,
the ego-only floor, camera_cnn, the reference driver (closed_driver) and the percept bound (percept_expert:
`closedloop.percept`) on the clean cell and blackout S5
(`--slice`: the paper's seven cells), the seconds each cell spends rendering, planning, tracking and scoring,
and the slice's projected wall time with `-n 2` (cells dealt longest first to two workers; each worker builds a
route's backdrop once, as here), from each cell's CPU seconds (single-threaded torch and OpenCV: on an idle
machine CPU time is the wall time; on a shared one it is what the wall would be without the neighbours).

    python benchmarks/closedloop.py [--seeds 1] [--slice] [--agents log|reactive] [--prefetch N]
                                    [--planners expert,constant_velocity,floor,camera_cnn,closed_driver,percept_expert]
                                    [--collisions all|at_fault] [--routes N] [--held-out]

`--routes N` drives the first N routes only (quick mode; default: the slice's 30 routes, the 6 val routes, 18
scenario routes and 6 light routes).

`--held-out` drives 40 other routes instead: scenario scenes 3000-3023 and light scenes 3000-3015 of the world's
seed, in neither the slice (0-17, 0-5) nor the reference driver's training routes (numbered from 1000; its recipe
refuses to reach 3000). Choices about a driver are made on these, so the slice stays a test it was not tuned on.

`--prefetch N` (N > 0) drives as the plugin does under `--drivedegrade-prefetch N`: N + 1 threads render a step's
cameras at once and judge the last plan's steps while the next cameras render (same runs, bit for bit); compare
its wall and CPU columns with `--prefetch 0` (the default, serial).
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import torch

from pytest_drivedegrade.closedloop import Corruption, load_routes, run_cell
from pytest_drivedegrade.closedloop.expert import WorldExpert
from pytest_drivedegrade.closedloop.percept import PerceptExpert
from pytest_drivedegrade.closedloop.routes import held_out_routes
from pytest_drivedegrade.closedloop.simulate import Rules, Timings

ROOT = Path(__file__).resolve().parents[1]
CELLS = (Corruption(), Corruption("blackout", 5))
SLICE = (Corruption(), Corruption("gaussian_blur", 3), Corruption("gaussian_blur", 5), Corruption("motion_blur", 3),
         Corruption("motion_blur", 5), Corruption("blackout", 3), Corruption("blackout", 5))


def load_planner_file(stem: str) -> Any:
    spec = importlib.util.spec_from_file_location(f"_bench_{stem}", ROOT / "planners" / f"{stem}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def planners(names: list[str], routes: list, cache_root: Path, root: Path) -> dict[str, Any]:
    from pytest_drivedegrade.data.nuscenes import NuScenesReader
    from pytest_drivedegrade.floor import load_or_train_floor

    make = {"expert": lambda: WorldExpert(routes), "percept_expert": lambda: PerceptExpert(routes),
            "constant_velocity": lambda: load_planner_file("constant_velocity").ConstantVelocity(),
            "floor": lambda: load_or_train_floor(NuScenesReader(root, split="train"), cache_root / "floor"),
            "camera_cnn": lambda: load_planner_file("camera_cnn").CameraCNNPlanner(),
            "closed_driver": lambda: load_planner_file("closed_driver").ClosedDriver()}
    return {name: make[name]() for name in names}


def _short(route: str) -> str:
    """A route's column label: the val scene's number, s<number> for a scenario route, L<number> for a light
    route."""
    if route.startswith(("scenario-", "lights-")):
        return f"{'s' if route.startswith('scenario-') else 'L'}{route.split('-')[1][-3:]}"
    return route[-4:]


def _route_cell(ds: list[float | None]) -> str:
    """A route's mean DS over its seeds, or "unsc" when a run of it is unscored."""
    scored = [d for d in ds if d is not None]
    return f"{sum(scored) / len(scored):6.1f}" if scored and len(scored) == len(ds) else f"{'unsc':>6}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache-root", type=Path, default=ROOT / ".pytest_cache/d/drivedegrade")
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--planners", default="expert,constant_velocity,floor,camera_cnn")
    parser.add_argument("--slice", action="store_true", help="the paper's seven cells instead of clean and S5 blackout")
    parser.add_argument("--agents", default="log", choices=("log", "reactive"))
    parser.add_argument("--prefetch", type=int, default=0, help="threads beside the planner: N + 1 (0: serial)")
    parser.add_argument("--collisions", default="all", choices=("all", "at_fault"))
    parser.add_argument("--routes", type=int, default=None, help="the first N routes only")
    parser.add_argument("--held-out", action="store_true", help="40 routes in neither the slice nor training")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    from pytest_drivedegrade.data.world import ensure_default_world

    root = ensure_default_world(args.cache_root)
    routes = held_out_routes(root) if args.held_out else load_routes(root)
    routes = routes[:args.routes] if args.routes is not None else routes
    print("routes: " + ", ".join(f"{r.name} ({r.length:.0f} m)" for r in routes))
    pool = ThreadPoolExecutor(args.prefetch + 1, "closed") if args.prefetch > 0 else None
    header = f"{'planner':<18} {'cell':<18} " + " ".join(f"{_short(r.name):>6}" for r in routes) + \
        "   mean  bounds          render  plan  track  score  wall   cpu"
    print(header)
    for name, planner in planners(args.planners.split(","), routes, args.cache_root, root).items():
        walls = []
        for corruption in SLICE if args.slice else CELLS:
            timings, start, cpu = Timings(), time.perf_counter(), time.process_time()
            cell = run_cell(planner, routes, corruption, tuple(range(args.seeds)), timings, agents=args.agents,
                            pool=pool, rules=Rules(args.collisions))
            wall, cpu = time.perf_counter() - start, time.process_time() - cpu
            walls.append(cpu)
            cols = " ".join(_route_cell([r.ds for r in cell.runs if r.route == route.name]) for route in routes)
            lo, hi = cell.bounds
            mean = f"{cell.mean:6.1f}" if cell.mean is not None else "   n/a"
            print(f"{name:<18} {cell.cell:<18} {cols} {mean}  [{lo:5.1f}, {hi:5.1f}]  {timings.render:6.1f} "
                  f"{timings.plan:5.1f} {timings.track:6.1f} {timings.score:6.1f} {wall:5.1f} {cpu:5.1f}")
            kinds = ", ".join(f"{k} {v}" for k, v in cell.infractions.items()) or "none"
            ends = ", ".join(f"{_short(r.route)}:{r.end}" for r in cell.runs)
            print(f"{'':<18} infractions: {kinds}; ends: {ends}")
        print(f"{name}: {len(walls)} cells, {sum(walls):.1f} CPU s serial; projected wall with -n 2: "
              f"{two_workers(walls):.1f} s")
    return 0


def two_workers(walls: list[float]) -> float:
    """The makespan of the cells dealt longest first to the less loaded of two workers."""
    load = [0.0, 0.0]
    for wall in sorted(walls, reverse=True):
        load[load.index(min(load))] += wall
    return max(load)


if __name__ == "__main__":
    raise SystemExit(main())
