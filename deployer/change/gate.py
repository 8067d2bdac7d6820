"""The one check on the way to a device: ``check_run``, called by ``run.request.prepare`` before anything is sent.

A saved plan is checked against the site policy (``check_approvals``) and must be the document that was
signed (the plan ``apply`` loaded is the one whose digest the signatures cover); a plain recipe is refused for
a device whose rule needs approvals, a reason or a ticket (those live in a plan). A plan carrying a signature
over another digest is refused under any policy or none. Refusals and authorizations go into the audit trail.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from ..errors import UsageError
from . import policy as policies
from .canonical import canonical, digest
from .check import fleet_entry_plan

if TYPE_CHECKING:
    from ..execute.job import Job
    from ..planning.model import Plan


class ChangeRefused(UsageError):
    """The change control refuses the run: nothing was sent. ``missing``: what it lacks, each said."""

    def __init__(self, message: str, missing: Sequence[str]) -> None:
        super().__init__(" ".join([message, *(f"({n}) {m}" for n, m in enumerate(missing, 1))]))
        self.missing = list(missing)


def _same_plan(doc: Mapping[str, Any], plan: Plan, name: str) -> bool:
    """The plan apply loaded is what the signed document says, member for member (the file was read twice:
    once by the loader, once here); in a saved fleet plan, device ``name``'s."""
    from ..planning.planfile import plan_to_json

    if str(doc.get("schema", "")).startswith("deployer.fleetplan/"):
        found = fleet_entry_plan(doc, name)
        if found is None:
            return False
        doc = found
    loaded = plan_to_json(plan)
    return all(canonical(doc.get(k)) == canonical(v) for k, v in loaded.items())


def check_run(
    *,
    command: str,
    source: str | None,
    jobs: Sequence[Job],
    policy_path: str | None,
    inventory: str | None,
    state_dir: str,
) -> dict[str, Any] | None:
    """Refuse (ChangeRefused) a run the change control does not allow; for a saved plan, what the report and
    the record say of its change (digest, author, reason, ticket, signatures checked), else None."""
    if command != "apply":
        return None  # a rollback restores what a device held before: the way back stays open (audited)
    policy = policies.site(policy_path, inventory)
    planned = [j for j in jobs if j.plan is not None]
    if planned and source is not None:
        from .check import check_approvals, stale
        from .files import read_plan

        doc = read_plan(source)
        url_unit = [(_url(j), j.unit) for j in planned]
        missing = stale(doc) if policy is None else []
        for url, unit in dict.fromkeys(url_unit):
            rule = policy.rule_for(url, unit) if policy is not None else policies.Rule()
            if policy is not None:
                missing += check_approvals(doc, policy, rule)
            if rule.signed_inputs:
                missing += _profiles_signed(doc, planned)
        if not all(_same_plan(doc, j.plan, j.name) for j in planned if j.plan is not None):
            missing.append(
                f"{source} changed while it was read (the plan loaded is not the document checked): run it again"
            )
        missing = list(dict.fromkeys(missing))
        info = _info(doc, policy)
        if missing:
            _audit(state_dir, policy, "apply-refused", info, "refused", missing=missing)
            raise ChangeRefused(f"{source}: the change control refuses this plan; nothing was sent. It lacks:", missing)
        if policy is not None:
            _audit(state_dir, policy, "apply-authorized", info, "ok")  # fail closed: unrecorded, not run
        return info
    if policy is None:
        return None
    refused = []
    for j in jobs:
        rule = policy.rule_for(_url(j), j.unit, j.name)
        if rule.needs_plan:
            refused.append(
                f"{j.name}: its change control needs {rule.said()}: only an approved plan changes it "
                "(deployer plan RECIPE --device URL --out PLAN.json --reason TEXT, deployer approve, "
                "deployer apply PLAN.json)"
            )
        elif rule.signed_inputs:
            refused += [f"{j.name}: {m}" for m in _files_signed(j, policy)]
    if refused:
        _audit(state_dir, policy, "apply-refused", {"recipe": source}, "refused", missing=refused)
        raise ChangeRefused("the change control refuses this run; nothing was sent:", refused)
    return None


def _url(job: Job) -> str:
    from ..transport.urls import describe

    return describe(job.url)


def _profiles_signed(doc: Mapping[str, Any], jobs: Sequence[Job]) -> list[str]:
    """The profile apply uses now is the one whose signed digest the plan records."""
    change = doc.get("change")
    inputs = change.get("inputs") if isinstance(change, Mapping) else None
    signed = {str(i.get("sha256")) for i in inputs or [] if isinstance(i, Mapping) and i.get("kind") == "profile"}
    out = []
    for j in jobs:
        path = j.recipe.profile.source
        if path is None:
            continue  # a built-in profile ships with deployer itself
        try:
            with open(path, "rb") as f:
                now = hashlib.sha256(f.read()).hexdigest()
        except OSError as e:
            out.append(f"the profile {path} cannot be read: {e.strerror}")
            continue
        if now not in signed:
            out.append(f"the profile {path} is not the signed one the plan records")
    return out


def _files_signed(job: Job, policy: policies.Policy) -> list[str]:
    from .check import inputs_missing
    from .files import input_record

    files = [("recipe", job.recipe.path), ("profile", job.recipe.profile.source)]
    return inputs_missing([input_record(k, p) for k, p in files if p], policy.signers)


def _info(doc: Mapping[str, Any], policy: policies.Policy | None) -> dict[str, Any]:
    from .check import verdicts

    change = doc.get("change") if isinstance(doc.get("change"), Mapping) else {}
    assert isinstance(change, Mapping)
    out: dict[str, Any] = {"digest": digest(doc)}
    for k in ("author", "reason", "ticket", "time"):
        if isinstance(change.get(k), str):
            out[k] = change[k]
    sigs = doc.get("signatures")  # none: nothing to check (and cryptography need not load)
    out["signatures"] = (
        [v.to_json() for v in verdicts(doc, policy.signers if policy is not None else None)] if sigs else []
    )
    if policy is None:  # nobody vouched for the keys: say the signatures were not checked against any
        for s in out["signatures"]:
            s["holds"] = None
            s.pop("why", None)
    return out


def _audit(
    state_dir: str, policy: policies.Policy | None, event: str, info: Mapping[str, Any], result: str, **detail: Any
) -> None:
    from ..audit import record

    record.append_cli(
        state_dir,
        policy.audit.trail if policy is not None else None,
        [
            record.event(
                event,
                result=result,
                reason=info.get("reason"),
                plan=info.get("digest"),
                detail={**{k: v for k, v in info.items() if k != "signatures"}, **detail},
            )
        ],
    )
