"""The `drivedegrade` commands that take results computed elsewhere through the suite's analysis: CARLA leaderboard
results (`closed-loop import`), a model's own per-cell table (`analyse`), and the cells a foreign evaluator must run
(`ladder`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .keys import signing_key


def _closed_loop_import(args: argparse.Namespace) -> int:
    """CARLA leaderboard results files (one per cell) through the closed-loop analysis into closed_loop.csv,
    closed_loop_summary.json and report.html."""
    from ..report.closed_import import NullChoice, import_results

    lines, null_ok = import_results(args.files, Path(args.out), args.flat, NullChoice(args.null, args.null_identical))
    for line in lines:
        print(line)
    return 0 if null_ok else 1


def add_closed_loop_commands(sub: argparse._SubParsersAction) -> None:
    """closed-loop import: runs of a real simulator into the closed-loop analysis."""
    from ..constants import DEFAULT_FLAT

    p = sub.add_parser("closed-loop", help="closed-loop results from a simulator: import CARLA leaderboard runs")
    actions = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    q = actions.add_parser("import", help="read CARLA leaderboard results files (one per cell, clean among them) "
                                          "into the closed-loop analysis: closed_loop.csv, closed_loop_summary.json "
                                          "and report.html")
    q.add_argument("files", nargs="+", metavar="RESULTS.json",
                   help="the leaderboard's --checkpoint files, one per cell: CELL=FILE (e.g. blackout-s5=bo5.json), or "
                        "FILE named by its \"drivedegrade\": {\"cell\": ...} object or its file name")
    q.add_argument("--out", required=True, help="output folder")
    q.add_argument("--null", choices=("blackout-s3", "clean-rerun"),
                   help="the null control's results: blackout-s3 (the rear views a front-camera agent never reads), "
                        "or clean-rerun (a second clean run, given as clean-rerun=FILE: for an agent that reads its "
                        "rear cameras); default: clean-rerun when such a file is given, else blackout-s3")
    q.add_argument("--null-identical", action="store_true",
                   help="blackout S3 must reproduce clean run for run (DS and end): a front-only agent on a "
                        "deterministic CARLA setup; exit 1 naming the first route that differs")
    q.add_argument("--flat", type=float, default=DEFAULT_FLAT, metavar="F",
                   help=f"retention at or above which an axis counts as flat (default {DEFAULT_FLAT}; the plugin's "
                        "--drivedegrade-flat)")
    q.set_defaults(func=_closed_loop_import)


def _analyse(args: argparse.Namespace) -> int:
    """A per-cell table computed by a model's own evaluator through the suite's analysis, per model."""
    from ..report.table_import import analyse_table

    for line in analyse_table(args.table, args.out, convention=args.convention, flat=args.flat, metric=args.metric,
                              floor=args.floor, floor_l2=args.floor_l2, models=args.model or (), split=args.split,
                              null_identical=args.null_identical, signing_key=signing_key(args)):
        print(line)
    return 0


def _ladder(args: argparse.Namespace) -> int:
    """Print the cells a certification needs, for a model's own evaluation under patch_loader."""
    from ..foreign.ladder import ladder_cells, render

    families = [f for f in args.families.split(",") if f] if args.families else None
    severities = [int(s) for s in args.severities.split(",") if s] if args.severities else None
    sys.stdout.write(render(list(ladder_cells(args.set, families=families, severities=severities, seed=args.seed,
                                              seeds=args.seeds)), args.format))
    return 0


def add_foreign_commands(sub: argparse._SubParsersAction) -> None:
    """analyse and ladder: the paper's workflow, a model's own evaluator run once per cell."""
    from ..constants import DEFAULT_FLAT

    p = sub.add_parser("analyse", help="analyse a per-cell table from a model's own evaluator: cells.csv, "
                                       "report.html and an imported certificate per model")
    p.add_argument("table", metavar="TABLE", help="the per-cell CSV (docs/how-to/foreign-evaluator.md)")
    p.add_argument("--out", required=True, help="output folder: writes <out>/<model>/cells.csv, report.html and "
                                                "certificate.json")
    p.add_argument("--convention", choices=("stp3", "uniad"),
                   help="the L2 convention to analyse (default: stp3 when the table gives it, else uniad)")
    p.add_argument("--metric", choices=("l2", "pdms", "epdms"),
                   help="the retention the verdict is put on (default: L2 when clean has it, else PDMS, else EPDMS)")
    p.add_argument("--flat", type=float, default=DEFAULT_FLAT, metavar="F",
                   help=f"retention at or above which an axis counts as flat (default {DEFAULT_FLAT})")
    p.add_argument("--floor", metavar="MODEL", help="a model of the table whose clean L2 is the ego-only floor")
    p.add_argument("--floor-l2", type=float, metavar="M", help="the ego-only floor's clean L2 (metres)")
    p.add_argument("--model", action="append", metavar="MODEL", help="analyse only this model (repeatable)")
    p.add_argument("--split", default="as given", help="the split the figures were computed on (recorded)")
    p.add_argument("--null-identical", action="store_true",
                   help="blackout-s3 must give every figure clean gives (models that read no rear camera): a "
                        "difference fails the null control and makes the verdict undetermined")
    p.add_argument("--sign-key", metavar="PATH", help="sign the certificates with this Ed25519 private key "
                                                       "(default: $DRIVEDEGRADE_SIGNING_KEY)")
    p.set_defaults(func=_analyse)

    p = sub.add_parser("ladder", help="print the cells (family, severity, seed) a model's own evaluation must run "
                                      "under patch_loader, one per line")
    p.add_argument("--set", choices=("full", "axes", "slice"), default="full",
                   help="full: every family at S1..S5; axes: every family at S5 (the verdict); slice: the paper's "
                        "seven-cell slice (default full)")
    p.add_argument("--families", metavar="LIST", help="comma-separated families to keep")
    p.add_argument("--severities", metavar="LIST", help="comma-separated severities to keep (1..5)")
    p.add_argument("--seed", type=int, default=0, help="the first corruption seed (default 0)")
    p.add_argument("--seeds", type=int, default=1, metavar="N", help="seeds per random family (default 1)")
    p.add_argument("--format", choices=("text", "csv", "json", "shell"), default="text",
                   help="text (aligned), csv (the table's key columns), json, or shell ('CELL FAMILY SEVERITY "
                        "SEED' per line, for `while read`)")
    p.set_defaults(func=_ladder)
