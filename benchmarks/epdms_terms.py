"""Per-term EPDMS figures of the world's expert plans with noise, written to JSON, and two such files compared
term by term (issue 39: what the change to NAVSIM v2.2's terms moved). Run it once per checkout, then compare:

    PYTHONPATH=<old checkout> python benchmarks/epdms_terms.py --scenes 6 --seed 7 --out old.json
    PYTHONPATH=<this checkout> python benchmarks/epdms_terms.py --scenes 6 --seed 7 --out new.json
    python benchmarks/epdms_terms.py --compare old.json new.json

Quick mode: the defaults (2 scenes). Each plan: the frame's expert + N(0, sigma^2) per coordinate (one draw,
seed 0, frames in reader order), scored by `PreparedFrame` (the PDMS and the EPDMS terms, the human filter;
ec is a two-frame term and left out).
"""

from __future__ import annotations

import argparse
import json
import tempfile

import numpy as np

SIGMAS: tuple[float, ...] = (0.0, 0.3, 1.0)
TERMS: tuple[str, ...] = ("nc", "dac", "ddc", "ep", "ttc", "lk", "hc")
SHOWN: tuple[str, ...] = ("nc", "ttc", "ddc", "lk", "hc", "f_hc", "f_lk", "f_ddc", "epdms", "pdms")


def measure(scenes: int, seed: int) -> list[dict[str, float]]:
    from pytest_drivedegrade.data.nuscenes import NuScenesReader
    from pytest_drivedegrade.data.world import write_world
    from pytest_drivedegrade.metrics import pdms
    from pytest_drivedegrade.metrics.pdms import extended

    reader = NuScenesReader(write_world(tempfile.mkdtemp(prefix="ddterms-"), scenes=scenes, seed=seed,
                                       val_images=False), split="all")
    frames = reader.scorable_frames()
    prepared = [pdms.PreparedFrame.of(f, reader.drivable_area(f), lane_map=reader.lane_map(f)) for f in frames]
    rng = np.random.default_rng(0)
    rows = []
    for sigma in SIGMAS:
        for f, p in zip(frames, prepared):
            plan = f.gt_future + rng.normal(0.0, sigma, f.gt_future.shape) if sigma else f.gt_future
            ps = pdms.tracked_states(plan[None], [p.initial])[0]
            result = p.score_tracked(plan, ps)
            terms = p.extended(ps, result)
            assert p.human is not None
            kept = terms.filtered(p.human)
            rows.append({"sigma": sigma, **{k: getattr(terms, k) for k in TERMS},
                         **{"f_" + k: getattr(kept, k) for k in TERMS},
                         "epdms": extended.epdms_score(kept, float("nan")), "pdms": result.pdms})
    return rows


def compare(old: list[dict[str, float]], new: list[dict[str, float]]) -> None:
    print("| sigma | term | plans changed | mean before | mean after |")
    print("|---|---|---|---|---|")
    for sigma in SIGMAS:
        a_rows = [r for r in old if r["sigma"] == sigma]
        b_rows = [r for r in new if r["sigma"] == sigma]
        for k in SHOWN:
            a, b = np.array([r[k] for r in a_rows]), np.array([r[k] for r in b_rows])
            print(f"| {sigma:g} | {k} | {int((a != b).sum())} of {len(a)} | {np.nanmean(a):.4f} | "
                  f"{np.nanmean(b):.4f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=2)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--out", default="")
    ap.add_argument("--compare", nargs=2, metavar=("OLD", "NEW"))
    args = ap.parse_args()
    if args.compare:
        compare(*(json.loads(open(p).read()) for p in args.compare))
        return
    rows = measure(args.scenes, args.seed)
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(rows, fh)
    for sigma in SIGMAS:
        sel = [r for r in rows if r["sigma"] == sigma]
        print(f"sigma {sigma:g}: " + ", ".join(f"{k} {np.nanmean([r[k] for r in sel]):.4f}" for k in SHOWN))


if __name__ == "__main__":
    main()
