"""The ladder driver for foreign evaluators: the cells a certification needs, each with the family, severity and
seed a model's own evaluation must run under (`patch_loader(..., family, severity, seed=seed)`), and the table
row it fills. ``drivedegrade ladder`` prints them; `ladder_cells` yields them to a Python script.

Sets: ``full`` is every camera family at S1..S5 (the plugin's default run, without its diagnostic null and blind
cells, which need the suite's own loader); ``axes`` is what the verdict needs and no more: every core and
contamination family at S5 (the axes, dropout and occlusion beside them); ``slice`` is the paper's closed-loop
slice (clean, gaussian and motion blur at S3 and S5, blackout S3 and S5). Clean is first and runs with no
injection. A random family runs under `seeds` seeds (seed .. seed + seeds - 1), as ``--drivedegrade-seeds``
does; a deterministic one once. Adaptive certification is not offered: it decides the next cell from the last
one's per-frame results, which a shell loop over a printed list cannot do.
"""

from __future__ import annotations

import csv
import io
import json
import shlex
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass

from ..cells import cell_id, run_order
from ..closedloop.cells import SLICE
from ..corruptions.ladder import FAMILIES
from ..errors import DataError

SETS: tuple[str, ...] = ("full", "axes", "slice")
FORMATS: tuple[str, ...] = ("text", "csv", "json", "shell")


@dataclass(frozen=True)
class LadderCell:
    """One evaluation to run: its cell id, family, severity (0: clean, no injection) and corruption seed."""

    cell: str
    family: str
    severity: int
    seed: int

    @property
    def inject(self) -> bool:
        """Whether the evaluation runs under `patch_loader` (every cell but clean)."""
        return self.family != "clean"


def _pairs(which: str, families: Sequence[str] | None, severities: Sequence[int] | None) -> list[tuple[str, int]]:
    """(family, severity) of the set, clean first; `families` / `severities` narrow it."""
    if which not in SETS:
        raise DataError(f"--set {which}: one of {', '.join(SETS)}")
    unknown = [f for f in families or () if f not in FAMILIES]
    if unknown:
        raise DataError(f"unknown family {unknown[0]!r}: one of {', '.join(FAMILIES)}")
    bad = [s for s in severities or () if not 1 <= int(s) <= 5]
    if bad:
        raise DataError(f"severity {bad[0]}: the ladder's severities are 1..5")
    if which == "full":
        pairs = [p for p in run_order(list(FAMILIES), range(1, 6), ego=False) if p[0] in ("clean", *FAMILIES)]
    elif which == "axes":
        pairs = [("clean", 0), *((f, 5) for f in FAMILIES)]
    else:
        pairs = list(SLICE)
    keep = set(families) if families else set(FAMILIES)
    sev = {int(s) for s in severities} if severities else set(range(1, 6))
    return [(f, s) for f, s in pairs if f == "clean" or (f in keep and s in sev)]


def ladder_cells(which: str = "full", *, families: Sequence[str] | None = None,
                 severities: Sequence[int] | None = None, seed: int = 0, seeds: int = 1) -> Iterator[LadderCell]:
    """Every evaluation the set needs, in run order (clean first); see the module docstring."""
    if seeds < 1:
        raise DataError(f"--seeds {seeds}: at least 1")
    for fam, sev in _pairs(which, families, severities):
        runs = range(seeds) if fam in FAMILIES and FAMILIES[fam].random else range(1)
        for k in runs:
            yield LadderCell(cell_id(fam, sev), fam, sev, int(seed) + k)


def render(cells: Sequence[LadderCell], fmt: str) -> str:
    """The cells as text (aligned columns), csv (``cell,family,severity,seed``: the table's key columns), json (a
    list of objects) or shell (one line per cell: ``CELL FAMILY SEVERITY SEED``, for ``while read``)."""
    if fmt == "json":
        return json.dumps([asdict(c) for c in cells], indent=1) + "\n"
    if fmt == "csv":
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(["cell", "family", "severity", "seed"])
        writer.writerows([c.cell, c.family, c.severity, c.seed] for c in cells)
        return buf.getvalue()
    if fmt == "shell":
        return "".join(" ".join(shlex.quote(str(v)) for v in (c.cell, c.family, c.severity, c.seed)) + "\n"
                       for c in cells)
    if fmt != "text":
        raise DataError(f"--format {fmt}: one of {', '.join(FORMATS)}")
    width = max([len(c.cell) for c in cells] + [4])
    lines = [f"{'cell':<{width}}  {'family':<14} severity  seed"]
    lines += [f"{c.cell:<{width}}  {c.family:<14} {c.severity:>8}  {c.seed:>4}" for c in cells]
    return "\n".join(lines) + f"\n{len(cells)} evaluation(s); clean runs with no injection\n"
