"""Quality and speed of the reference planners on the embedded world's val split, on one CPU thread.

    python benchmarks/planners.py                       # all frames of the val split, 200 timed frames
    python benchmarks/planners.py --frames 300 --json out.json

Quality: l2_avg (stp3 and uniad), collision and VRU collision at 3 s (both conventions), clean and with CAM_FRONT
blacked out (retention = clean / blackout L2). Speed: ``predict`` calls per second on decoded full-resolution
images (all six cameras, read-only), after a warm-up; decoding is not timed, the planner's own resize is.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from pytest_drivedegrade.constants import CAMERAS
from pytest_drivedegrade.floor import load_or_train_floor
from pytest_drivedegrade.metrics import trajectory as metrics
from pytest_drivedegrade.planning import planner_cameras, predict_checked

ROOT = Path(__file__).resolve().parents[1]


def load_planner_file(stem: str) -> Any:
    spec = importlib.util.spec_from_file_location(f"_bench_{stem}", ROOT / "planners" / f"{stem}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def images_of(reader: Any, frame: Any, cameras: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Decoded read-only images; cameras the planner does not read are zero (they cannot change its output)."""
    out = {}
    for cam in CAMERAS:
        info = frame.cameras[cam]
        img = reader.load_image(info) if cam in cameras else np.zeros((info.height, info.width, 3), np.uint8)
        img.flags.writeable = False
        out[cam] = img
    return out


def quality(planner: Any, reader: Any, frames: list[Any]) -> dict[str, float]:
    """Mean metrics over `frames`, clean and with CAM_FRONT zeroed."""
    cams = planner_cameras(planner)
    rows, l2_black = [], []
    for frame in frames:
        imgs = images_of(reader, frame, cams)
        rows.append(metrics.frame_metrics(predict_checked(planner, imgs, frame.ego, frame.command, frame.token),
                                          frame))
        black = {**imgs, "CAM_FRONT": np.zeros_like(imgs["CAM_FRONT"])}
        pred = predict_checked(planner, black, frame.ego, frame.command, frame.token)
        l2_black.append(metrics.l2_per_step(pred, frame.gt_future))
    per = {k: np.array([r[k] for r in rows], dtype=float) for k in ("l2", "collision", "collision_vru")}
    out = {"frames": len(frames)}
    for conv in metrics.CONVENTIONS:
        out[f"l2_avg_{conv}"] = float(metrics.l2_avg(per["l2"], conv).mean())
        out[f"collision_3s_{conv}"] = float(metrics.at_horizons(per["collision"], conv)[:, 2].mean())
        out[f"collision_vru_3s_{conv}"] = float(metrics.at_horizons(per["collision_vru"], conv)[:, 2].mean())
    out["l2_avg_stp3_cam_front_blackout"] = float(metrics.l2_avg(np.array(l2_black)).mean())
    out["cam_front_blackout_retention"] = out["l2_avg_stp3"] / out["l2_avg_stp3_cam_front_blackout"]
    out["jerk"] = float(np.mean([r["jerk"] for r in rows]))
    return out


def speed(planner: Any, samples: list[tuple[dict, Any, Any]], repeats: int = 1) -> float:
    """predict() calls per second over pre-decoded samples, after a 10-call warm-up."""
    for imgs, ego, cmd in samples[:10]:
        planner.predict(imgs, ego, cmd)
    start = time.perf_counter()
    for _ in range(repeats):
        for imgs, ego, cmd in samples:
            planner.predict(imgs, ego, cmd)
    return repeats * len(samples) / (time.perf_counter() - start)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache-root", type=Path, default=ROOT / ".pytest_cache/d/drivedegrade")
    parser.add_argument("--frames", type=int, default=None, help="val frames for quality (default: all)")
    parser.add_argument("--timed", type=int, default=200, help="frames for the speed measurement")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    from pytest_drivedegrade.data.nuscenes import NuScenesReader
    from pytest_drivedegrade.data.world import ensure_default_world

    root = ensure_default_world(args.cache_root)
    val = NuScenesReader(root, split="val")
    frames = list(val.scorable_frames(limit=args.frames))
    planners = {
        "constant_velocity": load_planner_file("constant_velocity").ConstantVelocity(),
        "ego_mlp": load_or_train_floor(NuScenesReader(root, split="train"), args.cache_root / "floor"),
        "camera_cnn": load_planner_file("camera_cnn").CameraCNNPlanner(),
    }
    timed = [(images_of(val, f, CAMERAS), f.ego, f.command) for f in frames[: args.timed]]
    results = {"dataset_fingerprint": val.fingerprint(), "threads": torch.get_num_threads()}
    for name, planner in planners.items():
        results[name] = {**quality(planner, val, frames), "frames_per_s": speed(planner, timed)}
        print(name, json.dumps(results[name], indent=1), flush=True)
    cnn, flr = results["camera_cnn"], results["ego_mlp"]
    results["camera_cnn_over_floor_l2"] = cnn["l2_avg_stp3"] / flr["l2_avg_stp3"]
    print(f"camera_cnn / floor l2_avg (stp3): {results['camera_cnn_over_floor_l2']:.3f}; "
          f"CAM_FRONT blackout retention {cnn['cam_front_blackout_retention']:.3f}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
