"""The certificate's ``closed_loop`` section (SPEC section 13): a run's closed cells (`ClosedRun`), their figures
with the closed settings, how the loop was simulated and each stored cell's content digest; the certificate of a
run that drove closed cells only; and what `drivedegrade verify` recomputes (`check_closed_loop`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime, timezone

from ..closedloop.analysis import CLEAN, NULL, parting_step
from ..closedloop.cells import ClosedPayload, ClosedRecord, Json
from ..closedloop.leaderboard import (
    BLOCKED_S,
    BLOCKED_SPEED,
    DEVIATION_M,
    DEVIATION_SHARE,
    MIN_SPEED_CHECKPOINTS,
    PENALTIES,
    PERCENT_PENALTIES,
)
from ..scoring.closed_loop import ClosedAnalysis, analyse_rows, check_section
from ..scoring.verdict import VERDICT_LABELS
from ..settings import RunSettings
from .seal import SCHEMA, Provenance

#: How the loop is simulated, as the section says it.
SIMULATOR: dict[str, Json] = {
    "world": "the embedded world, rendered at the simulated pose (only the cameras the planner reads)",
    "tracker": "NAVSIM LQR tracker and kinematic bicycle model at 10 Hz",
    "agents": "non-reactive: the other agents replay their logs",
    "score": "the CARLA leaderboard's Driving Score (spec/leaderboard.md): 100 x route completion x the product of "
             "every infraction's factor; the collisions counted are closed_collisions' (all: every collision, as "
             "the leaderboard; at_fault: NAVSIM's at-fault rule)",
    "penalties": {k: v for k, v in PENALTIES.items()},
    "percentage_penalties": {k: [c, d] for k, (c, d) in PERCENT_PENALTIES.items()},
    "outside_route_lanes": "the share of the driven route covered with the ego's centre outside the driving and "
                           "parking lanes (by more than 0.5 m) or in an oncoming lane of the route's road",
    "min_speed": f"{MIN_SPEED_CHECKPOINTS} route checkpoints, the ego's mean speed against the logged expert's over "
                 "the same ticks (the world has no background flow around the ego)",
    "route_deviation": f"the run ends {DEVIATION_M:g} m from the route, or once over {DEVIATION_SHARE:.0%} of the "
                       f"route was driven more than {DEVIATION_M / 2:g} m from it",
    "blocked": f"the run ends after the ego stood (slower than {BLOCKED_SPEED:g} m/s) with the road ahead free for "
               f"half the scene's duration (the leaderboard's {BLOCKED_S:g} s, scaled: a scene lasts 20 s)"}


@dataclass(frozen=True)
class ClosedRun:
    """A run's closed cells, in selection order, the ones missing, and the settings they ran under."""

    payloads: Mapping[str, ClosedPayload]
    settings: RunSettings
    missing: tuple[str, ...] = ()

    @property
    def records(self) -> dict[str, ClosedRecord]:
        return {c: p.record for c, p in self.payloads.items()}

    @property
    def reads_rear(self) -> bool:
        """The planner reads a rear camera: the null cell carries a clean rerun, the null of such a planner."""
        null = self.payloads.get(NULL)
        return null is not None and bool(null.record.null_runs)

    def first_step(self) -> int | None:
        """The planner step where blackout S3's first differing run parts from clean's (identical mode)."""
        clean, null = self.records.get(CLEAN), self.records.get(NULL)
        if clean is None or null is None or self.reads_rear:
            return None
        from ..closedloop.analysis import RunRow, first_difference

        rows = [RunRow.of(r) for r in null.runs]
        first = first_difference([RunRow.of(r) for r in clean.runs], rows)
        if first is None or first not in rows:
            return None if first is None else 0
        at = rows.index(first)
        return parting_step(clean.runs[at], null.runs[at], 10 // self.settings.closed_hz) \
            if at < len(clean.runs) else 0

    def analysis(self, open_label: str | None, flat: float) -> ClosedAnalysis:
        from ..closedloop.analysis import RunRow

        null = self.records.get(NULL)
        return analyse_rows({c: [RunRow.of(r) for r in rec.runs] for c, rec in self.records.items()},
                            reads_rear=self.reads_rear,
                            null_rows=[RunRow.of(r) for r in null.null_runs] if null is not None else [],
                            flat=flat, open_label=open_label, first_step=self.first_step())

    def section(self, open_label: str | None, flat: float) -> dict[str, Json]:
        """The ``closed_loop`` section: settings, simulator, figures, each cell's record digest, missing cells."""
        digests: dict[str, Json] = {c: rec.digest() for c, rec in self.records.items()}
        missing: list[Json] = list(self.missing)
        return {**self.settings.closed_loop_settings(), "simulator": SIMULATOR,
                **self.analysis(open_label, flat).figures(), "record_digests": digests, "missing_cells": missing}


def closed_only_certificate(prov: Provenance, run: ClosedRun, flat: float, created: str | None = None,
                            isolated: bool = False) -> dict[str, object]:
    """The unsealed certificate of a run that drove closed cells only (``--drivedegrade-loop closed``): no open
    cell, so its open-loop axes are empty and its open-loop verdict undetermined; the ``closed_loop`` section
    says what the closed cells do."""
    return {
        "schema": SCHEMA, "spec_version": prov.spec_version,
        "planner": {"name": prov.planner_name, "fingerprint": prov.planner_fingerprint,
                    **({"file": prov.planner_file} if prov.planner_file else {})},
        "dataset": {"fingerprint": prov.dataset_fingerprint, "split": prov.split, "frames": 0,
                    "frames_unscored": prov.frames_unscored, "frames_requested": prov.frames_requested,
                    "source": prov.data_source},
        "cells": [], "thresholds": {}, "axes": {"quality": None, "removal": None, "gap": None, "mean": None},
        "floor": {}, "null_control": {}, "settings": {"seed": prov.seed, "flat": flat, "planner_isolated": isolated},
        "verdict": {"label": "undetermined", "flat": flat,
                    "reason": "closed loop only (--drivedegrade-loop closed): no open-loop cell ran"},
        "tool": {"name": "pytest-drivedegrade", "version": prov.tool_version, "command": prov.command,
                 "versions": dict(prov.versions)},
        "created": created or datetime.now(timezone.utc).replace(microsecond=0).isoformat(),
        "closed_loop": run.section(None, flat),
        "completeness": {"complete": not run.missing, "missing_cells": list(run.missing)},
    }


def check_closed_loop(cert: Mapping[str, object]) -> list[str]:
    """The ``closed_loop`` section recomputed from its own run rows (and the open-loop label of a certificate
    that has open cells); empty when it adds up or there is no such section."""
    section = cert.get("closed_loop")
    if not isinstance(section, Mapping) or "cells" not in section:
        return []
    verdict = cert.get("verdict")
    label = verdict.get("label") if isinstance(verdict, Mapping) and cert.get("cells") else None
    return check_flat(cert, section) + check_section(section, label if label in (*VERDICT_LABELS, "undetermined")
                                                     else None)


def check_flat(cert: Mapping[str, object], section: Mapping[str, object]) -> list[str]:
    """The closed section's flat line is the run's (``settings.flat``, the line the open verdict is drawn at):
    a certificate resealed with another closed flat line would otherwise carry another closed label that its
    own rows recompute (issue 37)."""
    settings, closed_verdict = cert.get("settings"), section.get("verdict")
    flat = settings.get("flat") if isinstance(settings, Mapping) else None
    mine = closed_verdict.get("flat") if isinstance(closed_verdict, Mapping) else None
    if flat is None:
        return []
    if not isinstance(mine, (int, float)) or isinstance(mine, bool) or not isinstance(flat, (int, float)) \
            or float(mine) != float(flat):
        return [f"closed_loop.verdict.flat: certificate says {mine!r}, but the run's settings.flat is {flat!r}; "
                "the closed label is drawn at the run's flat line"]
    return []
