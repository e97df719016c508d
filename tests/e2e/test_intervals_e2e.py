"""End-to-end checks of issue 15: `--drivedegrade-seeds` runs the random families under several seeds and the
certificate carries intervals; with one seed every output equals the pre-interval output but for the new fields.

The pre-interval output is `tests/data/golden/e2e_seeds1.json`, written by the code before intervals existed
(rewrite it with DRIVEDEGRADE_WRITE_GOLDEN=1 only when a change is meant to move these numbers).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import load_json, read_csv, verify_cli  # noqa: E402 - after register_assert_rewrite

pytest_plugins = ["plugin_support"]

GOLDEN = Path(__file__).parents[1] / "data" / "golden" / "e2e_seeds1.json"
#: Two deterministic families, one random (gaussian_noise) and blackout, at S1 and S5.
FAMILIES = "gaussian_blur,gaussian_noise,jpeg,blackout"
SEVERITIES = "1,5"
#: Fields that identify the machine-made provenance rather than results (compared elsewhere).
VOLATILE_COLUMNS = ("planner_fingerprint", "dataset_fingerprint")
#: Fields issue 15 adds; everything else must equal the pre-interval output.
NEW_THRESHOLD_KEYS = ("s10_ci", "s25_ci", "s10_never", "s25_never")
NEW_AXIS_KEYS = ("quality_ci", "removal_ci", "gap_ci", "mean_ci")
NEW_VERDICT_KEYS = ("confidence", "borderline")
NEW_SETTINGS_KEYS = ("seeds", "seed_values", "intervals", "planner_isolated")  # the last: issue 37's isolation
#: Fields the Trust issue adds (partial results, data faults), with their values in a run without failures.
TRUST_FIELDS = {"data_errors": 0, "partial": [], "reason": None, "failed_cells": {}, "frames_compared": 4}


def without_trust(entry: dict) -> dict:
    """`entry` without the Trust fields, each checked to hold its no-failure value first (a threshold's
    `partial` is False; a CSV cell is text)."""
    for key in set(entry) & set(TRUST_FIELDS):
        assert entry[key] in (TRUST_FIELDS[key], False, str(TRUST_FIELDS[key])), (key, entry[key])
    return {k: v for k, v in entry.items() if k not in TRUST_FIELDS and k != "computed_label"}


def comparable(folder: Path) -> dict:
    """What a seeds=1 run must keep from before intervals: cells.csv rows (fingerprints aside) and the
    certificate's result sections with the issue-15 fields removed."""
    rows = [without_trust({k: v for k, v in r.items() if k not in VOLATILE_COLUMNS})
            for r in read_csv(folder / "cells.csv")]
    cert = load_json(folder / "certificate.json")
    thresholds = {f: without_trust({k: v for k, v in t.items() if k not in NEW_THRESHOLD_KEYS})
                  for f, t in cert["thresholds"].items()}
    verdict = without_trust({k: v for k, v in cert["verdict"].items() if k not in NEW_VERDICT_KEYS})
    assert cert["verdict"]["computed_label"] == cert["verdict"]["label"]
    verdict["text"] = verdict["text"].split(" Borderline:")[0].split(" No confidence is stated:")[0]
    return {"csv": rows, "cells": [without_trust(c) for c in cert["cells"]], "thresholds": thresholds,
            "axes": without_trust({k: v for k, v in cert["axes"].items() if k not in NEW_AXIS_KEYS}),
            "verdict": verdict, "null_control": without_trust(cert["null_control"]),
            "settings": {k: v for k, v in cert["settings"].items() if k not in NEW_SETTINGS_KEYS}}


def test_seeds_1_equals_the_pre_interval_output(dd):
    dd.write_planner()
    result = dd.run(families=FAMILIES, severities=SEVERITIES)
    result.assert_outcomes(passed=11)
    got = comparable(dd.folder())
    if os.environ.get("DRIVEDEGRADE_WRITE_GOLDEN") == "1":
        GOLDEN.write_text(json.dumps(got, indent=1, sort_keys=True) + "\n")
    assert got == json.loads(GOLDEN.read_text())
    # issue 36: the small world's frames are one scene, so the intervals say they treat frames as independent
    # and the verdict states no confidence
    cert = load_json(dd.folder() / "certificate.json")
    assert cert["settings"]["intervals"]["basis"].startswith("frame bootstrap, 4 frames (one scene")
    assert cert["verdict"]["confidence"] is None and "one scene" in cert["settings"]["intervals"]["confidence_reason"]
    result.stdout.fnmatch_lines(["interval basis: frame bootstrap, 4 frames (one scene*"])


def test_seeds_2_runs_random_families_twice_records_the_seeds_and_yields_intervals(dd):
    dd.write_planner()
    one = dd.run(families=FAMILIES, severities=SEVERITIES, report="rep1")
    one.assert_outcomes(passed=11)
    two = dd.run("--drivedegrade-seeds", "2", "-n", "2", families=FAMILIES, severities=SEVERITIES, report="rep2")
    two.assert_outcomes(passed=11)  # one item per cell, whatever the seeds
    folder = dd.folder(report="rep2")
    cert = load_json(folder / "certificate.json")
    assert cert["settings"]["seeds"] == 2 and cert["settings"]["seed_values"] == [0, 1]
    assert verify_cli(folder / "certificate.json").returncode == 0
    noise = load_json(folder / "cells" / "gaussian_noise-s5.json")["record"]
    assert noise["seeds"] == [0, 1] and len(noise["seed_runs"]) == 1  # random: run under both seeds
    assert noise["seed_runs"][0]["plans"] != noise["plans"]  # another noise realisation moves the plan
    assert "seed_runs" not in load_json(folder / "cells" / "jpeg-s5.json")["record"]  # deterministic: once
    rows = {r["cell"]: r for r in read_csv(folder / "cells.csv")}
    first = {r["cell"]: r for r in read_csv(dd.folder(report="rep1") / "cells.csv")}
    assert rows["jpeg-s5"]["retention"] == first["jpeg-s5"]["retention"]
    assert rows["gaussian_noise-s5"]["retention"] != first["gaussian_noise-s5"]["retention"]
    for fam in ("gaussian_blur", "gaussian_noise", "jpeg", "blackout"):
        assert {"s10_ci", "s25_ci", "s10_never", "s25_never"} <= set(cert["thresholds"][fam])
    low, high = cert["axes"]["removal_ci"]
    assert low <= cert["axes"]["removal"] <= high
    two.stdout.fnmatch_lines(["axes 95% intervals: quality n/a  removal [[]0.*, 0.*[]]*", "thresholds 95%*"])

    # the baseline gate: a one-seed baseline against a two-seed run is refused, by name, before any cell runs
    baseline = dd.pytester.path / "one_seed.json"
    baseline.write_text((dd.folder(report="rep1") / "certificate.json").read_text())
    refused = dd.run("--drivedegrade-seeds", "2", "--drivedegrade-baseline", str(baseline), families=FAMILIES,
                     severities=SEVERITIES, report="rep3")
    assert refused.ret == pytest.ExitCode.USAGE_ERROR
    refused.stderr.fnmatch_lines(["*--drivedegrade-baseline*1 corruption seed(s)*this run uses 2*"])


def test_seeds_must_be_at_least_one(dd):
    dd.write_planner()
    result = dd.run("--drivedegrade-seeds", "0", families="jpeg", severities="1")
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    result.stderr.fnmatch_lines(["*--drivedegrade-seeds: must be at least 1*"])
