"""Benchmark the embedded world: default build time (parallel and serial), reader throughput, event fraction.

Run by hand: `python benchmarks/world.py [--out DIR] [--repeat 3] [--workers N] [--no-serial] [--against CHECKOUT]`.
With `--against` (another checkout of the package, e.g. main's), builds the default world `--repeat` times with
each code base in turn (old, new, old, new, ...; each a fresh Python process, as a first run is), prints the medians
of each, their ratio, and compares the sha256 of every file of the two worlds; then stops. Otherwise builds the default
world `--repeat` times on the default worker processes (one per available core, at most 8) and as many times in
one process (the serial path), each into a fresh temporary folder, and prints the median wall time of each, their
ratio, the CPU seconds they used (this process and its workers), and whether both built byte-identical files.
Then the reader's frames per second (tables only, and decoding all six images), the fraction of val frames with a
camera-only event, and the frame counts, on the world at `--out`.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")


def _cpu_s() -> float:
    """CPU seconds (user + system) of this process and of its finished children (the pool's workers)."""
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def _tree_sha(root: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(root)).encode() + hashlib.sha256(p.read_bytes()).digest())
    return h.hexdigest()


def _builds(repeat: int, workers: int | None, keep: Path | None) -> tuple[list[float], list[float], str]:
    """Wall and CPU seconds of `repeat` default builds on `workers` processes, and the last tree's hash."""
    from pytest_drivedegrade.data.world import build

    walls, cpus, sha = [], [], ""
    for i in range(repeat):
        out = Path(tempfile.mkdtemp(prefix="ddworld-bench-"))
        cpu, start = _cpu_s(), time.perf_counter()
        build.write_world(out, workers=workers)
        walls.append(time.perf_counter() - start)
        cpus.append(_cpu_s() - cpu)
        sha = _tree_sha(out)
        if keep is not None and i == repeat - 1 and not (keep / build.MANIFEST).exists():
            shutil.copytree(out, keep, dirs_exist_ok=True)
        shutil.rmtree(out)
    return walls, cpus, sha


_BUILD = """
import json, os, resource, sys, time
os.environ.setdefault("OMP_NUM_THREADS", "1")
t0 = time.perf_counter()
from pytest_drivedegrade.data.world import build
build.write_world(sys.argv[1])
wall = time.perf_counter() - t0
use = [resource.getrusage(w) for w in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
print(json.dumps({"wall": wall, "cpu": sum(u.ru_utime + u.ru_stime for u in use), "code": build.__file__}))
"""


def _file_shas(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _build_in(checkout: Path, out: Path) -> dict:
    """One default build by the package in `checkout`, in a fresh interpreter (imports included in its wall)."""
    env = {**os.environ, "PYTHONPATH": str(checkout)}
    done = subprocess.run([sys.executable, "-c", _BUILD, str(out)], env=env, cwd=checkout, check=True,
                          capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def compare(against: Path, repeat: int) -> int:
    """Old (`against`) and new (this checkout) default builds alternating; medians, ratio, per-file sha256."""
    new_code = Path(__file__).resolve().parents[1]
    runs: dict[str, list[dict]] = {"old": [], "new": []}
    shas: dict[str, dict[str, str]] = {}
    for i in range(repeat):
        for which, code in (("old", against), ("new", new_code)):
            out = Path(tempfile.mkdtemp(prefix=f"ddworld-{which}-"))
            try:
                runs[which].append(_build_in(code, out))
                if i == 0:
                    shas[which] = _file_shas(out)
            finally:
                shutil.rmtree(out, ignore_errors=True)
            r = runs[which][-1]
            print(f"  {which} #{i + 1}: {r['wall']:.1f} s wall, {r['cpu']:.1f} s CPU ({r['code']})", flush=True)
    med = {k: (statistics.median(r["wall"] for r in v), statistics.median(r["cpu"] for r in v))
           for k, v in runs.items()}
    print(f"default world, {repeat} builds each, alternating: old median {med['old'][0]:.1f} s wall "
          f"({med['old'][1]:.1f} s CPU), new median {med['new'][0]:.1f} s wall ({med['new'][1]:.1f} s CPU); "
          f"new / old wall = {med['new'][0] / med['old'][0]:.2f}, CPU = {med['new'][1] / med['old'][1]:.2f}")
    old, new = shas["old"], shas["new"]
    differ = sorted(k for k in old.keys() | new.keys() if old.get(k) != new.get(k))
    print(f"files: {len(new)} new, {len(old)} old; sha256 of every file "
          + ("identical" if not differ else f"DIFFERENT in {len(differ)}: {differ[:5]}"))
    return 1 if differ else 0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--workers", type=int, default=None, help="worker processes (default: one per core, <= 8)")
    ap.add_argument("--no-serial", action="store_true", help="skip the serial reference builds")
    ap.add_argument("--against", default=None, help="another checkout: compare its build with this one's")
    args = ap.parse_args()
    if args.against:
        raise SystemExit(compare(Path(args.against).resolve(), args.repeat))
    import cv2

    from pytest_drivedegrade.data.nuscenes import NuScenesReader
    from pytest_drivedegrade.data.world import build, tasks

    cv2.setNumThreads(1)  # one core per process, as the workers run
    out = Path(args.out or tempfile.mkdtemp(prefix="ddworld-bench-"))
    workers = args.workers or tasks.default_workers(build.DEFAULT_SCENES)
    walls, cpus, sha = _builds(args.repeat, workers, out)
    par = statistics.median(walls)
    print(f"default world on {workers} worker process(es) ({os.cpu_count()} cores): median {par:.1f} s wall over "
          f"{args.repeat} builds {[round(w, 1) for w in walls]}; {statistics.median(cpus):.1f} s CPU")
    if not args.no_serial:
        s_walls, s_cpus, s_sha = _builds(args.repeat, 1, None)
        ser = statistics.median(s_walls)
        print(f"serial (one process): median {ser:.1f} s wall {[round(w, 1) for w in s_walls]}; "
              f"{statistics.median(s_cpus):.1f} s CPU; parallel / serial wall = {par / ser:.2f}; "
              f"files {'byte-identical' if s_sha == sha else 'DIFFERENT'}")
    manifest = json.loads((out / build.MANIFEST).read_text())
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
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    print(f"world at {out}; {size / 1e6:.0f} MB")


if __name__ == "__main__":
    main()
