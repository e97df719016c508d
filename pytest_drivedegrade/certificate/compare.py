"""`drivedegrade compare CERT... --out DIR` (SPEC section 10): several planners' certificates side by side.

One row per certificate: planner, clean L2, clean PDMS, the axes (L2 and PDMS, the ego axis), the thresholds,
the verdicts and the floor; ranks by clean L2 (lower is better) and by mean retention (higher is better), and a
rank reversal flagged where a planner is better than another on clean L2 but worse on mean retention (or the
other way round): a planner that plans better on clean images yet relies on them more. Every certificate is
verified first, digest and arithmetic (`consistency`): one verify rejects is refused, an incomplete one is
compared and marked (``status``); certificates of different spec versions, data sets or settings that change
the numbers (`check_comparable` names each) are refused unless ``force``. The CSV's text cells are neutralised
against spreadsheet formulas.

Written with pandas (imported here only): ``compare.csv`` and a self-contained ``compare.html``.
"""

from __future__ import annotations

import html
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..atomic import atomic_write_text, neutralise
from ..errors import DriveDegradeError
from ..scoring.records import AXES, EGO_AXES, Axes, FamilyThresholds
from .fields import IMPORTED_TEXT, is_imported
from .seal import verify

if TYPE_CHECKING:
    import pandas as pd

#: The axes a row shows: the camera axes and the ego axis on L2 retention; the camera axes on PDMS retention.
ROW_AXES = (*AXES, *EGO_AXES)
PDMS_AXES = AXES


class CompareError(DriveDegradeError):
    """Certificates that cannot be compared (another spec version or data set) or none at all."""


def _clean(cert: Mapping[str, Any], key: str) -> float | None:
    row: Mapping[str, Any] = next((c for c in cert.get("cells", []) if c.get("cell") == "clean"), {})
    value = row.get(key)
    return None if value is None else float(value)


def _section(cert: Mapping[str, Any], key: str) -> Mapping[str, Any]:
    got = cert.get(key)
    return got if isinstance(got, Mapping) else {}


def certificate_row(cert: Mapping[str, Any], source: str = "") -> dict[str, object]:
    """One certificate's comparison row, flat: axes as ``axis_<name>`` / ``pdms_axis_<name>``, thresholds as
    ``<family>_s10`` / ``<family>_s25``."""
    axes, pdms_axes = Axes.from_builtins(cert.get("axes")), Axes.from_builtins(cert.get("axes_pdms"))
    verdict, planner = _section(cert, "verdict"), _section(cert, "planner")
    row: dict[str, object] = {
        "planner": planner.get("name"),
        "planner_fingerprint": planner.get("fingerprint"),
        "clean_l2": _clean(cert, "l2_avg"),
        "clean_pdms": _clean(cert, "pdms"),
        **{f"axis_{k}": axes.value(k) for k in ROW_AXES},
        **{f"pdms_axis_{k}": pdms_axes.value(k) for k in PDMS_AXES},
        "verdict": verdict.get("label"),
        "ego_label": verdict.get("ego_label"),
        "certification": "adaptive" if cert.get("adaptive") else "full",
        "verdict_metric": verdict.get("metric", "l2"),
        "floor_l2": _section(cert, "floor").get("l2_avg"),
        "imported": is_imported(cert),
        "verdict_confidence": verdict.get("confidence"),
        "interval_basis": interval_basis(cert),
        # spec 5's plan movement: a certificate without it had its label read on accuracy alone
        "plan_movement": "recorded" if isinstance(cert.get("reliance"), Mapping) else "not recorded",
        # spec 5's command_swap figure: empty for a certificate without it (spec 4, or no command_swap cell)
        "command_following": _section(cert, "command").get("following"),
        "command_label": _section(cert, "command").get("label"),
    }
    for fam, entry in sorted(_section(cert, "thresholds").items()):
        row.update((f"{fam}_{key}", t.value) for key, t in FamilyThresholds.from_builtins(entry).levels.items())
    row.update(spec_version=cert.get("spec_version"), dataset_fingerprint=_section(cert, "dataset").get(
        "fingerprint"), certificate=source)
    return row


def interval_basis(cert: Mapping[str, object]) -> str:
    """What the certificate's intervals resample, in words (`scoring.intervals.Basis`); a certificate from before
    the basis was written (spec 4) resampled frames as if independent, and says its scheme only."""
    settings = cert.get("settings")
    iv = _section(settings, "intervals") if isinstance(settings, Mapping) else {}
    if not iv.get("computed", True):
        return "no intervals"
    return str(iv.get("basis") or f"frame bootstrap ({iv.get('scheme', 'paired frames')}; frames treated as "
                                  "independent)")


#: What else makes two certificates' retentions the same quantity, besides the settings table's SAME rows
#: (`RunSettings.baseline_differences`): (what, section, key); ``tool`` is read in ``tool.versions``.
COMPARABLE: tuple[tuple[str, str, str], ...] = (
    ("spec version", "", "spec_version"), ("data set", "dataset", "fingerprint"),
    ("scored frames", "dataset", "frames"), ("metric convention", "settings", "convention"),
    ("retention kind", "settings", "kind"), ("retention metric", "settings", "metric"),
    ("threshold levels", "settings", "threshold_levels"), ("OpenCV version", "versions", "opencv"),
    ("numpy version", "versions", "numpy"))


def _value(cert: Mapping[str, object], section: str, key: str) -> object:
    if not section:
        return cert.get(key)
    part = _section(_section(cert, "tool"), "versions") if section == "versions" else _section(cert, section)
    return part.get(key)


def _settings_differences(certs: Sequence[tuple[str, Mapping[str, Any]]]) -> list[str]:
    """The settings table's rows that make retentions another quantity (the gate's), each certificate against
    the first, as 'label (flag): X in A; Y in B'."""
    from ..settings import RunSettings

    read = []
    for path, cert in certs:
        try:
            read.append((path, RunSettings.from_certificate(cert)))
        except DriveDegradeError as exc:
            return [f"unreadable settings in {path} ({exc})"]
    out = []
    first_path, first = read[0]
    for path, other in read[1:]:
        out += [f"different {d.setting.label} ({d.setting.flag}): {d.theirs!r} in {first_path}; {d.mine!r} in "
                f"{path}" for d in other.baseline_differences(first)]
    return out


def check_comparable(certs: Sequence[tuple[str, Mapping[str, Any]]], force: bool = False) -> list[str]:
    """The differences between the certificates in what makes their retentions comparable (spec version, data
    set, scored frames, metric, seeds and the other settings the gate compares, the OpenCV and numpy versions
    that render the corruptions), as lines naming each value and file; raise `CompareError` unless `force` (then
    they are returned as warnings)."""
    problems = []
    for what, section, key in COMPARABLE:
        seen: dict[str, list[str]] = {}
        for path, cert in certs:
            seen.setdefault(repr(_value(cert, section, key)), []).append(path)
        if len(seen) > 1:
            problems.append(f"different {what}: " + "; ".join(f"{v} in {', '.join(p)}" for v, p in seen.items()))
    problems += _settings_differences(certs)
    if problems and not force:
        raise CompareError(" and ".join(problems) + "; retentions are comparable only under the same ladder, data "
                           "and settings (pass --force to compare anyway)")
    return problems


#: The note on a comparison of adaptive with full certificates (issue 37, low: they were mixed without one).
MIXED_NOTE = ("mixes adaptive and full certificates: an adaptive certificate's retentions are estimates from the "
              "units each cell needed (stopped once its decisions settled, with wider intervals), a full one's are "
              "over every frame; compare like with like for a ranking (column certification)")


def mixed_note(certs: Sequence[tuple[str, Mapping[str, object]]]) -> str | None:
    """`MIXED_NOTE` naming the adaptive certificates when the comparison mixes both kinds, else None."""
    adaptive = [path for path, cert in certs if cert.get("adaptive")]
    if not adaptive or len(adaptive) == len(certs):
        return None
    return f"{MIXED_NOTE}; adaptive: {', '.join(adaptive)}"


def check_sound(path: str, cert: Mapping[str, Any]) -> str:
    """A certificate's status for the comparison: ``complete``, or ``incomplete: <what is missing>`` (compared,
    and marked); `CompareError` when verify's arithmetic does not add up (a certificate verify rejects is never
    compared, not even with --force)."""
    from .consistency import check_consistency, incompleteness

    problems = check_consistency(cert)
    if problems:
        shown = "; ".join(problems[:3]) + (f"; and {len(problems) - 3} more" if len(problems) > 3 else "")
        raise CompareError(f"{path}: the digest verifies but the arithmetic does not add up ({shown}); `drivedegrade "
                           f"verify {path}` names every field: refused")
    missing = incompleteness(cert)
    return "complete" if missing is None else f"incomplete: {missing}"


def movement_notes(certs: Sequence[tuple[str, Mapping[str, object]]]) -> list[str]:
    """A note for each certificate that records no plan movement (``reliance``, spec 5) compared beside one that
    does: its label was read on accuracy alone, so its ``not-shown-to-use-cameras`` may be a planner whose plans
    move while accuracy holds (``camera-sensitive`` since spec 5). Empty when all or none record it."""
    has = {path: isinstance(cert.get("reliance"), Mapping) for path, cert in certs}
    if all(has.values()) or not any(has.values()):
        return []
    return [f"{path} (spec {cert.get('spec_version')}) records no plan movement: its label "
            f"{_section(cert, 'verdict').get('label')!r} is read on accuracy alone, and 'camera-sensitive' (plans "
            "move, accuracy holds) did not exist for it; compare labels with that in mind"
            for path, cert in certs if not has[path]]



def compare_frame(certs: Sequence[tuple[str, Mapping[str, Any]]]) -> pd.DataFrame:
    """The comparison table (a pandas DataFrame), one row per certificate, with the ranks and reversals."""
    import pandas as pd

    df = pd.DataFrame([certificate_row(c, path) for path, c in certs])
    df["rank_clean_l2"] = df["clean_l2"].rank(method="min", ascending=True).astype("Int64")
    df["rank_mean_retention"] = df["axis_mean"].astype(float).rank(method="min", ascending=False).astype("Int64")
    reversals = []
    for i in range(len(df)):
        others = []
        for j in range(len(df)):
            a, b = df.loc[i], df.loc[j]
            if i == j or pd.isna(a["rank_clean_l2"]) or pd.isna(b["rank_clean_l2"]) \
                    or pd.isna(a["rank_mean_retention"]) or pd.isna(b["rank_mean_retention"]):
                continue
            l2 = int(a["rank_clean_l2"]) - int(b["rank_clean_l2"])
            ret = int(a["rank_mean_retention"]) - int(b["rank_mean_retention"])
            if l2 * ret < 0:
                others.append(str(b["planner"]))
        reversals.append(", ".join(others))
    df["rank_reversal"] = [bool(r) for r in reversals]
    df["reversed_with"] = reversals
    head = ["planner", "clean_l2", "clean_pdms", "rank_clean_l2", "rank_mean_retention", "rank_reversal",
            "reversed_with"]
    return df[head + [c for c in df.columns if c not in head]]


#: The first table of compare.html, one screen wide: who, whether it is sound, the verdict and the figures it
#: rests on. Every column follows in the full table below it.
SUMMARY = ("planner", "status", "verdict", "ego_label", "verdict_metric", "verdict_confidence", "interval_basis",
           "clean_l2", "floor_l2", "axis_quality", "axis_removal", "axis_mean")


def floor_warnings(df: pd.DataFrame) -> list[str]:
    """A line per planner far worse than its ego-only floor on clean frames (`report.terminal.floor_warning`'s
    rule: above twice the floor's L2 and by more than 0.1 m); a miswired adapter is one cause among others."""
    from ..constants import WORSE_FACTOR, WORSE_MARGIN

    out = []
    for r in df.itertuples():
        clean, floor = r.clean_l2, r.floor_l2
        if isinstance(clean, (int, float)) and isinstance(floor, (int, float)) and floor > 0 and \
                clean > WORSE_FACTOR * floor and clean - floor > WORSE_MARGIN:
            out.append(f"{r.planner}: clean L2 {clean:.3f} m against the ego-only floor's {floor:.3f} m: a planner "
                       "that reads no camera plans far better (a miswired adapter, other data, too little training "
                       "or a perception-free design); read its retention with that in mind")
    return out


def _html(df: pd.DataFrame, warnings: Sequence[str], comparison_notes: Sequence[str] = ()) -> str:
    summary = df[[c for c in SUMMARY if c in df.columns]].to_html(
        index=False, escape=True, na_rep="—", float_format=lambda v: f"{v:.3f}", classes="cmp", border=0)
    table = df.to_html(index=False, escape=True, na_rep="—", float_format=lambda v: f"{v:.3f}",
                       classes="cmp", border=0)
    flagged = df[df["rank_reversal"]]
    notes = "".join(f"<li>{html.escape(str(r.planner))}: better on one ranking, worse on the other, against "
                    f"{html.escape(str(r.reversed_with))}</li>" for r in flagged.itertuples())
    warn = "".join(f"<p class='warn'>Compared with --force: {html.escape(w)}</p>" for w in warnings)
    warn += "".join(f"<p class='warn'>IMPORTED: {html.escape(str(r.certificate))}: {IMPORTED_TEXT}</p>"
                    for r in df.itertuples() if r.imported)
    warn += "".join(f"<p class='warn'>Note: {html.escape(n)}</p>" for n in comparison_notes)
    warn += "".join(f"<p class='warn'>INCOMPLETE, compared as it is: {html.escape(str(r.certificate))}: "
                    f"{html.escape(str(r.status))}</p>" for r in df.itertuples() if r.status != "complete")
    warn += "".join(f"<p class='warn'>FLOOR: {html.escape(w)}</p>" for w in floor_warnings(df))
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>DriveDegrade comparison</title>
<style>
body {{ font:14px/1.5 -apple-system, "Segoe UI", Roboto, Arial, sans-serif; color:#1f2933; margin:28px; }}
table.cmp {{ border-collapse:collapse; font-size:12.5px; font-variant-numeric:tabular-nums; }}
table.cmp th, table.cmp td {{ padding:4px 8px; border-bottom:1px solid #e4e7eb; text-align:right; }}
table.cmp th {{ background:#fafbfc; color:#616e7c; }}
.warn {{ background:#fef3c7; border:1px solid #f59e0b; padding:6px 10px; border-radius:6px; }}
</style></head><body>
<h1>DriveDegrade comparison: {len(df)} certificate(s)</h1>
<p>Ranks: by clean L2 (1 = lowest error) and by mean S5 retention over the core families (1 = least damage).
A rank reversal: a planner better than another on one ranking and worse on the other.</p>
{warn}
{"<h2>Rank reversals</h2><ul>" + notes + "</ul>" if notes else "<p>No rank reversals.</p>"}
<h2>Verdicts</h2>
<div style="overflow-x:auto">{summary}</div>
<h2>Every column</h2>
<div style="overflow-x:auto">{table}</div>
</body></html>
"""


def write_compare(paths: Sequence[str | os.PathLike[str]], out: str | os.PathLike[str], *,
                  force: bool = False) -> tuple[Path, Path, pd.DataFrame]:
    """Verify and compare the certificates; write ``compare.csv`` and ``compare.html`` into `out`. Returns
    (csv path, html path, the DataFrame)."""
    if not paths:
        raise CompareError("no certificate given")
    certs = [(os.fspath(p), verify(p)) for p in paths]
    status = [check_sound(path, cert) for path, cert in certs]
    warnings = check_comparable(certs, force)
    df = compare_frame(certs)
    df.insert(1, "status", status)
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    safe = df.copy()
    for col in safe.select_dtypes(exclude="number").columns:  # text cells only: numbers stay numbers
        safe[col] = safe[col].map(neutralise)
    csv_path = atomic_write_text(folder / "compare.csv", safe.to_csv(index=False, float_format="%.6g"))
    note = mixed_note(certs)
    df.attrs["note"] = note
    notes = ([f"this comparison {note}"] if note else []) + movement_notes(certs)
    html_path = atomic_write_text(folder / "compare.html", _html(df, warnings, notes))
    return csv_path, html_path, df
