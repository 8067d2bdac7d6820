"""Change control (docs/change-control.md): a plan's digest, signatures over it, and whether a policy lets it run.

The surface others use:

``digest(doc)``
    ``sha256:HEX`` of a plan document without its ``signatures`` (what every signature covers).
``sign(digest, signer, meaning, key)``
    a signature entry (SSHSIG, ``ssh-keygen -Y`` compatible) by ``key`` (``signer_of(path)``).
``verify(entry, digest, allowed)``
    a ``Verdict``: who, what, when, and whether it holds against the trusted keys (``load_signers(path)``).
``check_approvals(doc, policy)``
    what the plan lacks to run under the site policy (``load_policy(path)``), each said; empty: it may run.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .canonical import digest
    from .check import check_approvals
    from .policy import Policy, Rule
    from .policy import load as load_policy
    from .signature import MEANINGS, Verdict, sign, signer_of, verify
    from .signers import load as load_signers

# loaded on first use: a run without change control never imports cryptography (about 60 ms)
_WHERE = {
    "digest": ("canonical", "digest"),
    "check_approvals": ("check", "check_approvals"),
    "Policy": ("policy", "Policy"),
    "Rule": ("policy", "Rule"),
    "load_policy": ("policy", "load"),
    "MEANINGS": ("signature", "MEANINGS"),
    "Verdict": ("signature", "Verdict"),
    "sign": ("signature", "sign"),
    "signer_of": ("signature", "signer_of"),
    "verify": ("signature", "verify"),
    "load_signers": ("signers", "load"),
}

__all__ = [
    "MEANINGS",
    "Policy",
    "Rule",
    "Verdict",
    "check_approvals",
    "digest",
    "load_policy",
    "load_signers",
    "sign",
    "signer_of",
    "verify",
]


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    module, attr = _WHERE[name]
    return getattr(importlib.import_module(f"{__name__}.{module}"), attr)
