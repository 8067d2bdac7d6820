"""A replaced device: back at factory values after being unreachable, another revision (Function 43): its
as-left values restored except per-unit ones; another model refused with nothing written. The endurance budget."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from deployer.profile import Profile, load_profile
from deployer.testing.simulator import Quirks, SimulatorThread
from tests.agent_helpers import PROFILE, AgentProcess, event, until, write_site

pytestmark = pytest.mark.timeout(120)

ACME = {0: "ACME", 1: "D100", 2: "1.0"}


def on_port(prof: Profile, port: str, **kw: Any) -> SimulatorThread:
    """A simulator on the port another one left. The agent keeps connecting there while nothing listens, and
    Linux may pick that very port as the connection's own (a socket connected to itself): it holds the port
    until the agent's read times out, so binding is tried again for a while."""
    for _ in range(100):
        t = SimulatorThread(prof, listen=f"tcp://127.0.0.1:{port}", **kw)
        try:
            t.__enter__()
            return t
        except RuntimeError:
            t._loop.call_soon_threadsafe(t._loop.stop)
            time.sleep(0.2)
    raise AssertionError(f"port {port} stayed taken")


def configured(sim: object) -> None:
    for name, regs in (("accel", [20]), ("decel", [30]), ("speed", [3000]), ("address", [7])):
        sim.write(name, regs)  # type: ignore[attr-defined]


def test_replaced_device_restored_per_unit_untouched_other_model_refused(tmp_path: Path) -> None:
    (tmp_path / "drive.yaml").write_text(PROFILE)
    prof = load_profile(str(tmp_path / "drive.yaml"))
    first = SimulatorThread(prof, quirks=Quirks(identity=dict(ACME)))
    sim = first.__enter__()
    port = sim.url.rsplit(":", 1)[1]
    configured(sim)
    inv = write_site(tmp_path, {"d1": sim.url})
    agent = AgentProcess(inv, tmp_path / "state", "--on-replace", "restore")
    try:
        c = agent.client
        until(lambda: c.device("d1")["status"] == "ok", why="d1 as left")
        assert c.device("d1")["identity"]["objects"] == {"vendor": "ACME", "product_code": "D100", "revision": "1.0"}
        first.__exit__(None, None, None)  # the drive is swapped: gone for a while ...
        until(lambda: event(c, "unreachable", "d1"), why="unreachable")
        # ... and a new unit of the same model answers: another revision, factory values, its own address set
        second = on_port(prof, port, init={20: 9}, quirks=Quirks(identity={**ACME, 2: "1.1"}))
        new = second.sim
        try:
            until(lambda: event(c, "restored", "d1"), why="restored")
            ev = event(c, "replaced", "d1")
            assert ev is not None and "revision '1.0' -> '1.1'" in ev["message"]
            assert new.read("accel") == (20,) and new.read("decel") == (30,) and new.read("speed") == (3000,)
            assert new.read("address") == (9,)  # per_unit: the new unit keeps its own
            assert not [e for e in new.log if e.function in (6, 16) and e.address == 20]
        finally:
            second.__exit__(None, None, None)
        until(lambda: c.device("d1")["status"] == "unreachable", why="gone again")
        # a different model at the address: refused, nothing written
        third = on_port(prof, port, quirks=Quirks(identity={0: "ACME", 1: "D200", 2: "3.0"}))
        other = third.sim
        try:

            def by_model() -> list[dict[str, Any]]:  # (a socket the agent connected to itself while the port
                # was free answers nonsense, refused as another kind of device: not this event)
                return [e for e in c.events(kind="replace-refused", device="d1") if "another model" in e["message"]]

            ev2 = until(by_model, why="refused")[-1]
            assert "product_code 'D100' -> 'D200'" in ev2["message"]
            c.check()
            c.check()
            assert [e for e in other.log if e.function in (6, 16)] == []
            assert c.device("d1")["status"] == "replaced"
            assert len(by_model()) == 1  # said once, not at every check
        finally:
            third.__exit__(None, None, None)
        assert agent.terminate() == 0
    finally:
        agent.kill()


def test_identity_registers_of_another_kind_refused(tmp_path: Path) -> None:
    (tmp_path / "drive.yaml").write_text(PROFILE)
    prof = load_profile(str(tmp_path / "drive.yaml"))
    with SimulatorThread(prof, init={0: 0x0B00}) as sim:
        inv = write_site(tmp_path, {"d1": sim.url})
        agent = AgentProcess(inv, tmp_path / "state", "--on-replace", "restore", "--on-drift", "restore")
        try:
            ev = until(lambda: event(agent.client, "replace-refused", "d1"), why="refused")
            assert "0x0B00" in ev["message"]
            agent.client.check()
            assert [e for e in sim.log if e.function in (6, 16)] == []
            assert agent.terminate() == 0
        finally:
            agent.kill()


def test_endurance_warns_then_refuses_unless_forced(tmp_path: Path) -> None:
    profile = PROFILE.replace("endurance: 1000", "endurance: 3")
    (tmp_path / "drive.yaml").write_text(profile)
    prof = load_profile(str(tmp_path / "drive.yaml"))
    with SimulatorThread(prof) as sim:
        inv = write_site(tmp_path, {"d1": sim.url}, profile=profile)
        agent = AgentProcess(inv, tmp_path / "state", "--endurance-warn", "0.5")
        env = {**os.environ, "DEPLOYER_AGENT": agent.url}
        try:
            c = agent.client
            for _ in range(2):  # each apply writes the values (write-all) and commits: 1 write per register
                end = c.apply(write_all=True)
                assert end["exit_code"] == 0, end
            assert event(c, "endurance-warning", "d1") is not None
            end = c.apply(write_all=True)
            assert end["exit_code"] == 0
            before = len(sim.log)
            refused = subprocess.run(
                [sys.executable, "-m", "deployer", "apply", "--yes", "--write-all"],
                capture_output=True,
                text=True,
                timeout=60,
                env=env,
            )
            assert refused.returncode == 1 and "past the rated endurance" in refused.stderr, refused.stderr
            assert "--force-endurance" in refused.stderr
            assert [e for e in sim.log[before:] if e.function in (6, 16)] == []
            forced = subprocess.run(
                [sys.executable, "-m", "deployer", "apply", "--yes", "--write-all", "--force-endurance"],
                capture_output=True,
                text=True,
                timeout=60,
                env=env,
            )
            assert forced.returncode == 0, forced.stderr
            assert agent.terminate() == 0
        finally:
            agent.kill()


def test_back_at_factory_values_after_being_unreachable_is_a_replacement(tmp_path: Path) -> None:
    """A device without Function 43: the factory values after a gap are what gives it away."""
    (tmp_path / "drive.yaml").write_text(PROFILE)
    prof = load_profile(str(tmp_path / "drive.yaml"))
    first = SimulatorThread(prof)
    sim = first.__enter__()
    port = sim.url.rsplit(":", 1)[1]
    configured(sim)
    inv = write_site(tmp_path, {"d1": sim.url})
    agent = AgentProcess(inv, tmp_path / "state", "--on-replace", "restore")
    try:
        c = agent.client
        until(lambda: c.device("d1")["status"] == "ok", why="d1 as left")
        assert c.device("d1")["identity"]["function_43"] is False
        first.__exit__(None, None, None)
        until(lambda: event(c, "unreachable", "d1"), why="unreachable")
        second = on_port(prof, port, init={20: 9})
        try:
            new = second.sim
            until(lambda: event(c, "restored", "d1"), why="restored")
            ev = event(c, "replaced", "d1")
            assert ev is not None and "factory defaults" in ev["message"]
            assert new.read("accel") == (20,) and new.read("address") == (9,)
        finally:
            second.__exit__(None, None, None)
        assert agent.terminate() == 0
    finally:
        agent.kill()
