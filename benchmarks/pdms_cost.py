"""CPU per prediction of the PDMS score, as a cell pays it (issue 24 wires NAVSIM's tracker in; issue 23 counts
the suite's own CPU per prediction).

The world's scorable frames (2 scenes, seed 7: 68 frames) are prepared once (`PreparedFrame.of`, as the run
caches them per process), then `--cells` cells' worth of plans (the expert plus N(0, 0.3^2) noise, one draw per
cell) are scored: one plan at a time (`PreparedFrame.score`) and, where the code has it, a cell's plans together
(`pdms.score_plans`), and the PDMS with the EPDMS's terms as `pacing.score_cell_pdms` scores a cell (spec 4.1).
Prints CPU ms (process time, which a loaded
machine disturbs less than wall time) per plan for each.
Run it on another checkout with that checkout on PYTHONPATH to compare (a checkout without `score_plans` prints
the one-at-a-time figure only).

    python benchmarks/pdms_cost.py [--cells 5]
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np

from pytest_drivedegrade.data.nuscenes import NuScenesReader
from pytest_drivedegrade.data.world import write_world
from pytest_drivedegrade.metrics import pdms


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=5)
    args = ap.parse_args()
    reader = NuScenesReader(write_world(tempfile.mkdtemp(prefix="ddcost-"), scenes=2, seed=7, val_images=False),
                            split="all")
    frames = reader.scorable_frames()
    start = time.process_time()
    prepared = [pdms.PreparedFrame.of(f, reader.drivable_area(f), lane_map=reader.lane_map(f)) for f in frames]
    prepare_ms = (time.process_time() - start) * 1e3 / len(frames)
    cells = [np.stack([f.gt_future + np.random.default_rng(c).normal(0.0, 0.3, (6, 2)) for f in frames])
             for c in range(args.cells)]
    n = args.cells * len(frames)
    start = time.process_time()
    for plans in cells:
        for p, plan in zip(prepared, plans):
            p.score(plan)
    alone_ms = (time.process_time() - start) * 1e3 / n
    print(f"{len(frames)} frames, {args.cells} cells: prepare {prepare_ms:.2f} ms per frame (once per process)")
    print(f"one plan at a time: {alone_ms:.2f} ms per plan")
    if hasattr(pdms, "score_plans"):
        start = time.process_time()
        for plans in cells:
            pdms.score_plans(prepared, plans)
        print(f"a cell's plans together (score_plans): {(time.process_time() - start) * 1e3 / n:.2f} ms per plan")
    if hasattr(pdms.PreparedFrame, "extended"):  # spec 4.1: the EPDMS terms too, as pacing.score_cell_pdms does
        from pytest_drivedegrade.metrics.pdms.extended import epdms_score, extended_comfort

        start = time.process_time()
        for plans in cells:
            states = pdms.tracked_states(plans, [p.initial for p in prepared])
            for k, (p, plan, st) in enumerate(zip(prepared, plans, states)):
                terms = p.extended(st, p.score_tracked(plan, st))
                epdms_score(terms, extended_comfort(st, states[k - 1] if k else None))
        print(f"PDMS and EPDMS of a cell's plans: {(time.process_time() - start) * 1e3 / n:.2f} ms per plan")


if __name__ == "__main__":
    main()
