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
#: The environment variable that signs every certificate of a run: a key file's path, or the PEM text itself
#: (a CI secret). ``--drivedegrade-sign-key`` wins over it.
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
    """The exact bytes a signature is taken over: the canonical body of `cert`."""
    return canonical_json(canonicalize({k: v for k, v in cert.items() if k not in UNSIGNED_KEYS}))


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


def read_key_source(source: str, where: str) -> bytes:
    """The PEM bytes of a signing key given as PEM text (``-----BEGIN``...) or as a path to a key file."""
    text = source.strip()
    if text.startswith("-----BEGIN"):
        return text.encode() + b"\n"
    try:
        return Path(text).expanduser().read_bytes()
    except FileNotFoundError:
        raise DriveDegradeError(f"{where}: no such key file {text!r}") from None
    except OSError as exc:
        raise DriveDegradeError(f"{where}: cannot read the key file {text!r}: {exc.strerror or exc}") from None


def load_private_key(pem: bytes, where: str) -> Ed25519PrivateKey:
    """An Ed25519 private key from PEM bytes; a clear error naming `where` otherwise."""
    from cryptography.hazmat.primitives import serialization

    ed25519 = _crypto()
    try:
        key = serialization.load_pem_private_key(pem, password=None)
    except (ValueError, TypeError) as exc:
        raise DriveDegradeError(f"{where}: not an unencrypted PEM private key ({exc}); make one with "
                                "`drivedegrade keygen NAME`") from None
    if not isinstance(key, ed25519.Ed25519PrivateKey):
        raise DriveDegradeError(f"{where}: a {type(key).__name__}, not an Ed25519 key; make one with "
                                "`drivedegrade keygen NAME`")
    return key


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
    body = {k: v for k, v in cert.items() if k not in UNSIGNED_KEYS}
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
