"""``--agent URL`` (or ``DEPLOYER_AGENT``): apply, plan, diff, status, confirm and rollback as clients of a
site agent (docs/agent.md). The agent executes; the command line sends the request, streams the progress
and exits with the code the same command has without the agent.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

import click

from ..errors import EXIT_CHANGES, EXIT_FAILED, EXIT_OK, EXIT_UNREACHABLE, UsageError
from .base import echo, stdin_is_terminal

# options of apply that mean something only where the command line itself talks to the devices
_LOCAL_ONLY = (
    "device",
    "unit",
    "timeout",
    "retries",
    "allow_broadcast",
    "html_path",
    "pause",
    "ask",
    "inventory",
    "meta",
    "compact",
    "workers",
    "policy",
)  # meta, compact: with --html; policy: the agent's own


def client(url: str) -> Any:
    """The agent's client: the token (--agent-token-file, else DEPLOYER_AGENT_TOKEN, else for a loopback URL the
    one this user's agent made), the CA (--agent-ca), a client certificate (--agent-cert/--agent-key)."""
    import os

    from ..agent.client import Agent
    from ..agent.security import read_token

    meta = click.get_current_context(silent=True)
    given = meta.meta if meta is not None else {}
    path = given.get("deployer.agent.agent_token_file")
    token = read_token(path, "--agent-token-file") if path else (os.environ.get("DEPLOYER_AGENT_TOKEN") or None)
    return Agent(
        url,
        token=token,
        ca=given.get("deployer.agent.agent_ca"),
        cert=given.get("deployer.agent.agent_cert"),
        key=given.get("deployer.agent.agent_key"),
    )


def _refuse_local(kw: Mapping[str, Any], what: str) -> None:
    given = [k for k in _LOCAL_ONLY if kw.get(k) not in (None, False, ())]
    if given:
        names = ", ".join("--" + k.removesuffix("_path").replace("_", "-") for k in given)
        raise UsageError(
            f"{names}: not with --agent ({what} runs in the agent, on its inventory's devices; "
            "edit the inventory instead)"
        )


def _say(ev: Mapping[str, Any], url: str) -> None:
    kind = ev.get("event")
    if kind == "device-started":
        echo(f"{ev['name']}: writing", err=True)
    elif kind in ("device-finished", "device-changed"):
        d = ev["device"]
        what = f" - {d['error']}" if d.get("error") else ""
        echo(f"{d['name']}: {d['status']}{what}", err=True)
    elif kind == "soak-started":
        echo(f"soaking {', '.join(ev['devices'])} until {ev['deadline']}", err=True)
    elif kind == "window-waiting":
        echo(
            f"waiting for the confirmation until {ev['deadline']} (the agent holds the window: this command "
            f"may end): deployer confirm --agent {url} {ev['run']}",
            err=True,
        )
    elif kind == "window-confirmed":
        echo("confirmed: the commit goes out", err=True)
    elif kind == "window-expired":
        echo("not confirmed in time: rolled back", err=True)


def apply(
    url: str, source: str | None, kw: dict[str, Any], *, command: str = "apply", force_endurance: bool = False
) -> int:
    """``deployer apply --agent URL [RECIPE]``: the agent rolls out its files (RECIPE must be the one they name)."""
    import os

    _refuse_local(kw, command)
    if source is not None and source.endswith(".json"):
        raise UsageError(
            "a saved plan is not applied through the agent: it rolls out the validated files "
            "(deployer plan --agent shows what would change)"
        )
    c = client(url)
    seen: str | None = None  # the files shown: the agent refuses the run if they changed since
    if not kw.get("yes"):
        if not stdin_is_terminal():
            raise UsageError("refusing to write without confirmation: stdin is not a terminal; pass --yes")
        pending = _pending(c)
        seen = pending.get("files_sha256")
        _print_pending(pending)
        if not click.confirm("apply these changes through the agent?", default=False):
            echo("nothing was sent", err=True)
            return EXIT_OK
    body = {
        "command": "apply",
        "limit": kw.get("limit"),
        "batch": kw.get("batch"),
        "max_failures": kw.get("max_failures"),
        "parallel": kw.get("parallel"),
        "soak": _secs(kw.get("soak")),
        "health_interval": _secs(kw.get("health_interval")),
        "confirm_within": _secs(kw.get("confirm_within")),
        "allow_unhealthy": kw.get("allow_unhealthy") or None,
        "rollback_on_failure": kw.get("rollback_on_failure"),
        "write_all": kw.get("write_all"),
        "force_endurance": force_endurance or None,
        "recipe": os.path.abspath(source) if source else None,
        "files_sha256": seen,
    }
    run = c.start_run(**body)
    echo(f"run {run['id']} started in the agent at {url}", err=True)
    end = c.follow(run["id"], lambda ev: _say(ev, url))
    return _finish(end, kw)


def _finish(end: Mapping[str, Any], kw: Mapping[str, Any]) -> int:
    import os

    from ..api.commands import report_from_json, write_output
    from .outcome import print_outcome

    if end.get("error"):
        echo(f"error: {end['error']}", err=True)
    doc = end.get("report")
    if doc is not None:
        if kw.get("report_path"):
            path = str(kw["report_path"])
            os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
            write_output(path, json.dumps(doc, indent=2) + "\n")
        print_outcome(
            report_from_json(doc), fleet_run=True, as_json=bool(kw.get("as_json")), report_path=kw.get("report_path")
        )
    return int(end.get("exit_code") or 0)


def _secs(v: Any) -> str | None:
    return None if v is None else f"{float(v)}s"


def _print_pending(pending: Mapping[str, Any]) -> None:
    devices = pending.get("devices") or []
    if not devices:
        echo("the files hold no change that is not adopted (a run writes only what devices lack)")
    for d in devices:
        echo(f"{d['name']}:")
        for ch in d["changes"]:
            echo(f"  {ch['name']}: {ch['adopted'] or '-'} -> {ch['files'] if ch['files'] is not None else '-'}")
        plan = d.get("plan")
        if plan is not None:
            n = len(plan.get("writes") or [])
            echo(f"  {n} write request{'s' if n != 1 else ''} against what it held at its last check")
    for p in pending.get("problems") or []:
        echo(p, err=True)


def _pending(c: Any) -> dict[str, Any]:
    """The files' changes: taken up now (a reload, role engineer), else as an engineer took them up last."""
    from ..errors import AgentError

    try:
        return dict(c.reload())
    except AgentError as e:
        if e.kind != "forbidden":
            raise
    echo("(the files as an engineer took them up last: taking up an edit needs the role engineer)", err=True)
    return dict(c.pending())


def plan(url: str, *, as_json: bool, detailed_exitcode: bool) -> int:
    """``deployer plan --agent URL``: the files' changes the agent has not adopted, as plans per device."""
    pending = _pending(client(url))
    if as_json:
        echo(json.dumps(pending, indent=2))
    else:
        _print_pending(pending)
    return EXIT_CHANGES if detailed_exitcode and pending.get("devices") else EXIT_OK


def diff(url: str, *, limit: str | None, as_json: bool) -> int:
    """``deployer diff --agent URL``: check now; the devices that do not hold the adopted state (exit 2)."""
    devices = client(url).check(limit)
    if as_json:
        echo(json.dumps({"devices": devices}, indent=2))
    drifted = [d for d in devices if d["drift"]]
    unreachable = [d for d in devices if d["status"] == "unreachable"]
    if not as_json:
        for d in drifted:
            for p in d["drift"]:
                echo(f"{d['name']}: {p['name']}: adopted {p['adopted']}, device {p['device']}")
        for d in unreachable:
            echo(f"{d['name']}: unreachable - {d['unreachable']}", err=True)
        if not drifted:
            echo("no drift: every device reachable holds the adopted state")
    if devices and len(unreachable) == len(devices):
        return EXIT_UNREACHABLE
    return EXIT_CHANGES if drifted else EXIT_OK


def status(url: str, *, as_json: bool) -> int:
    s = client(url).status()
    # 2 while something needs a look (a device not ok, a window open, a run in flight), as deployer status
    look = EXIT_CHANGES if s["devices"] or s["windows"] or s["runs"] else EXIT_OK
    if as_json:
        echo(json.dumps(s, indent=2))
        return look
    a = s["agent"]
    echo(f"agent {a['url']} (PID {a['pid']}), {a['inventory']}, state {a['state_dir']}")
    for d in s["devices"]:
        extra = d.get("unreachable") or d.get("replaced") or d.get("not_owned") or ""
        pend = f", {d['pending']} pending" if d.get("pending") else ""
        echo(f"  {d['name']}: {d['status']}{pend}{' - ' + extra if extra else ''}")
    for w in s["windows"]:
        echo(
            f"  window: run {w['run']} ({w['kind']}) {', '.join(w['devices'])} until {w['deadline']}: "
            f"deployer confirm --agent {a['url']} {w['run']}"
        )
    for r in s["runs"]:
        echo(f"  run {r['id']} ({r['command']}): {r['state']}")
    if not (s["devices"] or s["windows"] or s["runs"]):
        echo("  every device holds the adopted state; nothing waits")
    return look


def confirm(url: str, run: str | None) -> int:
    """Confirm through the agent, then wait for the outcome as ``deployer confirm`` does: exit 4 when a
    commit was not sent."""
    c = client(url)
    r = c.confirm(run)
    echo(f"confirmed run {r['id']}: the agent sends the commit now")
    end = c.follow(r["id"], lambda ev: _say(ev, url))
    if end.get("exit_code"):
        echo(f"run {r['id']} ended with exit code {end['exit_code']}: see deployer status --agent {url}", err=True)
        return EXIT_FAILED
    return EXIT_OK


def rollback(url: str, runs: tuple[str, ...], kw: dict[str, Any]) -> int:
    """``deployer rollback --agent URL --from-report RUN``: the agent restores what its run RUN wrote."""
    import os

    _refuse_local(kw, "rollback")
    if len(runs) != 1:
        raise UsageError("with --agent: rollback --from-report RUN (one run of the agent, by id or its report)")
    run = os.path.basename(runs[0]).removesuffix(".json")
    c = client(url)
    started = c.rollback(run)
    echo(f"run {started['id']} rolls back run {run} in the agent at {url}", err=True)
    return _finish(c.follow(started["id"], lambda ev: _say(ev, url)), kw)
