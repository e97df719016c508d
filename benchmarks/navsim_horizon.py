"""NAVSIM's 4 s horizon (issue 39): the NAVSIM-style example's clean cell (and, with --cells, jpeg-s3 and
blackout-s3) with six poses on a world with 3 s of future and on the same world with 4 s, and with eight poses on
the 4 s world: mean PDMS, EPDMS, NC, EP and L2, and a hash of every per-frame array, so that a six-pose planner's
cells can be seen to be bit-identical on both worlds.

    python benchmarks/navsim_horizon.py [--scenes 2] [--seed 0] [--cells] [--out DIR]

Quick by default: two scenes (one val scene, 34 frames), the clean cell; a minute or two on one core.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import tempfile
from pathlib import Path

import numpy as np

from pytest_drivedegrade.cells import FRAME_ARRAYS, CellRecord
from pytest_drivedegrade.data.world import write_world
from pytest_drivedegrade.run import RunContext
from pytest_drivedegrade.settings import RunSettings

EXAMPLE = Path(__file__).resolve().parents[1] / "planners" / "examples" / "navsim_style.py"


def agent(poses: int):
    spec = importlib.util.spec_from_file_location("navsim_style_bench", EXAMPLE)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.NavsimStyleAgent(poses=poses)


def digest(record: CellRecord) -> str:
    h = hashlib.sha256()
    for a in FRAME_ARRAYS:
        h.update(np.ascontiguousarray(record.array(a.name), dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


def row(label: str, record: CellRecord) -> str:
    mean = {k: float(np.nanmean(record.array(k))) for k in ("pdms", "epdms", "nc", "ep", "l2")}
    return (f"| {label} | {record.cell} | {len(record.frames)} | {mean['pdms']:.4f} | {mean['epdms']:.4f} | "
            f"{mean['nc']:.4f} | {mean['ep']:.4f} | {mean['l2']:.4f} | {digest(record)} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cells", action="store_true", help="also jpeg-s3 and blackout-s3")
    ap.add_argument("--out", type=Path, default=None, help="where the two worlds go (default: a temporary folder)")
    args = ap.parse_args()
    cells = [("clean", 0)] + ([("jpeg", 3), ("blackout", 3)] if args.cells else [])
    with tempfile.TemporaryDirectory() as tmp:
        root = args.out or Path(tmp)
        worlds = {s: write_world(root / f"world-future{s}", scenes=args.scenes, seed=args.seed, future_s=s)
                  for s in (3, 4)}
        print("| world, planner | cell | frames | PDMS | EPDMS | NC | EP | L2 | arrays hash |")
        print("|---|---|---|---|---|---|---|---|---|")
        for future, poses in ((3, 6), (4, 6), (4, 8)):
            context = RunContext.open(RunSettings(data=worlds[future]), planner_path=EXAMPLE)
            for family, severity in cells:
                print(row(f"{future} s world, {poses} poses", context.run_cell(agent(poses), family, severity)))


if __name__ == "__main__":
    main()
