"""The paper's workflow with the NAVSIM-style example: the agent's *own* evaluation loop, run once per cell with
the injector inside its image loader (`patch_loader` on ``cv2.imread``), writing a per-cell table that
``drivedegrade analyse`` reads. Copy it and replace `evaluate`'s body with your evaluator's.

    python planners/examples/navsim_own_loop.py WORLD_OR_NUSCENES_ROOT --out foreign/ --frames 8 --set axes
    drivedegrade analyse foreign/table.csv --out reports-foreign/

What the loop does per cell of ``drivedegrade ladder`` (clean with no injection):

- reads each frame's three front images with ``cv2.imread`` (BGR), as NAVSIM's loader does, under
  ``patch_loader(cv2, "imread", family, severity, seed=seed, channel_order="BGR", key=...)``; the ``key`` maps a
  file path to (sample token, camera), so the random families draw the realisation the plugin draws for that
  frame (its default key, the file stem, draws another, equally valid one);
- plans with the agent and scores the plan with its own metrics (here: the suite's L2 and collision functions,
  standing in for the evaluator's own), one per-frame CSV per cell;
- writes ``table.csv``: one row per cell, its per-frame file named in ``frames_file``.

Frame dropout is left out of the ``axes`` set here: the hook holds the last image *it* delivered per camera, while
the plugin holds the last one delivered in the same scene, so the two paths differ there by construction.
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from contextlib import nullcontext
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from pytest_drivedegrade import patch_loader
from pytest_drivedegrade.corruptions.hooks import camera_of
from pytest_drivedegrade.data.frame import Frame
from pytest_drivedegrade.data.nuscenes import NuScenesReader
from pytest_drivedegrade.foreign.ladder import LadderCell, ladder_cells
from pytest_drivedegrade.metrics.trajectory import at_horizons, frame_metrics

sys.path.insert(0, str(Path(__file__).resolve().parent))
from navsim_style import NavsimStyleAgent  # noqa: E402 - the example agent beside this file

#: The per-frame columns this loop writes (the table format's names, stp3 convention).
COLUMNS: tuple[str, ...] = (*(f"{k}_{h}s_stp3" for k in ("l2", "collision", "vru") for h in (1, 2, 3)), "jerk")


def path_key(frames: Iterable[Frame]) -> Callable[[object], tuple[str, str]]:
    """The hook's key: an image path -> (its keyframe's sample token, its camera), as the plugin seeds them."""
    token_of = {str(cam.path): f.token for f in frames for cam in f.cameras.values()}
    return lambda path: (token_of[str(path)], camera_of(str(path)))


def load_front(frame: Frame, cameras: Sequence[str]) -> dict[str, np.ndarray]:
    """The agent's images as its own loader reads them: ``cv2.imread`` (BGR), then RGB."""
    return {cam: cv2.cvtColor(cv2.imread(str(frame.cameras[cam].path)), cv2.COLOR_BGR2RGB) for cam in cameras}


def evaluate(agent: NavsimStyleAgent, frames: Sequence[Frame]) -> list[dict[str, Any]]:
    """The agent's own evaluation of `frames`: one row of figures per frame."""
    rows = []
    for frame in frames:
        plan = agent.predict(load_front(frame, agent.cameras), frame.ego, frame.command)
        m = frame_metrics(plan, frame)
        row: dict[str, Any] = {"frame": frame.token, "jerk": m["jerk"]}
        for kind, key in (("l2", "l2"), ("collision", "collision"), ("vru", "collision_vru")):
            for h, v in zip((1, 2, 3), at_horizons(np.asarray(m[key], dtype=float), "stp3")):
                row[f"{kind}_{h}s_stp3"] = repr(float(v))
        rows.append(row)
    return rows


def run_cell(agent: NavsimStyleAgent, frames: Sequence[Frame], cell: LadderCell) -> list[dict[str, Any]]:
    """One cell: the evaluation under the injector (none for clean)."""
    hook = patch_loader(cv2, "imread", cell.family, cell.severity, seed=cell.seed, channel_order="BGR",
                        key=path_key(frames)) if cell.inject else nullcontext()
    with hook:
        return evaluate(agent, frames)


def write_csv(path: Path, header: Sequence[str], rows: Iterable[Mapping[str, Any]]) -> None:
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(header), lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)


def own_loop(root: Path, out: Path, *, frames: int | None = None, split: str = "val", which: str = "axes",
             families: Sequence[str] | None = None, model: str = "navsim_style") -> Path:
    """Every cell of the ladder set through the agent's own loop; returns the table's path."""
    chosen = NuScenesReader(root, split=split).scorable_frames(limit=frames)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the example's fixture: the CPU kernels are deterministic per thread count
    try:
        agent = NavsimStyleAgent()
        out.mkdir(parents=True, exist_ok=True)
        table = []
        for cell in ladder_cells(which, families=families):
            name = f"{cell.cell}-seed{cell.seed}.csv"
            write_csv(out / name, ("frame", *COLUMNS), run_cell(agent, chosen, cell))
            table.append({"model": model, "cell": cell.cell, "seed": cell.seed, "frames": len(chosen),
                          "frames_file": name})
    finally:
        torch.set_num_threads(threads)
    write_csv(out / "table.csv", ("model", "cell", "seed", "frames", "frames_file"), table)
    return out / "table.csv"


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("root", type=Path, help="a nuScenes root (or the embedded world: drivedegrade world --out)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--frames", type=int, default=None)
    p.add_argument("--set", default="axes", choices=("full", "axes", "slice"))
    p.add_argument("--families", help="comma-separated families to keep")
    args = p.parse_args(argv)
    families = args.families.split(",") if args.families else None
    print(own_loop(args.root, args.out, frames=args.frames, which=args.set, families=families))
    return 0


if __name__ == "__main__":
    sys.exit(main())
