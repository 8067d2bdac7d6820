"""The agent's credentials as files, TLS, and where it may listen (docs/operations.md).

Every request needs a credential, in every mode (access.py checks it): a user's (``--users FILE``), the site's
token (``--token-file``), or the one the agent made itself when given neither (``local_token``: then it listens
on loopback only). Beyond loopback only with users or a token given, and TLS: a token sent in clear text over a
plant network is a token given away. ``--tls-client-ca`` asks clients for a certificate that CA signed; the
users file maps certificates to users.
"""

from __future__ import annotations

import ipaddress
import os
import socket
import ssl
import sys

from ..errors import UsageError


def read_token(path: str, what: str = "--token-file") -> str:
    """The token: the file's first line, without whitespace; at least 16 characters."""
    try:
        with open(path, encoding="utf-8") as f:
            text = f.readline().strip()
    except (OSError, UnicodeDecodeError) as e:
        raise UsageError(f"{what} {path}: cannot read it: {getattr(e, 'strerror', None) or e}") from None
    if len(text) < 16:
        raise UsageError(
            f"{what} {path}: the token must be at least 16 characters on the first line "
            "(e.g. python3 -c 'import secrets; print(secrets.token_urlsafe(32))')"
        )
    if any(c.isspace() or not c.isprintable() for c in text):
        raise UsageError(f"{what} {path}: the token must not contain spaces or control characters")
    if os.name == "posix" and what == "--token-file":
        try:
            mode = os.stat(path).st_mode
        except OSError:
            mode = 0
        if mode & 0o077:  # said, not refused: systemd's LoadCredential= copies are 0400 anyway
            print(
                f"warning: {what} {path} can be read by other users of this machine (chmod 600 it)",
                file=sys.stderr,
                flush=True,
            )
    return text


def server_ssl(cert: str | None, key: str | None, client_ca: str | None = None) -> ssl.SSLContext | None:
    """The TLS context of ``--tls-cert``/``--tls-key`` (both or neither); TLS 1.2 at least. ``client_ca``
    (``--tls-client-ca``): clients may present a certificate, which this CA must have signed (one it did not
    sign ends the handshake); a client without one logs in with a token."""
    if cert is None and key is None:
        if client_ca is not None:
            raise UsageError("--tls-client-ca needs TLS: --tls-cert FILE --tls-key FILE")
        return None
    if cert is None or key is None:
        raise UsageError("--tls-cert and --tls-key go together")
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(cert, key)
    except (OSError, ssl.SSLError) as e:
        raise UsageError(
            f"--tls-cert {cert} --tls-key {key}: cannot load them: {getattr(e, 'strerror', None) or e}"
        ) from None
    if client_ca is not None:
        try:
            ctx.load_verify_locations(cafile=client_ca)
        except (OSError, ssl.SSLError) as e:
            raise UsageError(
                f"--tls-client-ca {client_ca}: cannot load it: {getattr(e, 'strerror', None) or e}"
            ) from None
        ctx.verify_mode = ssl.CERT_OPTIONAL
    return ctx


def is_loopback(host: str) -> bool:
    """Whether every address ``host`` names is a loopback address (a name is resolved)."""
    try:
        addresses = {ipaddress.ip_address(host)}
    except ValueError:
        try:
            addresses = {ipaddress.ip_address(str(a[4][0]).split("%")[0]) for a in socket.getaddrinfo(host, None)}
        except OSError as e:
            raise UsageError(f"--listen {host}: cannot resolve it: {e}") from None
    return bool(addresses) and all(a.is_loopback for a in addresses)


def check_listen(host: str, *, token: bool, tls: bool, listen: str) -> None:
    """Beyond loopback only with users or a token given (``token``), and TLS; refused before anything starts."""
    if is_loopback(host):
        return
    if not token:
        raise UsageError(
            f"--listen {listen}: without --token-file or --users the agent listens on loopback only "
            "(127.0.0.1, ::1), with a token of its own for its own user; give --users FILE (or "
            "--token-file) and --tls-cert/--tls-key"
        )
    if not tls:
        raise UsageError(
            f"--listen {listen}: beyond loopback the agent needs TLS as well as the token "
            "(--tls-cert FILE --tls-key FILE): a token sent in clear text is given away"
        )
