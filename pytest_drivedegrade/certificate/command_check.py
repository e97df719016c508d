"""`drivedegrade verify` on the certificate's ``command`` section (spec 5, issue 40): the command-following figure,
its 95 % interval and its label recomputed from the per-frame sums the certificate stores (``sums``: each scored
junction frame's <plan change, expert change> and |expert change|^2, kept to the certificate's six decimals, which
is what the run computed the figure from: `scoring.command.swap_probe`), under the run's seed and resample count,
resampling the scenes the section's ``scenes`` names (each sum's scene; a section without it, as spec 5.0.0's
first certificates, resamples frames as they did). Spec 5.0.0 had no ``command-partial`` label: a 5.0.x
certificate's "undetermined" between the lines 0.1 and 0.5 is what its rule said, and verifies.

The sums themselves come from the plans, which a certificate does not carry; the cell's ``plans_digest`` and the
record digests tie them to the stored records. A certificate without the section (spec 4 and earlier, or a run
without command_swap) has nothing to check here.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import replace

import numpy as np

from ..constants import COMMAND_SWAP
from ..scoring.command import from_sums

TOLERANCE = 1e-6  #: the certificate's precision


def _number(v: object) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else None


def _sums(section: Mapping[str, object]) -> tuple[np.ndarray, np.ndarray] | str:
    rows = section.get("sums")
    if not isinstance(rows, list) or not all(isinstance(r, list) and len(r) == 2 and all(_number(x) is not None
                                                                                            for x in r) for r in rows):
        return "command.sums: not a list of [number, number] pairs, so the figure cannot be recomputed"
    return np.array([float(r[0]) for r in rows]), np.array([float(r[1]) for r in rows])


def _scenes(section: Mapping[str, object], n: int) -> list[int] | None | str:
    rows = section.get("scenes")
    if rows is None:
        return None
    if not isinstance(rows, list) or len(rows) != n or not all(isinstance(x, int) and not isinstance(x, bool)
                                                               and x >= 0 for x in rows):
        return f"command.scenes: not a list of {n} scene indices (one per sum), so the interval cannot be recomputed"
    return rows


def check_command(cert: Mapping[str, object]) -> list[str]:
    """Every figure of the ``command`` section that its stored sums do not give, as ``command.<field>:
    certificate says X, its sums give Y``; empty without the section."""
    section = cert.get("command")
    if section is None:
        return []
    if not isinstance(section, Mapping):
        return [f"command: certificate says {section!r}, not a section"]
    got = _sums(section)
    if isinstance(got, str):
        return [got]
    scenes = _scenes(section, len(got[0]))
    if isinstance(scenes, str):
        return [scenes]
    settings = cert.get("settings")
    settings = settings if isinstance(settings, Mapping) else {}
    seed, n = settings.get("seed", 0), settings.get("n_resamples", 0)
    intervals = settings.get("intervals")
    if isinstance(intervals, Mapping) and intervals.get("computed") is False:
        n = 0
    want = from_sums(*got, n_resamples=int(n) if isinstance(n, int) else 0, seed=int(seed) if isinstance(seed, int)
                     else 0, scenes=scenes)
    if str(cert.get("spec_version", "")).startswith("5.0.") and want.label == "command-partial":
        want = replace(want, label="undetermined")  # spec 5.0.0 had no partial label: between its lines it said so
    problems = []
    for key, value in (("following", want.value), ("low", want.low), ("high", want.high)):
        said = _number(section.get(key))
        if (said is None) != (value is None) or (said is not None and value is not None
                                                 and abs(said - value) > TOLERANCE):
            problems.append(f"command.{key}: certificate says {section.get(key)!r}, its sums give {value!r}")
    for key, exact in (("label", want.label), ("frames", want.frames)):
        if section.get(key) != exact:
            problems.append(f"command.{key}: certificate says {section.get(key)!r}, its sums give {exact!r}")
    junction = section.get("junction_frames")
    if not isinstance(junction, int) or isinstance(junction, bool) or junction < want.frames:
        problems.append(f"command.junction_frames: certificate says {junction!r}, fewer than the {want.frames} "
                        "frames it scored")
    cells = cert.get("cells")
    if isinstance(cells, list) and not any(isinstance(c, Mapping) and c.get("cell") == COMMAND_SWAP for c in cells):
        problems.append(f"command: the certificate has a command section but no {COMMAND_SWAP!r} cell")
    return problems
