"""Benchmark the embedded world: default generation time (one core), reader throughput, event fraction.

Run by hand: `python benchmarks/world.py [--out DIR]`. Prints the time to render and write the val split,
the time for the train split's tables, frames per second of the reader (tables only, and with decoding all six
images), the fraction of val frames with a camera-only event, and the frame counts.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")


def main() -> None:
    import cv2

    from pytest_drivedegrade.data.nuscenes import NuScenesReader
    from pytest_drivedegrade.data.world import build

    cv2.setNumThreads(1)  # one core, as the target says
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    out = args.out or tempfile.mkdtemp(prefix="ddworld-bench-")
    stamps: list[tuple[str, float]] = []
    start = time.perf_counter()
    build.write_world(out, progress=lambda s: stamps.append((s, time.perf_counter() - start)))
    total = time.perf_counter() - start
    train_end = max(t for s, t in stamps if "(train" in s)
    print(f"default world: {total:.1f} s in all; train tables {train_end:.1f} s; "
          f"val split rendered and written {total - train_end:.1f} s (target < 60 s)")
    manifest = json.loads(open(os.path.join(out, build.MANIFEST)).read())
    for split in ("train", "val"):
        reader = NuScenesReader(out, split=split)
        t0 = time.perf_counter()
        frames = list(reader.frames())
        dt = time.perf_counter() - t0
        scorable = sum(f.scorable for f in frames)
        print(f"{split}: {len(frames)} frames, {scorable} scorable; reader {len(frames) / dt:.0f} frames/s "
              f"(tables only); events {manifest['events'][split]}")
    reader = NuScenesReader(out, split="val")
    t0 = time.perf_counter()
    frames = reader.scorable_frames(limit=30)
    for f in frames:
        for cam in f.cameras.values():
            reader.load_image(cam)
    dt = time.perf_counter() - t0
    print(f"val reader with six decoded images per frame: {len(frames) / dt:.1f} frames/s")
    size = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(out) for f in fs)
    print(f"world at {out}; {size / 1e6:.0f} MB")


if __name__ == "__main__":
    main()
