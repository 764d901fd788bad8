"""Firmware signing keys on the host: generate a pair, load a private key to sign images with.

Signing uses the ``cryptography`` package (extra ``sign``), imported only here and only when a
key is made or used; verifying needs nothing (``spiel_edge.protocol.signing``).

Files: the private key is PKCS#8 PEM (what ``openssl pkey`` reads), written with mode 0600;
the public key is the text the C build includes (``make FW_KEY=PATH.pub``): 32 bytes as
``0x..,`` under a comment naming its key id.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from spiel_edge.errors import InputError
from spiel_edge.protocol.signing import DEV_PUBLIC_KEY, key_id, public_key_text

__all__ = ["FirmwareKey", "generate_key", "is_dev_key", "load_private_key"]

DEV_MARK = "DEVELOPMENT KEY"
_DEV_COMMENT = (
    f"{DEV_MARK}: shipped with spiel-edge, its private half is public. Anyone can sign\n"
    "images for a board built with it. A release build (make RELEASE=1) refuses it."
)


def _crypto():
    try:
        from cryptography.hazmat.primitives import serialization
        from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
    except ImportError as exc:
        raise InputError(
            "signing firmware needs the 'sign' extra: pip install 'spiel-edge[sign]'"
        ) from exc
    return serialization, Ed25519PrivateKey


@dataclass(frozen=True)
class FirmwareKey:
    """A private key that signs images (``spiel_edge.protocol.signing.Signer``)."""

    _key: object
    public_key: bytes

    def sign(self, message: bytes) -> bytes:
        return self._key.sign(bytes(message))  # type: ignore[attr-defined]

    @property
    def key_id(self) -> str:
        return key_id(self.public_key).hex()


def is_dev_key(public_key: bytes) -> bool:
    return bytes(public_key) == DEV_PUBLIC_KEY


def load_private_key(path: str | os.PathLike) -> FirmwareKey:
    """The key in ``path`` (keygen's private key file); InputError in one line otherwise."""
    serialization, private_cls = _crypto()
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read the key ({exc.strerror or exc})") from exc
    try:
        key = serialization.load_pem_private_key(raw, password=None)
    except (ValueError, TypeError) as exc:
        raise InputError(
            f"{path}: not an unencrypted Ed25519 private key in PEM (the file keygen writes)"
        ) from exc
    if not isinstance(key, private_cls):
        raise InputError(f"{path}: a {type(key).__name__}, not an Ed25519 private key")
    public = key.public_key().public_bytes(
        serialization.Encoding.Raw, serialization.PublicFormat.Raw
    )
    return FirmwareKey(key, public)


def generate_key(private_path: Path, public_path: Path, *, dev: bool = False) -> FirmwareKey:
    """A new key pair: the private key written with mode 0600 (never readable by others, not
    even for a moment), the public key as the C build takes it. Existing files are not
    overwritten (the caller decides)."""
    serialization, private_cls = _crypto()
    key = private_cls.generate()
    pem = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    public = key.public_key().public_bytes(
        serialization.Encoding.Raw, serialization.PublicFormat.Raw
    )
    note = f"# {_DEV_COMMENT.replace(chr(10), chr(10) + '# ')}\n".encode() if dev else b""
    fd = os.open(private_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as fh:
        fh.write(note + pem)
    comment = _DEV_COMMENT if dev else "Built into the boot stage: make FW_KEY=" + public_path.name
    public_path.write_text(public_key_text(public, comment=comment))
    return FirmwareKey(key, public)
