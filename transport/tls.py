"""TLS for the live transports (Python's :mod:`ssl` over asyncio streams): the contexts both ends use.

The server loads a certificate chain and its key (``quadcast server --tls-cert/--tls-key``); the client verifies
the server against the system's CAs, or a CA file of its own (``--tls-ca``, e.g. the server's self-signed
certificate), or not at all (``--insecure``: encrypted, but open to a man in the middle -- for tests and trusted
networks). TLS 1.2 is the floor. The server starts TLS on an accepted connection itself
(:meth:`asyncio.StreamWriter.start_tls`), so the handshake counts against the connection's pre-auth limits and
handshake timeout (:mod:`quadcast.protocol.admission`).
"""
from __future__ import annotations

import ssl
from pathlib import Path

__all__ = ["server_context", "client_context"]


def server_context(cert: str | Path, key: str | Path | None = None) -> ssl.SSLContext:
    """A server-side context with the certificate chain ``cert`` (PEM) and its private key ``key`` (PEM; None:
    in ``cert``). ValueError naming the file when one is missing or unusable."""
    for name, path in (("--tls-cert", cert), ("--tls-key", key)):
        if path is not None and not Path(path).is_file():
            raise ValueError(f"{name} {path}: no such file")
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(str(cert), None if key is None else str(key))
    except (ssl.SSLError, OSError) as exc:
        raise ValueError(f"--tls-cert {cert} / --tls-key {key}: cannot load the certificate and key ({exc})") from None
    return ctx


def client_context(ca: str | Path | None = None, insecure: bool = False) -> ssl.SSLContext:
    """A client-side context: verify the server against ``ca`` (a PEM file of trusted certificates) or the system's
    CAs, hostname included; ``insecure`` verifies nothing (encryption only)."""
    if ca is not None and insecure:
        raise ValueError("--tls-ca and --insecure: give one or the other")
    if ca is not None and not Path(ca).is_file():
        raise ValueError(f"--tls-ca {ca}: no such file")
    try:
        ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=None if ca is None else str(ca))
    except (ssl.SSLError, OSError) as exc:
        raise ValueError(f"--tls-ca {ca}: cannot load it ({exc})") from None
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    if insecure:
        ctx.check_hostname = False
        ctx.verify_mode = ssl.CERT_NONE
    return ctx
