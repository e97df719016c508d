"""NAVSIM's two-stage pseudo-simulation on the embedded world (issue 39, `closedloop.twostage`): a planner's
cells scored in one stage (the cell's EPDMS) and in two (stage one times the weighted stage-two EPDMS at the start
poses around where its plans end), with the EPDMS retention of each corrupted cell against clean both ways.

    python benchmarks/navsim_two_stage.py [--data ROOT] [--frames N] [--cells clean,jpeg-s3,gaussian_blur-s5]
                                          [--planner navsim_style|camera_cnn] [--poses 6|8]

Quick by default: a two-scene world generated into a temporary folder (one val scene), 8 frames, the NAVSIM-style
example, clean and two corrupted cells. --data the default world (or any world root) for more frames. A whole
certification in this mode is ``pytest --drivedegrade PLANNER --drivedegrade-two-stage`` (docs/explanation/navsim.md).
"""

from __future__ import annotations

import argparse
import importlib.util
import tempfile
from pathlib import Path

import numpy as np

from pytest_drivedegrade.closedloop.twostage import STAGE_TWO_STARTS, stage_two_cell
from pytest_drivedegrade.data.world import write_world
from pytest_drivedegrade.run import RunContext
from pytest_drivedegrade.settings import RunSettings

PLANNERS = Path(__file__).resolve().parents[1] / "planners"


def build(planner: str, poses: int):
    if planner == "camera_cnn":
        path = PLANNERS / "camera_cnn.py"
        spec = importlib.util.spec_from_file_location("bench_camera_cnn", path)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return path, module.CameraCNNPlanner()
    path = PLANNERS / "examples" / "navsim_style.py"
    spec = importlib.util.spec_from_file_location("bench_navsim_style", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return path, module.NavsimStyleAgent(poses=poses)


def split_cell(cell: str) -> tuple[str, int]:
    if cell == "clean":
        return "clean", 0
    family, sev = cell.rsplit("-s", 1)
    return family, int(sev)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--cells", default="clean,jpeg-s3,gaussian_blur-s5")
    ap.add_argument("--planner", default="navsim_style", choices=("navsim_style", "camera_cnn"))
    ap.add_argument("--poses", type=int, default=6, choices=(6, 8))
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data or write_world(Path(tmp) / "world", scenes=2, future_s=4 if args.poses == 8 else 3)
        path, planner = build(args.planner, args.poses)
        context = RunContext.open(RunSettings(data=data, frames=args.frames), planner_path=path)
        print(f"{args.planner}, {args.poses} poses, {len(context.frames)} frames of {data}, "
              f"{len(STAGE_TWO_STARTS)} stage-two starts per frame")
        print("| cell | frames with stage two | EPDMS (one stage) | stage two | two-stage EPDMS | "
              "retention one stage | retention two-stage |")
        print("|---|---|---|---|---|---|---|")
        clean_one = clean_two = float("nan")
        for cell in args.cells.split(","):
            family, severity = split_cell(cell)
            record = context.run_cell(planner, family, severity)
            two = stage_two_cell(context, planner, record)
            have = np.isfinite(two.two_stage)
            one_mean = float(np.nanmean(record.epdms[have]))
            two_mean = float(np.nanmean(two.two_stage))
            if cell == "clean":
                clean_one, clean_two = one_mean, two_mean
            print(f"| {cell} | {two.frames} | {one_mean:.4f} | {float(np.nanmean(two.stage_two)):.4f} | {two_mean:.4f} "
                  f"| {one_mean / clean_one:.4f} | {two_mean / clean_two:.4f} |")


if __name__ == "__main__":
    main()
