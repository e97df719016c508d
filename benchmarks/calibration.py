"""Calibration of the adaptive certificate and the sequential gate (issue 36): the plugin's own rules replayed on
per-frame populations under many seeded draw orders, at the plugin's per-side level.

For each population (paired per-frame L2 of clean and of C stopping cells) and each draw order:

* **the adaptive rule** (`sequential.stop_at` on the cell's levels 0.9 and 0.75, single-frame units, each side at
  alpha / (2 C)) stops each cell; the cell's anytime-valid interval (`sequential.retention_span`, first crossings
  over the units it ran) is wrong when it excludes the cell's population retention. Every settled decision lies
  inside the interval's reading, so a draw order is a family-wise error when any cell's interval is wrong;
  ``FWE`` is their share with a 95 % Wilson interval, beside alpha;
* **the gate** (`adaptive.gate_cell` at alpha / C per cell, tolerance 0.02) against the population as its own
  baseline: unchanged (a "regression" is a false alarm), and with a regression confined to 5 % of the frames
  (retention dropped by 0.03 and by 0.05: "no regression" is wrong; "regression" is power);
* **cost**: units used over the population, averaged over cells and orders.

Populations: synthetic (204 frames in 6 scenes of 34, like the embedded world; C = 87 cells whose retentions
spread over 0.40-1.05, a third of them on or next to a level): iid heavy-tailed (lognormal, log-sd 0.9),
scene-autocorrelated (AR(1) 0.9 in log L2 within each scene), 5 % failure frames (cell L2 x 6 on 5 % of frames);
plus the real per-frame L2 of a run's ``cells/`` folder (``--cells DIR``: every stopping cell with every frame,
camera_cnn's full run for the note).

    python benchmarks/calibration.py [--orders 1000] [--alpha 0.05,0.10] [--method betting] [--cells DIR]
    python benchmarks/calibration.py --quick      # 40 orders, 24 cells: a smoke run (tests use it)
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]

from pytest_drivedegrade.scoring import sequential as sq  # noqa: E402
from pytest_drivedegrade.scoring.adaptive import DEFAULT_BOUND, GateBaseline, gate_cell  # noqa: E402

LEVELS = (0.9, 0.75)
TOLERANCE = 0.02
FRAMES, SCENE = 204, 34
#: The stopping cells of a default full run (the union bound's C the plugin uses: alpha / (2 x 87) per side).
UNION = 87


@dataclass(frozen=True)
class Population:
    """Per-frame L2 of clean (n,) and of the stopping cells (C, n), and the scene of each frame."""

    name: str
    clean: np.ndarray
    cells: np.ndarray
    scenes: np.ndarray
    union: int = 0  #: C of the union bound when it is not the cells replayed (a real run's 87 stopping cells)
    names: tuple[str, ...] = ()  #: the cells' ids (a real run's)

    def label(self, i: int) -> str:
        return self.names[i] if self.names else f"cell {i}"

    def retention(self) -> np.ndarray:
        return self.clean.sum() / self.cells.sum(axis=1)


def wilson(k: int, n: int) -> tuple[float, float]:
    """The 95 % Wilson interval of a share k / n."""
    if n == 0:
        return (math.nan, math.nan)
    p, z = k / n, 1.96
    mid = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, mid - half), min(1.0, mid + half)


def _retentions(count: int) -> np.ndarray:
    """C retentions over 0.40-1.05, a third on or next to the levels (the hardest cells to settle)."""
    near = np.array([0.9, 0.75, 0.905, 0.745, 0.895, 0.755, 0.91, 0.74])
    spread = np.linspace(0.40, 1.05, count)
    return np.concatenate([np.resize(near, count // 3), spread[: count - count // 3]])


def _cells_from(clean: np.ndarray, noise: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Cells clean / r x noise, rescaled so each cell's population retention is exactly its target."""
    cells = clean[None, :] / targets[:, None] * noise
    return cells * (clean.sum() / targets / cells.sum(axis=1))[:, None]


def synthetic(kind: str, count: int, seed: int, frames: int = FRAMES) -> Population:
    """One synthetic population (see the module docstring) of `frames` frames in scenes of SCENE."""
    rng = np.random.default_rng(seed)
    FRAMES = frames  # noqa: N806 - the population's size
    scenes = np.arange(FRAMES) // SCENE
    targets = _retentions(count)
    if kind == "iid heavy-tailed":
        clean = rng.lognormal(np.log(0.7), 0.9, FRAMES)
        noise = rng.lognormal(-0.045, 0.3, (count, FRAMES))
    elif kind == "scene AR 0.9":
        z = np.zeros((count + 1, FRAMES))
        eps = rng.normal(0, 1, (count + 1, FRAMES))
        for i in range(FRAMES):
            z[:, i] = eps[:, i] if i % SCENE == 0 else 0.9 * z[:, i - 1] + math.sqrt(1 - 0.81) * eps[:, i]
        clean = np.exp(np.log(0.7) + 0.6 * z[0])
        noise = np.exp(0.3 * z[1:] - 0.045)
    elif kind == "5% failure frames":
        clean = rng.lognormal(np.log(0.7), 0.4, FRAMES)
        noise = rng.lognormal(-0.02, 0.2, (count, FRAMES))
        fail = rng.random((count, FRAMES)) < 0.05
        noise = np.where(fail, noise * 6.0, noise)
    else:
        raise ValueError(f"unknown population {kind!r}")
    return Population(kind, clean, _cells_from(clean, noise, targets), scenes)


def from_cells(folder: Path) -> Population:
    """The real per-frame L2 of a run's ``cells/`` folder: clean and every ladder cell with every frame."""
    from pytest_drivedegrade.cells import is_camera_ladder
    from pytest_drivedegrade.payload import CellPayload

    records = {}
    for path in sorted(folder.glob("*.json")):
        rec = CellPayload.from_builtins(json.loads(path.read_text())).record
        records[rec.cell] = rec
    if "clean" not in records:
        raise SystemExit(f"{folder}: no clean cell among the stored results")
    clean = records["clean"].l2_avg_per_frame()
    ok = np.isfinite(clean)
    names = tuple(c for c, r in sorted(records.items())
                  if is_camera_ladder(r.family) and np.isfinite(r.l2_avg_per_frame()[ok]).all())
    cells = [records[c].l2_avg_per_frame()[ok] for c in names]
    scenes = np.array([hash(t.split("-")[0]) for t in np.array(records["clean"].frames)[ok]])
    return Population(f"real ({folder.parent.name}, {len(cells)} cells)", clean[ok], np.array(cells), scenes,
                      union=UNION, names=names)


def covers(a: np.ndarray, b: np.ndarray, truth: float, population: int, a_side: float, method: str) -> bool:
    """Whether the cell's interval (first crossings over the units run) holds its population retention: no
    "below" at the truth and no "above" a hair (the interval's 1e-4 rounding) above it."""
    from pytest_drivedegrade.scoring.adaptive import settle_retention

    kw = {"population": population, "alpha": a_side, "method": method}
    if len(a) == population:  # every unit ran: the exact value
        return True
    return (settle_retention(a, b, truth, **kw).side != "below"  # type: ignore[arg-type]
            and settle_retention(a, b, truth + 1e-4, **kw).side != "above")  # type: ignore[arg-type]


def stop_units(a: np.ndarray, b: np.ndarray, population: int, a_side: float, method: str) -> int:
    """Where `stop_at` stops on the whole stream (first crossings: one call reads what the loop would)."""
    got = sq.stop_at(a, b, LEVELS, population=population, alpha=a_side, method=method)
    return population if got is None else got.units


def regressed(pop: Population, drop: float, rng: np.random.Generator) -> np.ndarray:
    """Each cell with its retention dropped by `drop`, the extra L2 on 5 % of the frames only."""
    n = len(pop.clean)
    hit = rng.choice(n, max(1, n // 20), replace=False)
    out = pop.cells.copy()
    extra = pop.clean.sum() / (pop.retention() - drop) - pop.cells.sum(axis=1)
    out[:, hit] += (extra / len(hit))[:, None]
    return out


@dataclass
class Tally:
    """Counts over the draw orders of one population at one alpha."""

    cell_miss: np.ndarray
    orders: int = 0
    fwe: int = 0
    used: float = 0.0
    gate_false_regression: int = 0
    gate_tests: int = 0
    gate_wrong_pass: dict[float, int] = field(default_factory=lambda: {0.03: 0, 0.05: 0})
    gate_power: dict[float, int] = field(default_factory=lambda: {0.03: 0, 0.05: 0})
    gate_used: float = 0.0


def replay(pop: Population, orders: int, alpha: float, method: str, seed: int, gate_cells: int) -> Tally:
    """Every draw order: the adaptive rule on every cell, the gate on the first `gate_cells` cells."""
    n, count = len(pop.clean), len(pop.cells)
    a_side = alpha / (2 * max(count, pop.union))
    truth = pop.retention()
    rng = np.random.default_rng(seed)
    worse = {d: regressed(pop, d, np.random.default_rng(seed + 1)) for d in (0.03, 0.05)}
    t = Tally(cell_miss=np.zeros(count))
    for _ in range(orders):
        order = [int(i) for i in rng.permutation(n)]
        a = pop.clean[order]
        wrong = False
        for c in range(count):
            b = pop.cells[c][order]
            k = stop_units(a, b, n, a_side, method)
            t.used += k / (n * count)
            if not covers(a[:k], b[:k], float(truth[c]), n, a_side, method):
                t.cell_miss[c] += 1
                wrong = True
        t.fwe += int(wrong)
        t.orders += 1
        for c in range(min(gate_cells, count)):
            base = GateBaseline(pop.clean, pop.cells[c])
            same = gate_cell(pop.clean, pop.cells[c], base, order, tolerance=TOLERANCE, alpha=2 * a_side,
                             method=method)
            t.gate_false_regression += int(same.side == "below")
            t.gate_used += same.units / (n * min(gate_cells, count))
            t.gate_tests += 1
            for d, cells in worse.items():
                got = gate_cell(pop.clean, cells[c], base, order, tolerance=TOLERANCE, alpha=2 * a_side,
                                method=method)
                t.gate_wrong_pass[d] += int(got.side == "above")
                t.gate_power[d] += int(got.side == "below")
    return t


def report(pop: Population, t: Tally, alpha: float) -> list[str]:
    lo, hi = wilson(t.fwe, t.orders)
    worst = np.argsort(-t.cell_miss)[:3]
    ok = t.fwe / t.orders <= alpha and hi <= 1.5 * alpha
    lines = [f"{pop.name:<34} alpha {alpha:<4g} FWE {t.fwe / t.orders:.4f} [{lo:.4f}, {hi:.4f}] "
             f"{'OK' if ok else 'ABOVE TARGET'} (point <= {alpha:g}, upper <= {1.5 * alpha:.3g}); "
             f"cost {t.used / t.orders:.3f} of the units",
             "    per-cell miscoverage, worst: " + ", ".join(
                 f"{pop.label(i)} (r {pop.retention()[i]:.3f}) {t.cell_miss[i] / t.orders:.4f}" for i in worst)
             + f"; claimed per cell {alpha / max(len(pop.cells), pop.union):.2g}"]
    g = max(1, t.gate_tests)
    lines.append(f"    gate ({t.gate_tests} tests): false 'regression' {t.gate_false_regression / g:.4f}; "
                 + "; ".join(f"drop {d:g} on 5 % of frames: false 'no regression' {t.gate_wrong_pass[d] / g:.4f}, "
                             f"power {t.gate_power[d] / g:.3f}" for d in (0.03, 0.05))
                 + f"; cost (unchanged) {t.gate_used / max(1, t.orders):.3f}")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--orders", type=int, default=1000)
    parser.add_argument("--cells-count", type=int, default=87, help="synthetic stopping cells (the union bound's C)")
    parser.add_argument("--gate-cells", type=int, default=6, help="cells the gate is replayed on per order")
    parser.add_argument("--alpha", default="0.05,0.10")
    parser.add_argument("--method", default=sq.METHOD, choices=("betting", "asymptotic", "asymptotic-wor"))
    parser.add_argument("--cells", type=Path, action="append", default=[], help="a run's cells/ folder (real L2)")
    parser.add_argument("--populations", default="iid heavy-tailed,scene AR 0.9,5% failure frames")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frames", type=int, default=FRAMES, help="synthetic frames (6019: nuScenes val's size)")
    parser.add_argument("--quick", action="store_true", help="40 orders, 24 cells, 2 gate cells")
    args = parser.parse_args(argv)
    if args.quick:
        args.orders, args.cells_count, args.gate_cells = 40, 24, 2
    pops = [synthetic(k, args.cells_count, args.seed + i, args.frames)
            for i, k in enumerate(p for p in args.populations.split(",") if p)]
    pops += [from_cells(folder) for folder in args.cells]
    print(f"calibration: {args.orders} draw orders, method {args.method}, bound {DEFAULT_BOUND:g} m, levels "
          f"{LEVELS}, single-frame units")
    for alpha in (float(a) for a in args.alpha.split(",")):
        for i, pop in enumerate(pops):
            for line in report(pop, replay(pop, args.orders, alpha, args.method, args.seed + 100 * i,
                                           args.gate_cells), alpha):
                print(line, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
