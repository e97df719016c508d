"""The table of `--drivedegrade-*` flags (`OPTIONS`): each flag, its ini name, its help and its argparse
arguments, in one place; `options` parses and checks their values, the plugin registers them, and the docs'
reference page is generated from this table."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from ..constants import DEFAULT_FLAT, DEFAULT_TOLERANCE


@dataclass(frozen=True)
class OptionSpec:
    flag: str
    dest: str
    help: str
    argparse: dict[str, Any] = field(default_factory=dict)


ENABLE = "drivedegrade"
OPTIONS: tuple[OptionSpec, ...] = (
    OptionSpec("--drivedegrade", ENABLE, "certify the planner fixture of PATH (a .py file), or with no PATH the "
               "`planner` fixture of your conftest.py", {"nargs": "?", "const": "", "metavar": "PATH"}),
    OptionSpec("--drivedegrade-data", "drivedegrade_data", "nuScenes data root (default: the embedded world, "
               "rendered into pytest's cache on first use)", {"metavar": "DIR"}),
    OptionSpec("--drivedegrade-split", "drivedegrade_split", "split to score: val (default), train, mini_val, "
               "mini_train, all, junction (a world's junction scenes: drivedegrade world --junction-scenes N)",
               {"metavar": "SPLIT"}),
    OptionSpec("--drivedegrade-frames", "drivedegrade_frames", "score a deterministic subset of N frames: each "
               "scene's middle contiguous run, scenes sharing N by their frame counts (default: all scorable "
               "frames); a subset's intervals speak for those frames, not for the full run's", {"metavar": "N"}),
    OptionSpec("--drivedegrade-families", "drivedegrade_families", "comma-separated ladder families, the ego "
               "cells ego_noise, ego_blind and the command cells command_blind, command_swap (default: all sixteen, "
               "both ego cells and both command cells; a list runs only what it names)",
               {"metavar": "LIST"}),
    OptionSpec("--drivedegrade-severities", "drivedegrade_severities", "comma-separated severities 1..5 (default: "
               "all five)", {"metavar": "LIST"}),
    OptionSpec("--drivedegrade-seed", "drivedegrade_seed", "seed of every random corruption (default 0)",
               {"metavar": "INT"}),
    OptionSpec("--drivedegrade-batch", "drivedegrade_batch", "frames per predict_batch() call for a planner "
               "that has predict_batch and no reset (default 1: one predict() per frame)", {"metavar": "B"}),
    OptionSpec("--drivedegrade-no-reuse", "drivedegrade_no_reuse", "call the planner on every frame, also where "
               "its inputs equal the clean cell's (default: a deterministic planner without reset reuses the clean "
               "plan there, e.g. blackout of cameras it does not read)", {"action": "store_true"}),
    OptionSpec("--drivedegrade-device", "drivedegrade_device", "where the planner runs: cpu (default), cuda or "
               "cuda:N; a planner reads it as drivedegrade_context.device or $DRIVEDEGRADE_DEVICE",
               {"metavar": "DEVICE"}),
    OptionSpec("--drivedegrade-seeds", "drivedegrade_seeds", "run each random family's cells under N corruption "
               "seeds (seed, seed+1, ...) and fold them into the intervals (default 1)", {"metavar": "N"}),
    OptionSpec("--drivedegrade-report", "drivedegrade_report", "folder for <planner>/cells.csv, report.html and "
               "certificate.json (default reports)", {"metavar": "DIR"}),
    OptionSpec("--drivedegrade-baseline", "drivedegrade_baseline", "a stored certificate.json: fail cells and axes "
               "whose retention regressed", {"metavar": "FILE"}),
    OptionSpec("--drivedegrade-baseline-public-key", "drivedegrade_baseline_public_key", "require the baseline "
               "certificate to be signed by this Ed25519 public key (NAME.pub): an unsigned baseline, or one signed "
               "by another key or edited after signing, fails the run (default: the digest is checked, not who "
               "issued it)", {"metavar": "PUB"}),
    OptionSpec("--drivedegrade-baseline-partial", "drivedegrade_baseline_partial", "accept a baseline that does "
               "not cover this run (an incomplete run, cells or axes it lacks): gate on what both have and list "
               "what was not compared (default: such a baseline fails)", {"action": "store_true"}),
    OptionSpec("--drivedegrade-baseline-any-planner", "drivedegrade_baseline_any_planner", "accept a baseline "
               "certified for a planner of another name (default: refused; the same planner retrained keeps its "
               "name and needs no flag)", {"action": "store_true"}),
    OptionSpec("--drivedegrade-tolerance", "drivedegrade_tolerance", "allowed retention drop below the baseline "
               f"(default {DEFAULT_TOLERANCE:g})", {"metavar": "X"}),
    OptionSpec("--drivedegrade-no-resume", "drivedegrade_no_resume", "recompute every cell, reusing no stored "
               "result (default: a cell stored with the same run key is reused; the key holds the planner's "
               "fingerprint, which covers its file and the modules it imports from outside site-packages)",
               {"action": "store_true"}),
    OptionSpec("--drivedegrade-report-overwrite", "drivedegrade_report_overwrite", "replace the outputs of "
               "another planner (another planner file) that hold the report folder of this planner's name "
               "(default: refused)", {"action": "store_true"}),
    OptionSpec("--drivedegrade-flat", "drivedegrade_flat", "retention at or above which an axis counts as flat "
               f"(default {DEFAULT_FLAT:g})", {"metavar": "X"}),
    OptionSpec("--drivedegrade-shard", "drivedegrade_shard", "run shard I of N (1-based; scene-contiguous, "
               "balanced by frame count) and write its cells for `drivedegrade merge`", {"metavar": "I/N"}),
    OptionSpec("--drivedegrade-ray", "drivedegrade_ray", "run the cells' scene groups on a pool of Ray planner "
               "actors, each building the planner once: `local` starts a local cluster, `auto` joins a running one, "
               "or ray://HOST:PORT / HOST:PORT (needs the ray extra; not with -n)", {"metavar": "ADDRESS"}),
    OptionSpec("--drivedegrade-ray-actors", "drivedegrade_ray_actors", "planner actors of --drivedegrade-ray "
               "(default: 2 on a local cluster; on a cluster, its GPUs / --drivedegrade-ray-gpus, or its CPUs)",
               {"metavar": "N"}),
    OptionSpec("--drivedegrade-ray-gpus", "drivedegrade_ray_gpus", "GPUs each planner actor asks for (default 0; "
               "fractional allowed, e.g. 0.5 puts two actors on one GPU)", {"metavar": "G"}),
    OptionSpec("--drivedegrade-metric", "drivedegrade_metric", "the retention the verdict is put on: l2 (default, "
               "M = mean L2), pdms (the PDMS-like score), epdms (NAVSIM v2's extended score) or epdms2 (the two-stage "
               "EPDMS, with --drivedegrade-two-stage); all are always computed and reported",
               {"metavar": "METRIC"}),
    OptionSpec("--drivedegrade-ego-box", "drivedegrade_ego_box", "the ego box the PDMS and EPDMS score with: "
               "nuscenes (default, 4.084 x 1.85 m) or pacifica (NAVSIM's, 5.176 x 2.297 m)", {"metavar": "BOX"}),
    OptionSpec("--drivedegrade-two-stage", "drivedegrade_two_stage", "score every open-loop cell also by NAVSIM "
               "v2's two-stage pseudo-simulation: per frame, a second stage from start poses around where the plan "
               "ends, its cameras rendered there by the embedded world and corrupted by the cell; the cell's "
               "two-stage EPDMS (epdms2) and its retention join the outputs (embedded world only; not with "
               "--drivedegrade-ray, --drivedegrade-adaptive, --drivedegrade-seeds above 1 or a planner with "
               "reset())", {"action": "store_true"}),
    OptionSpec("--drivedegrade-timeout", "drivedegrade_timeout", "seconds one predict() call may take before the "
               "frame fails (default 60; 0 = no limit)", {"metavar": "SECONDS"}),
    OptionSpec("--drivedegrade-prefetch", "drivedegrade_prefetch", "frames decoded and corrupted ahead of the "
               "planner, on a thread beside it, while another thread scores the frame before (0: all in one thread, "
               "one frame after the other; every output is the same either way). Default: 2 where this machine "
               "has more cores than the processes running cells (the -n workers, the local Ray actors, or 1), "
               "else 0, so that the threads never slow the other workers", {"metavar": "N"}),
    OptionSpec("--drivedegrade-loop", "drivedegrade_loop", "open (default): the planner on the data's replayed frames; "
               "closed: it drives the embedded world through the degraded cameras (cells closed-clean, "
               "closed-blackout-s5, ...); both", {"metavar": "open|closed|both"}),
    OptionSpec("--drivedegrade-closed-cells", "drivedegrade_closed_cells", "closed-loop cells: slice (default: "
               "clean, gaussian_blur and motion_blur S3/S5, blackout S3 (the null control) and S5), all (the slice, "
               "every other family at S3 and S5 and command_swap), or a list such as clean,blackout-s5; "
               "command_swap drives the junction routes with their command swapped (straight on where the log "
               "turned) and reports the mean completion as 'command followed in closed loop'",
               {"metavar": "CELLS"}),
    OptionSpec("--drivedegrade-closed-seeds", "drivedegrade_closed_seeds", "corruption seeds every closed-loop "
               "route runs under (default 2)", {"metavar": "K"}),
    OptionSpec("--drivedegrade-closed-hz", "drivedegrade_closed_hz", "closed-loop planner calls per second: 1, 2 "
               "(default), 5 or 10; the plan is tracked at 10 Hz", {"metavar": "HZ"}),
    OptionSpec("--drivedegrade-closed-routes", "drivedegrade_closed_routes", "drive only the first N routes "
               "(default: every val scene of the world)", {"metavar": "N"}),
    OptionSpec("--drivedegrade-closed-agents", "drivedegrade_closed_agents", "the other road users of the closed "
               "loop: log (default: they replay their logs) or reactive (they follow their logged paths and brake "
               "for the ego by IDM)", {"metavar": "log|reactive"}),
    OptionSpec("--drivedegrade-closed-collisions", "drivedegrade_closed_collisions", "which collisions the "
               "closed-loop Driving Score counts: all (default: every collision, as the CARLA leaderboard) or "
               "at_fault (NAVSIM's rule: only those the ego is at fault for)", {"metavar": "all|at_fault"}),
    OptionSpec("--drivedegrade-closed-scenarios", "drivedegrade_closed_scenarios", "scenario routes the closed "
               "loop drives after the val routes (default 18: with the 6 light routes, 30 routes on the default "
               "world; 0: none)",
               {"metavar": "N"}),
    OptionSpec("--drivedegrade-closed-lights", "drivedegrade_closed_lights", "light routes (a traffic light whose "
               "red meets the ego) the closed loop drives after the scenario routes (default 6: 30 routes on the "
               "default world; 0: none)", {"metavar": "N"}),
    OptionSpec("--drivedegrade-closed-steps", "drivedegrade_closed_steps", "end each closed-loop run after N "
               "planner calls (default: at the route's end)", {"metavar": "N"}),
    OptionSpec("--drivedegrade-adaptive", "drivedegrade_adaptive", "certify at a fraction of the cost: each cell "
               "draws windows of frames in a seeded order and stops once its anytime-valid interval settles every "
               "decision the certificate takes from it; severities are scheduled (S5 first, then bisection); the "
               "certificate's `adaptive` section states the guarantee (see README, Adaptive certification)",
               {"action": "store_true"}),
    OptionSpec("--drivedegrade-alpha", "drivedegrade_alpha", "the adaptive run's error level: every interval and "
               "settled decision of the certificate holds together with probability >= 1 - alpha (default 0.05)",
               {"metavar": "X"}),
    OptionSpec("--drivedegrade-isolate", "drivedegrade_isolate", "run every planner call (build, predict, "
               "predict_batch, reset) in a child process started with a clean environment that receives only the "
               "frame's inputs, so planner code cannot find which cell is running from the stack, the garbage "
               "collector or PYTEST_CURRENT_TEST; the certificate records it (settings.planner_isolated). Needs a "
               "planner file; not with --drivedegrade-ray", {"action": "store_true"}),
    OptionSpec("--drivedegrade-dry-run", "drivedegrade_dry_run", "stop after the pre-flight check (the planner's "
               "declared needs against the data, one clean frame predicted and validated, the run's predictions "
               "counted and its wall time estimated): no cell runs", {"action": "store_true"}),
    OptionSpec("--drivedegrade-sign-key", "drivedegrade_sign_key", "REFUSED (as is DRIVEDEGRADE_SIGNING_KEY in "
               "the run's environment): the planner could read the key; sign the finished certificate with "
               "`drivedegrade sign CERT --key PATH`", {"metavar": "PATH"}),
)
