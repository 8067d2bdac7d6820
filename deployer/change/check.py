"""Whether a plan may run under a policy: ``check_approvals`` names everything it lacks."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from .canonical import digest
from .policy import Policy, Rule, _described

if TYPE_CHECKING:
    from .signature import Verdict
    from .signers import AllowedSigners


def plan_device(doc: Mapping[str, Any]) -> tuple[str | None, int | None]:
    """The device a plan writes (URL as runs describe it, unit): the one place that reads the plan's insides."""
    dev = doc.get("device")
    if not isinstance(dev, Mapping):
        return None, None
    url, unit = dev.get("url"), dev.get("unit")
    return (_described(url) if isinstance(url, str) else None), (unit if isinstance(unit, int) else None)


def plan_devices(doc: Mapping[str, Any]) -> list[tuple[str | None, int | None]]:
    """Every device a plan writes: a saved plan's one, or each device of a saved fleet plan."""
    devices = doc.get("devices")
    if not str(doc.get("schema", "")).startswith("deployer.fleetplan/") or not isinstance(devices, list):
        return [plan_device(doc)]
    out = []
    for e in devices:
        if isinstance(e, Mapping) and isinstance(e.get("plan"), Mapping):
            out.append(plan_device(e["plan"]))
        elif isinstance(e, Mapping) and "plan_of" in e:  # an earlier device's plan, for its own device
            out.append(plan_device(e))
    return out


def fleet_entry_plan(doc: Mapping[str, Any], name: str) -> Mapping[str, Any] | None:
    """Device ``name``'s plan in a saved fleet plan, as a saved plan's JSON (a shared plan with the device's own
    ``device``); None when the document does not hold exactly one."""
    devices = doc.get("devices")
    entries = [e for e in devices if isinstance(e, Mapping)] if isinstance(devices, list) else []
    found = [e for e in entries if e.get("name") == name]
    if len(found) != 1:
        return None
    entry = found[0]
    if "plan_of" in entry:
        base = fleet_entry_plan(doc, str(entry["plan_of"])) if entry["plan_of"] != name else None
        if base is None or not isinstance(entry.get("device"), Mapping):
            return None
        return {**base, "device": entry["device"]}
    plan = entry.get("plan")
    return plan if isinstance(plan, Mapping) else None


def verdicts(doc: Mapping[str, Any], allowed: AllowedSigners | None) -> list[Verdict]:
    """Every signature of a plan, checked against its digest now."""
    from .signature import verify

    sigs = doc.get("signatures")
    d = digest(doc)
    return [verify(e, d, allowed) for e in (sigs if isinstance(sigs, list) else [])]


def stale(doc: Mapping[str, Any]) -> list[str]:
    """Signatures made over another digest: the plan changed after they were made (no key needed to see it)."""
    d = digest(doc)
    sigs = doc.get("signatures")
    out = []
    for e in sigs if isinstance(sigs, list) else []:
        if isinstance(e, Mapping) and e.get("digest") != d:
            out.append(
                f"the {e.get('meaning', 'signature')} signature of {e.get('signer', '?')} was made over other "
                f"content ({str(e.get('digest'))[:19]}...; the plan is {d[:19]}... now): the plan changed "
                "after it was signed"
            )
    return out


def check_approvals(doc: Mapping[str, Any], policy: Policy | None, rule: Rule | None = None) -> list[str]:
    """What the plan ``doc`` lacks to run under ``policy`` (its device's rule, or ``rule``): empty when it may.

    Every signature it carries must hold; the rule may ask for a reason, a ticket, signed inputs and N approvals
    by distinct users other than the author, whose own ``authored`` signature must then hold."""
    if policy is None:
        return stale(doc)
    if rule is None:  # a fleet plan: what the rules of all its devices ask, each said once
        return list(
            dict.fromkeys(
                m for url, unit in plan_devices(doc) for m in check_approvals(doc, policy, policy.rule_for(url, unit))
            )
        )
    checked = verdicts(doc, policy.signers)
    missing = [f"the signature {v.said()} does not hold: {v.why}" for v in checked if not v.holds]
    change = doc.get("change") if isinstance(doc.get("change"), Mapping) else {}
    assert isinstance(change, Mapping)
    author = change.get("author") if isinstance(change.get("author"), str) else None
    if rule.reason and not str(change.get("reason") or "").strip():
        missing.append("a reason (deployer plan ... --out PLAN.json --reason TEXT)")
    if rule.ticket and not str(change.get("ticket") or "").strip():
        missing.append("a change ticket (deployer plan ... --out PLAN.json --ticket ID)")
    if rule.approvals:
        missing += _approvals(checked, author, rule.approvals)
    if rule.signed_inputs:
        missing += inputs_missing(change.get("inputs"), policy.signers)
    return missing


def _approvals(checked: Sequence[Verdict], author: str | None, needed: int) -> list[str]:
    out = []
    if author is None:
        out.append("an author (the plan has no change.author: make it with deployer plan ... --out)")
    elif not any(v.holds and v.meaning == "authored" and v.signer == author for v in checked):
        out.append(
            f"the author's signature: {author} signs the plan as authored (deployer plan ... --out "
            f"PLAN.json --sign-key KEY, or deployer sign PLAN.json --meaning authored --key KEY)"
        )
    approvers, void = _counted(sorted(checked, key=lambda v: v.signer), author)
    if len(approvers) < needed:
        so_far = f"{len(approvers)} so far: {', '.join(approvers)}" if approvers else "none so far"
        uncounted = "".join(
            f"; not counted: {v.said()} was made with the key "
            + (f"of the author {author}" if other is None else f"that approved as {other}")
            for v, other in void
        )
        out.append(
            f"{needed} approval{'s' if needed != 1 else ''} by distinct users other than the author "
            f"{author or '?'} ({so_far}{uncounted}): deployer approve PLAN.json --key KEY"
        )
    return out


def _counted(checked: Sequence[Verdict], author: str | None) -> tuple[list[str], list[tuple[Verdict, str | None]]]:
    """The approvals that count, in ``checked``'s order: their signers, and the ones that hold but do not count with
    why (None: made with the author's key; a name: with the key that approved as that name).

    Four eyes are two people, and a key is one person whatever names allowed_signers gives it ("alice,alice-ops
    ssh-ed25519 ..."): an approval with the author's own key, or with a key counted already, does not count. An
    agent's key attests for the users it authenticated: those are told apart by their names."""
    own = {v.key for v in checked if v.holds and v.meaning == "authored" and v.signer == author and not v.attested_by}
    approvers: list[str] = []
    keys: dict[str, str] = {}
    void: list[tuple[Verdict, str | None]] = []
    for v in checked:
        if not (v.holds and v.meaning == "approved") or v.signer == author or v.signer in approvers:
            continue
        if not v.attested_by:
            if v.key in own or v.key in keys:
                void.append((v, keys.get(v.key) if v.key not in own else None))
                continue
            keys[v.key] = v.signer
        approvers.append(v.signer)
    return approvers, void


def same_person(
    signatures: Any, author: Any, signer: str, key: str, digest: str, allowed: AllowedSigners | None
) -> str | None:
    """Why ``signer``'s approval over ``digest`` with the key ``key`` (a fingerprint) would not count as a second
    person's, by the rule the policy counts with (``_counted``): the key made the author's signature, or approved
    already under another name. None: it may approve."""
    from .signature import Verdict, verify

    entries = signatures if isinstance(signatures, list) else []
    checked = sorted((verify(e, digest, allowed) for e in entries), key=lambda v: v.signer)  # as the policy orders them
    new = Verdict(signer, "approved", "", digest, True, "", None, key)
    _, void = _counted([*checked, new], author if isinstance(author, str) else None)
    mine = [other for v, other in void if v is new]
    if not mine:
        return None
    other = mine[0]
    if other is None:
        return f"the key ({key}) signed the plan as its author {author}: an author cannot approve their own change"
    return f"the key ({key}) approved it already, as {other}: one key is one person"


def inputs_missing(inputs: Any, allowed: AllowedSigners | None) -> list[str]:
    """Each recipe and profile file the plan records must carry an ``approved`` signature over its bytes."""
    from .signature import verify

    if not isinstance(inputs, list) or not inputs:
        return ["signed inputs: the plan records no input files (make it again with deployer plan ... --out)"]
    out = []
    for item in inputs:
        if not isinstance(item, Mapping):
            out.append("signed inputs: an entry of change.inputs is not an object")
            continue
        what = f"{item.get('kind', 'input')} {item.get('path', '?')}"
        sigs = item.get("signatures")
        found = [verify(e, f"sha256:{item.get('sha256')}", allowed) for e in (sigs if isinstance(sigs, list) else [])]
        if not any(v.holds and v.meaning == "approved" for v in found):
            why = "; ".join(f"{v.said()}: {v.why}" for v in found if not v.holds) or "it carries none"
            out.append(
                f"an approved signature of the {what} ({why}): deployer sign {item.get('path', 'FILE')} "
                "--meaning approved --key KEY, then make the plan again"
            )
    return out
