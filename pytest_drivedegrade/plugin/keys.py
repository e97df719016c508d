"""The run's signing key, kept out of everything the run records or runs (issue 20, item 1).

A key's value is never recorded: ``--drivedegrade-sign-key`` (and its ini value) takes a path only, PEM text is
taken only from ``DRIVEDEGRADE_SIGNING_KEY``, errors never quote a key, and the command line the certificate and
the report record has the option's value replaced unless it is a key file's path. The variable is read at
start-up and deleted from the environment before any conftest.py or planner file is imported, so neither the
planner nor the xdist workers and Ray actors started later (which inherit the environment) can read it; only the
controller signs, so a worker never loads the key.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import pytest

from ..errors import DriveDegradeError

FLAG = "--drivedegrade-sign-key"
DEST = "drivedegrade_sign_key"
#: What the recorded command line shows in place of a signing key option's value that is not a key file's path.
REDACTED = "<redacted>"


def _stash_key() -> pytest.StashKey[str | None]:
    from . import SIGNING_KEY_ENV  # the entry module's key: the same in every copy of this module

    return SIGNING_KEY_ENV


def take_from_environment(config: pytest.Config) -> str | None:
    """``$DRIVEDEGRADE_SIGNING_KEY`` as it was at start-up, deleted from ``os.environ`` the first time this runs
    for `config` (the value is kept on the config for `signing_key_pem`)."""
    from ..certificate.signing import ENV_VAR

    key = _stash_key()
    if key not in config.stash:
        config.stash[key] = os.environ.pop(ENV_VAR, None) or None
    return config.stash[key]


def _configured(config: pytest.Config) -> str | None:
    """The option's value: the command line's, else the ini file's."""
    got = config.getoption(DEST, default=None)
    return got if got is not None else (config.getini(DEST) or None)


def signing_key_pem(config: pytest.Config, here: Path) -> bytes | None:
    """The PEM bytes of the run's Ed25519 signing key, checked now so that a bad key is a usage error before any
    cell runs: ``--drivedegrade-sign-key PATH`` (relative to `here`), else ``$DRIVEDEGRADE_SIGNING_KEY`` (a path
    or the PEM text). None in an xdist worker (only the controller signs) and for an unsigned run. A key file
    readable by its group or others is warned about."""
    from ..certificate.signing import ENV_VAR, key_file_path, load_private_key, loose_permissions, read_key_source

    from_env = take_from_environment(config)
    if hasattr(config, "workerinput"):
        return None
    raw, where, pem_allowed = _configured(config), FLAG, False
    if raw is None:
        raw, where, pem_allowed = from_env, ENV_VAR, True
        if raw is None:
            return None
    try:
        pem = read_key_source(str(raw), where, pem_allowed=pem_allowed, base=here)
        load_private_key(pem, where)
    except DriveDegradeError as exc:
        raise pytest.UsageError(str(exc)) from None
    path = key_file_path(str(raw), here)
    loose = loose_permissions(path) if path is not None else None
    if loose:
        config.issue_config_time_warning(pytest.PytestConfigWarning(f"{where}: {loose}"), stacklevel=2)
    return pem


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
