"""A run never holds a signing key (issue 37 H1; issue 20 item 1 before it).

Deleting ``DRIVEDEGRADE_SIGNING_KEY`` from ``os.environ`` is not enough: the kernel keeps every process's initial
environment in ``/proc/<pid>/environ``, readable by any process of the same user, so a planner (in the controller
under ``-n 0``, in a worker reading its parent's, in a Ray actor scanning ``/proc/*/environ``) could read the key,
and a key file's path given to the run is as exposed. So a run given ``--drivedegrade`` REFUSES a key in its
environment, on its command line or in its ini file, before any conftest.py or planner file is imported, and says
how to sign instead: run unsigned, then ``drivedegrade sign CERT --key PATH`` (or ``drivedegrade merge --sign-key``)
in a step that runs no planner code. The command line the certificate records still has any key-looking value
replaced (`recorded_args`).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import pytest

FLAG = "--drivedegrade-sign-key"
DEST = "drivedegrade_sign_key"
#: What the recorded command line shows in place of a signing key option's value that is not a key file's path.
REDACTED = "<redacted>"
#: How to sign instead, the end of every refusal.
HOW_TO_SIGN = ("a run never holds the signing key, since the planner it runs could read it (from "
               "/proc/<pid>/environ or the key file): run unsigned, then sign the finished certificate in a step "
               "that runs no planner code: `drivedegrade sign REPORT/PLANNER/certificate.json --key PATH` (or "
               "`drivedegrade merge SHARDS --out DIR --sign-key PATH` for a sharded run)")


def refuse_run_key(config: pytest.Config) -> None:
    """A usage error when the run was given a signing key: ``$DRIVEDEGRADE_SIGNING_KEY`` set in its environment,
    or ``--drivedegrade-sign-key`` (or its ini value). Called before any conftest.py is imported. The key's
    value is never quoted."""
    from ..certificate.signing import ENV_VAR

    if os.environ.get(ENV_VAR):
        raise pytest.UsageError(f"{ENV_VAR} is set in the environment of this run (its value is not shown): "
                                f"{HOW_TO_SIGN}. Unset it for the run (`env -u {ENV_VAR} pytest ...`) and keep it "
                                "out of every process of the user the planner runs as")
    given = getattr(config.known_args_namespace, DEST, None)
    if given is None:
        try:
            given = config.getini(DEST) or None
        except (ValueError, KeyError):  # pragma: no cover - the ini value is not known yet
            given = None
    if given is not None:
        raise pytest.UsageError(f"{FLAG} is refused (its value is not shown): {HOW_TO_SIGN}")


def _redacted(value: str, here: Path) -> str:
    from ..certificate.signing import key_file_path

    return value if key_file_path(value, here) is not None else REDACTED


def recorded_args(args: Sequence[str], here: Path) -> list[str]:
    """`args` (pytest's command line) as the certificate and the report record them: the signing key option's
    value (``--drivedegrade-sign-key V``, ``=V``, or through ``-o drivedegrade_sign_key=V``) replaced by
    `REDACTED` unless it is the path of a key file, and any argument that looks like key text replaced too."""
    from ..certificate.signing import is_key_text

    out: list[str] = []
    pending = ""  # the option whose value comes next: the flag, or -o / --override-ini
    for arg in map(str, args):
        if pending == FLAG:
            arg = _redacted(arg, here)
        else:
            heads = (f"{DEST}=",) if pending else (f"{FLAG}=", f"-o{DEST}=", f"--override-ini={DEST}=")
            for head in heads:
                if arg.startswith(head):
                    arg = head + _redacted(arg[len(head):], here)
        pending = arg if arg in (FLAG, "-o", "--override-ini") else ""
        out.append(REDACTED if is_key_text(arg) else arg)
    return out
