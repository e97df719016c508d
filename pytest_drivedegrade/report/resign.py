"""`drivedegrade sign`: a finished run's certificate signed after the run, in a process that runs no planner code
(issue 37 H1), with report.html's seal rows rewritten for the new digest."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey


def sign_file(path: str | os.PathLike[str], private_key: Ed25519PrivateKey,
              problems: list[str] | None = None) -> tuple[str, str, list[Path]]:
    """Sign the certificate file `path` in place, after the run, in a process that runs no planner code (issue 37
    H1: a run never holds the key). The certificate must verify first (its digest, and no entry in `problems`,
    the arithmetic checks the caller ran); one already signed is refused, since a second signature would
    replace the first. ``report.html`` beside it has its seal rows rewritten for the new digest. Returns (the
    public key's fingerprint, the sealed digest, the files written)."""
    from ..atomic import atomic_write_set
    from ..certificate.seal import CertificateError, certificate_text, seal, verify
    from ..certificate.signing import sign
    from .html import reseal_page

    where = os.fspath(path)
    cert = verify(where)
    if problems:
        raise CertificateError(f"{where}: not signed: its digest verifies but its arithmetic does not add up "
                               f"({'; '.join(problems)}); `drivedegrade verify {where}` names every field")
    section = cert.get("signature")
    if section is not None:
        held = section.get("public_key_fingerprint") if isinstance(section, Mapping) else None
        raise CertificateError(f"{where}: already signed (by the key with fingerprint {held}); a certificate is "
                               "signed once, by the run's issuer")
    sealed = seal(sign(cert, private_key))
    digest, fingerprint = str(sealed["digest"]), str(sealed["signature"]["public_key_fingerprint"])
    files = {Path(where): certificate_text(sealed).encode("utf-8")}
    page_path = Path(where).parent / "report.html"
    if page_path.is_file():
        page = reseal_page(page_path.read_text(encoding="utf-8"), digest, fingerprint)
        if page is not None:
            files = {page_path: page.encode("utf-8"), **files}  # the certificate last: it vouches for the rest
    atomic_write_set(files)
    return fingerprint, digest, list(files)
