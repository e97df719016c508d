"""`drivedegrade merge --baseline BASE`: the gate of a sharded run (issue 37: a baseline under a shard is refused,
since a shard scores part of the frames, and nothing gated the merged run). The merged certificate is compared
with the baseline as `--drivedegrade-baseline` compares a whole run's (`plugin.controller.gate`), and any cell or
axis regression beyond the tolerance fails the merge (exit 1)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from ..errors import DriveDegradeError


def load_verified_baseline(path: Path, public_key: Path | None) -> Mapping[str, object]:
    """The baseline certificate, verified as `drivedegrade verify` does (digest, arithmetic, and the signature
    when `public_key` is given); a DriveDegradeError naming why otherwise."""
    from ..certificate.consistency import check_consistency
    from ..certificate.seal import CertificateError, verify
    from ..certificate.signing import load_public_key, verify_signature

    try:
        cert = verify(path)
        if public_key is not None:
            verify_signature(cert, load_public_key(public_key), where=str(path))
    except CertificateError as exc:
        raise DriveDegradeError(f"--baseline: {exc}") from None
    problems = check_consistency(cert)
    if problems:
        raise DriveDegradeError(f"--baseline: {path}: refused: the digest verifies but the arithmetic does not add "
                                f"up ({'; '.join(problems[:3])}): it cannot be trusted as a baseline")
    return cert


def gate_merged(cert: Mapping[str, object], baseline: Mapping[str, object],
                tolerance: float) -> tuple[list[str], bool]:
    """(the lines to print, whether the merge fails): every axis and cell regression beyond `tolerance` fails,
    as does anything `plugin.controller.gate` fails a run for (another planner, a part not compared)."""
    from ..scoring.baseline import BaselineError, compare_to_baseline
    from .controller import gate

    if cert.get("adaptive"):
        raise DriveDegradeError("--baseline: an adaptive sharded run is gated by its sequential test, which needs the "
                                "whole run: gate it unsharded (--drivedegrade-adaptive --drivedegrade-baseline)")
    lines, failed = gate(cert, baseline, tolerance)
    try:
        cells = compare_to_baseline(cert, baseline, tolerance)["cells"]
    except BaselineError:
        cells = []  # `gate` has said why
    lines = [f"REGRESSION {reg.message()}" for reg in cells] + lines
    return lines, failed or bool(cells)
