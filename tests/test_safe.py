"""Safe changes: health checks, soak, commit-confirmed writes and automatic rollback, against real sockets."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from decimal import Decimal
from pathlib import Path

import jsonschema
import pytest

from deployer.errors import UsageError
from deployer.load import schema
from deployer.load.durations import format_duration, parse_duration
from deployer.profile import builtin_profile
from deployer.testing.simulator import Faults, LogEntry, Simulator, SimulatorThread, parse_fault_rule
from deployer.window.confirm import awaiting, confirm_run
from tests.helpers import Simulators, cli, profile_from, wait_for

pytestmark = pytest.mark.timeout(180)
PROFILE = builtin_profile("example-inverter")
FAULT = PROFILE.health[0].address  # wire 0x2000: "drive fault code is zero"
COMMIT = PROFILE.commit[0].address  # wire 0x08FF: store to EEPROM
F07 = PROFILE.parameter("F07").address
MBPOLL = shutil.which("mbpoll")
TRIP = parse_fault_rule("F07 < 2 s: 0x2000=7", PROFILE)  # the drive trips on a short acceleration time


def recipe(tmp: Path, f07: str, url: str | None = None, name: str = "r.yaml") -> str:
    p = tmp / name
    device = f"device: {{url: '{url}', unit: 1}}\n" if url else ""
    p.write_text(f"recipe: ramp\nprofile: example-inverter\n{device}parameters:\n  F07: {f07}\n  F08: 3 s\n")
    return str(p)


def inventory(tmp: Path, urls: dict[str, str]) -> str:
    p = tmp / "inventory.yaml"
    p.write_text(
        "defaults: {timeout: 2.0, retries: 1}\ndevices:\n"
        + "".join(f"  {n}: {{url: '{u}'}}\n" for n, u in urls.items())
    )
    return str(p)


def writes_to(log: list[LogEntry], address: int) -> list[int]:
    """Indexes of the write requests (FC06/16) that reach ``address``."""
    return [i for i, e in enumerate(log) if e.function in (6, 16) and e.address <= address < e.address + e.count]


def reads_of(log: list[LogEntry], address: int) -> list[int]:
    return [i for i, e in enumerate(log) if e.function in (3, 4) and e.address <= address < e.address + e.count]


def deployer(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "deployer", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


# ---- profiles and durations -----------------------------------------------------------------------


def test_health_checks_load_with_bits_ranges_and_input_registers(tmp_path: Path) -> None:
    prof = profile_from(
        tmp_path,
        """profile: p
addressing: modicon
health:
  - {register: 40049, equals: 0, description: drive fault code is zero}
  - {register: 40050, bits: 3, equals: 0, description: no alarm}
  - {register: 30010, register_type: input, min: 100, max: 850, description: DC bus}
parameters:
  x: {register: 40065, type: uint16}
""",
    )
    fault, alarm, bus = prof.health
    assert (fault.address, fault.function, fault.holds(0), fault.holds(7)) == (48, 3, True, False)
    assert alarm.holds(0xFFF7) and not alarm.holds(0x0008)
    assert (bus.address, bus.function, bus.holds(100), bus.holds(850), bus.holds(851)) == (9, 4, True, True, False)
    assert bus.failure(900) == "input register 0x0009 (DC bus) is 900, expected 100..850"
    assert alarm.failure(8) == "register 0x0031 bit 3 (no alarm) is 1, expected 0"


@pytest.mark.parametrize(
    ("text", "seconds"),
    [("250ms", 0.25), ("30s", 30), ("5m", 300), ("1h", 3600), ("1.5 s", 1.5), ("2", 2), ("2min", 120)],
)
def test_durations(text: str, seconds: float) -> None:
    assert parse_duration(text) == seconds
    assert parse_duration(format_duration(seconds)) == seconds


def test_a_bare_number_is_in_the_callers_unit_and_nonsense_is_refused() -> None:
    assert parse_duration("250", bare="ms") == 0.25
    for bad in ("5 parsecs", "-1s", "s", "", "2w", "9999h"):
        with pytest.raises(ValueError, match="duration|unknown unit|longer than a week"):
            parse_duration(bad)


def test_a_bad_duration_option_is_a_usage_error(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code, _, err = cli(capsys, "apply", recipe(tmp_path, "3 s", "tcp://127.0.0.1:9"), "--yes", "--soak", "5 parsecs")
    assert code == 1 and "unknown unit 'parsecs'" in err


def test_soak_without_health_checks_is_refused_up_front(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    p = tmp_path / "r.yaml"
    p.write_text("recipe: r\nprofile: omron-m1\ndevice: {url: 'tcp://127.0.0.1:9'}\nparameters:\n  F07: 10 s\n")
    code, _, err = cli(capsys, "apply", str(p), "--yes", "--soak", "30s")
    assert code == 1 and "profile omron-m1 declares none" in err


# ---- the soak -----------------------------------------------------------------------------------


def test_a_healthy_soak_ends_ok_and_the_commit_follows_it(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    with SimulatorThread(PROFILE) as sim:
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
        assert code == 0 and "watching the health of ramp for 300ms (every 100ms)" in err
        dev = json.loads(out)["devices"][0]
        assert dev["status"] == "ok" and dev["commit"] == "sent"
        log = list(sim.log)
    (write,) = writes_to(log, F07)
    (commit,) = writes_to(log, COMMIT)
    health = reads_of(log, FAULT)
    before, *soaked = health  # read once before the change (a device already in alarm is not written) ...
    assert before < write and len(soaked) >= 2 and write < soaked[0] and soaked[-1] < commit  # ... soaked, committed
    events = [json.loads(x)["event"] for x in (tmp_path / "s" / "audit.jsonl").read_text().splitlines()]
    assert events.index("soak-started") < events.index("soak-finished") < events.index("commit")


def test_a_fault_during_the_soak_rolls_back_exactly_and_never_commits(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    with SimulatorThread(PROFILE, faults=Faults(rules=(TRIP,))) as sim:
        before = sim.registers()
        code, out, _ = cli(
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
            "--report",
            str(tmp_path / "run.json"),
        )
        after = sim.registers()
        log = list(sim.log)
    assert code == 4
    report = json.loads(out)
    jsonschema.validate(report, schema.schema("report"))
    dev = report["devices"][0]
    assert dev["status"] == "rolled-back" and dev["commit"] == "not sent"
    assert "register 0x2000 (drive fault code is zero) is 7, expected 0" in dev["error"]
    assert "rolled back from the snapshot (verified)" in dev["error"]
    assert "of the 1h soak (its first check after the write): " in dev["error"]  # it trips on the write
    assert report["summary"]["rolled-back"] == 1
    f07 = next(p for p in dev["parameters"] if p["name"] == "F07")
    assert f07["status"] == "rolled-back" and f07["after_raw"] == f07["before_raw"] == [0, 500]
    # every parameter register is back to what it was; only the fault register (the device's own) differs
    assert {a: v for a, v in after.items() if a != FAULT} == {a: v for a, v in before.items() if a != FAULT}
    assert after[FAULT] == 7 and writes_to(log, COMMIT) == []
    journal = [json.loads(x) for x in (tmp_path / "s" / "audit.jsonl").read_text().splitlines()]
    failed = next(r for r in journal if r["event"] == "health-failed")
    assert "is 7, expected 0" in failed["reason"]
    assert [r["event"] for r in journal if r["event"] in ("soak-started", "rolled-back", "soak-finished")] == [
        "soak-started",
        "rolled-back",
        "soak-finished",
    ]
    # a rollback from that report leaves the device alone: it was already restored
    code, _, err = cli(
        capsys, "rollback", "--report", str(tmp_path / "run.json"), "--yes", "--state-dir", str(tmp_path / "s")
    )
    assert code == 1 and "already rolled it back" in err


@pytest.mark.skipif(MBPOLL is None, reason="mbpoll (libmodbus) is not installed")
def test_a_fault_written_by_mbpoll_during_the_soak_rolls_back(tmp_path: Path) -> None:
    """An independent client (libmodbus) makes the device fault while the change soaks."""
    assert MBPOLL is not None
    with SimulatorThread(PROFILE) as sim:
        before = sim.registers()
        state = tmp_path / "s"
        proc = deployer(
            "apply",
            recipe(tmp_path, "3 s", sim.url),
            "--yes",
            "--json",
            "--soak",
            "1h",
            "--health-interval",
            "100ms",
            "--state-dir",
            str(state),
        )
        try:
            wait_for(lambda: len(reads_of(list(sim.log), FAULT)) >= 2)  # the soak is under way
            port = sim.url.rsplit(":", 1)[1]
            poke = subprocess.run(
                [MBPOLL, "-m", "tcp", "-p", port, "-a", "1", "-0", "-1", "-r", str(FAULT), "-t", "4", "127.0.0.1", "9"],
                capture_output=True,
                text=True,
                timeout=30,
            )
            assert poke.returncode == 0, poke.stdout + poke.stderr
            out, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
        log = list(sim.log)
        after = sim.registers()
    assert proc.returncode == 4, err
    dev = json.loads(out)["devices"][0]
    assert dev["status"] == "rolled-back" and "is 9, expected 0" in dev["error"]
    assert "first check" not in dev["error"]  # the fault came while the soak was under way
    assert {a: v for a, v in after.items() if a != FAULT} == {a: v for a, v in before.items() if a != FAULT}
    assert writes_to(log, COMMIT) == []


def test_the_simulator_trips_only_when_the_rule_holds(tmp_path: Path) -> None:
    assert (TRIP.parameter, TRIP.op, TRIP.value, TRIP.register, TRIP.raw) == ("F07", "<", Decimal(2), 0x2000, 7)
    coast = parse_fault_rule("stop_mode == coast: 0x2000=3", PROFILE)
    assert coast.by_label and coast.value == 1
    assert parse_fault_rule("F07 <= 1500 ms: 8192=1", PROFILE).value == 1.5
    for bad, why in [
        ("F07 ~ 2 s: 1=1", "not a fault rule"),
        ("nope < 2: 1=1", "not a numeric holding-register parameter"),
        ("F07 < 2 Hz: 1=1", "convertible"),
        ("F07 < x: 1=1", "not a number"),
    ]:
        with pytest.raises(ValueError, match=why):
            parse_fault_rule(bad, PROFILE)
    with pytest.raises(ValueError, match="not declared"):
        Simulator(PROFILE, faults=Faults(rules=(parse_fault_rule("F07 < 2 s: 0x7000=1", PROFILE),)))


def test_health_on_input_registers_reads_function_04(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    prof = profile_from(
        tmp_path,
        """profile: p
health:
  - {register: 0x10, register_type: input, max: 850, description: DC bus below 850}
commit:
  - {register: 0x20, raw: 1, description: store}
parameters:
  x: {register: 0x40, type: uint16}
""",
        "p.yaml",
    )
    with SimulatorThread(prof, init={prof.health[0].key: 900}) as sim:
        r = tmp_path / "r.yaml"
        r.write_text(f"recipe: r\nprofile: p.yaml\ndevice: {{url: '{sim.url}'}}\nparameters:\n  x: 5\n")
        code, out, _ = cli(
            capsys,
            "apply",
            str(r),
            "--yes",
            "--json",
            "--soak",
            "10s",
            "--health-interval",
            "100ms",
            "--state-dir",
            str(tmp_path / "s"),
        )
        log = list(sim.log)
        assert sim.read("x") == (0,)
    assert code == 4
    dev = json.loads(out)["devices"][0]
    assert "input register 0x0010 (DC bus below 850) is 900, expected at most 850" in dev["error"]
    assert any(e.function == 4 and e.address == 0x10 for e in log) and writes_to(log, 0x20) == []


# ---- confirm-within ---------------------------------------------------------------------------------


def test_confirmed_from_another_shell_sends_the_commit(tmp_path: Path) -> None:
    state = str(tmp_path / "s")
    with SimulatorThread(PROFILE) as sim:
        proc = deployer(
            "apply", recipe(tmp_path, "3 s", sim.url), "--yes", "--json", "--confirm-within", "1h", "--state-dir", state
        )
        try:
            wait_for(lambda: bool(awaiting(state)) or proc.poll() is not None)
            assert writes_to(list(sim.log), COMMIT) == []  # held back while it waits
            confirmed = subprocess.run(
                [sys.executable, "-m", "deployer", "confirm", "--state-dir", state],
                capture_output=True,
                text=True,
                timeout=60,
            )
            assert confirmed.returncode == 0, confirmed.stderr
            out, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
        log = list(sim.log)
    assert proc.returncode == 0, err
    assert "deployer confirm" in err and "waiting for confirmation" in err
    dev = json.loads(out)["devices"][0]
    assert dev["status"] == "ok" and dev["commit"] == "sent" and len(writes_to(log, COMMIT)) == 1
    assert writes_to(log, F07)[0] < writes_to(log, COMMIT)[0]
    events = [json.loads(x)["event"] for x in Path(state, "audit.jsonl").read_text().splitlines()]
    assert events.index("confirm-awaited") < events.index("confirmed") < events.index("commit")
    assert not os.listdir(os.path.join(state, "pending"))  # the report kept while waiting is gone


def test_not_confirmed_in_time_rolls_back_without_a_commit(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    with SimulatorThread(PROFILE) as sim:
        before = sim.registers()
        code, out, _ = cli(
            capsys,
            "apply",
            recipe(tmp_path, "3 s", sim.url),
            "--yes",
            "--json",
            "--confirm-within",
            "200ms",
            "--state-dir",
            str(tmp_path / "s"),
        )
        after = sim.registers()
        log = list(sim.log)
    assert code == 4
    dev = json.loads(out)["devices"][0]
    assert dev["status"] == "rolled-back" and "not confirmed within 200ms" in dev["error"]
    assert after == before and writes_to(log, COMMIT) == []
    events = [json.loads(x)["event"] for x in (tmp_path / "s" / "audit.jsonl").read_text().splitlines()]
    assert "confirm-expired" in events and "rolled-back" in events


def test_a_killed_waiter_is_shown_by_status_and_its_restore_command_works(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    state = str(tmp_path / "s")
    with SimulatorThread(PROFILE) as sim:
        before = sim.registers()
        proc = deployer(
            "apply", recipe(tmp_path, "3 s", sim.url), "--yes", "--confirm-within", "1h", "--state-dir", state
        )
        try:
            wait_for(lambda: bool(awaiting(state)) or proc.poll() is not None)
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.communicate(timeout=60)
        assert sim.registers()[F07 + 1] == 300  # the new value is in the device, uncommitted
        code, out, _ = cli(capsys, "status", "--state-dir", state)
        assert code == 2 and "awaited confirmation" in out and "never committed" in out
        restore = next(line.split("restore them with: ", 1)[1] for line in out.splitlines() if "restore them" in line)
        with pytest.raises(UsageError, match="process .* is gone"):
            confirm_run(state)
        code, _, err = cli(capsys, *restore.split()[1:])
        assert code == 0, err
        # restored; a rollback then stores the restored values (the profile's commit), as every rollback does
        assert {a: v for a, v in sim.registers().items() if a != COMMIT} == {
            a: v for a, v in before.items() if a != COMMIT
        }


def test_confirm_without_a_waiting_run_says_so(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code, _, err = cli(capsys, "confirm", "--state-dir", str(tmp_path / "s"))
    assert code == 1 and "no run waits for a confirmation" in err


# ---- fleets -----------------------------------------------------------------------------------------


def test_a_canary_failing_health_is_rolled_back_and_the_rest_skipped(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    with Simulators([Simulator(PROFILE, faults=Faults(rules=(TRIP,)) if i == 0 else None) for i in range(4)]) as sims:
        urls = {f"d{i}": s.url for i, s in enumerate(sims)}
        code, out, err = cli(
            capsys,
            "apply",
            recipe(tmp_path, "1.5 s"),
            "--inventory",
            inventory(tmp_path, urls),
            "--yes",
            "--json",
            "--batch",
            "1,100%",
            "--soak",
            "1h",
            "--health-interval",
            "100ms",
            "--state-dir",
            str(tmp_path / "s"),
        )
        logs = [list(s.log) for s in sims]
    assert code == 4
    assert "d0: rolled-back - health check failed after" in err  # a progress line when the soak rolls it back
    report = json.loads(out)
    jsonschema.validate(report, schema.schema("report"))
    first, *rest = report["devices"]
    assert first["status"] == "rolled-back" and writes_to(logs[0], COMMIT) == []
    for d, log in zip(rest, logs[1:], strict=True):
        assert d["status"] == "skipped" and "canary batch 1 failed its health checks (d0 rolled back)" in d["error"]
        assert log == []


def test_rollback_on_failure_restores_the_devices_that_passed(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """Batch 1 = d0 (healthy) and d1 (trips): d1 is rolled back by its soak, the rollout stops, and
    --rollback-on-failure restores d0 too (its committed values are committed back)."""
    with Simulators([Simulator(PROFILE, faults=Faults(rules=(TRIP,)) if i == 1 else None) for i in range(3)]) as sims:
        before = [s.registers() for s in sims]
        urls = {f"d{i}": s.url for i, s in enumerate(sims)}
        code, out, _ = cli(
            capsys,
            "apply",
            recipe(tmp_path, "1.5 s"),
            "--inventory",
            inventory(tmp_path, urls),
            "--yes",
            "--json",
            "--batch",
            "2,100%",
            "--soak",
            "300ms",
            "--health-interval",
            "100ms",
            "--rollback-on-failure",
            "--state-dir",
            str(tmp_path / "s"),
        )
        after = [s.registers() for s in sims]
        logs = [list(s.log) for s in sims]
    assert code == 4
    d0, d1, d2 = json.loads(out)["devices"]
    assert d0["status"] == "rolled-back" and "the rollout stopped" in d0["error"]
    assert d1["status"] == "rolled-back" and "is 7, expected 0" in d1["error"]
    assert d2["status"] == "skipped"
    assert after[2] == before[2] and logs[2] == []
    # d0 passed its soak and was committed; restored, its old values are committed again
    assert {a: v for a, v in after[0].items() if a != COMMIT} == {a: v for a, v in before[0].items() if a != COMMIT}
    _, second = writes_to(logs[0], COMMIT)
    assert writes_to(logs[0], F07)[-1] < second and writes_to(logs[1], COMMIT) == []
    assert {a: v for a, v in after[1].items() if a != FAULT} == {a: v for a, v in before[1].items() if a != FAULT}


def test_health_failures_count_against_max_failures(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    with Simulators([Simulator(PROFILE, faults=Faults(rules=(TRIP,)) if i == 1 else None) for i in range(4)]) as sims:
        urls = {f"d{i}": s.url for i, s in enumerate(sims)}
        code, out, _ = cli(
            capsys,
            "apply",
            recipe(tmp_path, "1.5 s"),
            "--inventory",
            inventory(tmp_path, urls),
            "--yes",
            "--json",
            "--batch",
            "1",
            "--soak",
            "200ms",
            "--health-interval",
            "100ms",
            "--max-failures",
            "1",
            "--state-dir",
            str(tmp_path / "s"),
        )
    statuses = [d["status"] for d in json.loads(out)["devices"]]
    assert code == 4 and statuses == ["ok", "rolled-back", "skipped", "skipped"]


def test_ask_needs_a_terminal_and_pause_needs_batches(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    inv = inventory(tmp_path, {"d0": "tcp://127.0.0.1:9"})
    code, _, err = cli(capsys, "apply", recipe(tmp_path, "3 s"), "--inventory", inv, "--yes", "--batch", "1", "--ask")
    assert code == 1 and "--ask asks before each batch: stdin is not a terminal" in err
    code, _, err = cli(capsys, "apply", recipe(tmp_path, "3 s"), "--inventory", inv, "--yes", "--pause", "1s")
    assert code == 1 and "give --batch too" in err


def test_pause_between_batches_is_announced(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    with Simulators([Simulator(PROFILE) for _ in range(2)]) as sims:
        urls = {f"d{i}": s.url for i, s in enumerate(sims)}
        code, _, err = cli(
            capsys,
            "apply",
            recipe(tmp_path, "3 s"),
            "--inventory",
            inventory(tmp_path, urls),
            "--yes",
            "--batch",
            "1",
            "--pause",
            "100ms",
            "--state-dir",
            str(tmp_path / "s"),
        )
    assert code == 0 and "batch 1 done (1 ok); batch 2 starts in 100ms" in err


# ---- the Ansible module --------------------------------------------------------------------------


@pytest.mark.skipif(
    not Path(sys.executable).with_name("ansible-playbook").exists() and shutil.which("ansible-playbook") is None,
    reason="ansible-core is a test extra",
)
def test_the_ansible_module_soaks_and_rolls_back_a_tripping_device(tmp_path: Path) -> None:
    from tests.test_ansible import inventory as hosts
    from tests.test_ansible import playbook, recap

    recipe_file = Path(recipe(tmp_path, "1.5 s"))
    with Simulators([Simulator(PROFILE, faults=Faults(rules=(TRIP,)) if i == 3 else None) for i in range(4)]) as sims:
        code, out, _ = playbook(
            tmp_path,
            hosts(tmp_path, {"site-a": sims[:2], "site-b": sims[2:]}, recipe_file),
            "-e",
            "deployer_soak=300ms",
            "-e",
            "deployer_health_interval=100ms",
        )
        logs = [list(s.log) for s in sims]
    assert code != 0
    assert recap(out, "site-a")["failed"] == 0 and recap(out, "site-b")["failed"] == 1
    assert "site-b-d1 rolled-back" in out and "is 7, expected 0" in out
    assert all(len(writes_to(log, COMMIT)) == 1 for log in logs[:3]) and writes_to(logs[3], COMMIT) == []
    assert sims[3].read("F07") == (0, 500) and sims[2].read("F07") == (0, 150)


# ---- the Python API -----------------------------------------------------------------------------


def test_the_api_soaks_and_confirms(tmp_path: Path) -> None:
    import asyncio

    import deployer
    import deployer.aio
    from tests.helpers import run_with

    state = str(tmp_path / "s")

    async def body(sim: Simulator) -> tuple[deployer.Report, deployer.Report, list[str]]:
        rec = deployer.load_recipe(recipe(tmp_path, "3 s", sim.url))
        soaked = await deployer.aio.apply(rec, state_dir=state, soak="200ms", health_interval="100ms")
        rec = deployer.load_recipe(recipe(tmp_path, "4 s", sim.url, "r2.yaml"))
        waiting = asyncio.Event()
        runs: list[str] = []

        def on_wait(run: str, deadline: float) -> None:
            runs.append(run)
            waiting.set()

        task = asyncio.create_task(
            deployer.aio.apply(rec, state_dir=state, confirm_within="1h", on_confirm_wait=on_wait)
        )
        await waiting.wait()
        assert writes_to(list(sim.log), COMMIT) == [writes_to(list(sim.log), COMMIT)[0]]  # only the first run's
        assert deployer.confirm(state_dir=state) == runs[0]
        return soaked, await task, runs

    sim = Simulator(PROFILE)
    soaked, confirmed, _ = run_with(sim, body)
    assert soaked.devices[0].status == "ok" and soaked.devices[0].commit == "sent"
    assert confirmed.devices[0].status == "ok" and confirmed.devices[0].commit == "sent"
    assert len(writes_to(list(sim.log), COMMIT)) == 2 and sim.read("F07") == (0, 400)
    with pytest.raises(UsageError, match="soak: "):
        deployer.apply(deployer.load_recipe(recipe(tmp_path, "3 s", sim.url)), soak="soon")


def test_a_run_killed_during_its_soak_is_shown_by_status_with_its_restore_command(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    state = str(tmp_path / "s")
    with SimulatorThread(PROFILE) as sim:
        before = sim.registers()
        proc = deployer(
            "apply",
            recipe(tmp_path, "3 s", sim.url),
            "--yes",
            "--soak",
            "1h",
            "--health-interval",
            "100ms",
            "--state-dir",
            state,
        )
        try:
            # the soak's first read is the second one (the first is before the write)
            wait_for(lambda: len(reads_of(list(sim.log), FAULT)) >= 2 or proc.poll() is not None)
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.communicate(timeout=60)
        assert writes_to(list(sim.log), COMMIT) == []
        code, out, _ = cli(capsys, "status", "--state-dir", state)
        assert code == 2 and "died while its change soaked" in out
        restore = next(line.split("restore them with: ", 1)[1] for line in out.splitlines() if "restore them" in line)
        code, _, err = cli(capsys, *restore.split()[1:])
        assert code == 0, err
        assert {a: v for a, v in sim.registers().items() if a != COMMIT} == {
            a: v for a, v in before.items() if a != COMMIT
        }


def test_limit_from_a_report_retries_the_rolled_back_devices(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    with Simulators([Simulator(PROFILE, faults=Faults(rules=(TRIP,)) if i == 1 else None) for i in range(3)]) as sims:
        urls = {f"d{i}": s.url for i, s in enumerate(sims)}
        inv, run = inventory(tmp_path, urls), str(tmp_path / "run.json")
        code, _, _ = cli(
            capsys,
            "apply",
            recipe(tmp_path, "1.5 s"),
            "--inventory",
            inv,
            "--yes",
            "--soak",
            "200ms",
            "--health-interval",
            "100ms",
            "--report",
            run,
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 4
        sims[1].set_register(FAULT, 0)  # the drive's fault was reset
        code, out, err = cli(
            capsys,
            "apply",
            recipe(tmp_path, "2.5 s", name="safer.yaml"),
            "--inventory",
            inv,
            "--limit",
            f"@{run}",
            "--yes",
            "--json",
            "--soak",
            "200ms",
            "--health-interval",
            "100ms",
            "--state-dir",
            str(tmp_path / "s"),
        )
    assert code == 0, err
    assert [(d["name"], d["status"]) for d in json.loads(out)["devices"]] == [("d1", "ok")]


def test_ask_on_a_terminal_stops_the_rollout_on_no(tmp_path: Path) -> None:
    """--yes answers the write confirmation only: --ask still asks before batch 2, on a real terminal (a pty)."""
    import pty
    import select

    with Simulators([Simulator(PROFILE) for _ in range(2)]) as sims:
        urls = {f"d{i}": s.url for i, s in enumerate(sims)}
        master, slave = pty.openpty()
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "deployer",
                "apply",
                recipe(tmp_path, "3 s"),
                "--inventory",
                inventory(tmp_path, urls),
                "--yes",
                "--batch",
                "1",
                "--ask",
                "--report",
                str(tmp_path / "run.json"),
                "--state-dir",
                str(tmp_path / "s"),
            ],
            stdin=slave,
            stdout=slave,
            stderr=slave,
            close_fds=True,
        )
        os.close(slave)
        seen = b""
        try:
            end = time.monotonic() + 120
            while b"Continue with batch 2?" not in seen:
                assert time.monotonic() < end and proc.poll() is None, seen.decode(errors="replace")
                if select.select([master], [], [], 0.5)[0]:
                    seen += os.read(master, 4096)
            os.write(master, b"n\n")
            proc.wait(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
            os.close(master)
        assert proc.returncode == 4
        assert sims[1].log == []
    d0, d1 = json.loads((tmp_path / "run.json").read_text())["devices"]
    assert d0["status"] == "ok" and d1["status"] == "skipped"
    assert "stopped at the question before batch 2 (--ask)" in d1["error"]


def test_devices_behind_one_gateway_soak_together(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """Two units behind one address: written one after the other (one bus), then watched together over one
    connection; only the unit whose new ramp trips it is rolled back."""
    with Simulators([Simulator(PROFILE, units=(1, 2), faults=Faults(rules=(TRIP,)))]) as (sim,):
        inv = tmp_path / "inventory.yaml"
        inv.write_text(
            f"defaults: {{timeout: 2.0, retries: 1}}\ndevices:\n  d1: {{url: '{sim.url}', unit: 1}}\n"
            f"  d2: {{url: '{sim.url}', unit: 2, parameters: {{F07: 1.5 s}}}}\n"
        )
        code, out, _ = cli(
            capsys,
            "apply",
            recipe(tmp_path, "3 s"),
            "--inventory",
            str(inv),
            "--yes",
            "--json",
            "--soak",
            "1s",
            "--health-interval",
            "100ms",
            "--state-dir",
            str(tmp_path / "s"),
        )
        log = list(sim.log)
    assert code == 4
    d1, d2 = json.loads(out)["devices"]
    assert d1["status"] == "ok" and d2["status"] == "rolled-back"
    written = writes_to(log, F07)[:2]  # the apply's writes (the rollback's come after the soak's reads)
    assert sorted(log[i].unit for i in written) == [1, 2]
    for i in written:  # each unit's health read once before its write (a device in alarm is not written) ...
        assert any(j < i and log[j].unit == log[i].unit for j in reads_of(log, FAULT))
    first = log[min(written)].unit  # ... and the soak once both are written (not the first one's meanwhile)
    assert not [j for j in reads_of(log, FAULT) if min(written) < j < max(written) and log[j].unit == first]
    health = [log[j].unit for j in reads_of(log, FAULT) if j > max(written)]
    assert health[:2] in ([1, 2], [2, 1])  # then both are watched at once
    assert [log[i].unit for i in writes_to(log, COMMIT)] == [1]


@pytest.mark.parametrize("held", [["--confirm-within", "1h"], ["--soak", "1h", "--health-interval", "100ms"]])
def test_ctrl_c_while_a_change_is_held_rolls_it_back(tmp_path: Path, held: list[str]) -> None:
    """Ctrl-C during the confirmation wait (or the soak) is a no: the devices are restored at once, no commit."""
    state = str(tmp_path / "s")
    with SimulatorThread(PROFILE) as sim:
        before = sim.registers()
        proc = deployer("apply", recipe(tmp_path, "3 s", sim.url), "--yes", *held, "--state-dir", state)
        try:
            # the soak's first read: the second one (the first is before the write)
            wait_for(
                lambda: bool(awaiting(state)) or len(reads_of(list(sim.log), FAULT)) >= 2 or proc.poll() is not None
            )
            proc.send_signal(signal.SIGINT)
            proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert sim.registers() == before and writes_to(list(sim.log), COMMIT) == []
    assert awaiting(state) == [] and not os.listdir(os.path.join(state, "pending"))
    events = [json.loads(x)["event"] for x in Path(state, "audit.jsonl").read_text().splitlines()]
    assert "rolled-back" in events


def test_confirm_during_the_soak_says_it_comes_after(tmp_path: Path) -> None:
    state = str(tmp_path / "s")
    with SimulatorThread(PROFILE) as sim:
        proc = deployer(
            "apply",
            recipe(tmp_path, "3 s", sim.url),
            "--yes",
            "--soak",
            "1h",
            "--health-interval",
            "100ms",
            "--confirm-within",
            "1h",
            "--state-dir",
            state,
        )
        try:
            # the soak's first read is the second one (the first is before the write)
            wait_for(lambda: len(reads_of(list(sim.log), FAULT)) >= 2 or proc.poll() is not None)
            with pytest.raises(UsageError, match="is still soaking: it asks for the confirmation once its soak"):
                confirm_run(state)
        finally:
            proc.send_signal(signal.SIGINT)
            proc.communicate(timeout=120)
