"""A device (or gateway) that serves one TCP connection at a time: every step of a device's window (the soak's
health reads, the rollback, the re-read before the commit, the commit) goes over one connection at a time, so a
rollback is never left waiting behind the watch's own connection (FIELD.md: gateways allow 1-4 connections)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from deployer.testing.simulator import Faults, Quirks, SimulatorThread
from tests.helpers import cli, profile_from, umodbus_server, wait_for
from tests.test_safe import COMMIT, F07, FAULT, PROFILE, TRIP, deployer, recipe, writes_to
from tests.test_window import WATCHED

pytestmark = pytest.mark.timeout(120)
ONE = Quirks(max_connections=1)


def test_the_simulator_refuses_a_second_connection(tmp_path: Path) -> None:
    """What the tests below stand on: with max_connections=1 a second client is closed while the first is open."""
    import socket

    with SimulatorThread(PROFILE, quirks=ONE) as sim:
        host, port = sim.url.removeprefix("tcp://").rsplit(":", 1)
        with socket.create_connection((host, int(port)), timeout=2) as first:
            with socket.create_connection((host, int(port)), timeout=2) as second:
                second.sendall(bytes.fromhex("000100000006010320000001"))
                assert second.recv(64) == b""  # closed, unanswered
            first.sendall(bytes.fromhex("000100000006010320000001"))
            assert first.recv(64)[7] == 3  # the first one is served
        assert sim.refused_connections == 1


def test_deployer_simulate_max_connections_refuses_the_second_client() -> None:
    import socket
    import sys

    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "deployer",
            "simulate",
            "example-inverter",
            "--listen",
            "tcp://127.0.0.1:0",
            "--max-connections",
            "1",
        ],
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()
        host, port = line.split(" on tcp://", 1)[1].split()[0].rsplit(":", 1)
        with socket.create_connection((host, int(port)), timeout=5) as first:
            with socket.create_connection((host, int(port)), timeout=5) as second:
                second.sendall(bytes.fromhex("000100000006010320000001"))
                assert second.recv(64) == b""
            first.sendall(bytes.fromhex("000200000006010320000001"))
            assert first.recv(64)[:2] == b"\x00\x02"
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_a_soak_that_trips_rolls_back_over_one_connection_and_never_commits(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    with SimulatorThread(PROFILE, faults=Faults(rules=(TRIP,)), quirks=ONE) as sim:
        before = sim.registers()
        code, out, err = cli(
            capsys,
            "apply",
            recipe(tmp_path, "1.5 s", sim.url),
            "--yes",
            "--json",
            "--soak",
            "1h",
            "--health-interval",
            "100ms",
            "--state-dir",
            str(tmp_path / "s"),
        )
        after, log, refused = sim.registers(), list(sim.log), sim.refused_connections
    assert code == 4, err
    dev = json.loads(out)["devices"][0]
    assert dev["status"] == "rolled-back" and dev["commit"] == "not sent", dev["error"]
    assert "rolled back from the snapshot (verified)" in dev["error"]
    assert refused == 0
    assert {a: v for a, v in after.items() if a != FAULT} == {a: v for a, v in before.items() if a != FAULT}
    assert after[FAULT] == 7 and writes_to(log, COMMIT) == []
    assert len(writes_to(log, F07)) == 2  # the change and its rollback


def test_a_passing_soak_commits_over_one_connection(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    with SimulatorThread(PROFILE, quirks=ONE) as sim:
        code, out, err = cli(
            capsys,
            "apply",
            recipe(tmp_path, "3 s", sim.url),
            "--yes",
            "--json",
            "--soak",
            "300ms",
            "--health-interval",
            "100ms",
            "--state-dir",
            str(tmp_path / "s"),
        )
        log, refused = list(sim.log), sim.refused_connections
    assert code == 0, err
    dev = json.loads(out)["devices"][0]
    assert dev["status"] == "ok" and dev["commit"] == "sent"
    assert refused == 0 and len(writes_to(log, COMMIT)) == 1 and len(writes_to(log, F07)) == 1


@pytest.mark.parametrize("trip", [False, True], ids=["expired", "tripped"])
def test_a_confirmation_window_rolls_back_over_one_connection(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, trip: bool
) -> None:
    """The confirmation runs out (or the health trips while it is awaited): rolled back, verified, no commit."""
    faults = Faults(rules=(TRIP,)) if trip else None
    with SimulatorThread(PROFILE, faults=faults, quirks=ONE) as sim:
        before = sim.registers()
        code, out, err = cli(
            capsys,
            "apply",
            recipe(tmp_path, "1.5 s", sim.url),
            "--yes",
            "--json",
            "--confirm-within",
            "1s" if not trip else "1h",
            "--health-interval",
            "100ms",
            "--state-dir",
            str(tmp_path / "s"),
        )
        after, log, refused = sim.registers(), list(sim.log), sim.refused_connections
    assert code == 4, err
    dev = json.loads(out)["devices"][0]
    assert dev["status"] == "rolled-back" and dev["commit"] == "not sent", dev["error"]
    assert "rolled back from the snapshot (verified)" in dev["error"]
    assert refused == 0 and writes_to(log, COMMIT) == []
    assert {a: v for a, v in after.items() if a != FAULT} == {a: v for a, v in before.items() if a != FAULT}


def test_a_single_threaded_umodbus_device_is_rolled_back_when_its_health_fails(tmp_path: Path) -> None:
    """umodbus serves one connection at a time: a second one waits in its backlog until the first closes."""
    prof = profile_from(tmp_path, WATCHED, "w.yaml")
    assert prof.commit
    store = {0x10: 1, 0x20: 0, 0x30: 0}
    wire: list[tuple[int, int, int]] = []
    with umodbus_server(store, wire=wire) as port:
        r = tmp_path / "r.yaml"
        r.write_text(f"recipe: r\nprofile: w.yaml\ndevice: {{url: 'tcp://127.0.0.1:{port}'}}\nparameters:\n  x: 5\n")
        proc = deployer(
            "apply",
            str(r),
            "--yes",
            "--json",
            "--soak",
            "1h",
            "--health-interval",
            "100ms",
            "--state-dir",
            str(tmp_path / "s"),
        )
        try:
            wait_for(lambda: any(w[:2] == (3, 0x20) for w in list(wire)) or proc.poll() is not None)
            store[0x20] = 9  # the device faults
            out, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
        finally:
            if proc.poll() is None:
                proc.kill()
    assert proc.returncode == 4, err
    dev = json.loads(out)["devices"][0]
    assert dev["status"] == "rolled-back" and dev["commit"] == "not sent", dev["error"]
    assert store == {0x10: 1, 0x20: 9, 0x30: 0}
    assert [w for w in wire if w[0] in (6, 16)] == [(16, 0x10, 1), (16, 0x10, 1)] or [
        w for w in wire if w[0] in (6, 16)
    ] == [(6, 0x10, 1), (6, 0x10, 1)]


def gateway(tmp_path: Path, url: str, trips: tuple[int, ...]) -> str:
    """Units 1-3 behind one address; the units in ``trips`` get a ramp that trips them."""
    inv = tmp_path / "inventory.yaml"
    inv.write_text(
        "defaults: {timeout: 2.0, retries: 1}\ndevices:\n"
        + "".join(
            f"  d{u}: {{url: '{url}', unit: {u}" + (", parameters: {F07: 1.5 s}}\n" if u in trips else "}\n")
            for u in (1, 2, 3)
        )
    )
    return str(inv)


def test_units_behind_a_one_connection_gateway_roll_back_one_after_another_and_the_rest_commit(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """Two units trip during the soak: each rollback waits for the watch's connection to close, the one still
    healthy is watched again over a new connection and committed."""
    with SimulatorThread(PROFILE, units=(1, 2, 3), faults=Faults(rules=(TRIP,)), quirks=ONE) as sim:
        inv = gateway(tmp_path, sim.url, (2, 3))
        code, out, err = cli(
            capsys,
            "apply",
            recipe(tmp_path, "3 s"),
            "--inventory",
            inv,
            "--yes",
            "--json",
            "--soak",
            "1s",
            "--health-interval",
            "100ms",
            "--state-dir",
            str(tmp_path / "s"),
        )
        log, refused = list(sim.log), sim.refused_connections
        f07 = {u: sim.read("F07", u) for u in (1, 2, 3)}
    assert code == 4, err
    d1, d2, d3 = json.loads(out)["devices"]
    assert (d1["status"], d1["commit"]) == ("ok", "sent")
    assert [(d["status"], d["commit"]) for d in (d2, d3)] == [("rolled-back", "not sent")] * 2, (d2, d3)
    assert all("rolled back from the snapshot (verified)" in d["error"] for d in (d2, d3))
    assert refused == 0
    assert f07 == {1: (0, 300), 2: (0, 500), 3: (0, 500)}
    assert [log[i].unit for i in writes_to(log, COMMIT)] == [1]
    assert "soak passed" in " ".join(d1["notices"])


def test_an_expired_confirmation_rolls_back_every_unit_of_a_one_connection_gateway(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    with SimulatorThread(PROFILE, units=(1, 2, 3), quirks=ONE) as sim:
        code, out, err = cli(
            capsys,
            "apply",
            recipe(tmp_path, "3 s"),
            "--inventory",
            gateway(tmp_path, sim.url, ()),
            "--yes",
            "--json",
            "--confirm-within",
            "1s",
            "--health-interval",
            "100ms",
            "--state-dir",
            str(tmp_path / "s"),
        )
        log, refused = list(sim.log), sim.refused_connections
        f07 = {u: sim.read("F07", u) for u in (1, 2, 3)}
    assert code == 4, err
    devices = json.loads(out)["devices"]
    assert [(d["status"], d["commit"]) for d in devices] == [("rolled-back", "not sent")] * 3, devices
    assert refused == 0 and writes_to(log, COMMIT) == []
    assert f07 == {1: (0, 500), 2: (0, 500), 3: (0, 500)}
