"""What the agent's routes answer with: its devices, windows, pending changes, its own state and a status."""

from __future__ import annotations

import os
import time
from typing import Any

from ..planning.model import Target
from ..planning.planfile import plan_to_json
from ..planning.steps import make_plan, pacing_for
from ..transport.urls import describe
from .core import Agent
from .model import API_VERSION, Device, iso


def device_json(agent: Agent, dev: Device, *, full: bool = False) -> dict[str, Any]:
    prof = dev.adopted.profile if dev.adopted else dev.job.recipe.profile
    status = "running" if dev.run else dev.status
    out: dict[str, Any] = {
        "name": dev.name,
        "url": describe(dev.job.url),
        "unit": dev.job.unit,
        "profile": prof.id,
        "status": status,
        "owned": dev.owned,
        "drifted": bool(dev.drift),
        "drift": dev.drift,
        "last_check": None if dev.last_check is None else iso(dev.last_check),
        "unreachable": dev.unreachable_why,
        "replaced": dev.replaced,
        "not_owned": dev.not_owned_why,
        "pending": len(dev.pending),
        "run": dev.run,
        "restores_last_hour": len(dev.restores),
        "writes": dev.writes,
        "check_every": dev.check_every,
        "on_drift": dev.on_drift,
        "on_replace": dev.on_replace,
    }
    if full and agent.store is not None:
        ident = agent.store.identity(dev.name)
        left = agent.store.asleft(dev.name)
        out.update(
            {
                "identity": None
                if ident is None
                else {"objects": ident[0], "registers": ident[1], "function_43": ident[2]},
                "adopted": {n: prof.parameter(n).show_registers(v) for n, v in dev.adopted_values.items()},
                "adopted_recipe": dev.adopted.path if dev.adopted else None,
                "last_values": None
                if dev.last_values is None
                else {n: prof.parameter(n).show_registers(v) for n, v in dev.last_values.items()},
                "asleft": None
                if left is None
                else {n: prof.parameter(n).show_registers(v) for n, v in left[0].items() if prof.get(n) is not None},
                "pending_changes": dev.pending,
            }
        )
    return out


def windows_json(agent: Agent) -> list[dict[str, Any]]:
    """The open soak and confirm windows."""
    assert agent.store is not None
    now = time.time()
    return [w.to_json(now) for w in agent.store.windows()]


def agent_json(agent: Agent) -> dict[str, Any]:
    from importlib.metadata import PackageNotFoundError, version

    try:
        v = version("modbus-deployer")
    except PackageNotFoundError:  # pragma: no cover - a source checkout without install
        v = "unknown"
    s = agent.settings
    return {
        "version": v,
        "api": API_VERSION,
        "url": agent.url,
        "inventory": os.path.abspath(s.inventory),
        "state_dir": agent.state_dir,
        "pid": os.getpid(),
        "boot_id": agent.boot,
        "started": iso(agent.started),
        "auth": "none",
        "files_sha256": agent.files.sha256 if agent.files else None,
        "options": {
            "check_every": s.check_every,
            "on_drift": s.on_drift,
            "on_replace": s.on_replace,
            "bus_share": s.bus_share,
            "max_restores": s.max_restores,
            "endurance_warn": s.endurance_warn,
            "first_restore_soak": s.first_restore_soak,
        },
        "restores_stopped": agent.first.stopped,
        "checks": agent.watch.checks,
        "last_check_seconds": agent.watch.check_seconds,
    }


def pending_json(agent: Agent) -> dict[str, Any]:
    out = []
    for dev in agent.devices.values():
        if not dev.pending:
            continue
        job = agent.files.jobs.get(dev.name) if agent.files else None
        plan = None
        if job is not None and dev.last_values is not None:
            plan = plan_to_json(
                make_plan(
                    job.recipe,
                    Target(describe(job.url), job.unit, job.recipe.profile_ref or job.recipe.profile.id),
                    dev.last_values,
                    pacing=pacing_for(job.url, job.recipe.profile),
                )
            )
        out.append({"name": dev.name, "changes": dev.pending, "plan": plan})
    return {
        "files_sha256": agent.files.sha256 if agent.files else None,
        "devices": out,
        "problems": agent.files_problem,
    }


def status_json(agent: Agent) -> dict[str, Any]:
    assert agent.store is not None
    look = [device_json(agent, d) for d in agent.devices.values() if d.status not in ("ok",) or d.run or d.pending]
    return {
        "agent": agent_json(agent),
        "devices": look,
        "windows": windows_json(agent),
        "runs": [r.to_json(report=False) for r in agent.runs.live.values() if r.state in ("running", "waiting")],
        "events": agent.store.events(limit=20),
        "files_problems": agent.files_problem,
    }
