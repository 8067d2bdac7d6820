"""The agent's first restores after a start go like a rollout: one device of each profile first, its health
watched, then the rest; the first device that does not end ok stops them, and the agent says so (an event,
sent to --notify receivers). A real agent process, five simulators of two profiles, a real HTTP receiver."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from deployer.profile import load_profile
from deployer.testing.simulator import Faults, LogEntry, Simulator, parse_fault_rule
from tests.agent_helpers import PROFILE, AgentProcess, event, until
from tests.helpers import Simulators
from tests.test_agent_notify import Receiver

pytestmark = pytest.mark.timeout(120)

OTHER = PROFILE.replace("profile: test-drive", "profile: other-drive")
RECIPE = "recipe: {name}\nprofile: {profile}\nparameters:\n  accel: 2 s\n  decel: 3 s\n  speed: 3000 rpm\n"
A = ["a1", "a2", "a3", "a4"]  # four drives of one profile, one of another
NAMES = [*A, "b1"]
WRITES = (6, 16)


@contextmanager
def site(tmp: Path, trip_a: bool = False) -> Iterator[tuple[Path, dict[str, Simulator]]]:
    """Five drives at their factory defaults: all drifted from the files when the agent starts. ``trip_a``: the
    drives of profile A trip (fault code 7) once their accel is below 3 s, which the recipe sets."""
    (tmp / "a.yaml").write_text(PROFILE)
    (tmp / "b.yaml").write_text(OTHER)
    (tmp / "ra.yaml").write_text(RECIPE.format(name="ra", profile="a.yaml"))
    (tmp / "rb.yaml").write_text(RECIPE.format(name="rb", profile="b.yaml"))
    pa, pb = load_profile(str(tmp / "a.yaml")), load_profile(str(tmp / "b.yaml"))
    trip = Faults(rules=(parse_fault_rule("accel < 3 s: 40=7", pa),)) if trip_a else None
    sims = [Simulator(pa, faults=trip) for _ in A] + [Simulator(pb)]
    with Simulators(sims):
        inv = tmp / "inv.yaml"
        inv.write_text(
            "devices:\n"
            + "".join(
                f'  {n}: {{url: "{s.url}", recipe: {"rb" if n == "b1" else "ra"}.yaml}}\n'
                for n, s in zip(NAMES, sims, strict=True)
            )
        )
        yield inv, dict(zip(NAMES, sims, strict=True))


def writes(log: list[LogEntry]) -> list[LogEntry]:
    return [e for e in log if e.function in WRITES]


def test_the_first_restores_go_one_device_of_each_profile_first(tmp_path: Path) -> None:
    with site(tmp_path) as (inv, sims):
        agent = AgentProcess(inv, tmp_path / "state", "--on-drift", "restore", first_restore_soak="1s")
        try:
            c = agent.client
            until(lambda: len(c.events(kind="restored")) == 5, why="all five restored", timeout=60)
            logs = {n: list(s.log) for n, s in sims.items()}
            runs = [r for r in c.runs() if r["command"] == "restore"]
        finally:
            agent.terminate()
    assert len(runs) == 1 and runs[0]["options"]["batch"] == "1,100%"  # one staged run, not five at once
    first_write = {n: writes(log)[0].time for n, log in logs.items()}
    canaries = sorted(NAMES, key=first_write.__getitem__)[:2]
    assert "b1" in canaries and len([n for n in canaries if n in A]) == 1  # one device of each profile
    rest = [n for n in NAMES if n not in canaries]
    for n in canaries:  # its health read before its write, and watched after it
        health = [e.time for e in logs[n] if e.function == 3 and e.address == 40]
        assert health[0] < first_write[n] < health[-1]
    # the rest started once the canaries' 1 s soak had passed (a lower bound: never flaky)
    assert min(first_write[n] for n in rest) >= max(first_write[n] for n in canaries) + 1.0
    assert all(s.read("accel") == (20,) for s in sims.values())


def test_a_failing_canary_stops_the_first_restores_and_notifies(tmp_path: Path) -> None:
    receiver = Receiver()
    with site(tmp_path, trip_a=True) as (inv, sims):
        agent = AgentProcess(
            inv, tmp_path / "state", "--on-drift", "restore", "--notify", receiver.url, first_restore_soak="1s"
        )
        try:
            c = agent.client
            stopped = until(lambda: event(c, "restores-stopped"), why="the restores stopped", timeout=60)
            until(lambda: any(b["kind"] == "restores-stopped" for b in receiver.got), why="notified")
            checks = c.info()["checks"]
            until(lambda: c.info()["checks"] >= checks + 5, why="more rounds of checks")  # drift: not restored
            logs = {n: list(s.log) for n, s in sims.items()}
            about = c.info()
            restored = [e["device"] for e in c.events(kind="restored")]
            drifted = {d["name"]: d["status"] for d in c.devices()}
        finally:
            agent.terminate()
    tripped = [n for n in A if writes(logs[n])]
    assert len(tripped) == 1  # the canary of profile A, written, tripped and rolled back
    (canary,) = tripped
    assert sims[canary].read("accel") == (50,)  # rolled back to what it held: 5 s
    assert [n for n in A if n != canary and writes(logs[n])] == []  # the rest: nothing written
    assert restored == ["b1"]  # the canary of the other profile passed
    assert f"stopped at {canary} (rolled-back: health check failed" in stopped["message"]
    assert "Automatic restores are off until the agent restarts" in stopped["message"]
    assert sorted(stopped["detail"]["not_restored"]) == sorted(A)
    assert about["restores_stopped"] is not None and about["options"]["first_restore_soak"] == 1.0
    assert all(drifted[n] == "drifted" for n in A if n != canary)


def test_an_apply_through_the_agent_keeps_health_before_the_change(tmp_path: Path) -> None:
    """POST /v1/runs: a soak does not write a device already in alarm; allow_unhealthy does, and needs a window."""
    from deployer.errors import AgentError

    (tmp_path / "a.yaml").write_text(PROFILE)
    (tmp_path / "ra.yaml").write_text(RECIPE.format(name="ra", profile="a.yaml"))
    prof = load_profile(str(tmp_path / "a.yaml"))
    with Simulators([Simulator(prof, init={40: 3})]) as (sim,):
        (tmp_path / "inv.yaml").write_text(f'devices:\n  d1: {{url: "{sim.url}", recipe: ra.yaml}}\n')
        agent = AgentProcess(tmp_path / "inv.yaml", tmp_path / "state")
        try:
            c = agent.client
            with pytest.raises(AgentError, match="allow_unhealthy goes with soak or confirm_within"):
                c.start_run(command="apply", allow_unhealthy=True)
            end = c.apply(command="apply", soak="200ms", health_interval="100ms")
            (dev,) = end["report"]["devices"]
            assert end["exit_code"] == 4 and dev["status"] == "failed"
            assert dev["error"].startswith(
                "health check already failing before the change: register 0x0028 (fault code is zero) is 3, expected 0"
            )
            assert writes(list(sim.log)) == []
            end = c.apply(command="apply", soak="200ms", health_interval="100ms", allow_unhealthy=True)
            assert end["exit_code"] == 0 and sim.read("accel") == (20,)
        finally:
            agent.terminate()
