"""Checks of the TLS files a zenoh configuration names, before zenoh reads them.

zenoh reads the files itself when a session opens, and refuses a link whose certificate
fails; but a missing file, an expired certificate or one from another CA comes back from
it as "Unable to connect to any of [tls/…]" (the reason only in its log). Checked here
first, each problem is one line naming the key and the file (docs/deployment.md):

    cell.toml: [zenoh]: key 'tls_certificate': /etc/daq/daemon.pem: expired on 2020-01-02 …

The checks are of the files alone: readable, PEM, within their validity dates, the
certificate issued by the named CA (by name: zenoh's TLS verifies the signatures). The
same checks serve ``daq router`` for the file keys of zenoh's own JSON5 configuration.
"""

from __future__ import annotations

import ssl
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, Protocol

from daq.errors import ConfigError


class TlsSettings(Protocol):
    """What the checks read of ``daq.config.ZenohConfig`` (not imported: config imports
    this module)."""

    @property
    def listen(self) -> tuple[str, ...]: ...
    @property
    def connect(self) -> tuple[str, ...]: ...
    @property
    def tls_ca(self) -> str: ...
    @property
    def tls_certificate(self) -> str: ...
    @property
    def tls_private_key(self) -> str: ...


#: ``[zenoh]`` keys that name a file, and the zenoh ``transport/link/tls`` key each sets
TLS_KEYS: dict[str, str] = {
    "tls_ca": "root_ca_certificate",
    "tls_certificate": "connect_certificate",
    "tls_private_key": "connect_private_key",
}


@dataclass(frozen=True)
class Certificate:
    """What the checks need of a PEM certificate: names as ``((key, value), …)`` and its
    validity, UTC seconds."""

    subject: tuple[tuple[str, str], ...]
    issuer: tuple[tuple[str, str], ...]
    not_before_s: float
    not_after_s: float

    @property
    def common_name(self) -> str:
        return next((v for k, v in self.subject if k == "commonName"), "")


def _names(rdns: Any) -> tuple[tuple[str, str], ...]:
    return tuple(sorted((str(k), str(v)) for rdn in rdns for k, v in rdn))


def read_certificate(path: str) -> Certificate:
    """The first certificate of a PEM file; ``ValueError`` (the reason) if it is none,
    ``OSError`` if it cannot be read."""
    with open(path, "rb") as fh:  # the OSError names the file and the reason
        head = fh.read(1 << 20)
    if b"-----BEGIN CERTIFICATE-----" not in head:
        raise ValueError("not a PEM certificate (no BEGIN CERTIFICATE line)")
    # the stdlib's own decoder of a certificate file (what ssl.getpeercert() returns)
    decoder = ssl._ssl  # type: ignore[attr-defined]
    decode: Callable[[str], dict[str, Any]] = decoder._test_decode_cert
    try:
        doc = decode(path)
    except ssl.SSLError as exc:
        raise ValueError(f"not a readable PEM certificate ({exc.reason or exc})") from None
    return Certificate(
        subject=_names(doc.get("subject", ())),
        issuer=_names(doc.get("issuer", ())),
        not_before_s=ssl.cert_time_to_seconds(doc["notBefore"]),
        not_after_s=ssl.cert_time_to_seconds(doc["notAfter"]),
    )


def _utc(seconds: float) -> str:
    return datetime.fromtimestamp(seconds, UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def certificate_refusal(path: str, ca_path: str | None, now_s: float | None = None) -> str | None:
    """Why the certificate in ``path`` would be refused (None: it would not): unreadable,
    not PEM, expired, not valid yet, or not issued by the CA in ``ca_path``."""
    now_s = time.time() if now_s is None else now_s
    try:
        cert = read_certificate(path)
        ca = read_certificate(ca_path) if ca_path else None
    except OSError as exc:
        return f"{exc.filename or path}: {exc.strerror or exc}"
    except ValueError as exc:
        return f"{path}: {exc}"
    if cert.not_after_s < now_s:
        return f"{path}: expired on {_utc(cert.not_after_s)}"
    if cert.not_before_s > now_s:
        return f"{path}: not valid before {_utc(cert.not_before_s)}"
    if ca is not None and cert.issuer != ca.subject:
        issuer = ", ".join(f"{k}={v}" for k, v in cert.issuer)
        return f"{path}: not issued by the CA in {ca_path} (issuer: {issuer})"
    return None


def key_refusal(path: str) -> str | None:
    """Why ``path`` is not a PEM private key (None: it looks like one)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 20)
    except OSError as exc:
        return f"{path}: {exc.strerror or exc}"
    if b"PRIVATE KEY-----" not in head:
        return f"{path}: not a PEM private key (no BEGIN … PRIVATE KEY line)"
    return None


def check_tls_files(
    zc: TlsSettings, source: str = "<config>", origins: Mapping[str, str] | None = None
) -> None:
    """Refuse (``ConfigError``, one line naming the key and file) TLS settings that no
    ``tls/`` link could use: a file missing or unreadable, a certificate expired or from
    another CA, a certificate without its key, or ``tls/`` endpoints without a CA."""

    def fail(key: str, why: str) -> ConfigError:
        origin = (origins or {}).get(f"zenoh.{key}", source)
        return ConfigError(f"{origin}: [zenoh]: key {key!r}: {why}")

    uses_tls = any(e.startswith("tls/") for e in (*zc.listen, *zc.connect))
    if (uses_tls or zc.tls_certificate) and not zc.tls_ca:
        why = "tls/ endpoints" if uses_tls else "a tls_certificate"
        raise fail("tls_ca", f"{why} need the CA certificate (a PEM file), got none")
    if bool(zc.tls_certificate) != bool(zc.tls_private_key):
        missing = "tls_private_key" if zc.tls_certificate else "tls_certificate"
        raise fail(missing, "tls_certificate and tls_private_key go together, got only one")
    if zc.tls_ca:
        refusal = certificate_refusal(zc.tls_ca, None)
        if refusal is not None:
            raise fail("tls_ca", refusal)
    if zc.tls_certificate:
        refusal = certificate_refusal(zc.tls_certificate, zc.tls_ca)
        if refusal is not None:
            raise fail("tls_certificate", refusal)
        refusal = key_refusal(zc.tls_private_key)
        if refusal is not None:
            raise fail("tls_private_key", refusal)


def zenoh_tls_entries(zc: TlsSettings) -> dict[str, Any]:
    """zenoh config entries (path -> value) of the ``[zenoh] tls_*`` keys: the CA for
    verifying the router, and with a certificate, mutual authentication."""
    out: dict[str, Any] = {}
    for key, zkey in TLS_KEYS.items():
        value = getattr(zc, key)
        if value:
            out[f"transport/link/tls/{zkey}"] = value
    if zc.tls_certificate:
        out["transport/link/tls/enable_mtls"] = True
    return out
