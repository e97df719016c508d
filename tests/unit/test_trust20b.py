"""Issue 20, part B (unit level): bad data is a data error naming file and row (M9), an image is refused by its
header before decoding (L5), and the content fingerprint covers the CAN bus and map expansion files."""

from __future__ import annotations

import json
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from pytest_drivedegrade.data import content
from pytest_drivedegrade.data.images import MAX_PIXELS, declared_size, decode_rgb
from pytest_drivedegrade.data.nuscenes import NuScenesReader
from pytest_drivedegrade.errors import DataError


@pytest.fixture(scope="module")
def tables_world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """3 scenes, tables, CAN bus and maps only (no images: nothing here decodes one)."""
    from pytest_drivedegrade.data.world import write_world

    return write_world(tmp_path_factory.mktemp("w20b"), scenes=3, seed=1, val_images=False)


@pytest.fixture()
def world(tables_world: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(tables_world, tmp_path / "world", copy_function=shutil.copy2))


def _table(root: Path, name: str) -> Path:
    return next(root.glob(f"v1.0-*/{name}.json"))


def _edit(root: Path, name: str, change: Callable[[list[dict]], None]) -> Path:
    path = _table(root, name)
    rows = json.loads(path.read_text())
    change(rows)
    path.write_text(json.dumps(rows))
    return path


def _read(root: Path) -> list:
    return NuScenesReader(root, split="all").scorable_frames()


def _first_camera_row(rows: list[dict]) -> dict:
    return next(r for r in rows if "/CAM_FRONT/" in r["filename"])


def _set_filename(suffix: str) -> Callable[[list[dict]], None]:
    def change(rows: list[dict]) -> None:
        row = _first_camera_row(rows)
        row["filename"] += suffix
    return change


# -- M9: seven kinds of bad data, each a data error naming the file and the row --------------------------------

def test_m9_a_nul_in_a_file_name_is_a_data_error_naming_the_row(world: Path) -> None:
    token = _first_camera_row(json.loads(_table(world, "sample_data").read_text()))["token"]
    _edit(world, "sample_data", _set_filename("\x00.jpg"))
    with pytest.raises(DataError, match=rf"sample_data\.json: the record with token '{token}': .*NUL"):
        _read(world)


def test_m9_a_file_name_that_is_not_utf8_is_a_data_error_naming_the_row(world: Path) -> None:
    """A lone surrogate: how Python carries a name's bytes that are not UTF-8 (JSON's \\udcff escape)."""
    token = _first_camera_row(json.loads(_table(world, "sample_data").read_text()))["token"]
    _edit(world, "sample_data", _set_filename("\udcff"))
    with pytest.raises(DataError, match=rf"sample_data\.json: the record with token '{token}': .*not UTF-8"):
        _read(world)


@pytest.mark.parametrize(("table", "text"), [("sample", "[" * 50_000 + "]" * 50_000),
                                              ("scene", '[{"a":' * 50_000 + "1" + "}" * 50_000 + "]")],
                         ids=["arrays", "objects"])
def test_m9_deeply_nested_json_in_a_table_is_a_data_error(world: Path, table: str, text: str) -> None:
    _table(world, table).write_text(text)
    with pytest.raises(DataError, match=rf"unreadable nuScenes table .*{table}\.json: JSON nested too deeply"):
        _read(world)


@pytest.mark.parametrize(("table", "field", "value", "expected"), [
    ("sample_annotation", "size", [1.0], "3 numbers"),
    ("ego_pose", "translation", ["a", 1.0, 2.0], "3 numbers"),
    ("ego_pose", "rotation", [1.0, 0.0, 0.0], "4 numbers"),
    ("calibrated_sensor", "camera_intrinsic", [[1.0, 0.0], [0.0, 1.0]], "3 lists of 3 numbers"),
])
def test_m9_malformed_json_in_a_table_is_a_data_error_naming_file_and_row(world: Path, table: str, field: str,
                                                                           value: list, expected: str) -> None:
    """A pose, a size or an intrinsic matrix of the wrong shape (an IndexError or a ValueError deep in the reader
    before): the table file, the record's token and the field are named."""
    rows = json.loads(_table(world, table).read_text())
    row = next(r for r in rows if r.get(field))
    _edit(world, table, lambda rs: next(r for r in rs if r["token"] == row["token"]).__setitem__(field, value))
    with pytest.raises(DataError, match=rf"{table}\.json: the record with token '{row['token']}' has {field}=.*"
                                        rf"expected {expected}"):
        _read(world)


def test_m9_a_lidar_without_intrinsics_is_not_malformed(world: Path) -> None:
    """nuScenes gives its lidar and radars an empty camera_intrinsic: that is the format, not a fault."""
    assert any(r["camera_intrinsic"] == [] for r in json.loads(_table(world, "calibrated_sensor").read_text()))
    assert _read(world)


@pytest.mark.parametrize(("data", "what"), [
    (b'{"utime": 1}', r"is a JSON dict, not a list of records"),
    (b"[\xff]", r"unreadable CAN bus file .*: 'utf-8' codec"),
    (b"[" * 50_000, r"unreadable CAN bus file .*: JSON nested too deeply"),
    (b"[1, 2]", r"record 0 \(1\) is not an object"),
    (b'[{"utime": 1, "vel": [1.0], "accel": [0, 0, 0], "rotation_rate": [0, 0, 0]}]', r"record 0 .* is not"),
    (b'[{"utime": 1, "vel": [0, 0, 0], "accel": [0, 0, 0]}]', r"three numbers in each of vel, accel, rotation"),
], ids=["object", "not-utf8", "nested", "numbers", "short-vel", "no-rotation-rate"])
def test_m9_a_malformed_can_bus_file_is_a_data_error_naming_file_and_record(world: Path, data: bytes,
                                                                             what: str) -> None:
    can = world / "can_bus" / "scene-0002_pose.json"
    can.write_bytes(data)
    with pytest.raises(DataError, match=what) as info:
        _read(world)
    assert "scene-0002_pose.json" in str(info.value)
    assert "delete the file" in str(info.value)  # what to do


@pytest.mark.parametrize("data", [b"{nope", b"[1]", b'{"\xff": 1}', b'{"fingerprint": "x", "splits": 3}',
                                  b'{"splits": {"val": ["scene-0003"]}}'])
def test_m9_a_malformed_world_manifest_is_a_data_error(world: Path, data: bytes) -> None:
    (world / "drivedegrade_world.json").write_bytes(data)
    with pytest.raises(DataError, match=r"(unreadable|malformed) world manifest .*drivedegrade_world\.json.*"
                                        r"regenerate the world"):
        _read(world)


def test_m9_a_malformed_map_expansion_nested_too_deeply_is_a_data_error(world: Path) -> None:
    reader = NuScenesReader(world, split="all")
    location = reader.scorable_frames()[0].location
    (world / "maps" / "expansion" / f"{location}.json").write_text("[" * 50_000)
    with pytest.raises(DataError, match=r"unreadable map expansion .*: JSON nested too deeply"):
        reader.drivable_area(location)


# -- L5: a decompression bomb is refused by its header -----------------------------------------------------------

def _encoded(ext: str, width: int, height: int, **params: int) -> bytes:
    flags = [cv2.IMWRITE_JPEG_PROGRESSIVE, params.get("progressive", 0)] if ext == ".jpg" else []
    ok, buf = cv2.imencode(ext, np.zeros((height, width, 3), np.uint8), flags)
    assert ok
    return buf.tobytes()


@pytest.mark.parametrize(("ext", "progressive"), [(".jpg", 0), (".jpg", 1), (".png", 0)])
def test_l5_the_declared_size_is_read_from_the_header(ext: str, progressive: int) -> None:
    assert declared_size(_encoded(ext, 53, 37, progressive=progressive)) == (53, 37)
    assert declared_size(b"BM" + bytes(60)) is None  # another format: left to the decoder


def _bomb(ext: str, width: int, height: int) -> bytes:
    """A small image whose header declares width x height (a decompression bomb)."""
    data = bytearray(_encoded(ext, 16, 16))
    if ext == ".png":
        data[16:24] = width.to_bytes(4, "big") + height.to_bytes(4, "big")
        return bytes(data)
    at = 2
    while data[at + 1] not in (0xC0, 0xC2):
        at += 2 + int.from_bytes(data[at + 2:at + 4], "big")
    data[at + 5:at + 9] = height.to_bytes(2, "big") + width.to_bytes(2, "big")
    return bytes(data)


@pytest.mark.parametrize("ext", [".jpg", ".png"])
def test_l5_a_decompression_bomb_is_refused_by_its_header_before_decoding(ext: str, tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / f"bomb{ext}"
    path.write_bytes(_bomb(ext, 60_000, 60_000))
    assert declared_size(path.read_bytes()) == (60_000, 60_000)
    decoded: list[int] = []
    monkeypatch.setattr(cv2, "imdecode", lambda *a: decoded.append(1))  # never reached
    with pytest.raises(DataError, match=r"declares 60000 x 60000 pixels, more than .*refused by its header"):
        decode_rgb(path, "f1")
    with pytest.raises(DataError, match=r"wrong-size image .*\(frame f1\): 60000 x 60000 pixels.*say 1600 x 900.*"
                                        r"refused by its header"):
        decode_rgb(path, "f1", (1600, 900))
    assert decoded == []
    assert 60_000 * 60_000 > MAX_PIXELS > 1600 * 900 * 10


# -- the content fingerprint covers the CAN bus and map expansion files of the scored scenes --------------------

@pytest.mark.parametrize("folder", ["can_bus", "maps/expansion"])
def test_the_content_fingerprint_covers_can_bus_and_map_expansion_files(world: Path, folder: str) -> None:
    """Mutations 'CAN bus files skipped' and 'map expansion files skipped' (issue 20): one byte more in the scored
    scene's file changes the fingerprint; the same change in a scene the run does not score does not."""
    reader = NuScenesReader(world, split="val")
    frames = reader.scorable_frames()
    scene, location = frames[0].scene_name, frames[0].location
    assert location and {f.scene_name for f in frames} == {scene}
    before = content.content_fingerprint(reader, frames)
    name = f"{scene}_pose.json" if folder == "can_bus" else f"{location}.json"
    others = [p for p in (world / folder).glob("*.json") if p.name != name]
    assert len(others) == 2
    for other in others:  # unscored scenes' files
        other.write_bytes(other.read_bytes() + b" ")
    assert content.content_fingerprint(reader, frames) == before
    scored = world / folder / name
    scored.write_bytes(scored.read_bytes() + b" ")  # still valid JSON: only its content changed
    assert content.content_fingerprint(reader, frames) != before


# -- L1: the three outputs are published as a set ---------------------------------------------------------------

def _outputs(folder: Path) -> dict[str, bytes]:
    return {name: (folder / name).read_bytes() for name in ("certificate.json", "cells.csv", "report.html")}


@pytest.mark.parametrize("fail_at", [1, 2, 3])
def test_l1_a_crash_between_the_outputs_leaves_the_previous_set_whole(tmp_path: Path, fail_at: int,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """The run is published once; a second publish of another run dies while writing its `fail_at`-th file
    (the disk fills, the process is killed): every output is still the first run's, and no temporary is left."""
    import os

    from test_publish import KEY, finished

    from pytest_drivedegrade.certificate.seal import run_provenance
    from pytest_drivedegrade.report.publish import publish
    from pytest_drivedegrade.settings import RunSettings

    publish(finished(), tmp_path)
    folder = tmp_path / "demo"
    before = _outputs(folder)
    other = RunSettings(frames=8, seed=4, flat=0.95, batch=4, reuse=False)
    second = finished(settings=other, provenance=run_provenance(other, planner_name="demo", key=KEY, frames=8,
                                                                frames_unscored=0, command="pytest"))
    calls = {"n": 0}
    real = os.fsync

    def dying(fd: int) -> None:
        calls["n"] += 1
        if calls["n"] == fail_at:
            raise OSError(28, "No space left on device")
        real(fd)

    monkeypatch.setattr(os, "fsync", dying)
    with pytest.raises(OSError, match="No space left"):
        publish(second, tmp_path)
    assert _outputs(folder) == before
    assert sorted(p.name for p in folder.iterdir()) == ["cells.csv", "certificate.json", "report.html"]
    monkeypatch.setattr(os, "fsync", real)
    publish(second, tmp_path)  # and without the crash the whole new set replaces it
    after = _outputs(folder)
    assert all(after[name] != before[name] for name in before)


def test_l1_a_set_is_renamed_in_order_after_every_file_is_written(tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    from pytest_drivedegrade.atomic import atomic_write_set

    events: list[str] = []
    real_replace, real_fsync = os.replace, os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (events.append("write"), real_fsync(fd))[1])
    monkeypatch.setattr(os, "replace", lambda a, b: (events.append(Path(b).name), real_replace(a, b))[1])
    atomic_write_set({tmp_path / "a.csv": b"1", tmp_path / "sub" / "b.json": b"2"})
    assert events == ["write", "write", "a.csv", "b.json"]
    assert (tmp_path / "a.csv").read_bytes() == b"1" and (tmp_path / "sub" / "b.json").read_bytes() == b"2"


# -- L3: the signature covers the values as stored, not as rounded again -----------------------------------------

def test_l3_a_value_edited_below_the_rounding_no_longer_verifies_its_signature() -> None:
    """A signed certificate whose clean L2 is edited by 4e-7 (below the 6-decimal rounding) and resealed (the digest
    is no secret): the digest verifies, the signature must not. The stored values are the rounded ones, so an
    untouched certificate verifies, and signing did not change a single stored value."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
    from test_publish import finished

    from pytest_drivedegrade.certificate.seal import compute_digest, seal, verify_data
    from pytest_drivedegrade.certificate.signing import SignatureFailure, sign, verify_signature
    from pytest_drivedegrade.report.outputs import write_outputs
    from pytest_drivedegrade.report.publish import analyse

    run, key = finished(), Ed25519PrivateKey.generate()
    with tempfile.TemporaryDirectory() as tmp:
        unsigned, _ = write_outputs(Path(tmp), run.provenance, run.records, analyse(run), (), gt=run.gt,
                                    montage=None)
    signed = seal(sign(unsigned, key))
    assert {k: v for k, v in signed.items() if k not in ("signature", "digest", "section_digests")} == \
        {k: v for k, v in unsigned.items() if k not in ("digest", "section_digests")}
    assert verify_signature(verify_data(signed), key.public_key())

    forged = json.loads(json.dumps(signed))
    cell = forged["cells"][0]
    l2 = cell["l2_avg"]
    assert isinstance(l2, float) and round(l2, 6) == l2
    cell["l2_avg"] = l2 + 4e-7
    forged["digest"] = compute_digest(forged)
    assert verify_data(forged)  # the digest is recomputed by anyone
    with pytest.raises(SignatureFailure, match="changed after signing"):
        verify_signature(forged, key.public_key())


# -- new-user (c): the negative-gap sentence only when the gap's interval excludes 0 ----------------------------

@pytest.mark.parametrize(("interval", "said"), [((-0.012, 0.009), False), ((-0.02, -0.0001), True), (None, True)])
def test_new_user_c_the_negative_gap_is_said_only_when_its_interval_excludes_zero(interval, said: bool) -> None:
    """A gap of -0.0008 whose 95 % interval holds 0 is not a planner misled by corrupted pixels: no flag, no
    sentence. Without an interval (no bootstrap) the gap alone decides, as before."""
    from pytest_drivedegrade.scoring.records import Axes, AxisIntervals
    from pytest_drivedegrade.scoring.verdict import verdict

    axes = Axes(0.9712, 0.972, -0.0008, 0.9716,
                intervals=None if interval is None else AxisIntervals(gap=interval))
    v = verdict(axes, 0.95)
    assert v.label == "not-shown-to-use-cameras"
    assert v.negative_gap is said and ("Negative gap (-0.001)" in v.text) is said


# -- new-user (a): a planner far worse than the ego-only floor gets a loud warning -------------------------------

@pytest.mark.parametrize(("floor", "warned"), [([0.1, 0.2], True), ([0.25, 0.3], False), ([3.0, 3.0], False),
                                               ([0.01, 0.02], True)])
def test_new_user_a_a_planner_far_worse_than_the_floor_is_warned_loudly(tmp_path: Path, floor: list[float],
                                                                       warned: bool) -> None:
    """Clean L2 0.393 m: against a floor of 0.15 m (2.6x, 0.24 m above) or 0.015 m the terminal summary (right
    under the verdict) and the report say so; against 0.275 m (1.4x) or 3.0 m they do not. The certificate is
    unchanged: it is a warning, not a figure."""
    from test_publish import finished

    from pytest_drivedegrade.certificate.finished import FloorFigures
    from pytest_drivedegrade.report.publish import publish

    out = publish(finished(floor=FloorFigures.of(floor)), tmp_path)
    clean = next(s.l2_avg for s in out.analysis.summaries if s.cell == "clean")
    ratio, above = clean / np.mean(floor), clean - np.mean(floor)
    assert warned is bool(ratio > 2.0 and above > 0.1)
    warning = [line for line in out.lines if line.startswith("WARNING: the planner is far worse than the ego-only")]
    assert bool(warning) is warned
    html = (tmp_path / "demo" / "report.html").read_text()
    assert ("far worse than the ego-only floor" in html) is warned
    if warned:
        assert out.lines.index(warning[0]) == 1 and "miswired adapter" in warning[0]
        assert f"clean L2 {clean:.3f} m, floor {np.mean(floor):.3f} m" in warning[0]
    assert "WARNING" not in json.dumps(out.certificate)  # a warning, not a recorded figure


def test_new_user_a_a_tiny_difference_is_not_warned_however_large_the_ratio() -> None:
    """Floor 0.01 m, clean 0.05 m: 5x, but 4 cm is no sign of a miswired adapter (the 0.1 m margin)."""
    from types import SimpleNamespace

    from pytest_drivedegrade.report.terminal import floor_warning

    def analysis(clean: float, floor: float) -> SimpleNamespace:
        return SimpleNamespace(summaries=[SimpleNamespace(cell="clean", l2_avg=clean)],
                               floor=SimpleNamespace(l2_avg=floor))

    assert floor_warning(analysis(0.05, 0.01)) is None  # type: ignore[arg-type]
    assert floor_warning(analysis(3.30, 0.34)).startswith("WARNING")  # type: ignore[arg-type, union-attr]
    assert floor_warning(analysis(float("nan"), 0.34)) is None  # type: ignore[arg-type]


# -- new-user (d): paths relative to rootdir -----------------------------------------------------------------------

def test_new_user_d_paths_are_shown_relative_to_rootdir_or_by_name(tmp_path: Path) -> None:
    from pytest_drivedegrade.settings import RunSettings, shown_arg, shown_path

    root = tmp_path / "repo"
    (root / "planners").mkdir(parents=True)
    assert shown_path(root / "planners" / "p.py", root) == "planners/p.py"
    assert shown_path("/home/alice/data/nuscenes", root) == ".../nuscenes"
    assert shown_path("planners/p.py", root) == "planners/p.py"  # relative: as given
    assert shown_arg(f"--drivedegrade-report={root}/out", root) == "--drivedegrade-report=out"
    assert shown_arg("/srv/ci.key", root) == ".../ci.key" and shown_arg("-k", root) == "-k"
    assert shown_arg("--drivedegrade-families=jpeg", root) == "--drivedegrade-families=jpeg"
    settings = RunSettings(data=Path("/data/sets/nuscenes"))
    assert settings.shown_source(root) == ".../nuscenes" and settings.data_source == "/data/sets/nuscenes"
    assert RunSettings().shown_source(root) == "embedded world"


# -- the contract: known answers for the 1 km bound and a data fault the planner caught ---------------------------

@pytest.mark.parametrize(("waypoint", "distance"), [((3.0, 1000.5), "1000.5 m"), ((-800.0, 800.0), "1131.37 m"),
                                                    ((0.0, -1200.0), "1200 m")])
def test_the_contract_bounds_the_distance_not_each_coordinate(waypoint: tuple[float, float], distance: str) -> None:
    """Mutation 'the 1 km bound checks |x| only': a waypoint 1 km sideways, or 800 m along both axes (1131 m
    away, each coordinate inside 1 km), breaks the contract; (700, 700) at 990 m does not."""
    from pytest_drivedegrade.errors import PlannerOutputError
    from pytest_drivedegrade.planning import validate_output

    plan = np.cumsum(np.full((6, 2), 0.5), axis=0)
    plan[3] = waypoint
    with pytest.raises(PlannerOutputError, match=f"waypoint {distance} from the ego at step 3"):
        validate_output(plan, "tok")
    plan[3] = (700.0, 700.0)
    assert validate_output(plan, "tok")[3].tolist() == [700.0, 700.0]


class _CatchesDataFaults:
    """Reads the front camera, and when the image cannot be produced (a data fault) catches the error and plans
    from ego status alone: the plan is a good one, the frame is still the data's fault."""

    cameras = ("CAM_FRONT",)
    name = "catcher"

    def __init__(self) -> None:
        self.caught = 0

    def predict(self, images: dict, ego: object, cmd: object) -> np.ndarray:
        try:
            images["CAM_FRONT"]
        except DataError:
            self.caught += 1
        return np.cumsum(np.full((6, 2), 0.5), axis=0)


def test_a_data_fault_the_planner_caught_and_planned_around_is_not_a_good_frame(world: Path) -> None:
    """Mutation 'a data fault the planner caught is scored as a good frame': the world without its images; the
    planner catches every missing-image error and returns a valid plan, yet every frame is a data error (NaN,
    named), none a scored frame."""
    from pytest_drivedegrade.run import RunContext
    from pytest_drivedegrade.settings import RunSettings

    context = RunContext.open(RunSettings(data=world, split="all", frames=4, timeout=0.0))
    planner = _CatchesDataFaults()
    record = context.run_cell(planner, "clean", 0)
    assert planner.caught == len(record.frames) == 4
    assert len(record.data_errors) == 4 and not record.errors
    assert all("missing image" in e and "CAM_FRONT" in e for e in record.data_errors)
    assert np.isnan(record.l2).all()
