"""The site's change-control policy: an inventory's ``change_control:`` member (docs/change-control.md).

Which inventories count: ``--policy FILE`` (or ``DEPLOYER_POLICY``) and the run's own ``--inventory``; where
several do, each requirement is the strictest of them. A device's rule is ``require`` made stricter by every
group of the inventory's device with that URL and unit.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .signers import AllowedSigners

ENV = "DEPLOYER_POLICY"
DEFAULT_BACKLOG = 10_000


@dataclass(frozen=True)
class Rule:
    """What a change needs. ``why``: where it came from (``site.yaml require``, ``group packaging``)."""

    approvals: int = 0
    reason: bool = False
    ticket: bool = False
    signed_inputs: bool = False
    why: tuple[str, ...] = ()

    def stricter(self, other: Rule) -> Rule:
        return Rule(
            max(self.approvals, other.approvals),
            self.reason or other.reason,
            self.ticket or other.ticket,
            self.signed_inputs or other.signed_inputs,
            tuple(dict.fromkeys(self.why + other.why)),
        )

    @property
    def needs_plan(self) -> bool:
        """Approvals, a reason or a ticket live in a plan: a plain recipe cannot carry them."""
        return self.approvals > 0 or self.reason or self.ticket

    @property
    def empty(self) -> bool:
        return not (self.needs_plan or self.signed_inputs)

    def said(self) -> str:
        parts = [f"{self.approvals} approval{'s' if self.approvals != 1 else ''}"] if self.approvals else []
        parts += [
            w
            for w, on in (("a reason", self.reason), ("a ticket", self.ticket), ("signed inputs", self.signed_inputs))
            if on
        ]
        return ", ".join(parts) + (f" ({'; '.join(self.why)})" if self.why else "")


@dataclass(frozen=True)
class Audit:
    trail: str | None = None
    syslog: str | None = None
    syslog_ca: str | None = None
    max_backlog: int = DEFAULT_BACKLOG


@dataclass(frozen=True)
class Policy:
    sources: tuple[str, ...] = ()
    default: Rule = Rule()
    groups: dict[str, Rule] = field(default_factory=dict)
    devices: tuple[tuple[str, str, int, tuple[str, ...]], ...] = ()  # name, URL as described, unit, groups
    signers: AllowedSigners | None = None
    audit: Audit = Audit()

    def rule_for(self, url: str | None, unit: int | None, name: str | None = None) -> Rule:
        """The rule of the device at ``url`` (as ``transport.urls.describe`` says it) and ``unit``."""
        rule = self.default
        for dname, durl, dunit, groups in self.devices:
            if (durl == url and dunit == unit) or (url is None and name is not None and dname == name):
                for g in groups:
                    if g in self.groups:
                        rule = rule.stricter(self.groups[g])
        return rule


def _rule(spec: Any, why: str) -> Rule:
    spec = spec or {}
    return Rule(
        int(spec.get("approvals", 0)),
        bool(spec.get("reason", False)),
        bool(spec.get("ticket", False)),
        bool(spec.get("signed_inputs", False)),
        (why,),
    )


def _described(url: str) -> str:
    """A URL as runs name it (``describe(parse_url(...))``), so the inventory's and the plan's compare."""
    from ..errors import UsageError
    from ..transport.urls import describe, parse_url

    try:
        return describe(parse_url(url))
    except (UsageError, ValueError):
        return url


def load(path: str) -> Policy | None:
    """The policy of the inventory at ``path`` (InputError when it is invalid); None when it has none."""
    from ..fleet.inventory import load_inventory
    from ..load import yamlsrc

    try:
        with open(path, "rb") as f:
            if b"change_control" not in f.read():  # a fleet's big inventory without a policy is not read twice
                return None
    except OSError:
        pass  # the loader says it, at its position
    inv = load_inventory(path)  # checked against the schema, change_control included
    data, _ = yamlsrc.load(path)
    spec = data.get("change_control") if isinstance(data, dict) else None
    if not isinstance(spec, dict):
        return None
    here = os.path.dirname(os.path.abspath(path))

    def rel(p: str | None) -> str | None:
        return None if p is None else os.path.join(here, os.path.expanduser(p))

    signers = None
    if spec.get("allowed_signers"):
        from . import signers as allowed

        signers = allowed.load(str(rel(spec["allowed_signers"])))
    name = os.path.basename(path)
    groups = {g: _rule(r, f"{name} group {g}") for g, r in (spec.get("groups") or {}).items()}
    a = spec.get("audit") or {}
    audit = Audit(
        rel(a.get("trail")), a.get("syslog"), rel(a.get("syslog_ca")), int(a.get("max_backlog", DEFAULT_BACKLOG))
    )
    devices = tuple((d.name, _described(d.url), d.unit, d.groups) for d in inv.devices)
    return Policy(
        (path,),
        _rule(spec.get("require"), f"{name} require") if spec.get("require") else Rule(),
        groups,
        devices,
        signers,
        audit,
    )


def combined(policies: Sequence[Policy]) -> Policy | None:
    """Several policies as one: every device's rule is the strictest of theirs."""
    if not policies:
        return None
    if len(policies) == 1:
        return policies[0]
    first = policies[0]
    return _Combined(
        tuple(s for p in policies for s in p.sources),
        first.default,
        {},
        (),
        next((p.signers for p in policies if p.signers is not None), None),
        next((p.audit for p in policies if p.audit != Audit()), Audit()),
        tuple(policies),
    )


@dataclass(frozen=True)
class _Combined(Policy):
    parts: tuple[Policy, ...] = ()

    def rule_for(self, url: str | None, unit: int | None, name: str | None = None) -> Rule:
        rule = Rule()
        for p in self.parts:
            rule = rule.stricter(p.rule_for(url, unit, name))
        return rule


def site(explicit: str | None = None, inventory: str | None = None) -> Policy | None:
    """The policy a command-line run goes by: ``explicit`` (``--policy``) or ``DEPLOYER_POLICY``, and the
    run's own inventory's; None when none of them has one."""
    from ..errors import UsageError

    named = explicit or os.environ.get(ENV) or None
    found = []
    if named:
        pol = load(named)
        if pol is None:
            what = "--policy" if explicit else ENV
            raise UsageError(f"{what} {named}: the inventory has no change_control: member (docs/change-control.md)")
        found.append(pol)
    if inventory and (named is None or os.path.abspath(inventory) != os.path.abspath(named)):
        pol = load(inventory)
        if pol is not None:
            found.append(pol)
    return combined(found)
