# The deployer.modbus modules' agent: option: the task runs through a site agent (deployer agent) over its
# HTTP API, with deployer's own client (deployer.Agent, public), instead of talking Modbus itself.
# The agent owns its devices and holds the desired state (its inventory and recipes); the task says which
# devices (limit) and how (batch, soak ...), the agent executes, and Ansible's serial: rolls sites out.

from __future__ import annotations

# the agent: option (documented in each module that takes it)
AGENT_SPEC = dict(
    url=dict(type="str", required=True),
    token=dict(type="str", no_log=True),
    token_file=dict(type="path"),
    ca=dict(type="path"),
    cert=dict(type="path"),
    key=dict(type="path", no_log=False),  # a path, not the key
    timeout=dict(type="float", default=30.0),
)

# what means something only where the module itself talks to the devices: the agent's inventory says it
NOT_WITH_AGENT = ("device", "devices", "inventory", "profile", "parameters", "name", "unit", "timeout", "retries")


def agent_exclusive(more=()):
    return [("agent", other) for other in NOT_WITH_AGENT + tuple(more)]


def client_of(module):
    """deployer.Agent for the task's agent: option (token given, or read from token_file on the target; or a client
    certificate the agent maps to a user, --tls-client-ca)."""
    from deployer.api import Agent

    a = module.params["agent"]
    token = a.get("token")
    if not token and a.get("token_file"):
        try:
            with open(a["token_file"], encoding="utf-8") as f:
                token = f.readline().strip()
        except OSError as e:
            module.fail_json(msg=f"agent.token_file {a['token_file']}: {e.strerror or e}; nothing was sent")
    if bool(a.get("cert")) != bool(a.get("key")):
        module.fail_json(
            msg="agent.cert and agent.key go together (the client certificate and its key); nothing was sent"
        )
    return Agent(
        a["url"], token=token or None, ca=a.get("ca"), cert=a.get("cert"), key=a.get("key"), timeout=a["timeout"]
    )


def agent_failed(module, e, **result):
    """An AgentError: the agent's own words, its kind, and the diagnostics of invalid files."""
    msg = f"agent {module.params['agent']['url']}: {e}"
    if getattr(e, "diagnostics", None):
        msg += ": " + "; ".join(e.diagnostics)
    module.fail_json(
        msg=msg,
        kind=getattr(e, "kind", None),
        exit_code=getattr(e, "exit_code", None),
        errors=list(getattr(e, "diagnostics", []) or []),
        **result,
    )


def _diff(name, rows):
    return {
        "before_header": name,
        "after_header": name,
        "before": "".join(f"{n}: {b}\n" for n, b, a in rows),
        "after": "".join(f"{n}: {a}\n" for n, b, a in rows),
    }


def agent_check(module, client):
    """Check mode: the agent reads its files again and checks the selected devices now; what a run would
    change is each device's drift (back to the adopted state) and the files' pending changes. Nothing is
    written to any device, nothing is adopted."""
    client.reload()
    checked = client.check(module.params.get("limit"))
    pending = {d["name"]: d for d in client.pending()["devices"]}
    devices, diffs, down = [], [], []
    for d in checked:
        name = d["name"]
        if d.get("status") in ("unreachable", "not-owned"):
            down.append(f"{name}: {d.get('unreachable') or d.get('not_owned') or d['status']}")
        rows = {
            c["name"]: (c["name"], c["device"] if c["device"] is not None else "?", c["adopted"])
            for c in d.get("drift") or []
        }
        for c in (pending.get(name) or {}).get("changes") or []:
            before = rows[c["name"]][1] if c["name"] in rows else c["adopted"]
            rows[c["name"]] = (c["name"], before if before is not None else "?", c["files"])
        devices.append(
            {
                "name": name,
                "status": "would change" if rows else d.get("status"),
                "changes": sorted(rows),
                "plan": (pending.get(name) or {}).get("plan"),
            }
        )
        if rows:
            diffs.append(_diff(name, [rows[k] for k in sorted(rows)]))
    result = {
        "changed": bool(diffs),
        "devices": devices,
        "diff": diffs,
        "plans": [{"name": d["name"], "plan": d["plan"]} for d in devices if d["plan"] is not None],
    }
    if down:
        module.fail_json(msg="; ".join(down), **result)
    module.exit_json(**result)


def agent_apply(module, client):
    """A run in the agent (its files' recipes for the selected devices, every guarantee of a command-line
    run), followed to its end; the task fails when the run's exit code is not 0."""
    import os

    p = module.params
    end = client.apply(
        command="apply",
        limit=p.get("limit"),
        recipe=os.path.abspath(p["recipe"]) if p.get("recipe") else None,
        batch=p.get("batch"),
        max_failures=p.get("max_failures"),
        parallel=p["parallel"],
        soak=p.get("soak"),
        health_interval=p["health_interval"],
        allow_unhealthy=p["allow_unhealthy"] or None,
        rollback_on_failure=p["rollback_on_failure"],
        write_all=p["write_all"],
    )
    report = end.get("report") or {}
    devices, diffs, problems, changed = [], [], [], False
    for d in report.get("devices") or []:
        params = d.get("parameters") or []
        moved = [
            (q["name"], q.get("before") or "?", q.get("after") or q.get("desired"))
            for q in params
            if q.get("status") == "ok" and q.get("before_raw") != q.get("after_raw")
        ]
        bad = [q for q in params if q.get("status") in ("failed", "mismatch", "unverified")]
        wrote = any(r.get("function") in (5, 6, 15, 16, 23) for r in d.get("requests") or [])
        changed = changed or wrote or bool(moved)
        devices.append(
            {
                "name": d["name"],
                "status": d["status"],
                "changed": [row[0] for row in moved],
                "failed": {q["name"]: q.get("error") for q in bad},
                "error": d.get("error"),
            }
        )
        if moved:
            diffs.append(_diff(d["name"], moved))
        if d["status"] != "ok":
            what = ", ".join(f"{q['name']} {q['status']}" + (f" ({q['error']})" if q.get("error") else "") for q in bad)
            problems.append(
                f"{d['name']} {d['status']}"
                + (f": {what}" if what else "")
                + (f" - {d['error']}" if d.get("error") else "")
            )
    result = {
        "changed": changed,
        "devices": devices,
        "report": report,
        "diff": diffs,
        "run": end.get("run"),
        "exit_code": end.get("exit_code"),
    }
    if end.get("exit_code") != 0 or problems:
        problems = problems or [
            f"the agent's run ended with exit code {end.get('exit_code')}"
            + (f": {end['error']}" if end.get("error") else "")
        ]
        module.fail_json(msg=f"run {end.get('run')} in the agent {p['agent']['url']}: " + "; ".join(problems), **result)
    module.exit_json(**result)


def agent_info(module, client):
    """The agent reads the selected devices now (a check: reads only); the facts are the values they hold
    of their adopted parameters (device name -> parameter -> value text)."""
    checked = client.check(module.params.get("limit"))
    facts, down = {}, []
    for d in checked:
        full = client.device(d["name"])
        if full.get("last_values") is None:
            down.append(f"{d['name']}: {d.get('unreachable') or d.get('not_owned') or d.get('status')}")
            continue
        facts[d["name"]] = dict(full["last_values"])
    result = {
        "changed": False,
        "ansible_facts": {"modbus_parameters": facts},
        "devices": [
            {k: d.get(k) for k in ("name", "status", "drifted", "drift", "pending", "last_check")} for d in checked
        ],
    }
    if down:
        module.fail_json(msg="unreachable: " + "; ".join(down), **result)
    module.exit_json(**result)
