"""The one end of a run: analyse a `FinishedRun`, put the floor and the settings into the analysis, draw the
montage, count the cost, write cells.csv, certificate.json and report.html, and say what happened.

The pytest controller and `drivedegrade merge` both end here, so a merged run's outputs are the unsharded run's.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..certificate.finished import FinishedRun
from ..constants import HORIZON_STEPS, STEP_SECONDS
from ..errors import DriveDegradeError
from ..scoring.records import RunAnalysis, cost_ledger

if TYPE_CHECKING:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey


@dataclass(frozen=True)
class Published:
    """What `publish` wrote and says: the sealed certificate (for the baseline gate), the analysis (for the
    JUnit suite properties) and the terminal summary's lines."""

    certificate: dict[str, Any]
    analysis: RunAnalysis | None  #: None for a run of closed-loop cells only
    lines: list[str]


def analyse(run: FinishedRun) -> RunAnalysis:
    """Every figure of the run, with the ego-only floor's and the run settings the analysis records."""
    from ..scoring.analyse import analyse_run

    settings = run.settings
    analysis = analyse_run(run.records.values(), flat=settings.flat, seed=run.provenance.seed,
                           floor_l2=run.floor.l2, seeds=settings.seeds, metric=settings.metric,
                           floor_ego_removal=run.floor.extra.get("ego_removal"), floor_frames=run.floor.per_frame,
                           scenes=run.scenes)
    analysis.settings.update(batch=settings.batch, reuse=settings.reuse, device=settings.device)
    analysis.settings["ego_box"] = settings.ego_box  # the box the PDMS and EPDMS scored with (issue 39)
    analysis.settings["planner_isolated"] = settings.isolate  # --drivedegrade-isolate (issue 37)
    if settings.two_stage:  # only then: a one-stage certificate keeps its form (absent reads as false)
        analysis.settings["two_stage"] = True
    # the horizon the PDMS and EPDMS scored: 3 s (six poses), or 4 s for a planner declaring NAVSIM's eight; L2
    # is always the first six poses' (nuScenes' 3 s convention)
    poses = max((r.plans.shape[1] for r in run.records.values()), default=HORIZON_STEPS)
    analysis.settings["pdms_horizon_s"] = poses * STEP_SECONDS
    return analysis


def cost_of(run: FinishedRun) -> dict[str, Any]:
    """The cost ledger, with the stored cells the run took instead of computing them (resume) where it knows:
    said in the certificate, not only in the terminal."""
    cost = cost_ledger(run.records.values())
    if run.resumed_cells is not None:
        cost["resumed_cells"] = sorted(run.resumed_cells)
    return cost


def montage_of(image: np.ndarray, token: str, seed: int) -> np.ndarray:
    """One front-camera image under every family at S4 (the report's figure)."""
    from ..corruptions.preview import montage

    return montage(image, severity=4, seed=seed, frame=token, camera="CAM_FRONT", width=220)


def front_montage(run: FinishedRun) -> np.ndarray | None:
    """The report's figure from the run's front image; None without one (the cells already reported why)."""
    if run.front is None:
        return None
    token, image = run.front
    try:
        return montage_of(image, token, run.provenance.seed)
    except DriveDegradeError:
        return None


def cost_line(cost: Mapping[str, Any]) -> str:
    """The cost ledger in one line of the terminal summary."""
    sec = cost["seconds"]
    fps = cost.get("planner_frames_per_second")
    staged = f" and {cost['stage_two_calls']} stage-two calls" if cost.get("stage_two_calls") else ""
    return (f"cost: {cost['predictions']} predictions{staged}, {cost['reused']} frames reused the clean plan; "
            f"seconds in cells: planner "
            f"{sec['planner']:.1f}" + (f" ({fps:.1f} frames/s)" if fps else "") + f", decode {sec['decode']:.1f}, "
            f"inject {sec['inject']:.1f}, scoring {sec['metrics'] + sec['pdms']:.1f}, input check {sec['check']:.1f}"
            + _busy(cost))


def _busy(cost: Mapping[str, Any]) -> str:
    """The cells' wall time and the planner's share of it, where the ledger has them."""
    wall, busy = cost.get("wall"), cost.get("planner_busy")
    if not wall or busy is None:
        return ""
    return f"; wall in cells {float(wall):.1f} (planner busy {100 * float(busy):.0f} %)"


def publish(run: FinishedRun, report_dir: Path, *, signing_key: Ed25519PrivateKey | None = None) -> Published:
    """Write `run`'s outputs into `report_dir/<planner>/` (the certificate signed with `signing_key` when given)
    and return them with the terminal summary's lines. A run with missing cells or shards says so in the
    certificate (``completeness``), so it is not mistaken for a complete baseline."""
    from .outputs import write_outputs
    from .terminal import summary_lines

    if not run.records and run.closed is not None:  # --drivedegrade-loop closed: the closed cells alone
        return publish_closed(run, report_dir, signing_key)
    analysis = analyse(run)
    cost = cost_of(run)
    completeness = {"complete": False, "missing_shards": list(run.missing_shards)} if run.missing_shards else {}
    cert, written = write_outputs(report_dir, run.provenance, run.records, analysis, run.missing_cells,
                                  gt=run.gt, montage=front_montage(run), completeness=completeness, cost=cost,
                                  signing_key=signing_key, closed=run.closed, adaptive=run.adaptive,
                                  digests=run.digests)
    lines = [*summary_lines(analysis, run.missing_cells, run.missing_advice), *run.notes]
    if run.closed is not None:
        from .closed_outputs import closed_lines

        lines += closed_lines(run.closed.analysis(analysis.verdict.label, run.settings.flat), run.closed)
    if run.missing_shards:
        lines.append(f"INCOMPLETE: shard(s) {', '.join(map(str, run.missing_shards))} missing; the certificate "
                     "says completeness: false")
    return Published(cert, analysis, [*lines, cost_line(cost), written])


def publish_closed(run: FinishedRun, report_dir: Path, signing_key: Ed25519PrivateKey | None) -> Published:
    """A run of closed-loop cells only: its certificate, closed_loop.csv and report (`closed_outputs`)."""
    from .closed_outputs import publish_closed_only

    assert run.closed is not None
    cert, lines = publish_closed_only(report_dir, run.provenance, run.closed, run.settings.flat,
                                      signing_key=signing_key, isolated=run.settings.isolate)
    return Published(cert, None, [*lines, *run.notes])
