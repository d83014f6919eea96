"""The TLS of the link between the front door and the SDK's server (`apps.foxglove.front_door`):
a certificate for 127.0.0.1 made at each start, signed by an authority made with it and
trusted by the front door alone. A browser that finds the SDK's internal port cannot complete a
handshake (it trusts no such authority), so every connection goes through the front door."""

from __future__ import annotations

import ssl
from dataclasses import dataclass

from cryptography.hazmat.primitives import serialization

from archery.mesh.credentials import issue, new_authority

__all__ = ["INNER_HOST", "InnerTls", "inner_tls"]

INNER_HOST = "127.0.0.1"  # where the SDK's server listens
_DAYS = 3650.0  # the certificate lives as long as the process: no expiry while it runs


@dataclass(frozen=True)
class InnerTls:
    """The SDK server's certificate and key (PEM, the key PKCS#8) and the front door's context
    that trusts that certificate only."""

    cert: bytes
    key: bytes
    client: ssl.SSLContext


def inner_tls() -> InnerTls:
    """A new authority, certificate and key for `INNER_HOST` (a few ms)."""
    authority = new_authority(days=_DAYS, name="archery foxglove front door")
    key, cert = issue(authority, "archery foxglove", hosts=(INNER_HOST,), days=_DAYS)
    key_pem = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    cert_pem = cert.public_bytes(serialization.Encoding.PEM)
    client = ssl.create_default_context(
        cadata=authority.cert.public_bytes(serialization.Encoding.PEM).decode()
    )
    return InnerTls(cert=cert_pem, key=key_pem, client=client)
