"""Trusted keys: an OpenSSH ``allowed_signers`` file (ssh-keygen(1), ALLOWED SIGNERS).

One line per key: ``PRINCIPALS [OPTIONS] KEYTYPE BASE64 [COMMENT]``. Principals are comma-separated
patterns (``*`` and ``?``; ``!`` before one excludes); options ``namespaces="a,b"``, ``valid-after=``,
``valid-before=`` (``YYYYMMDD[HHMM[SS]]``, UTC with a trailing ``Z``, else local time). ``cert-authority``
lines are skipped: certificates are not supported. A line that cannot be read is an error at its position.
"""

from __future__ import annotations

import base64
import binascii
import datetime
import re
import time
from dataclasses import dataclass

from ..errors import Diagnostic, InputError

KEY_TYPES = (
    "ssh-ed25519",
    "ssh-rsa",
    "ecdsa-sha2-nistp256",
    "ecdsa-sha2-nistp384",
    "ecdsa-sha2-nistp521",
    "sk-ssh-ed25519@openssh.com",
    "sk-ecdsa-sha2-nistp256@openssh.com",
    "ssh-dss",
)
MAX_FILE = 1 << 20


@dataclass(frozen=True)
class Signer:
    """One line: who (patterns), which key, where it may sign (namespaces) and when."""

    principals: tuple[str, ...]
    key: bytes  # the key's wire form
    namespaces: tuple[str, ...] | None  # None: any namespace (the option was not written)
    valid_after: datetime.datetime | None
    valid_before: datetime.datetime | None
    line: int

    def names(self, principal: str) -> bool:
        return matches(principal, self.principals)


@dataclass(frozen=True)
class AllowedSigners:
    path: str
    signers: tuple[Signer, ...]
    skipped: tuple[str, ...] = ()  # lines not used, and why (certificate authorities)

    def trusted(
        self,
        principal: str,
        key: bytes,
        namespace: str,
        when: datetime.datetime | None,
        *,
        explicit_namespace: bool = False,
    ) -> str | None:
        """None when ``key`` may sign as ``principal`` in ``namespace`` at ``when``; else why not.
        ``explicit_namespace``: the line must name the namespace (an agent attesting for others)."""
        lines = [s for s in self.signers if s.key == key]
        if not lines:
            return f"its key is not in {self.path}"
        named = [s for s in lines if s.names(principal)]
        if not named:
            return f"its key is in {self.path} (line {lines[0].line}) but not for {principal!r}"
        why = ""
        for s in named:
            if s.namespaces is None and explicit_namespace:
                why = f"line {s.line} of {self.path} does not name the namespace {namespace} (needed to attest)"
                continue
            if s.namespaces is not None and not matches(namespace, s.namespaces):
                why = f"line {s.line} of {self.path} does not allow the namespace {namespace}"
                continue
            if when is not None and s.valid_after is not None and when < s.valid_after:
                why = f"signed before the key's valid-after on line {s.line} of {self.path}"
                continue
            if when is not None and s.valid_before is not None and when >= s.valid_before:
                why = f"signed after the key's valid-before on line {s.line} of {self.path}"
                continue
            return None
        return why

    def knows(self, principal: str) -> bool:
        """Whether any line names ``principal`` (whatever its key)."""
        return any(s.names(principal) for s in self.signers)

    def principals_of(self, key: bytes) -> list[str]:
        """The plain names (no patterns) a key is listed for."""
        return [
            p
            for s in self.signers
            if s.key == key
            for p in s.principals
            if not p.startswith("!") and not set(p) & set("*?")
        ]


def matches(name: str, patterns: tuple[str, ...]) -> bool:
    """OpenSSH's pattern lists: any pattern matches and no negated one does."""
    hit = False
    for p in patterns:
        negated = p.startswith("!")
        rx = "".join(".*" if c == "*" else "." if c == "?" else re.escape(c) for c in (p[1:] if negated else p))
        if re.fullmatch(rx, name, re.DOTALL):
            if negated:
                return False
            hit = True
    return hit


def _tokens(line: str) -> list[str]:
    """Words split at blanks outside double quotes (options carry quoted lists)."""
    out: list[str] = []
    word: list[str] = []
    quoted = any_ = False
    for c in line:
        if c == '"':
            quoted, any_ = not quoted, True
            word.append(c)
        elif c in " \t" and not quoted:
            if word or any_:
                out.append("".join(word))
            word, any_ = [], False
        else:
            word.append(c)
    if quoted:
        raise ValueError("a quote is not closed")
    if word:
        out.append("".join(word))
    return out


def _options(text: str) -> dict[str, str]:
    out: dict[str, str] = {}
    parts: list[str] = []
    cur: list[str] = []
    quoted = False
    for c in text:
        if c == '"':
            quoted = not quoted
        elif c == "," and not quoted:
            parts.append("".join(cur))
            cur = []
            continue
        cur.append(c)
    parts.append("".join(cur))
    for p in parts:
        k, sep, v = p.partition("=")
        k = k.strip().lower()
        if k not in ("namespaces", "valid-after", "valid-before", "cert-authority"):
            raise ValueError(f"unknown option {k!r}")
        v = v.strip()
        if sep and len(v) >= 2 and v[0] == v[-1] == '"':
            v = v[1:-1]
        out[k] = v
    return out


def _when(text: str) -> datetime.datetime:
    """``YYYYMMDD[HHMM[SS]][Z]``: UTC with ``Z``, else local time (as OpenSSH)."""
    utc = text.endswith("Z")
    digits = text[:-1] if utc else text
    if not digits.isdigit() or len(digits) not in (8, 12, 14):
        raise ValueError(f"{text!r} is not YYYYMMDD[HHMM[SS]][Z]")
    t = datetime.datetime.strptime(digits.ljust(14, "0"), "%Y%m%d%H%M%S")
    if utc:
        return t.replace(tzinfo=datetime.UTC)
    return datetime.datetime.fromtimestamp(time.mktime(t.timetuple()), datetime.UTC)


def parse(path: str, text: str) -> AllowedSigners:
    from .sshsig import SigError, public_from_blob

    signers, skipped, errors = [], [], []
    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        try:
            words = _tokens(line)
            if len(words) < 3:
                raise ValueError("expected PRINCIPALS [OPTIONS] KEYTYPE BASE64")
            principals = tuple(p for p in words[0].strip('"').split(",") if p)
            opts: dict[str, str] = {}
            rest = words[1:]
            if rest[0] not in KEY_TYPES:
                opts = _options(rest[0])
                rest = rest[1:]
            if len(rest) < 2 or rest[0] not in KEY_TYPES:
                raise ValueError(f"expected a key type ({', '.join(KEY_TYPES[:5])}) after the principals")
            if "cert-authority" in opts:
                skipped.append(f"line {n}: a certificate authority (certificates are not supported)")
                continue
            blob = base64.b64decode(rest[1], validate=True)
            if rest[0].startswith(("sk-", "ssh-dss")):
                skipped.append(f"line {n}: {rest[0]} keys are not supported")
                continue
            public_from_blob(blob)  # a key we can use, of the type the line says
            ns = opts.get("namespaces")
            signers.append(
                Signer(
                    principals,
                    blob,
                    None if ns is None else tuple(x for x in ns.split(",") if x),
                    _when(opts["valid-after"]) if "valid-after" in opts else None,
                    _when(opts["valid-before"]) if "valid-before" in opts else None,
                    n,
                )
            )
        except (ValueError, binascii.Error, SigError) as e:
            errors.append(Diagnostic(path, n, 1, f"allowed signers: {e}"))
    if errors:
        raise InputError(errors)
    return AllowedSigners(path, tuple(signers), tuple(skipped))


def load(path: str) -> AllowedSigners:
    return parse(path, _read(path))


def _read(path: str) -> str:
    from .files import read_bounded

    data = read_bounded(path, MAX_FILE, "the allowed signers file")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise InputError([Diagnostic(path, 0, 0, "the allowed signers file is not UTF-8 text")]) from None
