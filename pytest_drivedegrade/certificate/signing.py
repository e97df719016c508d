"""Ed25519 signatures of certificates (SPEC section 11, levels of proof).

An unsigned certificate's digest proves integrity only: anyone who edits it can recompute the SHA-256 and reseal
it. A signature proves who issued it: only the holder of the private key can produce it, and ``drivedegrade
verify CERT --public-key NAME.pub`` checks it.

What is signed: the canonical JSON (``certificate.canonical_json``) of every top-level key but ``digest``,
``section_digests`` and ``signature`` (the *canonical body*), after the floats are rounded, so the signed bytes
are exactly what the file stores. The ``signature`` section is added *before sealing*: the SHA-256 digest (and
``section_digests["signature"]``) covers it, so an edited signature is reported as an edit like any other.

The ``signature`` section: ``{"algorithm": "ed25519", "public_key_fingerprint": sha256 hex of the 32 raw public
key bytes, "signature": base64 of the 64-byte signature}``.
"""

from __future__ import annotations

import base64
import hashlib
import os
from collections.abc import Mapping
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

from ..errors import DriveDegradeError
from .seal import CertificateError, canonical_json, canonicalize

if TYPE_CHECKING:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

ALGORITHM = "ed25519"
#: The signing key for ``drivedegrade sign`` and ``merge`` when no key file is given: a key file's path, or the PEM
#: text itself (a CI secret; the only place a key's text is accepted). A pytest run REFUSES it in its own
#: environment (issue 37 H1): the planner could read it from /proc/<pid>/environ.
ENV_VAR = "DRIVEDEGRADE_SIGNING_KEY"
#: The keys the signature does not cover (the seal's own, and the signature itself).
UNSIGNED_KEYS = ("digest", "section_digests", "signature")
UNSIGNED_TEXT = "integrity only, unsigned"


class SignatureFailure(CertificateError):
    """A certificate whose signature is absent (when one was required), from another key, or does not verify
    (CLI exit 1)."""


def _crypto() -> ModuleType:
    try:
        from cryptography.hazmat.primitives.asymmetric import ed25519
    except ImportError:  # pragma: no cover - a declared dependency
        raise DriveDegradeError("signing needs the `cryptography` package: pip install 'cryptography>=41'") \
            from None
    return ed25519


def signed_body(cert: Mapping[str, object]) -> bytes:
    """The exact bytes a signature is taken over: the body of `cert` as stored, in canonical JSON. Not rounded
    again here (issue 20 L3): `sign` rounds the values to the stored form (`canonicalize`, 6 decimals, the form
    the verdict is decided on) before it signs, so a stored value edited below that rounding (0.919 ->
    0.9190004) no longer verifies."""
    return canonical_json({k: v for k, v in cert.items() if k not in UNSIGNED_KEYS})


def fingerprint(public_key: Ed25519PublicKey) -> str:
    """sha256 hex of the raw 32-byte Ed25519 public key."""
    from cryptography.hazmat.primitives import serialization

    raw = public_key.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    return hashlib.sha256(raw).hexdigest()


def keygen(name: str | os.PathLike[str]) -> tuple[Path, Path]:
    """Write ``NAME.key`` (PEM PKCS8, mode 0600) and ``NAME.pub`` (PEM SubjectPublicKeyInfo); refuses to
    overwrite either."""
    from cryptography.hazmat.primitives import serialization

    ed25519 = _crypto()
    key_path, pub_path = Path(f"{os.fspath(name)}.key"), Path(f"{os.fspath(name)}.pub")
    for p in (key_path, pub_path):
        if p.exists():
            raise DriveDegradeError(f"{p} already exists: not overwriting a key (remove it or choose another NAME)")
    private = ed25519.Ed25519PrivateKey.generate()
    pem = private.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                serialization.NoEncryption())
    pub = private.public_key().public_bytes(serialization.Encoding.PEM,
                                            serialization.PublicFormat.SubjectPublicKeyInfo)
    try:
        fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(pem)
        os.chmod(key_path, 0o600)  # whatever the umask
        pub_path.write_bytes(pub)
    except OSError as exc:
        raise DriveDegradeError(f"cannot write the key pair {key_path}, {pub_path}: {exc.strerror or exc}") from None
    return key_path, pub_path


def is_key_text(value: str) -> bool:
    """Whether `value` looks like key material rather than a path: PEM armour, a key's name, or more than one
    line. Such a value is never echoed nor recorded."""
    return "-----" in value or "PRIVATE KEY" in value.upper() or "\n" in value.strip()


def read_key_source(source: str, where: str, *, pem_allowed: bool = False, base: Path | None = None) -> bytes:
    """The PEM bytes of a signing key: from a key file's path (relative to `base` when given), or, where
    `pem_allowed` (the ``DRIVEDEGRADE_SIGNING_KEY`` variable only), the PEM text itself. A key's value never
    appears in an error: PEM text where a path belongs is refused without echoing it, and a path that names no
    file is not echoed either (it may be key text without its armour)."""
    text = source.strip()
    if is_key_text(text):
        if pem_allowed and text.startswith("-----BEGIN"):
            return text.encode() + b"\n"
        raise DriveDegradeError(f"{where}: expected the path of a key file, got what looks like key text (not "
                                f"shown); a key's text goes in the {ENV_VAR} environment variable, never on the "
                                "command line or in an ini file, where it would be recorded")
    path = Path(text).expanduser()
    path = base / path if base is not None else path
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise DriveDegradeError(f"{where}: no such key file (the value given is not shown, in case it was key "
                                "material); give the path of a key made by `drivedegrade keygen NAME`") from None
    except OSError as exc:
        raise DriveDegradeError(f"{where}: cannot read the key file {path}: {exc.strerror or exc}") from None


def key_file_path(source: str, base: Path | None = None) -> Path | None:
    """The key file `source` names (relative to `base`), or None when it is key text or names no file."""
    text = source.strip()
    if not text or is_key_text(text):
        return None
    path = Path(text).expanduser()
    path = base / path if base is not None else path
    return path if path.is_file() else None


def loose_permissions(path: Path) -> str | None:
    """A warning when the private key file `path` is readable (or writable) by its group or by others, else
    None: a signing key should be its owner's alone (``drivedegrade keygen`` writes mode 0600)."""
    try:
        mode = path.stat().st_mode & 0o777
    except OSError:
        return None
    if not mode & 0o077:
        return None
    return (f"the signing key file {path} is accessible to its group or others (mode {mode:04o}): anyone who can "
            f"read it can sign certificates in your name; restrict it with `chmod 600 {path}`")


def load_private_key(pem: bytes, where: str) -> Ed25519PrivateKey:
    """An Ed25519 private key from PEM bytes; a clear error naming `where` otherwise, which never quotes the
    key (the parser's own message is kept only when no line of the input appears in it)."""
    from cryptography.hazmat.primitives import serialization

    ed25519 = _crypto()
    try:
        key = serialization.load_pem_private_key(pem, password=None)
    except (ValueError, TypeError) as exc:
        raise DriveDegradeError(f"{where}: not an unencrypted PEM private key{_quiet_reason(exc, pem)}; make one "
                                "with `drivedegrade keygen NAME`") from None
    if not isinstance(key, ed25519.Ed25519PrivateKey):
        raise DriveDegradeError(f"{where}: a {type(key).__name__}, not an Ed25519 key; make one with "
                                "`drivedegrade keygen NAME`")
    return key


def _quiet_reason(exc: BaseException, pem: bytes) -> str:
    """`exc`'s message in parentheses, or nothing when it could carry any part of `pem` (a line of 8 or more
    characters of it, or anything longer than a sentence)."""
    reason = str(exc)
    lines = [line.strip() for line in pem.decode("utf-8", "replace").splitlines() if len(line.strip()) >= 8]
    if not reason or len(reason) > 300 or any(line in reason for line in lines) or is_key_text(reason):
        return ""
    return f" ({reason})"


def load_public_key(path: str | os.PathLike[str]) -> Ed25519PublicKey:
    """An Ed25519 public key from a PEM file (``NAME.pub``); ``CertificateError`` (exit 2) when unusable."""
    from cryptography.hazmat.primitives import serialization

    ed25519 = _crypto()
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise CertificateError(f"{path}: cannot read the public key: {exc.strerror or exc}") from None
    try:
        key = serialization.load_pem_public_key(data)
    except (ValueError, TypeError) as exc:
        raise CertificateError(f"{path}: not a PEM public key ({exc})") from None
    if not isinstance(key, ed25519.Ed25519PublicKey):
        raise CertificateError(f"{path}: a {type(key).__name__}, not an Ed25519 public key")
    return key


def sign(cert: Mapping[str, object], private_key: Ed25519PrivateKey) -> dict[str, Any]:
    """`cert` with its ``signature`` section (seal it afterwards: the digest then covers the signature)."""
    body = canonicalize({k: v for k, v in cert.items() if k not in UNSIGNED_KEYS})  # the stored form
    sig = private_key.sign(signed_body(body))
    return {**body, "signature": {"algorithm": ALGORITHM, "public_key_fingerprint": fingerprint(
        private_key.public_key()), "signature": base64.b64encode(sig).decode("ascii")}}


def verify_signature(cert: Mapping[str, object], public_key: Ed25519PublicKey, where: str = "certificate") -> str:
    """Check `cert`'s signature with `public_key`; its fingerprint when it verifies, ``SignatureFailure`` naming
    why otherwise (unsigned, another key, an unknown algorithm, a bad signature)."""
    from cryptography.exceptions import InvalidSignature

    section = cert.get("signature")
    if section is None:
        raise SignatureFailure(f"{where}: the certificate is unsigned ({UNSIGNED_TEXT}), so it cannot prove it was "
                               "issued by the holder of this key")
    if not isinstance(section, Mapping):
        raise SignatureFailure(f"{where}: signature: expected an object, found {type(section).__name__}")
    if section.get("algorithm") != ALGORITHM:
        raise SignatureFailure(f"{where}: signature.algorithm is {section.get('algorithm')!r}, expected {ALGORITHM!r}")
    expected = fingerprint(public_key)
    if section.get("public_key_fingerprint") != expected:
        raise SignatureFailure(f"{where}: signed by the key with fingerprint {section.get('public_key_fingerprint')}, "
                               f"not by the given public key (fingerprint {expected}): wrong key")
    try:
        raw = base64.b64decode(str(section.get("signature", "")), validate=True)
        public_key.verify(raw, signed_body(cert))
    except (ValueError, InvalidSignature):
        raise SignatureFailure(f"{where}: the signature does not verify with the given public key: the signed "
                               "content was changed after signing (or the signature was forged)") from None
    return expected

