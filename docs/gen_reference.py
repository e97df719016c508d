"""Write the documentation site's reference pages from the code (run by the mkdocs hook `docs/hooks.py` before
every build, or by hand: ``python docs/gen_reference.py``): every option of the option registry, every cells.csv
column, the certificate's JSON Schema and the CLI's ``--help``. A new option or column without a place here
fails tests/unit/test_docs_reference.py, so the reference never lags the code.

The pages are build outputs (ignored by git): edit this script, not them.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import re
import sys
from collections.abc import Mapping
from pathlib import Path

HERE = Path(__file__).resolve().parent
if str(HERE.parent) not in sys.path:  # run from anywhere, against this checkout
    sys.path.insert(0, str(HERE.parent))

#: Every --drivedegrade-* option, in the section the options page lists it under. A new option goes here.
SECTIONS: dict[str, tuple[str, ...]] = {
    "What is certified": ("--drivedegrade", "--drivedegrade-data", "--drivedegrade-split", "--drivedegrade-frames",
                          "--drivedegrade-families", "--drivedegrade-severities", "--drivedegrade-seed",
                          "--drivedegrade-seeds", "--drivedegrade-metric", "--drivedegrade-flat",
                          "--drivedegrade-ego-box", "--drivedegrade-two-stage"),
    "How the planner is called": ("--drivedegrade-batch", "--drivedegrade-no-reuse", "--drivedegrade-device",
                                  "--drivedegrade-timeout", "--drivedegrade-prefetch", "--drivedegrade-dry-run",
                                  "--drivedegrade-isolate"),
    "Reports, resuming and the CI gate": (
        "--drivedegrade-report", "--drivedegrade-report-overwrite", "--drivedegrade-no-resume",
        "--drivedegrade-baseline", "--drivedegrade-baseline-public-key", "--drivedegrade-baseline-partial",
        "--drivedegrade-baseline-any-planner", "--drivedegrade-tolerance", "--drivedegrade-sign-key"),
    "Scale": ("--drivedegrade-shard", "--drivedegrade-ray", "--drivedegrade-ray-actors", "--drivedegrade-ray-gpus"),
    "Adaptive certification": ("--drivedegrade-adaptive", "--drivedegrade-alpha"),
    "Closed loop": ("--drivedegrade-loop", "--drivedegrade-closed-cells", "--drivedegrade-closed-seeds",
                    "--drivedegrade-closed-hz", "--drivedegrade-closed-routes", "--drivedegrade-closed-agents",
                    "--drivedegrade-closed-steps", "--drivedegrade-closed-collisions",
                    "--drivedegrade-closed-scenarios", "--drivedegrade-closed-lights"),
}

_H = {"1s": "1 s", "2s": "2 s", "3s": "3 s"}
_CONV = {"stp3": "ST-P3 convention (mean of the steps up to the horizon)",
         "uniad": "UniAD convention (the value at the horizon step)"}
_KIND = {"l2": "L2 distance of the plan from the logged future (m)",
         "collision": "share of frames whose plan collides with an annotated box",
         "vru": "share of frames whose plan collides with a pedestrian or cyclist box"}
#: Every cells.csv column not named by the per-horizon pattern (`_horizon_column`). A new column goes here.
COLUMNS: dict[str, str] = {
    "cell": "the cell's id: `clean`, `null`, `blind`, `<family>-s<severity>` or an ego cell",
    "family": "the corruption family (or the diagnostic cell's name)",
    "severity": "1..5 on the ladder; 0 for the diagnostic cells",
    "frames": "frames scored in the cell (failed frames left out)",
    "l2_avg": "mean L2 over the 1/2/3 s horizons, ST-P3 convention (m): the cell's figure of merit",
    "retention": "M(clean) / M(cell) on mean L2: 1 is no damage, below 1 is worse",
    "retention_ci_low": "low end of the retention's 95 % paired bootstrap interval (scenes resampled)",
    "retention_ci_high": "high end of the same interval",
    "l2_avg_stp3": "mean L2 over the three horizons, ST-P3 convention (m); equals `l2_avg`",
    "l2_avg_uniad": "mean L2 over the three horizons, UniAD convention (m)",
    "jerk": "mean absolute jerk of the plans (m/s^3)",
    "endpoint_shift": "mean distance of the 3 s waypoint from clean's (m)",
    "energy": "mean share of 1 bits in what the planner read (the energy proxy; clean's where unchanged)",
    "separable_from_null": "whether the cell's plans are told apart from the null control's beyond its spread",
    "conformance_errors": "frames on which the planner broke the contract (raised, wrong shape, NaN, timeout)",
    "data_errors": "frames whose images could not be produced (the data set's fault, not the planner's)",
    "pdms": "mean PDMS-like score (NAVSIM v1 terms) in [0, 1]",
    "nc": "no at-fault collision (PDMS term)", "dac": "drivable area compliance (PDMS term)",
    "ttc": "time to collision (PDMS term)", "ep": "ego progress (PDMS term)", "comfort": "comfort (PDMS term)",
    "pdms_retention": "PDMS retention M(cell) / M(clean) (a reward: above 1 is better)",
    "pdms_retention_ci_low": "low end of its 95 % paired bootstrap interval",
    "pdms_retention_ci_high": "high end of the same interval",
    "map_scored": "frames whose lane map let the map terms be scored",
    "epdms": "mean EPDMS (NAVSIM v2's extended score) in [0, 1]",
    "ddc": "driving direction compliance (EPDMS term)", "tlc": "traffic light compliance (EPDMS term; empty "
    "without traffic lights)", "lk": "lane keeping (EPDMS term)", "hc": "history comfort (EPDMS term)",
    "ec": "extended comfort (EPDMS term)",
    "epdms_retention": "EPDMS retention M(cell) / M(clean)",
    "epdms_retention_ci_low": "low end of its 95 % paired bootstrap interval",
    "epdms_retention_ci_high": "high end of the same interval",
    "planner": "the planner's name (its report folder)",
    "planner_fingerprint": "SHA-256 of the planner's source, the modules it imports and its weights",
    "dataset_fingerprint": "digest of the content of every file the scored frames read",
    "split": "the split scored", "spec_version": "the ladder's spec version", "seed": "the corruption seed",
    "convention": "the L2 convention of `l2_avg`",
    "command_following": "command_swap row: how far the plans follow an alternative command at junction frames "
                         "(0: they ignore it, 1: as the privileged expert with the swapped route)",
    "command_following_ci_low": "low end of its 95 % interval (junction frames resampled)",
    "command_following_ci_high": "high end of the same interval",
    "command_label": "command_swap row: command-following, command-partial, command-insensitive or undetermined",
    "command_frames": "command_swap row: the junction frames the figure is scored on",
    "junction_frames": "command_swap row: the scored frames where another command is meaningful",
    "epdms_stage2": "--drivedegrade-two-stage: mean stage-two EPDMS (per frame, its start poses' EPDMS weighted by "
                    "how close each start lies to where the stage-one plan ended); empty in a one-stage run",
    "epdms2": "--drivedegrade-two-stage: mean two-stage EPDMS (per frame, the EPDMS times the stage-two EPDMS, as "
              "NAVSIM v2 aggregates its two stages); empty in a one-stage run",
    "epdms2_frames": "--drivedegrade-two-stage: frames with a stage two (its keyframe holds the future to score)",
    "epdms2_retention": "two-stage EPDMS retention M(cell) / M(clean) over the frames with a stage two in both",
    "epdms2_retention_ci_low": "low end of its 95 % paired bootstrap interval",
    "epdms2_retention_ci_high": "high end of the same interval",
}


def _horizon_column(name: str) -> str | None:
    """l2_1s_stp3, collision_3s_uniad, vru_2s_stp3, ...: described from their parts."""
    match = re.fullmatch(r"(l2|collision|vru)_([123]s)_(stp3|uniad)", name)
    if match is None:
        return None
    kind, horizon, conv = match.groups()
    return f"{_KIND[kind]} at {_H[horizon]}, {_CONV[conv]}"


def column_description(name: str) -> str | None:
    return COLUMNS.get(name) or _horizon_column(name)


def _escape(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def options_page() -> str:
    from pytest_drivedegrade.plugin.options import OPTIONS

    by_flag = {spec.flag: spec for spec in OPTIONS}
    lines = ["# Options", "", "Generated from the option registry (`pytest_drivedegrade/plugin/options.py`) by "
             "`docs/gen_reference.py`. Every option is also an ini key of `[tool.pytest.ini_options]` (the name in "
             "the second column); the command line wins over the ini file.", ""]
    for title, flags in SECTIONS.items():
        lines += [f"## {title}", "", "| option | ini key | what it does |", "|---|---|---|"]
        for flag in flags:
            spec = by_flag[flag]
            metavar = spec.argparse.get("metavar")
            shown = f"`{flag} {metavar}`" if metavar else f"`{flag}`"
            lines.append(f"| {shown} | `{spec.dest}` | {_escape(spec.help)} |")
        lines.append("")
    return "\n".join(lines)


def columns_page() -> str:
    from pytest_drivedegrade.report.columns import CSV, STABLE

    lines = ["# cells.csv columns", "", "Generated from `pytest_drivedegrade/report/columns.py` by "
             "`docs/gen_reference.py`: one row per cell, these columns in this order. The first "
             f"{len(STABLE)} are stable (never renamed); others may be added.", "",
             "| column | meaning |", "|---|---|"]
    lines += [f"| `{name}` | {_escape(column_description(name) or '')} |" for name in CSV]
    return "\n".join(lines) + "\n"


def certificate_schema() -> dict[str, object]:
    """The certificate's JSON Schema (draft 2020-12), from the names the code seals: the required top-level keys,
    the schema tag, and every per-cell field."""
    from pytest_drivedegrade.certificate.fields import CERTIFICATE_CELL, STABLE
    from pytest_drivedegrade.certificate.seal import REQUIRED_KEYS, SCHEMA

    number = {"type": ["number", "null"]}
    cell = {"type": "object", "required": list(STABLE), "properties": {
        name: ({"type": "string"} if name in ("cell", "family") else
               {"type": "integer"} if name in ("severity", "frames", "conformance_errors", "data_errors") else
               {"type": ["boolean", "null"]} if name == "separable_from_null" else number)
        for name in CERTIFICATE_CELL} | {"plans_digest": {"type": "string"}}}
    props: dict[str, object] = {key: {"type": "object"} for key in REQUIRED_KEYS}
    props.update(schema={"const": SCHEMA}, spec_version={"type": "string"}, created={"type": "string"},
                 digest={"type": "string", "pattern": "^[0-9a-f]{64}$"}, cells={"type": "array", "items": cell},
                 section_digests={"type": "object", "additionalProperties": {"type": "string"}})
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "$id": SCHEMA, "title": "DriveDegrade "
            "certificate", "type": "object", "required": list(REQUIRED_KEYS), "properties": props}


def schema_page() -> str:
    text = json.dumps(certificate_schema(), indent=2)
    return ("# The certificate's JSON Schema\n\nGenerated from `pytest_drivedegrade/certificate/seal.py` and "
            "`fields.py` by `docs/gen_reference.py`. `drivedegrade verify` checks far more (the digest, the "
            "signature, the arithmetic); the schema says what a reader may rely on.\n\n```json\n" + text + "\n```\n")


def _help(parser: argparse.ArgumentParser) -> str:
    with contextlib.redirect_stdout(io.StringIO()) as out:
        parser.print_help()
    return out.getvalue()


def cli_page() -> str:
    from pytest_drivedegrade.cli import build_parser

    parser = build_parser()
    lines = ["# The drivedegrade command", "", "Generated from `pytest_drivedegrade/cli/` by "
             "`docs/gen_reference.py`: the `--help` of the command and of each subcommand.", "",
             "```text", _help(parser).rstrip(), "```", ""]
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))  # noqa: SLF001
    for name, sub in subs.choices.items():
        lines += [f"## drivedegrade {name}", "", "```text", _help(sub).rstrip(), "```", ""]
    return "\n".join(lines)


PAGES: Mapping[str, object] = {"options.md": options_page, "cells-csv.md": columns_page,
                               "certificate-schema.md": schema_page, "cli.md": cli_page}


def generate(folder: Path = HERE / "reference") -> list[Path]:
    """Write every generated page into `folder` (only where its text changed); returns the pages."""
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, page in PAGES.items():
        path = folder / name
        text = page()  # type: ignore[operator]
        if not path.is_file() or path.read_text() != text:
            path.write_text(text)
        written.append(path)
    return written


if __name__ == "__main__":
    for path in generate():
        print(path)
