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

from .canonical import digest
from .check import check_approvals
from .policy import Policy, Rule
from .policy import load as load_policy
from .signature import MEANINGS, Verdict, sign, signer_of, verify
from .signers import load as load_signers

__all__ = ["MEANINGS", "Policy", "Rule", "Verdict", "check_approvals", "digest", "load_policy", "load_signers",
           "sign", "signer_of", "verify"]
