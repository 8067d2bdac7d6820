"""Approvals through the agent (``POST /v1/approvals``): a signature the client made with its own key, checked;
or, for a user the agent authenticated, the agent's attestation signed with its own key (docs/change-control.md).

The HTTP side is one handler in ``agent/server.py``; everything it decides is here, with no HTTP in it.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

from ..errors import UsageError
from . import policy as policies
from .canonical import digest
from .check import check_approvals, same_person, stale
from .signature import MEANINGS, KeyFile, sign, verify
from .signers import AllowedSigners

KEY_FILE = "attest_ed25519"  # in STATE/agent/


class Refused(UsageError):
    """An approval the agent refuses: ``status`` is the HTTP status it answers with."""

    def __init__(self, message: str, status: int) -> None:
        super().__init__(message)
        self.status = status


def agent_key(folder: str) -> KeyFile:
    """The agent's own Ed25519 key (made on first use, readable by its user only)."""
    path = os.path.join(folder, KEY_FILE)
    if not os.path.exists(path):
        from cryptography.hazmat.primitives import serialization
        from cryptography.hazmat.primitives.asymmetric import ed25519

        pem = ed25519.Ed25519PrivateKey.generate().private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.OpenSSH, serialization.NoEncryption()
        )
        os.makedirs(folder, exist_ok=True)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o600)
        except FileExistsError:
            return KeyFile(path)  # another request made it a moment ago
        try:
            os.write(fd, pem)
            os.fsync(fd)
        finally:
            os.close(fd)
    return KeyFile(path)


def _attester(key: KeyFile, allowed: AllowedSigners | None) -> str:
    from .signature import ATTEST_NAMESPACE
    from .sshsig import key_line

    names = [
        s.principals[0]
        for s in (allowed.signers if allowed else ())
        if s.key == key.public_blob() and s.namespaces is not None and ATTEST_NAMESPACE in s.namespaces and s.principals
    ]
    if not names:
        import socket

        line = f'deployer-agent@{socket.gethostname()} namespaces="{ATTEST_NAMESPACE}" {key_line(key.key.public_key())}'
        where = allowed.path if allowed else "none configured yet: change_control.allowed_signers"
        raise Refused(
            f"this agent's key is not trusted to attest approvals: add this line to the site's "
            f"allowed_signers ({where}): {line}",
            409,
        )
    return names[0]


def approve(
    doc: Any, *, user: str | None, entry: Any, meaning: str, policy: policies.Policy | None, key_folder: str
) -> dict[str, Any]:
    """Add an approval (or a review) to the plan ``doc``: the client's ``entry`` when given (it must hold and be
    the authenticated user's, when there is one), else the agent's attestation for ``user``. Returns
    ``{digest, signature, plan, missing}``; Refused says why not."""
    if not isinstance(doc, dict) or not str(doc.get("schema", "")).startswith("deployer.plan/"):
        raise Refused("plan: a saved plan document (deployer plan ... --out PLAN.json) is needed", 400)
    if meaning not in MEANINGS or meaning == "authored":
        raise Refused(f"meaning {meaning!r}: approved or reviewed", 400)
    from ..errors import InputError
    from ..planning.planfile import plan_from_json

    try:  # an approval says a plan was read: one apply can run (as deployer validate checks it)
        plan_from_json(doc, "plan")
    except InputError as e:
        said = "; ".join(d.message for d in e.diagnostics[:5])
        raise Refused(f"plan: not a saved plan apply can run: {said}", 422) from None
    try:
        d = digest(doc)
    except (TypeError, ValueError) as e:
        raise Refused(f"plan: not a JSON document deployer can digest: {e}", 400) from None
    changed = stale(doc)
    if changed:
        raise Refused("the plan changed after it was signed: " + "; ".join(changed), 422)
    allowed = policy.signers if policy is not None else None
    change = doc.get("change") if isinstance(doc.get("change"), Mapping) else {}
    assert isinstance(change, Mapping)
    author = change.get("author")
    if entry is not None:
        v = verify(entry, d, allowed)
        if not v.holds:
            raise Refused(f"the signature {v.said()} does not hold: {v.why}", 422)
        if v.meaning != meaning:
            raise Refused(f"the signature says {v.meaning}, not {meaning}", 400)
        if user is not None and v.signer != user:
            raise Refused(f"the signature is {v.signer}'s, but you are {user}: sign as yourself", 403)
        signer, new = v.signer, dict(entry)
    else:
        if user is None:
            raise Refused(
                "an approval through the agent needs a named user (or a signature made with your own key: "
                "deployer approve PLAN.json --key KEY)",
                401,
            )
        signer, new = user, None
    if meaning == "approved" and signer == author:
        raise Refused(f"{signer} is the plan's author: an author cannot approve their own change", 403)
    if meaning == "approved" and entry is not None:  # a user's own signature: its key is one person too
        why = same_person(doc.get("signatures"), author, signer, v.key, d, allowed)
        if why is not None:
            raise Refused(why, 403)
    found = doc.get("signatures")
    sigs: list[Any] = found if isinstance(found, list) else []
    if any(isinstance(s, Mapping) and s.get("signer") == signer and s.get("meaning") == meaning for s in sigs):
        raise Refused(f"{signer} has signed it as {meaning} already", 409)
    if new is None:
        key = agent_key(key_folder)
        new = sign(d, signer, meaning, key, attested_by=_attester(key, allowed))
    plan = {**doc, "signatures": [*sigs, new]}
    return {
        "digest": d,
        "signature": new,
        "plan": plan,
        "missing": check_approvals(plan, policy) if policy is not None else [],
    }
