"""The agent's users file (``deployer agent --users FILE``): named users, their roles and credentials.

    users:
      alice:
        name: Alice Martin                  # the printed name records show
        roles: [engineer, approver]
        token: {id: 3f9a1c2b7d, scrypt: "$scrypt$ln=14,r=8,p=1$SALT$HASH"}
        certificate: {cn: alice.martin}     # or {sha256: HEX}: a TLS client certificate (--tls-client-ca)
        disabled: false

A token is ``dpl_ID_SECRET`` (ID names the user's entry, SECRET is 256 random bits) and is shown once, when it is
made; the file keeps only its scrypt hash (``hashlib.scrypt``, RFC 7914, with a random salt of 16 bytes; compared
with ``hmac.compare_digest``). The file is checked like every input file (``schemas/users.schema.json``, every
problem as ``FILE:LINE:COL: error: ...``); ``edit`` is the one way the commands and the agent change it: under a
lock, checked before it is written, written whole or not at all, never leaving no enabled admin where there was
one (``NoAdminLeft``). Standard library and the project's loaders only.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import hmac
import os
import re
import secrets
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

from ..errors import Diagnostic, InputError, UsageError
from .roles import ROLES

T = TypeVar("T")
PREFIX = "dpl"
SCRYPT = (14, 8, 1)  # log2(N), r, p: RFC 7914's interactive figures; 16 MiB, 0.15-0.2 s a check on the test machine
MAX_SCRYPT = (20, 32, 16)  # a file's own figures beyond these are refused (a check must not take the gateway)
_HASH = re.compile(r"^\$scrypt\$ln=(\d+),r=(\d+),p=(\d+)\$([A-Za-z0-9+/]+={0,2})\$([A-Za-z0-9+/]+={0,2})$")
_NUMBERISH = re.compile(r"[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)(?:[eE][-+]?[0-9]+)?")
_TOKEN = re.compile(rf"^{PREFIX}_([0-9a-f]{{10}})_([A-Za-z0-9_-]{{20,100}})$")
HEADER = (
    "# The deployer agent's users (deployer agent --users FILE; docs/agent.md). Tokens are kept as scrypt\n"
    "# hashes only. Changed by `deployer users ...`, which rewrites this file (comments are not kept:\n"
    "# use description:); the running agent takes a change up at its next request.\n"
)


class NoAdminLeft(UsageError):
    """An edit that would leave no enabled admin where there was one: refused (nobody could manage users)."""


@dataclass(frozen=True)
class User:
    name: str
    roles: frozenset[str]
    full_name: str | None = None
    token_id: str | None = None
    token_hash: str | None = None
    cert_cn: str | None = None
    cert_sha256: str | None = None
    disabled: bool = False

    def to_json(self) -> dict[str, Any]:
        """What the API and ``deployer users list`` show of a user (never the token's hash)."""
        cert = {"cn": self.cert_cn} if self.cert_cn else {"sha256": self.cert_sha256} if self.cert_sha256 else None
        return {
            "user": self.name,
            "name": self.full_name,
            "roles": sorted(self.roles, key=ROLES.index),
            "token": self.token_id is not None,
            "certificate": cert,
            "disabled": self.disabled,
        }


# ---- tokens -----------------------------------------------------------------------------------------------


def new_token() -> tuple[str, dict[str, str]]:
    """A new token and its entry for the file (its id and hash)."""
    token_id = secrets.token_hex(5)
    token = f"{PREFIX}_{token_id}_{secrets.token_urlsafe(32)}"
    return token, {"id": token_id, "scrypt": hash_token(token)}


def hash_token(token: str, cost: tuple[int, int, int] = SCRYPT) -> str:
    ln, r, p = cost
    salt = secrets.token_bytes(16)
    digest = hashlib.scrypt(token.encode(), salt=salt, n=1 << ln, r=r, p=p, dklen=32, maxmem=_maxmem(ln, r))
    return f"$scrypt$ln={ln},r={r},p={p}${_b64(salt)}${_b64(digest)}"


def check_token(token: str, hashed: str) -> bool:
    """Whether ``token`` is the one ``hashed`` was made of (constant-time compare of the digests)."""
    m = _HASH.match(hashed)
    if m is None:
        return False
    ln, r, p = (int(x) for x in m.group(1, 2, 3))
    try:
        salt, want = _unb64(m.group(4)), _unb64(m.group(5))
    except ValueError:
        return False
    got = hashlib.scrypt(token.encode(), salt=salt, n=1 << ln, r=r, p=p, dklen=len(want), maxmem=_maxmem(ln, r))
    return hmac.compare_digest(got, want)


def token_id(token: str) -> str | None:
    """The id a token names (None: not a users-file token)."""
    m = _TOKEN.match(token)
    return m.group(1) if m else None


def _maxmem(ln: int, r: int) -> int:
    return 128 * r * (1 << ln) * 2 + (1 << 20)


def _b64(b: bytes) -> str:
    return base64.b64encode(b).decode().rstrip("=")  # PHC strings carry base64 without its padding


def _decodes(text: str) -> bool:
    try:
        return len(_unb64(text)) > 0
    except ValueError:
        return False


def _unb64(text: str) -> bytes:
    return base64.b64decode(text + "=" * (-len(text) % 4), validate=True)


# ---- the file -----------------------------------------------------------------------------------------------


def load(path: str) -> dict[str, User]:
    """The users of the file at ``path`` (InputError with every problem at its position)."""
    from ..load import yamlsrc

    data, src = yamlsrc.load(path)
    return parse(data, src)


def parse(data: Any, src: Any) -> dict[str, User]:
    """The users of a loaded document (``src``: its positions); every problem at once."""
    from ..load import schema

    if not isinstance(data, dict):
        raise InputError([src.error((), "a users file is a mapping: users: {NAME: {roles: [...], ...}}")])
    errors: list[Diagnostic] = schema.validate(data, "users", src)
    if errors:
        raise InputError(errors)
    out: dict[str, User] = {}
    seen: dict[tuple[str, str], str] = {}
    for name, spec in (data.get("users") or {}).items():
        token = spec.get("token") or {}
        cert = spec.get("certificate") or {}
        for key, value in (
            ("token id", token.get("id")),
            ("certificate cn", cert.get("cn")),
            ("certificate sha256", str(cert.get("sha256") or "").lower() or None),
        ):
            if value is None:
                continue
            other = seen.setdefault((key, value), name)
            if other != name:
                part = ("token", "id") if key == "token id" else ("certificate", key.split()[1])
                errors.append(
                    src.error(
                        ("users", name, *part), f"{key} {value!r} is {other}'s already: one credential names one user"
                    )
                )
        m = _HASH.match(token.get("scrypt") or "")
        if m is not None and any(int(v) > top for v, top in zip(m.group(1, 2, 3), MAX_SCRYPT, strict=True)):
            errors.append(
                src.error(
                    ("users", name, "token", "scrypt"),
                    "scrypt figures beyond ln=20, r=32, "
                    "p=16: a check would take the gateway's memory or minutes (make a new token)",
                )
            )
        elif m is not None and (
            int(m.group(1)) < 1
            or int(m.group(2)) < 1
            or int(m.group(3)) < 1
            or not _decodes(m.group(4))
            or len(_unb64(m.group(5)) if _decodes(m.group(5)) else b"") < 16
        ):
            errors.append(
                src.error(
                    ("users", name, "token", "scrypt"),
                    "not a hash deployer made (figures of "
                    "at least 1, a salt and a digest of 16 bytes or more, in base64)",
                )
            )
        out[name] = User(
            name,
            frozenset(spec["roles"]),
            spec.get("name"),
            token.get("id"),
            token.get("scrypt"),
            cert.get("cn"),
            str(cert["sha256"]).lower() if cert.get("sha256") else None,
            bool(spec.get("disabled", False)),
        )
    if errors:
        raise InputError(errors)
    return out


def dump(doc: Mapping[str, Any]) -> str:
    import yaml

    class Dumper(yaml.SafeDumper):
        pass

    def text(dumper: yaml.SafeDumper, value: str) -> yaml.ScalarNode:
        # a token id of digits with one 'e' ("12345e6789") is a number to YAML 1.2 readers, ours included: quoted
        style = "'" if _NUMBERISH.fullmatch(value) else None
        return dumper.represent_scalar("tag:yaml.org,2002:str", value, style=style)

    Dumper.add_representer(str, text)
    return HEADER + yaml.dump(
        dict(doc), Dumper=Dumper, sort_keys=False, default_flow_style=None, allow_unicode=True, width=200
    )


def enabled_admins(users: Mapping[str, User]) -> set[str]:
    return {u.name for u in users.values() if "admin" in u.roles and not u.disabled}


@contextlib.contextmanager
def _locked(path: str) -> Iterator[None]:
    """The file's edit lock (``PATH.lock``, an OS lock dropped when its holder dies): one edit at a time."""
    from ..portable import O_BINARY, O_CLOEXEC
    from ..state import oslock

    try:
        fd = os.open(path + ".lock", os.O_RDWR | os.O_CREAT | O_CLOEXEC | O_BINARY, 0o600)
    except OSError as e:
        raise UsageError(
            f"cannot change the users file {path}: its lock {path}.lock: {e.strerror or e} (the agent "
            "changes it only where it may write; else change it as its owner: --users FILE)"
        ) from None
    try:
        oslock.backend().lock(fd)
        yield
    finally:
        os.close(fd)


def edit(path: str, change: Callable[[dict[str, Any]], T], *, create: bool = False) -> tuple[T, dict[str, User]]:
    """Change the file: ``change`` gets the document (``{"users": {...}}``) and edits it in place; the result is
    checked as the file is (InputError, nothing written), then written whole (mode 0600 when new). Returns what
    ``change`` returned and the users now. UsageError: no such file (without ``create``), or an edit that
    leaves no enabled admin where there was one."""
    from ..load import yamlsrc
    from ..state.durable import write_atomic

    folder = os.path.dirname(os.path.abspath(path))
    if create:
        os.makedirs(folder, exist_ok=True)
    with _locked(path):
        if os.path.exists(path):
            data, src = yamlsrc.load(path)
            before = parse(data, src)
        elif create:
            data, before = {"users": {}}, {}
        else:
            raise UsageError(f"no users file {path} (deployer users add NAME --role admin --users {path} makes it)")
        data.setdefault("users", {})
        result = change(data)
        text = dump(data)
        after = parse(*_reload(path, text))
        if enabled_admins(before) and not enabled_admins(after):
            raise NoAdminLeft("refused: no enabled admin would be left (give another user the role admin first)")
        with contextlib.suppress(FileExistsError):  # a new file: its owner's only (write_atomic keeps the mode)
            os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        write_atomic(path, text, what="the users file")
    return result, after


def _reload(path: str, text: str) -> tuple[Any, Any]:
    from ..load import yamlsrc

    return yamlsrc.load(path, text)
