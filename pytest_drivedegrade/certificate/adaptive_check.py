"""`drivedegrade verify` on an adaptive certificate: every stopping decision recomputed from the stored per-frame
results (``cells/<cell>.json`` beside the certificate), with the rule the run stopped on
(`scoring.sequential`), and the certificate's ``adaptive`` section compared with what its cells give.

It fails a cell that stopped before its own figures settled it (running on, for the sequential gate, only
tightens an anytime-valid interval), a family whose visited
severities are not the ones the schedule visits, a unit plan that is not the seeded draw order or whose seed is not
the one the planner's fingerprint and the baseline's digest give (`sequential.draw_seed`), and any field of
the section (intervals, decisions, stop reasons, the guarantee) that differs from the recomputation.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from ..cells import CellRecord, is_camera_ladder
from ..constants import DEFAULT_FLAT
from ..errors import InvalidInput
from ..payload import CellPayload, record_digest
from ..scoring import sequential
from ..scoring.verdict import FamilyGroups
from .seal import canonicalize


def load_records(folder: Path, cells: list[str],
                 digests: Mapping[str, object]) -> tuple[dict[str, CellRecord], list[str]]:
    """The stored records of `cells` in `folder` (``cells/<cell>.json``, each hashing to its own digest and to
    the certificate's ``record_digests``) and what is wrong."""
    records: dict[str, CellRecord] = {}
    problems = []
    for cell in cells:
        path = folder / f"{cell}.json"
        try:
            records[cell] = CellPayload.from_builtins(json.loads(path.read_text())).record
        except (OSError, ValueError, InvalidInput) as exc:
            problems.append(f"adaptive: cell {cell}: its stored results {path} cannot be read ({exc})")
            continue
        if cell in digests and digests[cell] != record_digest(records[cell].to_builtins()):
            problems.append(f"adaptive: cell {cell}: {path} is not the record the certificate sealed "
                            "(record_digests differs)")
    return records, problems


def missing_results(cert: Mapping[str, object], folder: Path) -> list[Path]:
    """An adaptive certificate's per-frame results that are not there (issue 37, low: verify said the
    arithmetic failed, exit 1, for a certificate copied without its `cells/`): the folder when it is absent,
    else each `cells/<cell>.json` of the certificate's cells that is. Empty for a full run's certificate."""
    if not isinstance(cert.get("adaptive"), Mapping):
        return []
    if not folder.is_dir():
        return [folder]
    rows = cert.get("cells")
    cells = [r.get("cell") for r in rows if isinstance(r, Mapping)] if isinstance(rows, list) else []
    return [folder / f"{c}.json" for c in cells if isinstance(c, str) and not (folder / f"{c}.json").is_file()]


def _differences(recorded: object, recomputed: object, where: str, out: list[str]) -> None:
    """Every leaf where the two (canonical) trees differ, as ``where: certificate says X, its cells give Y``."""
    if isinstance(recorded, Mapping) and isinstance(recomputed, Mapping):
        for key in sorted({*recorded, *recomputed}, key=str):
            _differences(recorded.get(key), recomputed.get(key), f"{where}.{key}", out)
    elif recorded != recomputed:
        out.append(f"{where}: certificate says {json.dumps(recorded)[:120]}, its cells give "
                   f"{json.dumps(recomputed)[:120]}")


def stop_problems(records: Mapping[str, CellRecord], plan: sequential.UnitPlan, *, alpha: float,
                      flat: float, groups: FamilyGroups) -> list[str]:
    """Families whose visited severities are not the schedule's (`sequential.family_plan` replayed on the
    recomputed outcomes) and cells that did not stop where their figures settle them."""
    axis = (*groups.quality, groups.removal)
    outcomes = sequential.ladder_outcomes(records, plan, alpha=alpha, flat=flat, axis_families=axis)
    problems = [f"adaptive: cell {c}: stopped after {o.units} of {plan.population} units with a decision open"
                 for c, o in outcomes.items() if o.reason == "open"]
    for c, r in records.items():  # no figure outside the units it ran
        ran = {i for u in plan.units[:int(r.units or 0)] for i in u.scored}
        outside = [i for i in range(len(r.frames)) if i not in ran and np.isfinite(r.l2[i]).any()]
        if outside:
            problems.append(f"adaptive: cell {c}: has figures on {len(outside)} frame(s) outside the "
                            f"{r.units} unit(s) it ran")
    fams: dict[str, dict[int, sequential.Outcome]] = {}
    for c, r in records.items():
        if is_camera_ladder(r.family):
            fams.setdefault(r.family, {})[r.severity] = outcomes[c]
    for fam, cells in sorted(fams.items()):
        if sorted(cells) != [1, 2, 3, 4, 5]:
            continue  # a run of some severities visits every one of them
        seen: dict[int, sequential.Outcome] = {}
        while (nxt := sequential.family_plan(seen)[0]) is not None and nxt not in seen:
            seen[nxt] = cells[nxt]
        visited = {s for s, o in cells.items() if o.reason != "skipped"}
        if visited != set(seen):
            problems.append(f"adaptive: family {fam}: visited S{sorted(visited)}, but its cells' decisions "
                            f"schedule S{sorted(seen)}")
    return problems


def _number(value: object, default: float) -> float:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else default


def check_adaptive(cert: Mapping[str, object], folder: Path | None, groups: FamilyGroups | None = None) -> list[str]:
    """What is wrong with an adaptive certificate's stopping decisions (empty: they recompute, or the run was
    not adaptive); `folder` holds the run's ``cells/`` (None: not found, which is itself reported); `groups`
    defaults to the ladder's family groups."""
    section = cert.get("adaptive")
    if not isinstance(section, Mapping):
        return []
    if folder is None or not folder.is_dir():
        return ["adaptive: no cells/ folder beside the certificate, so the stopping decisions cannot be "
                "recomputed; verify the certificate in its report folder"]
    if section.get("method") != sequential.METHOD:  # a former stopping rule: its stops are not this version's
        return [f"adaptive: its cells stopped on the {section.get('method')!r} confidence sequence; this version "
                f"stops on {sequential.METHOD!r} and recomputes only those stops: verify it with the release that "
                "made it (its `tool` section), or certify again"]
    try:
        plan = sequential.UnitPlan.from_builtins(section.get("plan") or {})
    except (TypeError, ValueError) as exc:
        return [f"adaptive: plan: {exc}"]
    planner, gate = cert.get("planner"), section.get("gate")
    baseline = gate.get("baseline_digest") if isinstance(gate, Mapping) else None
    seed_why = plan.seed_problem(planner.get("fingerprint") if isinstance(planner, Mapping) else None, baseline)
    problems = [f"adaptive: plan: {p}" for p in [plan.draw_order_problem(), seed_why] if p]
    rows = cert.get("cells")
    cells = [(str(c.get("cell")), str(c.get("family")), int(c.get("severity") or 0))
             for c in (rows if isinstance(rows, list) else []) if isinstance(c, Mapping)]
    digests = cert.get("record_digests")
    records, problems_read = load_records(folder, [c for c, _, _ in cells],
                                          digests if isinstance(digests, Mapping) else {})
    if problems_read or "clean" not in records:
        return problems + (problems_read or ["adaptive: no clean cell among the stored results"])
    alpha = _number(section.get("alpha"), 0.05)
    settings = cert.get("settings")
    flat = _number(settings.get("flat") if isinstance(settings, Mapping) else None, DEFAULT_FLAT)
    groups = groups or FamilyGroups.from_registry()
    rule = "gate" if section.get("rule") == "gate" else "certify"
    recomputed = sequential.adaptive_section(records, plan, [(f, s) for _, f, s in cells], alpha=alpha, flat=flat,
                                             quality=groups.quality, removal=groups.removal, rule=rule)
    mine = {k: v for k, v in section.items() if k != "gate"}  # a gate run's test parts: checked by gate_problems
    _differences(canonicalize(mine), canonicalize(recomputed), "adaptive", problems)
    a_side = sequential.alpha_side(alpha, [(f, s) for _, f, s in cells])
    if rule == "gate":  # cells stopped on the baseline's test (its parts are in the section): their decisions show
        return problems + gate_problems(section.get("gate"), records, plan, alpha=2 * a_side, flat=flat,
                                        groups=groups)
    return problems + stop_problems(records, plan, alpha=a_side, flat=flat, groups=groups)


def gate_problems(gate: object, records: Mapping[str, CellRecord], plan: sequential.UnitPlan, *, alpha: float,
                  flat: float, groups: FamilyGroups) -> list[str]:
    """A gate run's stops recomputed: each cell the gate's test stopped (``adaptive.gate.cells``: the test's level,
    the baseline's population mean and its control variates on the units the cell ran) settles where the
    certificate says and the cell ran exactly to there (to the last unit when it never settled), at the level the
    run's cell count gives (`alpha`); a cell without them stopped on its own decisions, which must be settled."""
    from ..scoring.seqgate import gate_settlement, unpack

    parts = gate.get("cells") if isinstance(gate, Mapping) else None
    if not isinstance(parts, Mapping):
        return ["adaptive: a gate run without adaptive.gate.cells (its test's parts per cell), so its stops cannot be "
                "recomputed"]
    problems = []
    clean = records["clean"].l2_avg_per_frame()
    axis = (*groups.quality, groups.removal)
    for cell, record in sorted(records.items()):
        units, part = int(record.units or 0), parts.get(cell)
        if record.family in sequential.FULL_CELLS or units == 0:
            continue
        if not isinstance(part, Mapping):  # no baseline for it: it stopped on its own decisions
            levels = sequential.levels_of(record.family, record.severity, axis, flat)
            if sequential.cell_outcome(plan, clean, record, levels, alpha=alpha / 2).reason == "open":
                problems.append(f"adaptive: cell {cell}: stopped after {units} of {plan.population} units with a "
                                "decision open and no gate test recorded")
            continue
        try:
            level, mean = float.fromhex(str(part["level"])), float.fromhex(str(part["mean"]))
            diffs = unpack(str(part["differences"]))
            lo, hi = (float.fromhex(str(v)) for v in part["range"])
        except (KeyError, ValueError, TypeError) as exc:
            problems.append(f"adaptive: cell {cell}: its gate test's parts are unreadable ({exc})")
            continue
        if len(diffs) != units:
            problems.append(f"adaptive: cell {cell}: the gate test has the baseline on {len(diffs)} unit(s), the "
                            f"cell ran {units}")
            continue
        a, b = sequential.unit_sums(plan, clean, record.l2_avg_per_frame(), units)
        got = gate_settlement(a, b, level, mean, diffs, plan.population, alpha, (lo, hi))
        said = (part.get("side"), part.get("units"), part.get("how"))
        if said != (got.side, got.units, got.how):
            problems.append(f"adaptive: cell {cell}: the gate's test says {said}, its cells give "
                            f"{(got.side, got.units, got.how)}")
        if units != (got.units if got.side != "open" else plan.population):
            problems.append(f"adaptive: cell {cell}: ran {units} unit(s), but the gate's test settles it "
                            + (f"after {got.units}" if got.side != "open" else "at none (it must run every unit)"))
    return problems


def check_gate_baseline(cert: Mapping[str, object], folder: Path, baseline_path: Path) -> list[str]:
    """`verify --baseline FILE`: a gate run's recorded test parts (``adaptive.gate``) recomputed from the baseline
    itself (its certificate, which must verify and be the one whose digest the gate recorded, and its cells/), so
    the control variates the stops were recomputed from are shown to be that baseline's."""
    from ..scoring.seqgate import gate_record
    from .seal import CertificateError, CertificateMismatch, verify

    section = cert.get("adaptive")
    gate = section.get("gate") if isinstance(section, Mapping) else None
    if not isinstance(section, Mapping) or not isinstance(gate, Mapping):
        return ["--baseline: the certificate is not an adaptive gate run (no adaptive.gate): there is nothing a "
                "baseline is needed for"]
    try:
        base_cert = verify(baseline_path)
    except (CertificateError, CertificateMismatch, OSError, ValueError) as exc:
        return [f"--baseline: {baseline_path}: {exc}"]
    if base_cert.get("digest") != gate.get("baseline_digest"):
        return [f"--baseline: {baseline_path} is not the baseline this run was gated against (digest "
                f"{base_cert.get('digest')}, the gate recorded {gate.get('baseline_digest')})"]
    rows = cert.get("cells")
    cells = [(str(c.get("cell")), str(c.get("family")), int(c.get("severity") or 0))
             for c in (rows if isinstance(rows, list) else []) if isinstance(c, Mapping)]
    digests, base_digests = cert.get("record_digests"), base_cert.get("record_digests")
    records, problems = load_records(folder, [c for c, _, _ in cells], digests if isinstance(digests, Mapping) else {})
    base, base_problems = load_records(baseline_path.parent / "cells", sorted(records),
                                       base_digests if isinstance(base_digests, Mapping) else {})
    if problems or "clean" not in records:
        return problems or ["adaptive: no clean cell among the stored results"]
    plan = sequential.UnitPlan.from_builtins(section.get("plan") or {})
    alpha = 2 * sequential.alpha_side(_number(section.get("alpha"), 0.05), [(f, s) for _, f, s in cells])
    recomputed = gate_record(records, base, plan, tolerance=_number(gate.get("tolerance"), 0.0), alpha=alpha)
    out: list[str] = []
    _differences(canonicalize(gate.get("cells")), canonicalize(recomputed), "adaptive.gate.cells", out)
    return [f"--baseline: {p}" for p in base_problems] + out
