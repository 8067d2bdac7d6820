"""The site agent as a real process against the simulator: ownership, the watch, drift, metrics, SIGTERM."""

from __future__ import annotations

import itertools
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families

from deployer.agent.client import Agent
from deployer.errors import AgentError
from deployer.profile import load_profile
from deployer.testing.simulator import Simulator, SimulatorThread
from tests.agent_helpers import PROFILE, AgentProcess, event, until, write_site

pytestmark = pytest.mark.timeout(90)


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[Simulator]:
    (tmp_path / "drive.yaml").write_text(PROFILE)
    with SimulatorThread(load_profile(str(tmp_path / "drive.yaml"))) as s:
        yield s


def external_write(sim: Simulator, address: int, value: int) -> None:
    """Another master writes a register (mbpoll where installed: a Modbus client we did not write)."""
    port = sim.url.rsplit(":", 1)[1]
    if shutil.which("mbpoll") is None:  # pragma: no cover - installed where the suite runs
        pytest.skip("mbpoll is not installed")
    subprocess.run(
        ["mbpoll", "-m", "tcp", "-a", "1", "-t", "4", "-r", str(address), "-0", "-p", port, "127.0.0.1", str(value)],
        check=True,
        capture_output=True,
        timeout=20,
    )


def test_drift_made_externally_is_found_and_restored(tmp_path: Path, sim: Simulator) -> None:
    inv = write_site(tmp_path, {"d1": sim.url})
    agent = AgentProcess(inv, tmp_path / "state", "--on-drift", "restore")
    try:
        c = agent.client
        # starting with --on-drift restore is consent to bring the device to the files' state
        until(lambda: event(c, "restored", "d1"), why="the first restore")
        assert sim.read("accel") == (20,) and sim.read("address") == (7,)
        until(lambda: c.device("d1")["status"] == "ok", why="d1 ok")
        before = len(c.events(kind="restored"))
        external_write(sim, 11, 77)  # decel 7.7 s, on the panel
        until(lambda: len(c.events(kind="restored")) > before, why="drift restored")
        drift = [e for e in c.events(kind="drift") if "decel is 7.7 s" in e["message"]]
        assert drift, c.events()
        assert sim.read("decel") == (30,)
        # within the tolerance (10 rpm) a different speed is no drift
        n = len(c.events(kind="drift"))
        external_write(sim, 12, 3005)
        c.check()
        c.check()
        assert len(c.events(kind="drift")) == n and sim.read("speed") == (3005,)
        assert agent.terminate() == 0
    finally:
        agent.kill()


def test_drift_only_reported_and_metrics_parse(tmp_path: Path, sim: Simulator) -> None:
    sim.write("accel", [20])
    sim.write("decel", [30])
    sim.write("speed", [3000])
    sim.write("address", [7])
    inv = write_site(tmp_path, {"d1": sim.url})
    agent = AgentProcess(inv, tmp_path / "state")  # --on-drift report (the default)
    try:
        c = agent.client
        until(lambda: c.device("d1")["status"] == "ok", why="d1 checked")
        external_write(sim, 10, 55)
        ev = until(lambda: event(c, "drift", "d1"), why="drift reported")
        assert "accel is 5.5 s (adopted 2 s)" in ev["message"]
        c.check()
        assert sim.read("accel") == (55,)  # reported, not written
        assert event(c, "restored") is None
        text = c.metrics()
        fams = {f.name: f for f in text_string_to_metric_families(text)}
        for name in (
            "deployer_device_status",
            "deployer_device_drifted",
            "deployer_drift_events",
            "deployer_drift_restores",
            "deployer_device_replaced",
            "deployer_register_writes",
            "deployer_last_check_timestamp_seconds",
            "deployer_pending_windows",
        ):
            assert name in fams, name

        def value(fam: str, **labels: str) -> float:
            for s in fams[fam].samples:
                if all(s.labels.get(k) == v for k, v in labels.items()):
                    return float(s.value)
            raise KeyError((fam, labels))

        assert value("deployer_device_drifted", device="d1") == 1
        assert value("deployer_device_status", device="d1", status="drifted") == 1
        assert value("deployer_device_status", device="d1", status="ok") == 0
        assert value("deployer_drift_events", device="d1") == 1
        assert value("deployer_register_writes", device="d1") == 0
        assert value("deployer_pending_windows", kind="confirm") == 0
        assert value("deployer_last_check_timestamp_seconds", device="d1") > 1.7e9
        # the device's log: the agent only read it
        assert all(e.function in (3, 43) for e in sim.log if e.values is None or e.function != 6 or e.address != 10)
        assert agent.terminate() == 0
        assert "agent stopped" in agent.log()
    finally:
        agent.kill()


def test_a_plain_apply_to_an_owned_device_is_refused_nothing_sent(tmp_path: Path, sim: Simulator) -> None:
    inv = write_site(tmp_path, {"d1": sim.url})
    agent = AgentProcess(inv, tmp_path / "state")
    try:
        until(lambda: agent.client.device("d1")["last_check"], why="a check")
        seen = len(sim.log)
        cli = subprocess.run(
            [
                sys.executable,
                "-m",
                "deployer",
                "apply",
                str(tmp_path / "r.yaml"),
                "--device",
                sim.url,
                "--yes",
                "--lock-timeout",
                "30",
                "--state-dir",
                str(tmp_path / "cli"),
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert cli.returncode == 3, cli.stderr
        said = cli.stdout + cli.stderr
        assert f"owned by the deployer agent at {agent.url}" in said and "--agent" in said, said
        assert "0 requests: 0 reads, 0 writes" in said
        ours = [e for e in sim.log[seen:] if e.function in (6, 16)]
        assert ours == []  # the agent only reads (report mode), and the CLI sent nothing
        assert agent.terminate() == 0
    finally:
        agent.kill()
    # the agent gone, its locks went with it: the same apply goes through
    ok = subprocess.run(
        [
            sys.executable,
            "-m",
            "deployer",
            "apply",
            str(tmp_path / "r.yaml"),
            "--device",
            sim.url,
            "--yes",
            "--state-dir",
            str(tmp_path / "cli"),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert ok.returncode == 0, ok.stderr


def test_api_errors_are_json_and_a_second_agent_is_refused(tmp_path: Path, sim: Simulator) -> None:
    inv = write_site(tmp_path, {"d1": sim.url})
    agent = AgentProcess(inv, tmp_path / "state")
    try:
        c = agent.client
        with pytest.raises(AgentError) as e:
            c.get("/v1/devices/nope")
        assert e.value.kind == "not-found"
        with pytest.raises(AgentError) as e:
            c.get("/v1/nothing-here")
        assert e.value.kind == "not-found"
        with pytest.raises(AgentError) as e:
            c.start_run(command="explode")  # type: ignore[arg-type]
        assert e.value.kind == "usage" and e.value.exit_code == 1
        info = c.info()
        assert info["api"] == 1 and info["auth"] == "token" and info["url"] == agent.url
        with pytest.raises(AgentError) as e:  # the files changed since the client looked: nothing sent
            c.start_run(files_sha256="0" * 64)
        assert e.value.kind == "conflict" and "changed since you looked" in str(e.value)
        asked = subprocess.run(
            [sys.executable, "-m", "deployer", "apply", "--agent", agent.url],
            capture_output=True,
            text=True,
            timeout=60,
            stdin=subprocess.DEVNULL,
        )
        assert asked.returncode == 1 and "pass --yes" in asked.stderr
        assert c.runs() == []
        second = subprocess.run(
            [
                sys.executable,
                "-m",
                "deployer",
                "agent",
                str(inv),
                "--state-dir",
                str(tmp_path / "state"),
                "--listen",
                "127.0.0.1:0",
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert second.returncode == 1 and "another agent runs on the state folder" in second.stderr
        wide = subprocess.run(
            [
                sys.executable,
                "-m",
                "deployer",
                "agent",
                str(inv),
                "--state-dir",
                str(tmp_path / "other"),
                "--listen",
                "0.0.0.0:0",
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert wide.returncode == 1 and "loopback only" in wide.stderr
        assert agent.terminate() == 0
    finally:
        agent.kill()
    with pytest.raises(AgentError) as e:
        Agent(agent.url, timeout=2).devices()
    assert e.value.kind == "unreachable" and e.value.exit_code == 3


def test_the_openapi_document_and_the_route_table_agree() -> None:
    import json
    import os

    from deployer.agent import server

    with open(os.path.join(os.path.dirname(server.__file__), "openapi.json"), encoding="utf-8") as f:
        doc = json.load(f)
    documented = {(m.upper(), p) for p, ops in doc["paths"].items() for m in ops}
    served = {(m, p) for m, p, _ in server.ROUTES}
    assert documented == served
    assert doc["info"]["version"] == "1" and all(p.startswith("/v1/") or p == "/metrics" for _, p in served)


def test_store_schema_version_and_a_newer_database_refused(tmp_path: Path) -> None:
    import sqlite3

    from deployer.agent.store import SCHEMA_VERSION, Store
    from deployer.errors import StateError

    s = Store(str(tmp_path / "a.sqlite3"))
    assert s.version() == SCHEMA_VERSION
    assert s.db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    s.event("drift", "d1: x", device="d1")
    s.close()
    again = Store(str(tmp_path / "a.sqlite3"))  # opening again migrates nothing and keeps the rows
    assert [e["kind"] for e in again.events()] == ["drift"]
    again.close()
    db = sqlite3.connect(tmp_path / "a.sqlite3")
    db.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    db.commit()
    db.close()
    with pytest.raises(StateError, match="newer than this deployer knows"):
        Store(str(tmp_path / "a.sqlite3"))


def test_per_group_settings_in_the_inventory(tmp_path: Path) -> None:
    (tmp_path / "drive.yaml").write_text(PROFILE)
    prof = load_profile(str(tmp_path / "drive.yaml"))
    with SimulatorThread(prof) as a, SimulatorThread(prof) as b:
        write_site(tmp_path, {})
        inv = tmp_path / "inv.yaml"
        inv.write_text(f"""\
defaults:
  recipe: r.yaml
groups:
  panel:
    agent: {{on_drift: restore, check_every: 200ms}}
devices:
  d1: {{url: "{a.url}", groups: [panel]}}
  d2: {{url: "{b.url}", agent: {{check_every: 250ms}}}}
""")
        agent = AgentProcess(inv, tmp_path / "state", check_every="1h")
        try:
            c = agent.client
            until(lambda: event(c, "restored", "d1"), why="d1 restored (its group restores)")
            until(lambda: event(c, "drift", "d2"), why="d2's drift")
            d2 = c.device("d2")
            assert d2["on_drift"] == "report" and d2["check_every"] == 0.25
            c.check()
            assert b.read("accel") == (50,) and a.read("accel") == (20,)
            assert agent.terminate() == 0
        finally:
            agent.kill()
    bad = tmp_path / "bad.yaml"
    bad.write_text(inv.read_text().replace("check_every: 200ms", "check_every: soon"))
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "deployer",
            "agent",
            str(bad),
            "--state-dir",
            str(tmp_path / "s2"),
            "--listen",
            "127.0.0.1:0",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 1 and "bad.yaml:5:" in out.stderr and "check_every" in out.stderr, out.stderr


def test_sighup_reads_the_files_again_and_a_device_that_keeps_drifting_is_not_fought(
    tmp_path: Path, sim: Simulator
) -> None:
    import signal

    inv = write_site(tmp_path, {"d1": sim.url})
    agent = AgentProcess(inv, tmp_path / "state", "--on-drift", "restore", "--max-restores", "2")
    try:
        c = agent.client
        until(lambda: event(c, "restored", "d1"), why="the first restore")  # the files' state at start: 1 of 2
        external_write(sim, 10, 66)
        until(lambda: len(c.events(kind="restored")) == 2, why="the second restore")
        external_write(sim, 10, 66)
        until(lambda: event(c, "restore-limit", "d1"), why="the limit")
        c.check()
        assert sim.read("accel") == (66,) and len(c.events(kind="restored")) == 2
        # an edit: SIGHUP reads it, shows it pending, writes nothing
        recipe = tmp_path / "r.yaml"
        recipe.write_text(recipe.read_text().replace("decel: 3 s", "decel: 4 s"))
        agent.proc.send_signal(signal.SIGHUP)
        until(lambda: event(c, "reload"), why="reloaded")
        pending = c.pending()["devices"]
        assert pending[0]["changes"] == [{"name": "decel", "adopted": "3 s", "files": "4 s"}]
        assert pending[0]["plan"] is not None
        assert sim.read("decel") == (30,)
        recipe.write_text("recipe: [broken")
        agent.proc.send_signal(signal.SIGHUP)
        ev = until(lambda: event(c, "reload-failed"), why="refused")
        assert any("r.yaml" in d for d in ev["detail"]["diagnostics"])
        assert c.pending()["devices"][0]["changes"][0]["files"] == "4 s"  # the last valid files still stand
        assert agent.terminate() == 0
    finally:
        agent.kill()


def test_a_device_from_another_library_watched_and_restored(tmp_path: Path) -> None:
    """umodbus serves the device (no Function 43): drift restored, the ledger equal to what it received."""
    from tests.helpers import umodbus_server

    # 40: the profile's health check (the first restore after the start reads it before and after its write)
    store = {0: 0x0A21, 10: 50, 11: 50, 12: 1500, 20: 1, 30: 0, 40: 0}
    wire: list[tuple[int, int, int]] = []
    with umodbus_server(store, wire=wire) as port:
        inv = write_site(tmp_path, {"d1": f"tcp://127.0.0.1:{port}"})
        agent = AgentProcess(inv, tmp_path / "state", "--on-drift", "restore")
        try:
            c = agent.client
            until(lambda: event(c, "restored", "d1"), why="restored at start")
            assert (store[10], store[11], store[12], store[20]) == (20, 30, 3000, 7)
            store[11] = 99  # changed on the device's own panel
            until(lambda: len(c.events(kind="restored")) == 2, why="restored again")
            assert store[11] == 30
            received: dict[int, int] = {}
            for fc, address, count in wire:
                if fc in (6, 16):
                    for a in range(address, address + count):
                        received[a] = received.get(a, 0) + 1
            led = {r["address"]: r["writes"] + r["commits"] for r in c.ledger()["devices"][0]["registers"]}
            assert led == received
            assert c.device("d1")["identity"]["function_43"] is False
            assert agent.terminate() == 0
        finally:
            agent.kill()


def test_watching_keeps_to_its_share_of_a_bus(tmp_path: Path) -> None:
    """Three units behind one address (one bus: a gateway's line), each answer 40 ms late: after reading a device
    the watch leaves the bus alone for at least four times as long (--bus-share 0.2), across rounds and a
    client's check at the same time too."""
    from deployer.testing.simulator import Faults

    (tmp_path / "drive.yaml").write_text(PROFILE)
    prof = load_profile(str(tmp_path / "drive.yaml"))
    with SimulatorThread(prof, listen="tcp://127.0.0.1:0", units=(1, 2, 3), faults=Faults(latency_ms=40)) as sim:
        port = sim.url.rsplit(":", 1)[1]
        write_site(tmp_path, {})
        inv = tmp_path / "inv.yaml"
        inv.write_text(
            "defaults: {recipe: r.yaml}\ndevices:\n"
            + "".join(f'  d{u}: {{url: "tcp://127.0.0.1:{port}", unit: {u}}}\n' for u in (1, 2, 3))
        )
        agent = AgentProcess(inv, tmp_path / "state", "--bus-share", "0.2", check_every="100ms")
        try:
            until(lambda: all(d["last_check"] for d in agent.client.devices()), why="all read")
            agent.client.check()
            assert agent.terminate() == 0
        finally:
            agent.kill()
    reads = [e for e in sim.log if e.function == 3]
    # consecutive reads of different units: the second starts at least 4 x 40 ms after the first answered
    gaps = [(b.time - a.time) for a, b in itertools.pairwise(reads) if a.unit != b.unit]
    assert gaps and min(gaps) >= 4 * 0.040 * 0.9, gaps


def test_runs_of_an_earlier_agent_are_listed_from_its_database(tmp_path: Path, sim: Simulator) -> None:
    inv = write_site(tmp_path, {"d1": sim.url})
    agent = AgentProcess(inv, tmp_path / "state")
    try:
        end = agent.client.apply()
        assert end["exit_code"] == 0
        assert agent.terminate() == 0
    finally:
        agent.kill()
    again = AgentProcess(inv, tmp_path / "state")
    try:
        runs = again.client.runs()
        assert [r["id"] for r in runs] == [end["run"]] and runs[0]["exit_code"] == 0
        assert runs[0]["report_path"].endswith(f"{end['run']}.json")
        with pytest.raises(AgentError) as e:
            again.client.run(end["run"])
        assert e.value.kind == "not-found" and "GET /v1/runs" in str(e.value)
        assert again.terminate() == 0
    finally:
        again.kill()
