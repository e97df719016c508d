"""Overlap: does the planner wait for the suite? A planner that sleeps 25 ms in predict() (as a GPU would, the
GIL released) certified on 48 frames and 6 families with -n 0, serially (--drivedegrade-prefetch 0) and with the
next frames made and the last one scored beside its calls (--drivedegrade-prefetch N), then the same on one local
Ray actor. For each it prints the cells' wall time from the certificate's cost ledger (``cost.wall``) over
predictions x 25 ms (1.00: the planner never waited), ``planner_busy``, and whether cells.csv is the same.

    python benchmarks/overlap.py [--frames 48] [--families jpeg,fog,...] [--prefetch 2] [--skip-ray] [--skip-local]
                                 [--reps 1]

With ``--reps N`` each layout runs N back-to-back pairs (serial, then prefetch) and ends with the median of each
ratio: the shared machine moves single readings by a few hundredths.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import statistics
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SLEEP_S = 0.025
FAMILIES = "jpeg,gaussian_noise,fog,motion_blur,lens_dirt,frame_dropout"

PLANNER = textwrap.dedent(f'''
    """A planner that reads every camera, then sleeps {SLEEP_S * 1000:g} ms (a GPU's compute: the GIL released)."""
    import time

    import numpy as np
    import pytest

    class Sleepy:
        name = "sleepy"
        fingerprint = "sleepy-1"

        def predict(self, images, ego, cmd):
            for image in images.values():  # read each camera as a planner uploading it would
                image[0, 0]
            time.sleep({SLEEP_S})
            v = np.asarray(ego.velocity, dtype=np.float64)
            return 0.5 * np.arange(1, 7, dtype=np.float64)[:, None] * v[None, :]


    @pytest.fixture(scope="session")
    def planner():
        return Sleepy()
''')


def certify(tmp: Path, name: str, extra: list[str]) -> tuple[dict, str]:
    """One certification in a fresh report folder: its cost ledger and its cells.csv without timing columns."""
    report = tmp / name
    cmd = [sys.executable, "-m", "pytest", "--drivedegrade", str(tmp / "sleepy.py"), "-q", "-p", "no:randomly",
           "--drivedegrade-report", str(report), *extra]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if proc.returncode not in (0, 1):
        sys.exit(f"{name}: run failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    cost = json.loads((report / "sleepy" / "certificate.json").read_text())["cost"]
    rows = list(csv.reader(io.StringIO((report / "sleepy" / "cells.csv").read_text())))
    keep = [i for i, h in enumerate(rows[0]) if not h.startswith("seconds") and h not in ("created", "tool_version")]
    return cost, "\n".join(",".join(r[i] for i in keep) for r in rows)


def line(label: str, cost: dict) -> str:
    asleep = cost["predictions"] * SLEEP_S
    return (f"{label:<28} {cost['predictions']:>6} predictions  cells' wall {cost['wall']:7.1f} s  "
            f"asleep {asleep:6.1f} s  ratio {cost['wall'] / asleep:5.2f}  planner busy "
            f"{100 * cost['planner_busy']:4.0f} %")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--families", default=FAMILIES)
    ap.add_argument("--prefetch", type=int, default=2)
    ap.add_argument("--skip-ray", action="store_true")
    ap.add_argument("--skip-local", action="store_true", help="only the Ray actor")
    ap.add_argument("--reps", type=int, default=1, help="back-to-back pairs per layout (medians printed)")
    args = ap.parse_args()
    common = ["--drivedegrade-frames", str(args.frames), "--drivedegrade-families", args.families]
    layouts = [] if args.skip_local else [("-n 0", ["-n", "0"])]
    if not args.skip_ray:
        layouts.append(("ray local, 1 actor", ["--drivedegrade-ray", "local", "--drivedegrade-ray-actors", "1"]))
    with tempfile.TemporaryDirectory() as name:
        tmp = Path(name)
        (tmp / "sleepy.py").write_text(PLANNER)
        for n, (label, layout) in enumerate(layouts):  # fresh report folders: nothing is resumed from a store
            ratios: dict[str, list[float]] = {"serial": [], "ahead": []}
            for rep in range(args.reps):
                serial, csv_serial = certify(tmp, f"serial{n}-{rep}", [*common, *layout, "--drivedegrade-prefetch",
                                                                       "0"])
                ahead, csv_ahead = certify(tmp, f"ahead{n}-{rep}", [*common, *layout, "--drivedegrade-prefetch",
                                                                    str(args.prefetch)])
                print(line(f"{label}, prefetch 0", serial))
                print(line(f"{label}, prefetch {args.prefetch}", ahead))
                print(f"{'':<28} cells.csv identical: {'yes' if csv_serial == csv_ahead else 'NO'}; wall ratio "
                      f"prefetch / serial {ahead['wall'] / serial['wall']:.2f}")
                for key, cost in (("serial", serial), ("ahead", ahead)):
                    ratios[key].append(cost["wall"] / (cost["predictions"] * SLEEP_S))
            if args.reps > 1:
                print(f"{label}: median ratio over {args.reps} pairs: prefetch 0 "
                      f"{statistics.median(ratios['serial']):.2f}, prefetch {args.prefetch} "
                      f"{statistics.median(ratios['ahead']):.2f} (each: "
                      f"{', '.join(f'{r:.2f}' for r in ratios['ahead'])})")


if __name__ == "__main__":
    main()
