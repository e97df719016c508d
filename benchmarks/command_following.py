"""Command following of the reference planners on the embedded world's junction frames (issue 40).

    python benchmarks/command_following.py                 # val split: floor, camera_cnn, temporal_cnn
    python benchmarks/command_following.py --split train   # more junction frames; no images there: the floor and
                                                           # constant_velocity only
    python benchmarks/command_following.py --quick         # val split, the floor and constant_velocity only

At each frame where another command is meaningful (`data.junctions.alternative`) every planner plans twice on
the clean images: with the logged command and with the alternative; `scoring.command.following` reads how far the
plan moved toward the privileged expert's path for the alternative (0: ignores the command, 1: the expert).
temporal_cnn is given the scene's two previous frames first (its memory warm, under the logged command).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from planners import ROOT, images_of, load_planner_file  # noqa: E402
from pytest_drivedegrade.data.junctions import alternative  # noqa: E402
from pytest_drivedegrade.data.nuscenes import NuScenesReader  # noqa: E402
from pytest_drivedegrade.floor import load_or_train_floor  # noqa: E402
from pytest_drivedegrade.planning import planner_cameras  # noqa: E402
from pytest_drivedegrade.scoring.command import following  # noqa: E402


def world_root() -> Path:
    """The embedded world the suite builds into the checkout's pytest cache (built now if missing)."""
    found = sorted((ROOT / ".pytest_cache" / "d" / "drivedegrade").glob("world-*-seed0"))
    if found:
        return found[-1]
    from pytest_drivedegrade.data.world import write_world

    return write_world(ROOT / ".pytest_cache" / "d" / "drivedegrade" / "world-bench", seed=0)


def plan(planner: Any, reader: Any, frame: Any, command: Any, history: list[Any]) -> np.ndarray:
    cams = planner_cameras(planner)
    if getattr(planner, "name", "") == "temporal_cnn":
        planner.reset(frame.scene_token)
        context = SimpleNamespace(scene_token=frame.scene_token)
        for past in history:
            planner.predict(images_of(reader, past, cams), past.ego, past.command, context)
        return np.asarray(planner.predict(images_of(reader, frame, cams), frame.ego, command, context), float)
    return np.asarray(planner.predict(images_of(reader, frame, cams), frame.ego, command), float)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--split", default="val")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    root = world_root()
    reader = NuScenesReader(root, split=args.split)
    frames = reader.scorable_frames(agents=False)
    by_scene: dict[str, list[Any]] = {}
    for f in frames:
        by_scene.setdefault(f.scene_token, []).append(f)
    scored = [(f, a) for f in frames if (a := alternative(reader.lane_map(f), f.pose, f.gt_future, f.command))]
    print(f"{args.split}: {len(scored)} of {len(frames)} scorable frames where another command is meaningful")
    planners: dict[str, Any] = {
        "ego_mlp (floor)": load_or_train_floor(NuScenesReader(root, split="train"), ROOT / ".pytest_cache" / "d" /
                                               "drivedegrade" / "floor"),
        "constant_velocity": load_planner_file("constant_velocity").ConstantVelocity(),
    }
    if not args.quick and args.split == "val":  # the world renders images for its val split only
        planners["camera_cnn"] = load_planner_file("camera_cnn").CameraCNNPlanner()
        planners["temporal_cnn"] = load_planner_file("temporal_cnn").TemporalCNNPlanner()
    logged = np.stack([f.gt_future for f, _ in scored]) if scored else np.zeros((0, 6, 2))
    target = np.stack([a.path for _, a in scored]) if scored else np.zeros((0, 6, 2))
    out = {"split": args.split, "frames": len(frames), "junction_frames": len(scored),
           "expert": following(logged, target, logged, target).__dict__}
    print(f"  privileged expert: {following(logged, target, logged, target).text()}")
    for name, planner in planners.items():
        p0, p1 = [], []
        for f, a in scored:
            history = [x for x in by_scene[f.scene_token] if x.index < f.index][-2:]
            p0.append(plan(planner, reader, f, f.command, history))
            p1.append(plan(planner, reader, f, a.command, history))
        got = following(np.array(p0), np.array(p1), logged, target) if scored else following(logged, logged,
                                                                                               logged, target)
        out[name] = got.__dict__
        print(f"  {name}: {got.text()}")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
