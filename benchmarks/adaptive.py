"""The adaptive certification study (issue 22), simulated.

1. Error rate under optional stopping: thousands of synthetic paired populations with known retention (on a
   threshold, just off it, far from it), one decision each at alpha = 0.05: the adaptive rule (betting CS, the
   asymptotic CS, and its without-replacement form the plugin stops on) against the naive "stop when the paired
   bootstrap 95% CI clears" rule; mean share of units used.
2. Severity scheduling on two non-monotone curves: how often the scheduled s*10 / s*25 equal the full curve's, how
   often a violation is flagged.
3. Extrapolation to nuScenes-val size (6,019 frames, 150 scenes, windows of 8 scored + 2 warm-up frames) of a
   UniAD-like retention profile built from the paper's Table "tab:thresh" (UniAD's s*10 column) and Table
   "tab:visrel" (UniAD: quality axis 0.739, blackout S5 0.680): the share of a full run's forward passes an
   adaptive certification needs, and the share the sequential gate needs for an unchanged planner. Simulated: the
   per-unit noise (log-sd 0.3 of cell / clean per window) and the curves' shape are assumptions, not measurements.

4. The plugin on the embedded world: each reference planner certified full and with --drivedegrade-adaptive (a
   pytest subprocess each, -n 2), then the predictions each used, the labels, and whether every full-run
   retention-threshold (s*10, s*25) and axis lies in the adaptive run's anytime-valid interval.

    python benchmarks/adaptive.py [--runs 1000] [--reps 10] [--seed 0] [--plugin] [--planners a,b]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests" / "unit")]

#: (scenario, level, true retention) of the error-rate study.
SCENARIOS = (("far above s10", 0.90, 1.00), ("near above s10", 0.90, 0.93), ("on the s10 line", 0.90, 0.90),
             ("just below s10", 0.90, 0.89), ("on the s25 line", 0.75, 0.75), ("on the flat line", 0.95, 0.95),
             ("far below s25", 0.75, 0.55))
#: UniAD's s*10 from the paper's tab:thresh (None: never reached); blackout's S5 from tab:visrel.
UNIAD_S10 = {"motion_blur": 2.19, "gaussian_blur": 2.47, "gaussian_noise": 3.38, "jpeg": 3.72, "downscale": 3.64,
             "color_quant": 4.12, "frame_dropout": 3.07, "snow": 4.67, "low_light": 4.77, "fog": None,
             "bit_error": None, "raindrop": 1.10, "occlusion": 2.78, "mud_splash": 3.13, "lens_dirt": 4.68}
UNIAD_QUALITY, UNIAD_BLACKOUT_S5 = 0.739, 0.680
FRAMES, SCENES, WINDOW, WARMUP, CELLS = 6019, 150, 8, 2, 89
TOLERANCE = 0.02
#: The lowest retention a curve is given (the paper: UniAD keeps about 0.52 under blur at S5).
FLOOR = 0.45
#: The retention the simulation gives the ego cells that stop on their own (ego_noise S5, ego_blind, against the
#: flat line): far below it (an assumption).
OTHER_R = 0.6


def study(runs: int, seed: int) -> None:
    from test_adaptive import error_rates

    print(f"\n1. optional stopping, alpha = 0.05 per decision, {runs} populations of 750 units each (B = 5 m)")
    print(f"{'scenario':<18} {'level':>5} {'true r':>6} {'betting err':>11} {'asympt err':>10} {'wor err':>7} "
          f"{'naive err':>9} {'betting units':>13} {'asympt units':>12} {'wor units':>9}")
    for i, (name, level, r) in enumerate(SCENARIOS):
        bet, naive, used_b = error_rates(r, level, runs, 750, seed + i)
        asy, _, used_a = error_rates(r, level, runs, 750, seed + i, method="asymptotic", naive=False)
        wor, _, used_w = error_rates(r, level, runs, 750, seed + i, method="asymptotic-wor", naive=False)
        print(f"{name:<18} {level:>5.2f} {r:>6.2f} {bet:>11.3f} {asy:>10.3f} {wor:>7.3f} {naive:>9.3f} "
              f"{used_b:>13.1%} {used_a:>12.1%} {used_w:>9.1%}")


def curve_for(s10: float | None, power: float) -> dict[int, float]:
    """r(s) = 1 - 0.1 (s / s10)^power, which crosses 0.90 at s10; 1 - 0.008 s when never reached."""
    if s10 is None:
        return {s: 1.0 - 0.008 * s for s in range(1, 6)}
    return {s: 1.0 - 0.1 * (s / s10) ** power for s in range(1, 6)}


def uniad_profile() -> dict[str, dict[int, float]]:
    """The UniAD-like curves: the power fitted so that the nine quality families' mean S5 is 0.739; blackout
    linear from 0.89 at S1 (it crosses at 1.00) to 0.680 at S5."""
    from pytest_drivedegrade.corruptions.ladder import QUALITY_FAMILIES

    lo, hi = 1.0, 4.0
    for _ in range(60):
        power = (lo + hi) / 2
        q = np.mean([max(FLOOR, curve_for(UNIAD_S10[f], power)[5]) for f in QUALITY_FAMILIES])
        lo, hi = (power, hi) if q > UNIAD_QUALITY else (lo, power)
    out = {f: {s: max(FLOOR, r) for s, r in curve_for(s10, power).items()} for f, s10 in UNIAD_S10.items()}
    out["blackout"] = {s: 0.89 - (0.89 - UNIAD_BLACKOUT_S5) * (s - 1) / 4 for s in range(1, 6)}
    return out


def nuscenes_units(seed: int) -> list[int]:
    """Forward passes per unit, in draw order, for 150 scenes summing to 6,019 frames."""
    from pytest_drivedegrade.data.frame import Command, EgoStatus, Frame

    sizes = [FRAMES // SCENES + (1 if i < FRAMES % SCENES else 0) for i in range(SCENES)]
    ego = EgoStatus((0.0, 0.0), (0.0, 0.0), 0.0)
    frames = [Frame(f"{i}-{j}", str(i), j, {}, ego, Command.STRAIGHT, np.zeros((6, 2)), np.ones(6, bool))
              for i, n in enumerate(sizes) for j in range(n)]
    from pytest_drivedegrade.scoring.adaptive import cut_units

    return [u.passes for u in cut_units(frames, window=WINDOW, warmup=WARMUP, seed=seed)]


def noise_for(r: float, model: str) -> float:
    """Per-unit log-sd of cell / clean: "scaled" 0.05 + 0.5 (1 - r) (a barely damaged cell barely moves a
    plan), or "flat" 0.3 whatever the damage (a pessimistic bound)."""
    return 0.05 + 0.5 * max(0.0, 1.0 - r) if model == "scaled" else 0.3


def certify_once(profile: dict[str, dict[int, float]], passes: np.ndarray, rng: np.random.Generator,
                 method: str, model: str, skip: bool = False) -> tuple[float, int, int]:
    """(share of the full run's passes, cells visited, monotonicity flags) of one simulated adaptive run: each
    family scheduled (`schedule_family`), each cell stopped by `run_cell` on the two thresholds, then the axes'
    S5 cells extended until `axis_settled` clears the flat line (or the data run out)."""
    from test_adaptive import population

    from pytest_drivedegrade.constants import DEFAULT_FLAT
    from pytest_drivedegrade.corruptions.ladder import QUALITY_FAMILIES
    from pytest_drivedegrade.scoring.adaptive import run_cell, schedule_family, violations

    n = len(passes)
    # the plugin's union bound: over the C stopping cells' two-sided sequences, alpha / (2 C) per side
    alpha = 0.05 / (2 * (CELLS - 2))
    cum = np.concatenate([[0], np.cumsum(passes)])
    base = np.minimum(rng.lognormal(np.log(0.8), 0.45, n), 2.5)  # the same clean units in every cell
    used: dict[tuple[str, int], int] = {}
    s5: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    flags = 0
    for fam, curve in profile.items():
        seen: dict[int, dict[float, str]] = {}
        # the plugin visits every severity since issue 36 (`sequential.family_plan`); `skip` replays the former
        # bisection schedule (`schedule_family`) for comparison
        order = iter(range(5, 0, -1))
        while (s := (schedule_family(seen).next_severity if skip else next(order, None))) is not None:
            clean, cell = population(rng, n, curve[s], noise_for(curve[s], model), clean=base)
            stop = run_cell(clean, cell, (0.9, 0.75), alpha=alpha, method=method)
            seen[s], used[fam, s] = {d.level: d.side for d in stop.decisions}, stop.units
            if s == 5:
                s5[fam] = (clean, cell)
        flags += bool(violations(seen))
    for axis in (QUALITY_FAMILIES, ("blackout",)):
        extend_axis(axis, s5, used, alpha, method)
    # charged as the plugin runs them: unit by unit, each window with its warm-up (a cell that needs every unit
    # costs cum[n] = 1.25 full streams; the earlier model capped it at one full stream, which the plugin never did)
    cost = sum(cum[u] for u in used.values())
    # the plugin's cost model: clean and the null control run every unit; of the other 7 non-ladder cells, blind
    # and ego_noise S1-S4 decide nothing and run no unit (`sequential.levels_of`), ego_noise S5 and ego_blind (the
    # ego axis) stop on the flat line, simulated here at retention OTHER_R (an assumption)
    cost += 2 * cum[n]
    for _ in range(2):
        clean, cell = population(rng, n, OTHER_R, noise_for(OTHER_R, model), clean=base)
        cost += cum[run_cell(clean, cell, (DEFAULT_FLAT,), alpha=alpha, method=method).units]
    return cost / (CELLS * FRAMES), len(used), flags


def extend_axis(axis: tuple[str, ...], s5: dict[str, tuple[np.ndarray, np.ndarray]],
                used: dict[tuple[str, int], int], alpha: float, method: str) -> None:
    """Grow the axis' S5 cells by 5 % of the units at a time until the axis clears the flat line."""
    from pytest_drivedegrade.scoring.adaptive import axis_settled, retention_interval

    n = len(next(iter(s5.values()))[0])
    while True:
        spans = [retention_interval(s5[f][0][:used[f, 5]], s5[f][1][:used[f, 5]], alpha=alpha, population=n,
                                    method=method) for f in axis]
        if axis_settled(spans)[0] != "open" or all(used[f, 5] == n for f in axis):
            return
        for f in axis:
            used[f, 5] = min(n, used[f, 5] + max(1, n // 20))


def gate_once(profile: dict[str, dict[int, float]], passes: np.ndarray, rng: np.random.Generator,
              method: str, model: str) -> float:
    """Share of the full run's passes the sequential gate needs to settle "no regression" for an unchanged
    planner (its per-unit results equal the baseline's) on every family cell; an open cell counts in full."""
    from test_adaptive import population

    from pytest_drivedegrade.scoring.adaptive import GateBaseline, alpha_per_decision, gate_cell

    n = len(passes)
    cum = np.concatenate([[0], np.cumsum(passes)])
    alpha = alpha_per_decision(0.05, 5 * len(profile))
    cost, most = 0.0, 0
    for curve in profile.values():
        for s in range(1, 6):
            clean, cell = population(rng, n, curve[s], noise_for(curve[s], model))
            d = gate_cell(clean, cell, GateBaseline(clean, cell), list(range(n)), tolerance=TOLERANCE, alpha=alpha,
                          method=method)
            used = n if d.side != "above" else d.units
            cost += cum[used]
            most = max(most, used)
    cost += 2 * cum[n] + (CELLS - 5 * len(profile) - 2) * cum[most]  # clean and null: every unit
    return cost / (CELLS * FRAMES)


def extrapolate(reps: int, seed: int, methods: tuple[str, ...] = ("betting", "asymptotic", "asymptotic-wor"),
                skip: bool = False) -> None:
    profile = uniad_profile()
    passes = np.asarray(nuscenes_units(seed))
    print(f"\n3. nuScenes-val size, simulated: {FRAMES} frames, {SCENES} scenes, {len(passes)} windows of {WINDOW} "
          f"scored + {WARMUP} warm-up frames; full run = {CELLS} cells x {FRAMES} frames; {reps} repetitions")
    print("   UniAD-like profile (paper tab:thresh s*10, tab:visrel quality 0.739 / blackout S5 0.680): "
          + ", ".join(f"{f} S5 {c[5]:.2f}" for f, c in profile.items()))
    print(f"{'method':<14} {'noise':<7} {'certify share':>13} {'(max)':>6} {'cells visited':>13} {'flags':>5} "
          f"{'gate share':>10} {'(max)':>6}")
    for model in ("scaled", "flat"):
        for method in methods:
            rng = np.random.default_rng(seed)
            runs = [certify_once(profile, passes, rng, method, model, skip) for _ in range(reps)]
            gates = [gate_once(profile, passes, rng, method, model) for _ in range(reps)]
            shares = [r[0] for r in runs]
            print(f"{method:<14} {model:<7} {np.mean(shares):>13.1%} {max(shares):>6.1%} "
                  f"{np.mean([r[1] for r in runs]):>13.1f} {sum(r[2] for r in runs):>5} {np.mean(gates):>10.1%} "
                  f"{max(gates):>6.1%}")


def nonmonotone(seed: int) -> None:
    from test_adaptive import visit

    from pytest_drivedegrade.scoring.retention import tolerance_threshold

    print("\n2. severity scheduling on non-monotone curves (exact decisions)")
    for curve in ({1: 0.95, 2: 0.85, 3: 0.80, 4: 0.95, 5: 0.70}, {1: 0.97, 2: 0.93, 3: 0.85, 4: 0.92, 5: 0.80}):
        seen, skipped, found = visit(curve)
        part = {s: curve[s] for s in seen}
        got = [tolerance_threshold(part, c) for c in (0.9, 0.75)]
        full = [tolerance_threshold(curve, c) for c in (0.9, 0.75)]
        print(f"   curve {list(curve.values())}: visited {sorted(seen)}, skipped {list(skipped)}, flagged "
              f"{bool(found)}, scheduled s10/s25 {got}, full {full}")


#: The reference planners of the embedded-world targets (the ego-only floor is ego_mlp).
PLANNERS = ("camera_cnn", "temporal_cnn", "ego_mlp", "constant_velocity")


def certify(planner: str, out: Path, adaptive: bool, workers: str) -> dict:
    """One certification of planners/<planner>.py into `out` (reused when already there); its certificate."""
    cert = out / planner / "certificate.json"
    if not cert.exists():
        cmd = [sys.executable, "-m", "pytest", "--drivedegrade", f"planners/{planner}.py", "-n", workers, "-q",
               "-p", "no:randomly", "--drivedegrade-report", str(out), "--drivedegrade-report-overwrite",
               *(["--drivedegrade-adaptive"] if adaptive else [])]
        subprocess.run(cmd, cwd=ROOT, check=False, capture_output=True)
    return json.loads(cert.read_text())


def inside(value: float | None, span: list) -> bool:
    """Whether a full-run threshold (None: never) lies in an adaptive interval [low, high] (None: never)."""
    low, high = span
    if value is None:
        return high is None
    return (low is None or low <= value + 1e-6) and (high is None or value <= high + 1e-6)


def plugin_table(planners: tuple[str, ...], folder: Path, workers: str) -> None:
    print(f"\n4. the plugin on the embedded world, full vs --drivedegrade-adaptive (reports under {folder})")
    print(f"{'planner':<18} {'full pred':>9} {'adapt pred':>10} {'share':>6} {'full label':<25} "
          f"{'adaptive label':<25} {'in interval':>11} {'cells skipped/settled/data':>26}")
    for name in planners:
        full = certify(name, folder / "full", False, workers)
        ada = certify(name, folder / "adaptive", True, workers)
        sec = ada["adaptive"]
        checks, misses = 0, []
        for fam, t in full["thresholds"].items():
            for key in ("s10", "s25"):
                checks += 1
                if fam in sec["families"] and not inside(t[key],
                                                         sec["families"][fam][key]):
                    misses.append(f"{fam} {key}")
        for axis, entry in sec["axes"].items():
            checks += 1
            low, high = entry["interval"]
            if not low - 1e-6 <= full["axes"][axis] <= high + 1e-6:
                misses.append(f"axis {axis}")
        stops = [c["stop"] for c in sec["cells"].values()]
        how = "/".join(str(stops.count(s)) for s in ("skipped", "settled", "data"))
        fp, ap = full["cost"]["predictions"], ada["cost"]["predictions"]
        print(f"{name:<18} {fp:>9} {ap:>10} {ap / fp:>6.1%} {full['verdict']['label']:<25} "
              f"{ada['verdict']['label']:<25} {checks - len(misses):>5}/{checks:<5} {how:>26}")
        for miss in misses:
            print(f"   not in the adaptive interval: {miss}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=1000)
    parser.add_argument("--reps", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--skip-study", action="store_true")
    parser.add_argument("--plugin", action="store_true", help="also run section 4 (certifications, minutes each)")
    parser.add_argument("--planners", default=",".join(PLANNERS))
    parser.add_argument("--reports", default="/tmp/drivedegrade-adaptive-bench")
    parser.add_argument("--workers", default="2")
    parser.add_argument("--plugin-only", action="store_true")
    parser.add_argument("--methods", default="betting,asymptotic,asymptotic-wor")
    parser.add_argument("--skip-severities", action="store_true", help="the former bisection schedule (pre issue 36)")
    args = parser.parse_args()
    if args.plugin or args.plugin_only:
        plugin_table(tuple(args.planners.split(",")), Path(args.reports), args.workers)
    if args.plugin_only:
        return
    if not args.skip_study:
        study(args.runs, args.seed)
    nonmonotone(args.seed)
    extrapolate(args.reps, args.seed, tuple(args.methods.split(",")), args.skip_severities)


if __name__ == "__main__":
    main()
