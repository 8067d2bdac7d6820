"""The command line's audit records, one call per command: ``after_run`` (apply, rollback), ``after_plan``
(``plan --out``), ``after_confirm``. Each appends to the trail of the site policy (``audit.trail``) or
``STATE/audit``; a trail that cannot take them is said (``not recorded``), never a lost run."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from ..errors import DeployerError
from . import record

if TYPE_CHECKING:
    from ..report import Report


def _folder(policy_path: str | None, inventory: str | None) -> str | None:
    from ..change import policy

    try:
        pol = policy.site(policy_path, inventory)
    except DeployerError:
        return None  # the run already went by it; a policy broken since is the next run's refusal
    return pol.audit.trail if pol is not None else None


def after_run(
    report: Report,
    *,
    command: str,
    change: Mapping[str, Any] | None,
    state_dir: str,
    policy_path: str | None = None,
    inventory: str | None = None,
    report_path: str | None = None,
) -> None:
    """A finished apply or rollback: its plan's change into the report (and its file), a record per device."""
    if change is not None:
        report.run = {**(report.run or {}), "change": dict(change)}
        if report_path:
            from ..state.durable import write_atomic

            try:
                write_atomic(report_path, json.dumps(report.to_json()) + "\n", what="the report")
            except DeployerError as e:
                report.unrecorded.append(str(e))
    try:
        record.append_cli(
            state_dir, _folder(policy_path, inventory), record.run_records(report, command=command, change=change)
        )
    except DeployerError as e:
        report.unrecorded.append(f"{e}; the report says what the devices hold")


def after_plan(
    doc: Mapping[str, Any], *, out_path: str, device: str | None, state_dir: str, policy_path: str | None = None
) -> list[str]:
    """``plan --out``: the plan made (its digest, author, reason, ticket, the device); what could not be recorded."""
    from ..change import digest

    change = doc.get("change") if isinstance(doc.get("change"), Mapping) else {}
    assert isinstance(change, Mapping)
    rec = record.event(
        "plan-made",
        user=change.get("author"),
        reason=change.get("reason"),
        device=device,
        result="ok",
        plan=digest(doc),
        detail={
            "file": out_path,
            **({"ticket": change["ticket"]} if change.get("ticket") else {}),
            "signatures": [_said(s) for s in doc.get("signatures") or [] if isinstance(s, Mapping)],
        },
    )
    return _append(state_dir, policy_path, [rec])


def signed(
    *,
    path: str,
    digest: str,
    entry: Mapping[str, Any],
    author: str | None,
    state_dir: str,
    policy_path: str | None = None,
) -> list[str]:
    """``approve``/``sign``: who signed what, with which meaning."""
    rec = record.event(
        "plan-signed" if author is not None or path.endswith(".json") else "file-signed",
        user=str(entry.get("signer")),
        result="ok",
        plan=digest,
        detail={"file": path, **_said(entry)},
    )
    return _append(state_dir, policy_path, [rec])


def refused(
    *,
    event: str,
    path: str,
    digest: str | None,
    user: str | None,
    why: str,
    state_dir: str,
    policy_path: str | None = None,
) -> list[str]:
    rec = record.event(event, user=user, result="refused", plan=digest, detail={"file": path, "why": why})
    return _append(state_dir, policy_path, [rec])


def after_confirm(run: str, outcome: Mapping[str, Any], *, state_dir: str) -> list[str]:
    """``deployer confirm``: the run confirmed, and where its commit went."""
    rec = record.event(
        "confirmed",
        run=run,
        result="ok",
        detail={k: list(v) for k, v in outcome.items() if isinstance(v, list | tuple)},
    )
    return _append(state_dir, None, [rec])


def _said(entry: Mapping[str, Any]) -> dict[str, Any]:
    return {k: entry.get(k) for k in ("signer", "meaning", "time", "attested_by") if entry.get(k) is not None}


def _append(state_dir: str, policy_path: str | None, records: Sequence[Mapping[str, Any]]) -> list[str]:
    try:
        record.append_cli(state_dir, _folder(policy_path, None), records)
    except DeployerError as e:
        return [str(e)]
    return []
