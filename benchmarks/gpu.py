"""camera_cnn on CUDA: frames/s of predict and predict_batch (B = 1, 16, 64) on CUDA and, for reference, on the
CPU with one thread (as the suite runs it), and the largest plan difference between CPU and CUDA.

Needs only this repository and torch with CUDA (plus numpy, opencv-python-headless and pyyaml, which the package
imports); no install and no download. From the repository root:

    PYTHONPATH=. python benchmarks/gpu.py [--world small|default] [--frames N] [--passes 5] [--batches 1,16,64]

The frames come from the embedded world, rendered from the repository itself: `--world default` is the one a
certification scores (6 val scenes, 204 frames; rendered once into .pytest_cache/d/drivedegrade and reused, about
90 s on a 2-core machine), `--world small` an 11-scene world with 2 val scenes (68 frames) rendered into a
temporary folder in about 15 s. `--frames N` keeps N of them. Two rates per row: the whole call (OpenCV
preprocessing on the CPU, the network, the plans back) and the network alone on preprocessed views. CUDA runs
with deterministic cuDNN (no autotuning, no TF32), so two CUDA passes must give the same bits: checked.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "planners"))


def load_frames(world: str, frames: int | None) -> tuple[list[dict[str, np.ndarray]], list, list]:
    """The scored frames' front images (decoded once), ego states and commands."""
    from pytest_drivedegrade.data.world import ensure_default_world, write_world
    from pytest_drivedegrade.loader import samples
    from pytest_drivedegrade.run import RunContext
    from pytest_drivedegrade.settings import RunSettings

    start = time.perf_counter()
    if world == "default":
        root = ensure_default_world(ROOT / ".pytest_cache" / "d" / "drivedegrade")
    else:
        root = write_world(Path(tempfile.mkdtemp(prefix="dd-gpu-")), scenes=11, seed=4)
    ctx = RunContext.open(RunSettings(data=root, frames=frames, timeout=0.0))
    unread = ("CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")
    images = [dict(s.items()) for s in samples(ctx.frames, "clean", 0, seed=0, decode=ctx.decode, unread=unread)]
    print(f"world {world}: {len(images)} val frames ready in {time.perf_counter() - start:.1f} s", flush=True)
    return images, [f.ego for f in ctx.frames], [f.command for f in ctx.frames]


def median_rate(fn: Callable[[], np.ndarray], frames: int, passes: int) -> tuple[float, np.ndarray]:
    """Frames per second over the median of `passes` timed passes (after one warm-up pass), and the plans."""
    out = fn()  # warm-up: CUDA context, cuDNN kernel choice, allocator
    runs = []
    for _ in range(passes):
        start = time.perf_counter()
        out = fn()  # plans come back to the host as numpy: the device is synchronised
        runs.append(time.perf_counter() - start)
    return frames / statistics.median(runs), out


def measure(device: str, images: list, egos: list, cmds: list, batches: list[int],
            passes: int) -> tuple[dict[str, tuple[float, float]], dict[str, np.ndarray]]:
    """Per call style: (whole-call frames/s, network-only frames/s), and the plans of each style."""
    import camera_cnn

    from pytest_drivedegrade.floor import ego_features

    planner = camera_cnn.CameraCNNPlanner(device=device)
    n = len(images)
    pix = np.stack([camera_cnn.preprocess(im) for im in images])
    feats = np.stack([ego_features(e, c) for e, c in zip(egos, cmds)])
    rows: dict[str, tuple[float, float]] = {}
    plans: dict[str, np.ndarray] = {}

    def per_frame() -> np.ndarray:
        return np.stack([planner.predict(im, e, c) for im, e, c in zip(images, egos, cmds)])

    def network_per_frame() -> np.ndarray:
        return np.concatenate([planner.predict_many(pix[i:i + 1], feats[i:i + 1]) for i in range(n)])

    rows["predict"] = (median_rate(per_frame, n, passes)[0], median_rate(network_per_frame, n, passes)[0])
    plans["predict"] = per_frame()
    for b in batches:
        def batched(b: int = b) -> np.ndarray:
            return np.concatenate([planner.predict_batch(images[i:i + b], egos[i:i + b], cmds[i:i + b], [])
                                   for i in range(0, n, b)])

        def network(b: int = b) -> np.ndarray:
            return np.concatenate([planner.predict_many(pix[i:i + b], feats[i:i + b]) for i in range(0, n, b)])

        whole, plans[f"batch {b}"] = median_rate(batched, n, passes)
        rows[f"predict_batch B={b}"] = (whole, median_rate(network, n, passes)[0])
    plans["again"] = per_frame()  # a second pass: bit-identical on a deterministic device
    return rows, plans


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", choices=("small", "default"), default="small")
    parser.add_argument("--frames", type=int, help="use N of the world's val frames (default: all)")
    parser.add_argument("--passes", type=int, default=5, help="timed passes per row; the median counts")
    parser.add_argument("--batches", default="1,16,64")
    parser.add_argument("--no-cpu", action="store_true", help="skip the CPU reference rows")
    args = parser.parse_args()
    import torch

    torch.set_num_threads(1)  # the suite's setting: one thread per worker process
    if not torch.cuda.is_available():
        sys.exit(f"no CUDA device visible to torch {torch.__version__} (built with CUDA {torch.version.cuda}); "
                 "this benchmark needs one")
    print(f"torch {torch.__version__}, CUDA {torch.version.cuda}, {torch.cuda.get_device_name(0)}; CPU reference "
          "with 1 thread", flush=True)
    batches = [int(b) for b in args.batches.split(",")]
    images, egos, cmds = load_frames(args.world, args.frames)
    results = {}
    for device in ("cuda", *(() if args.no_cpu else ("cpu",))):
        results[device] = measure(device, images, egos, cmds, batches, args.passes)
        print(f"\n{device}: frames/s (median of {args.passes} passes, {len(images)} frames)")
        print(f"  {'call':22s} {'whole call':>11s} {'network only':>13s}")
        for name, (whole, net) in results[device][0].items():
            print(f"  {name:22s} {whole:11.0f} {net:13.0f}")
        plans = results[device][1]
        worst = max(float(np.abs(plans[k] - plans["predict"]).max()) for k in plans if k.startswith("batch"))
        same = plans["again"].tobytes() == plans["predict"].tobytes()
        print(f"  largest batched vs per-frame plan difference {worst:.2e} m; two passes bit-identical: {same}",
              flush=True)
    if "cpu" in results:
        diff = float(np.abs(results["cuda"][1]["predict"] - results["cpu"][1]["predict"]).max())
        print(f"\nlargest plan difference CPU vs CUDA (predict, per frame): {diff:.2e} m")


if __name__ == "__main__":
    main()
