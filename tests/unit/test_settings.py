"""`RunSettings`: one table, seen alike by the run key, the certificate, a shard merge, the baseline gate and a rerun.

Each setting is changed alone and every consumer is asked whether it sees the change, through its real code path
(`RunContext.run_key`, `merge_shards` on written manifests, `check_baseline_compatible` on a built certificate,
`reproduce.rerun_argv`); the builtins forms round-trip exactly.
"""

from __future__ import annotations

import json
from dataclasses import fields, replace
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st
from test_analysis import GROUPS, synthetic_run

from pytest_drivedegrade.certificate import merge as mg
from pytest_drivedegrade.certificate import reproduce as rp
from pytest_drivedegrade.certificate import seal as cf
from pytest_drivedegrade.errors import DriveDegradeError, InvalidInput
from pytest_drivedegrade.planning import CallStyle
from pytest_drivedegrade.run import PlannerElsewhere, PlannerInfo, RunContext
from pytest_drivedegrade.scoring import baseline as bl
from pytest_drivedegrade.scoring.analyse import analyse_run
from pytest_drivedegrade.settings import DEFAULTS, TABLE, Gate, RunSettings, Shard, check_table, setting

#: A run that is not at the defaults where a default would hide a setting (batched, so reuse is keyed).
BASE = RunSettings(data=Path("/data/nuscenes"), split="val", frames=8, seed=0, batch=4)
#: One other value per setting.
CHANGED = {"data": Path("/elsewhere/nuscenes"), "split": "mini_val", "frames": 6, "seed": 3, "seeds": 2,
           "batch": 8, "reuse": False, "device": "cuda:1", "timeout": 5.0, "metric": "pdms", "flat": 0.9,
           "ego_box": "pacifica", "two_stage": True, "shard": Shard(2, 3), "prefetch": 3, "adaptive": True,
           "alpha": 0.1, "isolate": True, "loop": "both", "closed_cells": "all", "closed_seeds": 3, "closed_hz": 5,
           "closed_routes": 2, "closed_steps": 8, "closed_agents": "reactive", "closed_collisions": "at_fault",
           "closed_scenarios": 5, "closed_lights": 2}
#: Who sees that change, written out here rather than read off the table: (run key, merge, gate, rerun argv).
SEEN_BY = {"data": (False, False, False, False), "split": (False, True, True, True),
           "frames": (False, True, False, True), "seed": (True, True, True, True), "seeds": (True, True, True, True),
           "batch": (True, True, True, True), "reuse": (True, True, True, True), "device": (True, True, True, True),
           "timeout": (False, True, False, True), "metric": (False, True, True, True),
           "flat": (False, True, False, True), "ego_box": (True, True, True, True),
           "two_stage": (True, True, True, True),
           "shard": (False, False, False, False),
           "prefetch": (False, False, False, False), "adaptive": (True, True, False, True),
           # alpha alone in a full run: no run key holds it and no certificate records it (an option parse refuses
           # --drivedegrade-alpha without --drivedegrade-adaptive); shards still compare it
           "alpha": (False, True, False, False),
           # where the planner ran changes no plan, but an isolated run never reuses a cell made beside the stream
           "isolate": (True, True, False, True),
           # the closed loop: the open cells' run key and the gate ignore it (the closed cells' own key holds it);
           # a rerun repeats the closed settings only of a run whose loop was closed (its closed_loop section)
           "loop": (False, True, False, True),
           **dict.fromkeys(("closed_cells", "closed_seeds", "closed_hz", "closed_routes", "closed_steps",
                            "closed_agents", "closed_collisions", "closed_scenarios", "closed_lights"),
                         (False, True, False, False))}


def test_every_field_has_one_row_in_field_order_and_a_reason() -> None:
    assert check_table() == []
    assert [row.name for row in TABLE if row.gate is not Gate.FREE] == [n for n, seen in SEEN_BY.items() if seen[2]]
    assert set(CHANGED) == {f.name for f in fields(RunSettings)}  # this test changes every setting
    for row in TABLE:
        assert row.reason and row.flag.startswith("--drivedegrade-") and row.rerun in ("always", "changed", "never")
        assert setting(row.name) is row and row.default == getattr(DEFAULTS, row.name)


class Elsewhere(PlannerElsewhere):
    """A planner known only by its fingerprint: enough for a run key."""

    @property
    def info(self) -> PlannerInfo:
        return PlannerInfo(("CAM_FRONT",), "sha256:planner")

    @property
    def style(self) -> CallStyle:
        return CallStyle(False, False)


def run_key(settings: RunSettings) -> dict[str, object]:
    context = RunContext(None, [], settings, "sha256:data", None)  # type: ignore[arg-type]
    return dict(context.run_key(Elsewhere()))


def certificate(settings: RunSettings, recs: list, frames_scored: int = 8) -> dict:
    """A certificate built the way the controller builds one (analysis, its settings, the provenance)."""
    analysis = analyse_run(recs, groups=GROUPS, n_resamples=0, flat=settings.flat, seed=settings.seed,
                           seeds=settings.seeds, metric=settings.metric)
    analysis.settings.update(settings.certificate_settings())
    prov = cf.Provenance("demo", "sha256:planner", "sha256:data", settings.split, "2.0.0", seed=settings.seed,
                         frames=frames_scored, data_source=settings.data_source, frames_requested=settings.frames,
                         timeout=settings.timeout)
    cert = cf.build_certificate(analysis, prov)
    if settings.loop != "open":  # as the controller adds it (`report.closed_outputs`)
        cert["closed_loop"] = settings.closed_loop_settings()
    if settings.adaptive:  # as `report.outputs` writes it: the adaptive section records both settings
        cert["adaptive"] = {"enabled": True, "alpha": settings.alpha}
    return json.loads(json.dumps(cf.seal(cert)))


@pytest.fixture(scope="module")
def recs() -> list:
    return synthetic_run(8)[0]


def merge_error(tmp_path: Path, a: RunSettings, b: RunSettings) -> str:
    """What merging a shard of `a` with a shard of `b` says ("" when they merge as one run)."""
    folders = []
    for index, settings in ((1, a), (2, b)):
        prov = cf.Provenance("demo", "sha256:planner", "sha256:data", settings.split, "2.0.0", seed=settings.seed)
        manifest = mg.shard_manifest(index=index, count=2, planner="demo", key={"seed": 0}, provenance=prov,
                                     settings=replace(settings, shard=settings.shard or Shard(index, 2)),
                                     frames_total=8, cells=["clean"], missing=[], floor_l2=None,
                                     floor_ego_blind_l2=None, gt={}, data_root="/data")
        folder = tmp_path / f"{id(settings)}-{index}"
        folder.mkdir()
        (folder / mg.MANIFEST).write_text(json.dumps(manifest))
        folders.append(folder)
    try:
        mg.merge_shards(folders)
    except DriveDegradeError as exc:
        return str(exc) if "not from the same run" in str(exc) else ""
    return ""


@pytest.mark.parametrize("name", list(CHANGED))
def test_one_changed_setting_is_seen_by_the_run_key_merge_the_gate_and_reproduce(name, recs, tmp_path) -> None:
    row = setting(name)
    keyed, same_run, refused, rerun = SEEN_BY[name]
    other = replace(BASE, **{name: CHANGED[name]})
    assert other.differences(BASE) and [d.name for d in other.differences(BASE)] == [name]

    # the run key: the settings that change a stored cell (the frames key holds split and frames)
    assert (run_key(other) != run_key(BASE)) == keyed, name

    # merge: shards of one run share every setting but where the data lies and which shard each is
    said = merge_error(tmp_path, BASE, other)
    assert (name in said) == same_run, (name, said)

    # the gate: a baseline certified with BASE, this run with `other` (and the other way round)
    baseline = certificate(BASE, recs)
    for mine, theirs in ((other, baseline), (BASE, certificate(other, recs))):
        try:
            bl.check_baseline_compatible(theirs, spec_version="2.0.0", dataset_fingerprint="sha256:data",
                                         frames_scored=8, settings=mine)
            seen = ""
        except bl.BaselineError as exc:
            seen = str(exc)
        assert bool(seen) == refused, (name, seen)
        if refused and name != "seeds":  # the seed count has its own message
            assert row.flag in seen and row.label in seen

    # reproduce: the rerun's command line carries it (where it is a setting a rerun repeats)
    argv_base = rp.rerun_argv(baseline, Path("p.py"), ["clean"], Path("out"), None)
    argv_other = rp.rerun_argv(certificate(other, recs), Path("p.py"), ["clean"], Path("out"), None)
    assert (argv_base != argv_other) == rerun, name
    if rerun:
        assert row.flag in argv_other
        assert RunSettings.from_certificate(certificate(other, recs)) == replace(other, shard=None)


def test_the_gate_message_names_setting_both_values_and_option(recs) -> None:
    baseline = certificate(BASE, recs)
    with pytest.raises(bl.BaselineError, match=r"device: baseline 'cpu', this run 'cuda' \(--drivedegrade-device\)"):
        bl.check_baseline_compatible(baseline, spec_version="2.0.0", dataset_fingerprint="sha256:data",
                                     frames_scored=8, settings=replace(BASE, device="cuda"))
    # reuse unbatched changes no plan (the run key leaves it out): the gate lets it differ
    unbatched = replace(BASE, batch=1)
    bl.check_baseline_compatible(certificate(unbatched, recs), spec_version="2.0.0", dataset_fingerprint="sha256:data",
                                 frames_scored=8, settings=replace(unbatched, reuse=False))
    # the frames scored, not asked for: another count is refused whatever was asked
    with pytest.raises(bl.BaselineError, match=r"scored frames: baseline 8, this run 7 \(--drivedegrade-frames\)"):
        bl.check_baseline_compatible(baseline, spec_version="2.0.0", dataset_fingerprint="sha256:data",
                                     frames_scored=7, settings=BASE)


def test_run_key_keeps_the_exact_keys_of_stored_cells() -> None:
    key = run_key(DEFAULTS)
    assert list(key)[-1] == "seed" and key["seed"] == 0 and not {"seeds", "batch", "reuse", "device"} & set(key)
    full = run_key(RunSettings(seed=2, seeds=3, batch=4, reuse=False, device="cuda"))
    assert list(full)[-5:] == ["seed", "seeds", "batch", "reuse", "device"]
    assert [full[k] for k in list(full)[-5:]] == [2, 3, 4, False, "cuda"]
    assert "reuse" not in run_key(RunSettings(reuse=False))  # unbatched, reuse changes no plan


def test_rerun_argv_of_defaults_gives_split_seed_and_timeout_only() -> None:
    assert DEFAULTS.rerun_argv() == ["--drivedegrade-split", "val", "--drivedegrade-seed", "0",
                                     "--drivedegrade-timeout", "60"]
    assert "--drivedegrade-no-reuse" in RunSettings(reuse=False).rerun_argv()  # a flag that turns a default off


settings_values = st.builds(
    RunSettings,
    data=st.one_of(st.none(), st.sampled_from([Path("/d"), Path("rel/world")])),
    split=st.sampled_from(["val", "mini_val", "all"]),
    frames=st.one_of(st.none(), st.integers(1, 10**6)),
    seed=st.integers(0, 2**31), seeds=st.integers(1, 9), batch=st.integers(1, 4096), reuse=st.booleans(),
    device=st.sampled_from(["cpu", "cuda", "cuda:3"]),
    timeout=st.floats(0, 1e6, allow_nan=False), metric=st.sampled_from(["l2", "pdms"]),
    flat=st.floats(0, 1, allow_nan=False),
    shard=st.one_of(st.none(), st.integers(1, 9).flatmap(lambda n: st.builds(Shard, st.integers(1, n), st.just(n)))),
    prefetch=st.one_of(st.none(), st.integers(0, 64)),
)


@given(settings_values)
def test_builtins_round_trip_through_json(settings: RunSettings) -> None:
    data = settings.to_builtins()
    assert json.loads(json.dumps(data)) == data  # plain builtins
    assert RunSettings.from_builtins(json.loads(json.dumps(data))) == settings
    assert settings.differences(RunSettings.from_builtins(data)) == []


@given(settings_values)
def test_the_certificate_section_reads_back(settings: RunSettings) -> None:
    cert = {"dataset": {"split": settings.split, "frames_requested": settings.frames, "source": settings.data_source},
            "settings": json.loads(json.dumps(settings.certificate_settings()))}
    assert RunSettings.from_certificate(cert) == replace(settings, shard=None, prefetch=None)  # this machine's


def test_older_certificates_and_bad_builtins() -> None:
    old = {"dataset": {"split": "val", "frames": 12, "source": "embedded world"}, "settings": {"seed": 1}}
    got = RunSettings.from_certificate(old)  # before frames_requested, batch, reuse, device: the defaults
    assert got == RunSettings(frames=12, seed=1) and got.data_source == "embedded world"
    with pytest.raises(InvalidInput, match="'reuse'"):
        RunSettings.from_builtins({"reuse": "no"})
    with pytest.raises(InvalidInput, match="'shard'"):
        RunSettings.from_builtins({"shard": "3/2"})
