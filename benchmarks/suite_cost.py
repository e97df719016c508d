"""The suite's own cost per prediction (issue 23): this checkout against a reference commit, in one run.

Certifies PLANNER from this checkout and from a copy of REFERENCE (`git archive` into a temporary folder),
alternating, `--reps` times each, on the same data (this checkout's embedded world, given to both with
--drivedegrade-data) with the same options, each in a fresh report folder (nothing resumed). From each
certificate's cost ledger it reads the seconds the suite spent on its own work (decoding, injecting, the write
check, metrics and PDMS), over the predictions, and the planner's seconds per prediction as a control (the
planner is the same code in both trees, so its figure shows how loaded the machine was); `cpu` is the whole
run's CPU time (every process: world, floor, cells, report) per prediction, which load inflates less. Prints
every run, the medians per part and the ratio this checkout / reference. The ledger's parts are wall seconds
of each part in the process that ran it, so a loaded machine inflates them: quote the ratio, taken in one
alternating run.

    python benchmarks/suite_cost.py [--reference 99ab02d] [--frames N] [--reps 3] [-n 2] [-- extra pytest args]

The README's main job is `--frames 0 -n 2` (every frame, 89 cells: about 2.5 minutes a run on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SUITE_PARTS = ("decode", "inject", "check", "metrics", "pdms")
#: The main before issue 23's second pass: tracked PDMS and EPDMS scored, 512 MiB of decoded images.
DEFAULT_REFERENCE = "99ab02d"


def certify(tree: Path, planner: str, data: Path, args: argparse.Namespace, extra: list[str]) -> dict[str, float]:
    """One certification from `tree`; seconds per prediction of each ledger part, and the wall time."""
    with tempfile.TemporaryDirectory(prefix="ddcost-") as out:
        cmd = [sys.executable, "-m", "pytest", "--drivedegrade", planner, "-q", "-p", "no:randomly",
               "--drivedegrade-data", str(data), "--drivedegrade-report", out,
               "--drivedegrade-no-resume", "-n", str(args.n), *extra]
        if args.frames:
            cmd += ["--drivedegrade-frames", str(args.frames)]
        start, before = time.perf_counter(), _children_cpu()
        proc = subprocess.run(cmd, cwd=tree, capture_output=True, text=True,
                              env={**_env(), "PYTHONPATH": str(tree)})
        wall, cpu = time.perf_counter() - start, _children_cpu() - before
        found = sorted(Path(out).glob("*/certificate.json"))
        if proc.returncode not in (0, 1) or not found:
            sys.exit(f"certification from {tree} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n"
                     f"{proc.stderr[-3000:]}")
        cost = json.loads(found[0].read_text())["cost"]
    n = max(int(cost["predictions"]), 1)
    per = {part: 1e3 * float(cost["seconds"].get(part, 0.0)) / n for part in (*SUITE_PARTS, "planner")}
    per["suite"] = sum(per[p] for p in SUITE_PARTS)
    per["wall_s"] = wall
    per["cpu"] = 1e3 * cpu / n
    per["predictions"] = float(n)
    return per


def _children_cpu() -> float:
    """User + system CPU seconds of the finished child processes (the pytest run and its xdist workers)."""
    import resource

    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    return use.ru_utime + use.ru_stime


def _env() -> dict[str, str]:
    import os

    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTEST_ADDOPTS")}


def reference_tree(rev: str, into: Path) -> Path:
    """`rev` of this repository as files in `into` (no .git; the planner files and package of that commit)."""
    archive = subprocess.run(["git", "archive", rev], cwd=ROOT, capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into


def embedded_world() -> Path:
    """This checkout's embedded world (built on first use, as the plugin builds it)."""
    sys.path.insert(0, str(ROOT))
    from pytest_drivedegrade.data.world import ensure_default_world

    return ensure_default_world(ROOT / ".pytest_cache" / "d" / "drivedegrade")


def main() -> None:
    argv = sys.argv[1:]
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reference", default=DEFAULT_REFERENCE, help="the commit of the old path")
    ap.add_argument("--planner", default="planners/camera_cnn.py")
    ap.add_argument("--frames", type=int, default=48, help="scored frames (0: all)")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("-n", type=int, default=0, help="xdist workers")
    args = ap.parse_args(argv[: argv.index("--")] if "--" in argv else argv)
    data = embedded_world()
    runs: dict[str, list[dict[str, float]]] = {"reference": [], "this": []}
    with tempfile.TemporaryDirectory(prefix="ddref-") as tmp:
        trees = {"reference": reference_tree(args.reference, Path(tmp)), "this": ROOT}
        for rep in range(args.reps):
            for name in ("reference", "this") if rep % 2 == 0 else ("this", "reference"):
                per = certify(trees[name], args.planner, data, args, extra)
                runs[name].append(per)
                print(f"rep {rep + 1} {name:9s}: suite {per['suite']:.2f} ms/prediction "
                      f"({', '.join(f'{p} {per[p]:.2f}' for p in SUITE_PARTS)}), planner {per['planner']:.2f}, "
                      f"{int(per['predictions'])} predictions, wall {per['wall_s']:.1f} s", flush=True)
    print(f"\nmedians over {args.reps} runs each (ms per prediction; reference {args.reference}):")
    for part in (*SUITE_PARTS, "suite", "planner", "cpu", "wall_s"):
        ref = statistics.median(r[part] for r in runs["reference"])
        new = statistics.median(r[part] for r in runs["this"])
        ratio = f"{new / ref:.2f}" if ref else "-"
        print(f"  {part:8s} reference {ref:8.2f}  this {new:8.2f}  ratio {ratio}")
    # each rep's two runs are back to back: their ratio cancels the drift of a shared machine between reps
    paired = [t["suite"] / r["suite"] for t, r in zip(runs["this"], runs["reference"]) if r["suite"]]
    if paired:
        print(f"suite ratio per rep (this / reference, back to back): {', '.join(f'{x:.3f}' for x in paired)}; "
              f"median {statistics.median(paired):.3f}")


if __name__ == "__main__":
    main()
