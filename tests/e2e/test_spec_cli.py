"""The spec is emitted from the code, the CLI works end to end, and the plugin entry stays light."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import pytest
import yaml

from pytest_drivedegrade import FAMILIES, SPEC_VERSION
from pytest_drivedegrade.cli import main
from pytest_drivedegrade.corruptions.spec import render_spec, spec_dict

ROOT = Path(__file__).resolve().parents[2]


def test_committed_ladder_matches_the_code():
    committed = (ROOT / "spec" / "ladder.yaml").read_text()
    assert committed == render_spec("yaml"), (
        "spec/ladder.yaml differs from the injector: run `drivedegrade spec --out spec/ladder.yaml` and bump "
        "SPEC_VERSION if an operator or value changed")


def test_spec_carries_version_and_the_exact_table():
    spec = yaml.safe_load(render_spec("yaml"))
    assert spec["spec_version"] == SPEC_VERSION
    by_name = {f["name"]: f for f in spec["families"]}
    assert list(by_name) == list(FAMILIES)
    assert by_name["gaussian_blur"]["values"] == {"S1": 0.5, "S2": 1.0, "S3": 2.0, "S4": 3.5, "S5": 6.0}
    assert by_name["fog"]["values"]["S5"] == 35 and by_name["fog"]["unit"] == "m"
    assert by_name["blackout"]["values"]["S3"] == ["CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT"]
    assert by_name["bit_error"]["values"]["S1"] == 1e-7
    assert sum(f["core"] for f in spec["families"]) == 12
    assert sum(f["axis"] == "quality" for f in spec["families"]) == 9
    assert {n for n, f in by_name.items() if not f["random"]} == {
        "gaussian_blur", "jpeg", "downscale", "color_quant", "fog", "blackout"}


def _shown(value) -> str:
    """How the table prints one ladder value."""
    return "+".join(c.replace("CAM_", "") for c in value) if isinstance(value, tuple) else str(value)


def assert_table_lists_the_ladder(table: str) -> None:
    """Every family on its own row, in SPEC order, with its group, axis, S1..S5 and randomness as declared."""
    import re

    lines = table.splitlines()
    assert lines[0] == f"DriveDegrade ladder, spec version {SPEC_VERSION}"
    assert re.split(r"\s{2,}", lines[1]) == ["family", "group", "axis", "parameter (unit)", "S1", "S2", "S3", "S4",
                                              "S5", "random"]
    rows = [re.split(r"\s{2,}", line) for line in lines[3:]]
    assert [r[0] for r in rows] == list(FAMILIES) and len(rows) == 16
    for row, fam in zip(rows, FAMILIES.values()):
        assert row == [fam.name, fam.group, fam.axis, f"{fam.parameter} ({fam.unit})",
                       *[_shown(v) for v in fam.values], "yes" if fam.random else "no"], row
    by_name = {r[0]: r for r in rows}
    assert by_name["motion_blur"][4:9] == ["4", "8", "14", "22", "34"]
    assert by_name["blackout"][7] == "FRONT_LEFT+FRONT_RIGHT" and by_name["bit_error"][4] == "1e-07"


def test_cli_spec_formats(capsys, tmp_path):
    assert main(["spec", "--format", "table"]) == 0
    assert_table_lists_the_ladder(capsys.readouterr().out)
    assert main(["spec", "--format", "json", "--out", str(tmp_path / "l.json")]) == 0
    import json

    assert json.loads((tmp_path / "l.json").read_text()) == spec_dict()
    assert main(["spec", "--format", "yaml", "--out", str(tmp_path / "l.yaml")]) == 0
    assert (tmp_path / "l.yaml").read_text() == (ROOT / "spec" / "ladder.yaml").read_text()


def test_cli_preview_all_families_and_one_family(tmp_path, nuscenes_frames):
    front = str(nuscenes_frames["CAM_FRONT"][0])
    out = tmp_path / "m.png"
    assert main(["preview", front, "--severity", "4", "--out", str(out), "--width", "160"]) == 0
    montage = cv2.imread(str(out))
    tile_h = 42 + round(900 * 160 / 1600)  # a two-line label bar over each tile
    assert montage.shape[:2] == (3 * tile_h + 8, 6 * 160)  # clean + 16 families on a 6-wide grid
    out2 = tmp_path / "f.png"
    assert main(["preview", front, "--family", "fog", "--out", str(out2), "--width", "160"]) == 0
    assert cv2.imread(str(out2)).shape[:2] == (2 * tile_h + 8, 3 * 160)  # clean + S1..S5


def test_cli_errors_are_one_clear_line(tmp_path, capsys):
    assert main(["preview", str(tmp_path / "missing.jpg")]) == 2
    assert "missing.jpg: no such image file" in capsys.readouterr().err
    broken = tmp_path / "broken.jpg"
    broken.write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg")
    assert main(["preview", str(broken)]) == 2
    assert "broken.jpg: not a readable image" in capsys.readouterr().err
    good = tmp_path / "g.png"
    cv2.imwrite(str(good), cv2.UMat(8, 8, cv2.CV_8UC3).get())
    assert main(["preview", str(good), "--family", "haze"]) == 2
    assert "unknown corruption family 'haze'" in capsys.readouterr().err


def test_plugin_entry_imports_nothing_heavy():
    code = ("import sys, pytest_drivedegrade.plugin, pytest_drivedegrade\n"
            "heavy = [m for m in ('cv2', 'torch', 'pandas', 'matplotlib') if m in sys.modules]\n"
            "print(','.join(heavy))")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    assert out.strip() == ""


def test_console_script_is_installed():
    """The `drivedegrade` script sits beside this interpreter (not merely somewhere on PATH) and prints the
    ladder of this checkout (PYTHONPATH points it here; the installed copy may be another checkout)."""
    import os

    script = Path(sys.executable).parent / "drivedegrade"
    assert script.is_file() and os.access(script, os.X_OK), f"no console script at {script}"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    out = subprocess.run([str(script), "spec", "--format", "table"], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    assert_table_lists_the_ladder(out.stdout)


@pytest.mark.parametrize("width", [160, 220, 480])
def test_montage_labels_fit_their_tiles(width):
    """Every S4 label line (family and severity, then the parameter) fits inside its tile at the report's width."""
    from pytest_drivedegrade.corruptions.preview import _FONT, _MARGIN_PX, _fit_scale

    for name, fam in FAMILIES.items():
        for text in (f"{name} S4", fam.describe(4)):
            used = cv2.getTextSize(text, _FONT, _fit_scale(text, width), 1)[0][0]
            assert used <= width - 2 * _MARGIN_PX, (name, text, used)

