"""Train the camera CNN reference planner (planners/camera_cnn.py) on the embedded world's train split.

    python planners/train_camera_cnn.py                 # world in .pytest_cache/d/drivedegrade, write weights
    python planners/train_camera_cnn.py --data ROOT     # any nuScenes-format root with train and val splits

Deterministic: fixed seeds, ``torch.use_deterministic_algorithms(True)``, one thread and a seeded shuffle, so the
same data gives the same weights. Decoded, downsampled images are cached as ``.npy`` keyed by the data set
fingerprint, so a rerun does not decode again. Writes ``camera_cnn.pt`` and ``camera_cnn.json`` (data set
fingerprint, settings, val figures) atomically, and prints the val split figures the issue asks for.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pytest_drivedegrade import floor
from pytest_drivedegrade.constants import HORIZON_STEPS
from pytest_drivedegrade.metrics.trajectory import l2_avg

HERE = Path(__file__).resolve().parent
SETTINGS: dict[str, Any] = {
    "epochs": 16, "batch": 64, "lr": 1e-3, "weight_decay": 1e-4, "seed": 0, "flip": True, "freeze_base": True,
    "aux_weight": 1.0, "detach_facts": False,
}
#: Feature columns that change sign under a left-right mirror: vy, ay, yaw rate, the past y positions.
_MIRROR_NEGATE = [1, 3, 4, 6, 8, 10, 12]


def _planner_module() -> Any:
    spec = importlib.util.spec_from_file_location("_drivedegrade_camera_cnn", HERE / "camera_cnn.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


CNN = _planner_module()


def load_split(reader: Any, cache_dir: Path) -> dict[str, np.ndarray]:
    """Preprocessed pixels, ego features and targets of a split's scorable frames, cached by fingerprint."""
    w, h = CNN.INPUT_SIZE
    key = hashlib.sha256(f"{reader.fingerprint()}|{CNN.VIEWS}|{CNN.PERCEPTS}|{w}x{h}|2".encode()).hexdigest()[:16]
    folder = cache_dir / f"tensors-{key}"
    names = ("pix", "feats", "targets", "aux")
    if all((folder / f"{n}.npy").is_file() for n in names):
        return {n: np.load(folder / f"{n}.npy") for n in names}
    frames = list(reader.scorable_frames())
    pix = np.zeros((len(frames), len(CNN.VIEWS), h, w, 3), np.uint8)
    for i, frame in enumerate(frames):
        pix[i] = CNN.preprocess({c: reader.load_image(frame.cameras[c]) for c in CNN.CNN_CAMERAS})
        if i % 500 == 0:
            print(f"  decoded {i}/{len(frames)}", flush=True)
    data = {"pix": pix, **dict(zip(("feats", "targets"), floor.frames_to_arrays(frames))),
            "aux": perception_targets(frames)}
    folder.mkdir(parents=True, exist_ok=True)
    for name, arr in data.items():
        tmp = folder / f"{name}.tmp.npy"
        np.save(tmp, arr)
        os.replace(tmp, folder / f"{name}.npy")
    return data


def _path_offsets(gt: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Distance of points `xy` (N, 2) from the ego's future path: the 3 s of ground truth, then straight on."""
    pts = np.vstack([[0.0, 0.0], gt])
    step = pts[-1] - pts[-3]
    heading = step / np.linalg.norm(step) if np.linalg.norm(step) > 0.5 else np.array([1.0, 0.0])
    pts = np.vstack([pts, pts[-1] + np.arange(2.0, 80.0, 2.0)[:, None] * heading])
    seg_a, seg_b = pts[:-1], pts[1:]
    d = seg_b - seg_a
    t = np.clip(((xy[:, None] - seg_a[None]) * d[None]).sum(-1) / np.maximum((d**2).sum(-1), 1e-9)[None], 0, 1)
    near = seg_a[None] + t[..., None] * d[None]
    return np.linalg.norm(xy[:, None] - near, axis=-1).min(1)


def perception_targets(frames: list[Any]) -> np.ndarray:
    """(N, len(PERCEPTS)) float32: the scene facts the network's bottleneck is trained to read off the cameras,
    from the annotations 0.5 s ahead and the future path (training only; the planner never sees annotations)."""
    out = np.zeros((len(frames), len(CNN.PERCEPTS)), np.float32)
    for i, frame in enumerate(frames):
        gt = np.asarray(frame.gt_future, dtype=float)
        veh, vru = (0.0, 2.0), (0.0, 1.5, 0.0, 0.0)
        boxes = frame.agents[0]
        if len(boxes):
            c = np.asarray(boxes.center, dtype=float)
            off = _path_offsets(gt, c)
            is_vru = np.array([k in ("pedestrian", "cyclist") for k in boxes.category])
            lane = (~is_vru) & (c[:, 0] > 0) & (c[:, 0] < 60) & (off < 2.0)
            if lane.any():
                veh = (1.0, float(c[lane, 0].min()) / 30)
            near = is_vru & (c[:, 0] > 0) & (c[:, 0] < 45) & (off < 4.5)
            if near.any():
                j = np.flatnonzero(near)[c[near, 0].argmin()]
                vru = (1.0, c[j, 0] / 30, c[j, 1] / 4.5, float(off[j] < 1.8))
        out[i] = (*veh, *vru, gt[2, 1] / 3, gt[5, 1] / 10)
    return out


def mirrored(data: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The left-right mirror of a split: images flipped, FRONT_LEFT and FRONT_RIGHT swapped, lateral signs
    negated, LEFT and RIGHT commands swapped. Doubles the training data (a regulariser, not a claim of symmetry)."""
    feats = data["feats"].copy()
    feats[:, _MIRROR_NEGATE] *= -1
    n = floor.FEATURE_SIZE - len(floor.Command)
    right, left = n + floor.Command.RIGHT, n + floor.Command.LEFT
    feats[:, [right, left]] = feats[:, [left, right]]
    targets = data["targets"].copy()
    targets[:, 1::2] *= -1
    mirror = {"CAM_FRONT_LEFT": "CAM_FRONT_RIGHT", "CAM_FRONT_RIGHT": "CAM_FRONT_LEFT"}
    swap = [CNN.VIEWS.index((mirror.get(cam, cam), crop)) for cam, crop in CNN.VIEWS]  # crops are centred
    aux = data["aux"].copy()
    aux[:, [CNN.PERCEPTS.index(k) for k in ("vru_y", "path_y15", "path_y30")]] *= -1
    return {"pix": data["pix"][:, swap, :, ::-1], "feats": feats, "targets": targets, "aux": aux}


def warm_start(model: Any, base: floor.EgoMLP) -> None:
    """Start from the ego-only floor: copy its MLP and statistics, zero the camera head's last layer."""
    model.base.load_state_dict(base.net.state_dict())
    for name in ("x_mean", "x_std", "y_mean", "y_std"):
        getattr(model, name).copy_(getattr(base, name))
    torch.nn.init.zeros_(model.head[-1].weight)
    torch.nn.init.zeros_(model.head[-1].bias)


def train(data: dict[str, np.ndarray], base: floor.EgoMLP, settings: dict[str, Any]) -> Any:
    """Train the camera residual deterministically: the perception bottleneck on the scene facts (smooth L1),
    the planning head on mean waypoint L2 from the predicted facts; the floor MLP stays frozen by default."""
    with floor.deterministic_torch(settings["seed"]):
        model = CNN.CameraCNN()
        warm_start(model, base)
        pix = data["pix"][::10].reshape(-1, 3).astype(np.float64) / 255.0  # a tenth suffices for statistics
        model.pix_mean.copy_(torch.from_numpy(pix.mean(0)).float())
        model.pix_std.copy_(torch.from_numpy(pix.std(0)).float())
        if settings["flip"]:
            flipped = mirrored(data)
            data = {k: np.concatenate([data[k], flipped[k]]) for k in data}
        xs, fs, ys, aux = (torch.from_numpy(np.ascontiguousarray(data[k])) for k in ("pix", "feats", "targets", "aux"))
        if settings["freeze_base"]:  # the floor stays the floor; only the camera residual learns
            model.base.requires_grad_(False)
        params = [p for p in model.parameters() if p.requires_grad]
        opt = torch.optim.AdamW(params, lr=settings["lr"], weight_decay=settings["weight_decay"])
        steps = settings["epochs"] * (len(xs) // settings["batch"])
        sched = torch.optim.lr_scheduler.OneCycleLR(opt, settings["lr"], total_steps=steps, pct_start=0.1)
        gen = torch.Generator().manual_seed(settings["seed"])
        for epoch in range(settings["epochs"]):
            model.train()
            order, total, start = torch.randperm(len(xs), generator=gen), 0.0, time.perf_counter()
            for b in range(len(xs) // settings["batch"]):
                idx = order[b * settings["batch"] : (b + 1) * settings["batch"]]
                z = (fs[idx] - model.x_mean) / model.x_std
                facts = model.perceive(xs[idx], z)
                # detach_facts: the planning loss does not reach the cameras, they learn only to read the facts
                plan = model.plan(facts.detach() if settings["detach_facts"] else facts, z)
                err = (plan - ys[idx]).view(-1, HORIZON_STEPS, 2)
                loss = torch.sqrt((err**2).sum(-1) + 1e-6).mean()
                loss = loss + settings["aux_weight"] * torch.nn.functional.smooth_l1_loss(facts, aux[idx])
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                sched.step()
                total += float(loss.detach())
            print(f"  epoch {epoch + 1}/{settings['epochs']}: train loss {total / (b + 1):.3f} "
                  f"({time.perf_counter() - start:.0f} s)", flush=True)
        model.eval()
    return model


def val_l2(model: Any, data: dict[str, np.ndarray], blackout: str | None = None) -> float:
    """Mean l2_avg (stp3) on a split; `blackout` zeroes one camera (what the blackout family does)."""
    pix = data["pix"].copy()
    if blackout is not None:  # every view of that camera
        pix[:, [i for i, (cam, _) in enumerate(CNN.VIEWS) if cam == blackout]] = 0
    planner = CNN.CameraCNNPlanner.__new__(CNN.CameraCNNPlanner)
    planner.model = model
    preds = np.concatenate([planner.predict_many(pix[i : i + 256], data["feats"][i : i + 256])
                            for i in range(0, len(pix), 256)])
    gt = data["targets"].reshape(-1, HORIZON_STEPS, 2)
    return float(np.mean(l2_avg(np.linalg.norm(preds - gt, axis=-1))))


def save(model: Any, sidecar: dict[str, Any], out: Path) -> None:
    """Weights and sidecar JSON, each written atomically."""
    floor.save_atomic(model, out)
    sidecar["weights_sha256"] = hashlib.sha256(out.read_bytes()).hexdigest()
    tmp = out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(sidecar, indent=2, sort_keys=True) + "\n")
    os.replace(tmp, out.with_suffix(".json"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="nuScenes-format root (default: the embedded world)")
    parser.add_argument("--cache-root", type=Path, default=Path(".pytest_cache/d/drivedegrade"))
    parser.add_argument("--epochs", type=int, default=SETTINGS["epochs"])
    parser.add_argument("--out", type=Path, default=HERE / "camera_cnn.pt")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=JSON", help="override a setting")
    args = parser.parse_args(argv)
    from pytest_drivedegrade.data.nuscenes import NuScenesReader
    from pytest_drivedegrade.data.world import ensure_default_world
    from pytest_drivedegrade.progress import Sink

    root = args.data or ensure_default_world(args.cache_root, train_images=True, progress=Sink())
    readers = {s: NuScenesReader(root, split=s) for s in ("train", "val")}
    cache = args.cache_root / "camera_cnn"
    data = {s: load_split(r, cache) for s, r in readers.items()}
    print(f"train {len(data['train']['pix'])} frames, val {len(data['val']['pix'])} frames", flush=True)
    settings = {**SETTINGS, "epochs": args.epochs}
    settings.update({k: json.loads(v) for k, v in (item.split("=", 1) for item in args.set)})
    base = floor.fit_arrays(data["train"]["feats"], data["train"]["targets"], seed=settings["seed"])
    model = train(data["train"], base, settings)
    figures = {
        "floor_l2_avg": float(np.mean(l2_avg(np.linalg.norm(
            base.predict_many(data["val"]["feats"]) - data["val"]["targets"].reshape(-1, 6, 2), axis=-1)))),
        "clean_l2_avg": val_l2(model, data["val"]),
        "cam_front_blackout_l2_avg": val_l2(model, data["val"], blackout="CAM_FRONT"),
    }
    figures["ratio_to_floor"] = figures["clean_l2_avg"] / figures["floor_l2_avg"]
    figures["cam_front_blackout_retention"] = figures["clean_l2_avg"] / figures["cam_front_blackout_l2_avg"]
    print(json.dumps(figures, indent=2))
    sidecar = {
        "dataset_fingerprint": readers["train"].fingerprint(), "split": "train",
        "val_fingerprint": readers["val"].fingerprint(), "train_frames": len(data["train"]["pix"]),
        "settings": settings, "floor_settings": floor.SETTINGS, "floor_version": floor.FLOOR_VERSION,
        "input_size": list(CNN.INPUT_SIZE), "cameras": list(CNN.CNN_CAMERAS), "torch": torch.__version__,
        "views": [[cam, list(crop) if crop else None] for cam, crop in CNN.VIEWS],
        "val_figures": figures,
    }
    save(model, sidecar, args.out)
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
