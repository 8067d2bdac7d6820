"""Windows owned by the agent: the client may go; confirm through the agent; expiry rolls back; kill -9 and a
restart (and another boot) during a window; the command line as the agent's client."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from deployer.profile import load_profile
from deployer.testing.simulator import Simulator, SimulatorThread
from tests.agent_helpers import PROFILE, AgentProcess, event, until, write_site, writes_in_log

pytestmark = pytest.mark.timeout(120)


@pytest.fixture
def sims(tmp_path: Path) -> Iterator[tuple[Simulator, Simulator]]:
    (tmp_path / "drive.yaml").write_text(PROFILE)
    prof = load_profile(str(tmp_path / "drive.yaml"))
    with SimulatorThread(prof) as a, SimulatorThread(prof) as b:
        yield a, b


def cli(*args: str, env_agent: str | None = None) -> subprocess.Popen[str]:
    env = os.environ.copy()
    if env_agent:
        env["DEPLOYER_AGENT"] = env_agent
    return subprocess.Popen(
        [sys.executable, "-m", "deployer", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
    )


def commits(sim: Simulator) -> int:
    return sum(1 for e in sim.log if e.function in (6, 16) and e.address == 30)


def test_client_killed_in_its_window_then_confirmed_through_the_agent_another_expires(
    tmp_path: Path, sims: tuple[Simulator, Simulator]
) -> None:
    a, b = sims
    inv = write_site(tmp_path, {"d1": a.url, "d2": b.url})
    agent = AgentProcess(inv, tmp_path / "state")
    try:
        c = agent.client
        # the client asks for a confirm window, then is killed while the agent holds it
        p = cli("apply", "--agent", agent.url, "--yes", "--limit", "d1", "--confirm-within", "60s")
        assert p.stderr is not None
        waited = ""
        for line in p.stderr:
            waited += line
            if "waiting for the confirmation" in line:
                break
        assert "deployer confirm --agent" in waited, waited
        p.kill()
        p.wait(timeout=30)
        win = until(lambda: c.windows(), why="the window")
        assert win[0]["devices"] == ["d1"] and win[0]["kind"] == "confirm"
        run = win[0]["run"]
        assert a.read("accel") == (20,) and commits(a) == 0  # written, verified, commit held
        ok = subprocess.run(
            [sys.executable, "-m", "deployer", "confirm", run],
            capture_output=True,
            text=True,
            timeout=60,
            env={**os.environ, "DEPLOYER_AGENT": agent.url},
        )
        assert ok.returncode == 0, ok.stderr
        until(lambda: c.run(run)["state"] == "finished", why="the run's end")
        assert c.run(run)["exit_code"] == 0 and commits(a) == 1
        assert event(c, "window-confirmed") is not None
        # a second one is left to run out: rolled back, its commit never sent
        p2 = cli("apply", "--yes", "--limit", "d2", "--confirm-within", "1s", env_agent=agent.url)
        out, err = p2.communicate(timeout=60)
        assert p2.returncode == 4, err
        assert "not confirmed in time: rolled back" in err and "rolled-back" in out + err
        assert b.read("accel") == (50,) and commits(b) == 0
        assert b.read("address") == (1,)
        assert event(c, "window-expired") is not None
        assert c.windows() == []
        assert agent.terminate() == 0
    finally:
        agent.kill()


def test_agent_killed_and_restarted_during_windows(tmp_path: Path, sims: tuple[Simulator, Simulator]) -> None:
    a, b = sims
    inv = write_site(tmp_path, {"d1": a.url, "d2": b.url})
    state = tmp_path / "state"
    agent = AgentProcess(inv, state)
    try:
        c = agent.client
        long_run = c.start_run(limit="d1", confirm_within="60s")["id"]
        until(lambda: c.run(long_run)["state"] == "waiting", why="d1 waits")
        short_run = c.start_run(limit="d2", confirm_within="1s")["id"]
        until(lambda: c.run(short_run)["state"] == "waiting", why="d2 waits")
        os.kill(agent.proc.pid, signal.SIGKILL)
        agent.kill()
    finally:
        agent.kill()
    assert a.read("accel") == (20,) and b.read("accel") == (20,)  # both written, neither committed
    time.sleep(1.5)  # d2's window runs out while no agent lives
    # the journal (deployer status) names both runs meanwhile
    st = subprocess.run(
        [sys.executable, "-m", "deployer", "status", "--state-dir", str(state)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert long_run in st.stdout + st.stderr and short_run in st.stdout + st.stderr
    again = AgentProcess(inv, state)
    try:
        c = again.client
        # the expired window was rolled back at the start, its commit never sent
        until(lambda: b.read("accel") == (50,), why="d2 rolled back")
        assert commits(b) == 0
        expired = event(c, "window-expired")
        assert expired is not None and short_run in expired["message"]
        # the other keeps waiting, and is confirmed through the restarted agent
        waiting = c.windows()
        assert [w["run"] for w in waiting] == [long_run], again.log()
        ok = subprocess.run(
            [sys.executable, "-m", "deployer", "confirm", "--agent", again.url],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert ok.returncode == 0, ok.stderr
        until(lambda: commits(a) == 1, why="d1's commit")
        assert a.read("accel") == (20,)
        until(lambda: c.windows() == [], why="no window left")
        assert again.terminate() == 0
    finally:
        again.kill()
    st = subprocess.run(
        [sys.executable, "-m", "deployer", "status", "--state-dir", str(state)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert long_run not in st.stdout and short_run not in st.stdout, st.stdout


def test_after_a_reboot_every_open_window_counts_as_expired(tmp_path: Path, sims: tuple[Simulator, Simulator]) -> None:
    a, _ = sims
    inv = write_site(tmp_path, {"d1": a.url})
    state = tmp_path / "state"
    agent = AgentProcess(inv, state)
    try:
        c = agent.client
        run = c.start_run(confirm_within="10m")["id"]
        until(lambda: c.run(run)["state"] == "waiting", why="waiting")
        os.kill(agent.proc.pid, signal.SIGKILL)
    finally:
        agent.kill()
    # the power went: this machine booted again (another boot id in /proc), the deadline is far away
    db = sqlite3.connect(state / "agent" / "agent.sqlite3")
    db.execute("UPDATE windows SET boot_id = 'a-boot-before-the-power-cut'")
    db.commit()
    db.close()
    again = AgentProcess(inv, state)
    try:
        until(lambda: a.read("accel") == (50,), why="rolled back")
        ev = event(again.client, "window-expired")
        assert ev is not None and "another boot" in ev["message"]
        assert commits(a) == 0 and again.client.windows() == []
        assert again.terminate() == 0
    finally:
        again.kill()


def test_cli_through_the_agent_plan_diff_status_rollback_and_ledger(
    tmp_path: Path, sims: tuple[Simulator, Simulator]
) -> None:
    a, _ = sims
    inv = write_site(tmp_path, {"d1": a.url})
    agent = AgentProcess(inv, tmp_path / "state")
    env = {**os.environ, "DEPLOYER_AGENT": agent.url}

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "deployer", *args], capture_output=True, text=True, timeout=60, env=env
        )

    try:
        c = agent.client
        until(lambda: c.device("d1")["last_check"], why="a check")
        d = run("diff")
        assert d.returncode == 2 and "d1: accel: adopted 2 s, device 5 s" in d.stdout, d.stdout + d.stderr
        ap = run("apply", "--yes", "--json", "--report", str(tmp_path / "out" / "run.json"))
        assert ap.returncode == 0, ap.stderr
        assert '"status": "ok"' in ap.stdout
        import deployer  # the agent's report, written where --report says (its folder made)

        assert [(d.name, d.status) for d in deployer.load_report(tmp_path / "out" / "run.json").devices] == [
            ("d1", "ok")
        ]
        assert run("diff").returncode == 0
        # an edit of the files is pending, shown as a plan, never written by itself
        (tmp_path / "r.yaml").write_text((tmp_path / "r.yaml").read_text().replace("accel: 2 s", "accel: 4 s"))
        pl = run("plan", "--detailed-exitcode")
        assert pl.returncode == 2 and "accel: 2 s -> 4 s" in pl.stdout, pl.stdout + pl.stderr
        c.check()
        assert a.read("accel") == (20,)
        # an invalid edit changes nothing and says why
        good = (tmp_path / "r.yaml").read_text()
        (tmp_path / "r.yaml").write_text(good.replace("accel: 4 s", "accel: 4000 s"))
        bad = run("apply", "--yes")
        assert bad.returncode == 1 and "r.yaml:" in bad.stderr and "nothing was sent" in bad.stderr, bad.stderr
        (tmp_path / "r.yaml").write_text(good)
        # an ad hoc recipe is refused: the agent holds one desired state
        other = tmp_path / "other.yaml"
        other.write_text(good)
        adhoc = run("apply", "--yes", str(other))
        assert adhoc.returncode == 1 and "edit the files" in adhoc.stderr
        ap2 = run("apply", "--yes")
        assert ap2.returncode == 0 and a.read("accel") == (40,)
        runs = [r for r in c.runs() if r["command"] == "apply"]
        c.check()
        st = run("status")
        assert st.returncode == 0 and agent.url in st.stdout, st.stdout
        rb = run("rollback", "--from-report", runs[0]["id"])
        assert rb.returncode == 0, rb.stderr
        assert a.read("accel") == (20,)
        # the state rolled back to is the adopted one now (a drift restore never undoes a rollback); the files
        # still say 4 s: pending again, and status says something needs a look
        assert run("diff").returncode == 0
        assert c.pending()["devices"][0]["changes"] == [{"name": "accel", "adopted": "2 s", "files": "4 s"}]
        assert run("status").returncode == 2
        # the ledger against the device's own request log: every write request, per register
        led = {r["address"]: r["writes"] + r["commits"] for r in c.ledger()["devices"][0]["registers"]}
        assert led == writes_in_log(a.log), (led, writes_in_log(a.log))
        assert agent.terminate() == 0
    finally:
        agent.kill()


def test_sigterm_during_a_window_rolls_back_and_ends_cleanly(tmp_path: Path, sims: tuple[Simulator, Simulator]) -> None:
    a, _ = sims
    inv = write_site(tmp_path, {"d1": a.url})
    agent = AgentProcess(inv, tmp_path / "state")
    try:
        c = agent.client
        run = c.start_run(confirm_within="10m")["id"]
        until(lambda: c.run(run)["state"] == "waiting", why="waiting")
        assert a.read("accel") == (20,)
        assert agent.terminate() == 0
        assert a.read("accel") == (50,) and commits(a) == 0  # safely ended: rolled back, never committed
        assert "interrupted while waiting for the confirmation" in agent.log() or "rolled" in agent.log()
    finally:
        agent.kill()
    again = AgentProcess(inv, tmp_path / "state")
    try:
        assert again.client.windows() == []
        assert again.terminate() == 0
    finally:
        again.kill()


def test_a_soak_through_the_agent_passes_or_rolls_back(tmp_path: Path, sims: tuple[Simulator, Simulator]) -> None:
    a, b = sims
    inv = write_site(tmp_path, {"d1": a.url, "d2": b.url})
    agent = AgentProcess(inv, tmp_path / "state")
    try:
        c = agent.client
        end = c.apply(limit="d1", soak="1s", health_interval="200ms")
        assert end["exit_code"] == 0 and commits(a) == 1 and a.read("accel") == (20,)
        # d2 trips during its soak: rolled back, never committed
        seen: list[str] = []

        def trip(ev: dict[str, object]) -> None:
            seen.append(str(ev["event"]))
            if ev["event"] == "soak-started":
                b.set_register(40, 7)

        end = c.apply(limit="d2", soak="2s", health_interval="200ms", on_event=trip)
        assert "soak-started" in seen and end["exit_code"] == 4
        assert end["report"]["devices"][0]["status"] == "rolled-back"
        assert b.read("accel") == (50,) and commits(b) == 0
        assert c.windows() == []
        assert agent.terminate() == 0
    finally:
        agent.kill()
