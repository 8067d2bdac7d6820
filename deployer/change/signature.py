"""Signatures of a person (or an agent for a person) over a digest: the statement, making one, checking one.

The statement is the canonical JSON of ``{schema, digest, signer, meaning, time[, attested_by]}``; a
signature entry is the statement's members plus ``format``, ``namespace`` and ``signature`` (the armored
SSHSIG). docs/change-control.md says what each means.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..errors import UsageError
from . import sshsig
from .canonical import canonical, parse_time, utc_now
from .signers import AllowedSigners

STATEMENT = "deployer.statement/1"
MEANINGS = ("authored", "reviewed", "approved")
NAMESPACE = "deployer"
ATTEST_NAMESPACE = "deployer-attest"  # an agent signing for the user it authenticated
_STATEMENT_KEYS = ("schema", "digest", "signer", "meaning", "time", "attested_by")


def statement(
    digest: str, signer: str, meaning: str, *, time: str | None = None, attested_by: str | None = None
) -> dict[str, str]:
    if meaning not in MEANINGS:
        raise UsageError(f"meaning {meaning!r}: one of {', '.join(MEANINGS)}")
    if not signer.strip() or any(c.isspace() or c == "," for c in signer):
        raise UsageError(f"signer {signer!r}: a name without blanks or commas (as in allowed_signers)")
    st = {"schema": STATEMENT, "digest": digest, "signer": signer, "meaning": meaning, "time": time or utc_now()}
    if attested_by is not None:
        st["attested_by"] = attested_by
    return st


def statement_bytes(entry: Mapping[str, Any]) -> bytes:
    """What was signed: the canonical JSON of the statement members of ``entry``."""
    return canonical({k: entry[k] for k in _STATEMENT_KEYS if k in entry})


def entry_of(st: Mapping[str, str], armor: str) -> dict[str, str]:
    """The signature entry kept in a plan's ``signatures`` (or a FILE.signatures.json)."""
    ns = ATTEST_NAMESPACE if "attested_by" in st else NAMESPACE
    return {**st, "format": "sshsig", "namespace": ns, "signature": armor}


# ---- keys that sign ------------------------------------------------------------------------------


class KeyFile:
    """A private key file: OpenSSH's format (``ssh-keygen``; an encrypted one with its passphrase) or PEM."""

    def __init__(self, path: str, passphrase: bytes | None = None) -> None:
        from cryptography.hazmat.primitives import serialization

        try:
            with open(path, "rb") as f:
                data = f.read(1 << 20)
        except OSError as e:
            raise UsageError(f"--key {path}: cannot read it: {e.strerror}") from None
        self.path = path
        try:
            if b"BEGIN OPENSSH PRIVATE KEY" in data:
                key: Any = serialization.load_ssh_private_key(data, passphrase)
            else:
                key = serialization.load_pem_private_key(data, passphrase)
        except TypeError:  # encrypted and no passphrase, or a passphrase for a plain key
            raise (
                NeedsPassphrase(path)
                if passphrase is None
                else UsageError(f"--key {path}: the key is not encrypted, but a passphrase was given")
            ) from None
        except ValueError as e:
            why = "wrong passphrase" if passphrase is not None else str(e)
            raise UsageError(f"--key {path}: cannot read the private key ({why})") from None
        except Exception as e:  # UnsupportedAlgorithm and the like: say it, never a traceback
            raise UsageError(f"--key {path}: cannot use the key: {e}") from None
        if not isinstance(key, sshsig.PrivateKey):
            raise UsageError(f"--key {path}: an {type(key).__name__}: Ed25519, ECDSA or RSA keys sign")
        self.key = key

    def sign(self, message: bytes, namespace: str) -> str:
        return sshsig.sign(self.key, message, namespace)

    def public_blob(self) -> bytes:
        return sshsig.key_blob(self.key.public_key())


class NeedsPassphrase(UsageError):
    def __init__(self, path: str) -> None:
        super().__init__(
            f"--key {path}: the key is encrypted: its passphrase is needed (asked on a terminal; "
            "or give the public key, KEY.pub, and ssh-keygen signs with your ssh-agent)"
        )
        self.path = path


class SshKeygen:
    """``ssh-keygen -Y sign`` with a public key file: the private key stays in ssh-agent (or a token)."""

    def __init__(self, public_path: str) -> None:
        self.path = public_path
        exe = shutil.which("ssh-keygen")
        if exe is None:
            raise UsageError(
                f"--key {public_path} is a public key: signing with it needs ssh-keygen (OpenSSH), "
                "which is not installed"
            )
        self.exe = exe
        try:
            with open(public_path, encoding="utf-8") as f:
                words = f.read(65536).split()
            import base64

            self.blob = base64.b64decode(words[1], validate=True)
        except (OSError, IndexError, ValueError, UnicodeDecodeError):
            raise UsageError(f"--key {public_path}: not an OpenSSH public key line") from None

    def sign(self, message: bytes, namespace: str) -> str:
        proc = subprocess.run(
            [self.exe, "-Y", "sign", "-q", "-f", self.path, "-n", namespace],
            input=message,
            capture_output=True,
            timeout=300,
            check=False,
        )
        if proc.returncode != 0:
            why = proc.stderr.decode("utf-8", "replace").strip() or f"exit code {proc.returncode}"
            raise UsageError(f"ssh-keygen -Y sign -f {self.path}: {why}")
        return proc.stdout.decode("ascii", "replace")

    def public_blob(self) -> bytes:
        return self.blob


Signer = KeyFile | SshKeygen


def signer_of(path: str, passphrase: bytes | None = None) -> Signer:
    """A public key file signs through ssh-keygen (and ssh-agent); a private key file here."""
    try:
        with open(path, "rb") as f:
            head = f.read(64)
    except OSError as e:
        raise UsageError(f"--key {path}: cannot read it: {e.strerror}") from None
    if head.startswith((b"ssh-", b"ecdsa-", b"sk-")):
        return SshKeygen(path)
    return KeyFile(path, passphrase)


def sign(digest: str, signer: str, meaning: str, key: Signer, *, attested_by: str | None = None) -> dict[str, str]:
    """A signature entry by ``key`` over ``digest``, naming ``signer`` and ``meaning``; the time is now."""
    st = statement(digest, signer, meaning, attested_by=attested_by)
    armor = key.sign(statement_bytes(st), ATTEST_NAMESPACE if attested_by else NAMESPACE)
    entry = entry_of(st, armor)
    got = sshsig.parse(armor)  # ssh-keygen signed with the key we think it did
    if got.public_key != key.public_blob():
        raise UsageError("the signature was made with another key than the one given")
    return entry


# ---- checking --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Verdict:
    """One signature checked: who, what, when, and whether it holds (``why`` when it does not)."""

    signer: str
    meaning: str
    time: str
    digest: str
    holds: bool
    why: str = ""
    attested_by: str | None = None
    key: str = ""  # the key's fingerprint

    def said(self) -> str:
        via = f" (attested by {self.attested_by})" if self.attested_by else ""
        return f"{self.meaning} by {self.signer}{via} at {self.time}"

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "signer": self.signer,
            "meaning": self.meaning,
            "time": self.time,
            "digest": self.digest,
            "holds": self.holds,
        }
        if self.why:
            out["why"] = self.why
        if self.attested_by:
            out["attested_by"] = self.attested_by
        if self.key:
            out["key"] = self.key
        return out


def verify(entry: Any, digest: str, allowed: AllowedSigners | None) -> Verdict:
    """Check one signature entry against the content's ``digest`` now and the trusted keys (None: the
    signature alone, whose signer nobody vouches for: it does not hold)."""
    if not isinstance(entry, Mapping):
        return Verdict("?", "?", "?", "?", False, "a signature entry must be an object")
    fields = {k: entry.get(k) for k in ("signer", "meaning", "time", "digest")}
    shown = {k: v if isinstance(v, str) else "?" for k, v in fields.items()}
    attested = entry.get("attested_by")

    def no(why: str, key: str = "") -> Verdict:
        return Verdict(
            shown["signer"],
            shown["meaning"],
            shown["time"],
            shown["digest"],
            False,
            why,
            attested if isinstance(attested, str) else None,
            key,
        )

    if any(not isinstance(v, str) for v in fields.values()) or (attested is not None and not isinstance(attested, str)):
        return no("signer, meaning, time and digest must be texts")
    if entry.get("schema") != STATEMENT or entry.get("format") != "sshsig":
        return no(f"not a {STATEMENT} signature in the sshsig format")
    if shown["meaning"] not in MEANINGS:
        return no(f"meaning {shown['meaning']!r} is not one of {', '.join(MEANINGS)}")
    when = parse_time(shown["time"])
    if when is None:
        return no(f"time {shown['time']!r} is not an ISO 8601 time")
    if shown["digest"] != digest:
        return no(
            f"it was made over other content ({shown['digest'][:19]}...): the content changed after it was signed"
        )
    namespace = ATTEST_NAMESPACE if attested is not None else NAMESPACE
    try:
        sig = sshsig.parse(str(entry.get("signature")))
        sshsig.verify(sig, statement_bytes(entry), namespace)
    except sshsig.SigError as e:
        return no(str(e))
    fp = sshsig.fingerprint(sig.public_key)
    if allowed is None:
        return no("no allowed signers file to trust its key by (--allowed-signers, or the policy's)", fp)
    principal = attested if isinstance(attested, str) else shown["signer"]
    why = allowed.trusted(principal, sig.public_key, namespace, when, explicit_namespace=attested is not None)
    if why is not None:
        return no(f"{why} ({fp})", fp)
    return Verdict(
        shown["signer"],
        shown["meaning"],
        shown["time"],
        digest,
        True,
        "",
        attested if isinstance(attested, str) else None,
        fp,
    )


def default_signer() -> str:
    """The operating system's user: what ``--signer`` is when not given."""
    from ..portable import user_name

    return user_name()
