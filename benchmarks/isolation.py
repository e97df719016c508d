"""What --drivedegrade-isolate costs per frame: the median time of one ``predict`` call in process and through the
isolated stand-in (`plugin.childplanner`: the planner in a child process, each camera it reads sent through a
memfd on request), for camera_cnn on the embedded world's val frames, measured in the same process, in whole
passes over the frames alternated (in process, isolated, in process, ...) so a shared machine's load falls on
both alike. A second planner that reads the same three cameras and returns at once measures the transport alone.

    python benchmarks/isolation.py --quick        # 16 frames, 3 rounds
    python benchmarks/isolation.py --frames 64 --rounds 5
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import textwrap
import time
from pathlib import Path
from types import MappingProxyType

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

READER = textwrap.dedent('''
    """Reads camera_cnn's three cameras (one pixel each) and returns at once: the transport's cost alone."""
    import numpy as np
    import pytest

    class Reader:
        cameras = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT")
        name = "reader"

        def predict(self, images, ego, cmd):
            total = sum(int(images[c][0, 0, 0]) for c in self.cameras)
            return np.full((6, 2), 1e-3 * total)

    @pytest.fixture(scope="session")
    def planner():
        return Reader()
''')


def build(path: Path, context, root: Path, settings):
    """The planner of `path` in this process and its isolated stand-in."""
    from functools import partial

    from pytest_drivedegrade.plugin.actors import PlannerFile
    from pytest_drivedegrade.plugin.childplanner import spawn, start_child_planner

    here, _ = PlannerFile(path)(context)
    request = {"run": {"settings": settings.to_builtins(), "root": str(root), "planner_path": str(path),
                       "digest_cache": None},
               "collect_path": str(path), "module": None, "default_name": path.stem, "opencv_threads": 1}
    return here, start_child_planner(partial(spawn, request), 60.0)


def timed(planner, inputs) -> list[float]:
    out = []
    for view, ego, cmd in inputs:
        start = time.perf_counter()
        planner.predict(view, ego, cmd)
        out.append(time.perf_counter() - start)
    return out


def measure(path: Path, context, root: Path, settings, inputs, rounds: int) -> tuple[float, float, bool]:
    """Median seconds per call in process and isolated, and whether every plan was bit-identical."""
    here, apart = build(path, context, root, settings)
    try:
        same = all(np.array_equal(np.asarray(here.predict(*x)), np.asarray(apart.predict(*x))) for x in inputs)
        a: list[float] = []
        b: list[float] = []
        for _ in range(rounds):  # whole passes, alternated: a run calls one planner frame after frame, and a
            a += timed(here, inputs)  # process that waited through the other's call starts cold (calls
            b += timed(apart, inputs)  # interleaved one by one doubled the isolated time here)
    finally:
        apart.close()
    return statistics.median(a), statistics.median(b), same


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="16 frames, 3 rounds")
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--cache-root", type=Path, default=ROOT / ".pytest_cache/d/drivedegrade")
    args = ap.parse_args(argv)
    frames, rounds = (16, 3) if args.quick else (args.frames, args.rounds)
    import os

    os.environ["OMP_NUM_THREADS"] = "1"  # the child's torch too (it inherits the variable), as this process's
    import cv2
    import torch

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    from pytest_drivedegrade.constants import CAMERAS
    from pytest_drivedegrade.data.nuscenes import NuScenesReader
    from pytest_drivedegrade.data.world import ensure_default_world
    from pytest_drivedegrade.run import RunContext
    from pytest_drivedegrade.settings import RunSettings

    root = ensure_default_world(args.cache_root)
    settings = RunSettings(frames=frames)
    context = RunContext.open(settings, root=root)
    inputs = []
    for frame in context.frames:
        images = {}
        for cam in CAMERAS:
            image = NuScenesReader.load_image(frame.cameras[cam])
            image.setflags(write=False)
            images[cam] = image
        inputs.append((MappingProxyType(images), frame.ego, frame.command))
    size = sum(i.nbytes for i in inputs[0][0].values()) / 2**20
    print(f"{len(inputs)} frames of the embedded world ({size:.1f} MiB of images each, 3 cameras read), {rounds} "
          f"rounds, one thread each side; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs (each "
          "isolated call waits for the other process to be scheduled once per camera and once for the plan: on a "
          "busy machine that wait, not the copy, is most of the added time)")
    with tempfile.TemporaryDirectory() as tmp:
        reader = Path(tmp) / "reader.py"
        reader.write_text(READER)
        for label, path in (("camera_cnn", ROOT / "planners" / "camera_cnn.py"), ("transport only", reader)):
            here, apart, same = measure(path, context, root, settings, inputs, rounds)
            print(f"{label:<15} in process {1e3 * here:7.2f} ms/frame   isolated {1e3 * apart:7.2f} ms/frame   "
                  f"ratio {apart / here:5.2f}   added {1e3 * (apart - here):6.2f} ms   plans identical: {same}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
