"""The private key a `drivedegrade` command signs with: a flag's PATH, else $DRIVEDEGRADE_SIGNING_KEY. These
commands run no planner code, so holding the key here is safe (a run refuses one: issue 37)."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey


def signing_key(args: argparse.Namespace, flag: str = "--sign-key") -> Ed25519PrivateKey | None:
    """`flag`'s PATH (--sign-key, or sign's --key), else $DRIVEDEGRADE_SIGNING_KEY (a path or the PEM text: key
    text only there), else None; a key file readable by its group or others is warned about."""
    import os

    from ..certificate.signing import ENV_VAR, key_file_path, load_private_key, loose_permissions, read_key_source

    given = getattr(args, flag.lstrip("-").replace("-", "_"))
    source, where = (given, flag) if given else (os.environ.get(ENV_VAR), ENV_VAR)
    if not source:
        return None
    key = load_private_key(read_key_source(source, where, pem_allowed=where == ENV_VAR), where)
    path = key_file_path(source)
    loose = loose_permissions(path) if path is not None else None
    if loose:
        print(f"drivedegrade: warning: {where}: {loose}", file=sys.stderr)
    return key
