"""Steps and health checks that are coils (Function 05), and a device that keeps RAM and non-volatile memory
apart: a Danfoss FC 102 stores its parameters to EEPROM with coil 65; what is not stored is gone after a power
cycle. The simulator models both; an apply and its rollback each store what they wrote."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from deployer.errors import InputError
from deployer.profile import load_profile
from deployer.testing.simulator import Simulator
from tests.helpers import Simulators, cli, profile_from, reaped

pytestmark = pytest.mark.timeout(120)

FC102 = """\
profile: fc102
addressing: register-number
commit:
  - {register: 66, register_type: coil, raw: 1, description: store to EEPROM}
health:
  - {register: 67, register_type: coil, equals: 0, description: no alarm}
parameters:
  ramp_up_time: {register: 3411, type: uint32, unit: s, scale: 0.01, min: 0.01, max: 3600, default: 10}
  ramp_down_time: {register: 3421, type: uint32, unit: s, scale: 0.01, min: 0.01, max: 3600, default: 10}
"""
WRITES = (5, 6, 15, 16)


def files(tmp: Path, ramp: str = "3 s", profile: str = FC102) -> tuple[Path, Path]:
    (tmp / "fc102.yaml").write_text(profile)
    r = tmp / "r.yaml"
    r.write_text(f"recipe: r\nprofile: fc102.yaml\nparameters:\n  ramp_up_time: {ramp}\n  ramp_down_time: {ramp}\n")
    return tmp / "fc102.yaml", r


def test_a_coil_commit_step_is_sent_as_function_05_after_the_read_back(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    prof, recipe = files(tmp_path)
    with Simulators([Simulator(load_profile(str(prof)), nonvolatile=True)]) as (sim,):
        code, out, err = cli(
            capsys, "apply", str(recipe), "--device", sim.url, "--yes", "--json", "--state-dir", str(tmp_path / "s")
        )
        log = list(sim.log)
        stored = sim.stored()
    assert code == 0, err
    dev = json.loads(out)["devices"][0]
    assert dev["status"] == "ok" and dev["commit"] == "sent"
    writes = [(e.function, e.address, e.values) for e in log if e.function in WRITES]
    assert writes[-1] == (5, 65, [1])  # coil 66 by register number: wire address 65, written on
    last_read = max(i for i, e in enumerate(log) if e.function == 3)
    assert log.index(next(e for e in log if e.function == 5)) > last_read  # after the read-back
    assert (stored[3410], stored[3411]) == (0, 300)  # 3 s, stored


def test_a_coil_commit_deployed_and_rolled_back_stores_the_restored_values(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The issue's case: restored values must be stored too, or the next power cycle brings the change back."""
    prof, recipe = files(tmp_path)
    with Simulators([Simulator(load_profile(str(prof)), nonvolatile=True)]) as (sim,):
        before = (sim.read("ramp_up_time"), sim.read("ramp_down_time"))
        code, out, err = cli(
            capsys, "apply", str(recipe), "--device", sim.url, "--yes", "--json", "--state-dir", str(tmp_path / "s")
        )
        assert code == 0, err
        snapshot = json.loads(out)["devices"][0]["snapshot"]
        sim.power_cycle()  # stored: the change survives a power cycle
        assert sim.read("ramp_up_time") == (0, 300)
        commits = len([e for e in sim.log if e.function == 5])
        code, out, err = cli(capsys, "rollback", snapshot, "--yes", "--json", "--state-dir", str(tmp_path / "s"))
        assert code == 0, err
        assert json.loads(out)["devices"][0]["commit"] == "sent"
        assert len([e for e in sim.log if e.function == 5 and e.address == 65 and e.values == [1]]) == commits + 1
        sim.power_cycle()
        assert (sim.read("ramp_up_time"), sim.read("ramp_down_time")) == before  # the restored values survive


def test_writes_without_the_commit_are_gone_after_a_power_cycle(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The same registers written by a profile that knows no commit step: RAM only."""
    prof, _ = files(tmp_path)
    no_commit = tmp_path / "nocommit"
    no_commit.mkdir()
    _, bare = files(no_commit, profile=re.sub(r"commit:\n  - .*\n", "", FC102))
    with Simulators([Simulator(load_profile(str(prof)), nonvolatile=True)]) as (sim,):
        code, _, err = cli(capsys, "apply", str(bare), "--device", sim.url, "--yes", "--state-dir", str(tmp_path / "s"))
        assert code == 0, err
        assert sim.read("ramp_up_time") == (0, 300)
        sim.power_cycle()
        assert sim.read("ramp_up_time") == (0, 1000)  # the default it powered up with: the write was lost
        assert sim.power_cycles == 1


def test_without_the_model_a_power_cycle_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="nonvolatile"):
        Simulator(profile_from(tmp_path, FC102)).power_cycle()


@pytest.mark.skipif(not hasattr(signal, "SIGUSR2"), reason="SIGUSR2 is POSIX's (Windows: Simulator.power_cycle())")
def test_deployer_simulate_nonvolatile_power_cycles_on_sigusr2(tmp_path: Path) -> None:
    prof, _ = files(tmp_path)
    (tmp_path / "bare").mkdir()
    _, bare = files(tmp_path / "bare", profile=re.sub(r"commit:\n  - .*\n", "", FC102))
    proc = subprocess.Popen(
        [sys.executable, "-m", "deployer", "simulate", str(prof), "--listen", "tcp://127.0.0.1:0", "--nonvolatile"],
        stderr=subprocess.PIPE,
        text=True,
    )
    with reaped(proc):
        assert proc.stderr is not None
        line = proc.stderr.readline()
        url = re.search(r"on (tcp://\S+)", line)
        assert url and "SIGUSR2: a power cycle" in line, line
        run = subprocess.run(
            [
                sys.executable,
                "-m",
                "deployer",
                "apply",
                str(bare),
                "--device",
                url[1],
                "--yes",
                "--state-dir",
                str(tmp_path / "s"),
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert run.returncode == 0, run.stderr
        plan = [sys.executable, "-m", "deployer", "plan", str(bare), "--device", url[1], "--detailed-exitcode"]
        assert subprocess.run(plan, capture_output=True, text=True, timeout=60).returncode == 0  # holds it now
        proc.send_signal(signal.SIGUSR2)
        assert "power cycle 1" in proc.stderr.readline()
        assert subprocess.run(plan, capture_output=True, text=True, timeout=60).returncode == 2  # not stored: gone
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)


def test_coil_unlock_and_lock_steps_and_a_coil_health_check(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A device whose parameters are locked until coil 70 is on: unlock and lock as Function 05 around the writes;
    a coil health check read before a safe change (and failing: nothing written)."""
    text = FC102.replace(
        "commit:\n",
        "unlock:\n  - {register: 71, register_type: coil, raw: true}\n"
        "lock:\n  - {register: 71, register_type: coil, raw: false}\ncommit:\n",
    )
    prof, recipe = files(tmp_path, profile=text)
    p = load_profile(str(prof))
    assert [(a.register_type, a.address, a.registers) for a in (*p.unlock, *p.lock)] == [
        ("coil", 70, (1,)),
        ("coil", 70, (0,)),
    ]
    with Simulators([Simulator(p, nonvolatile=True)]) as (sim,):
        code, out, err = cli(
            capsys, "apply", str(recipe), "--device", sim.url, "--yes", "--state-dir", str(tmp_path / "s")
        )
        assert code == 0, out + err
        coils = [(e.address, e.values) for e in sim.log if e.function == 5]
        assert coils == [(70, [1]), (65, [1]), (70, [0])]  # unlock, commit, lock
        assert sim.registers(table="coil")[70] == 0  # locked again
        sim.set_register(66, 1, table="coil")  # an alarm
        recipe.write_text(recipe.read_text().replace("3 s", "4 s"))
        seen = len(sim.log)
        code, out, err = cli(
            capsys,
            "apply",
            str(recipe),
            "--device",
            sim.url,
            "--yes",
            "--soak",
            "1s",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 4
        assert "health check already failing before the change: coil 0x0042 (no alarm) is 1, expected 0" in out + err
        assert [e for e in sim.log[seen:] if e.function in WRITES] == []
        assert any(e.function == 1 and e.address == 66 for e in sim.log[seen:])


@pytest.mark.parametrize(
    ("item", "message"),
    [
        ("{register: 66, register_type: coil, raw: 2}", "a coil is written 1 or 0 (true or false), not 2"),
        ("{register: 66, register_type: coil, raw: 1, type: uint32}", "a coil is one bit: 'type' does not apply"),
        ("{register: 66, raw: true}", "true/false is a coil's value"),
    ],
)
def test_bad_coil_steps_are_refused_at_their_position(tmp_path: Path, item: str, message: str) -> None:
    text = re.sub(r"commit:\n  - .*\n", f"commit:\n  - {item}\n", FC102)
    (tmp_path / "p.yaml").write_text(text)
    with pytest.raises(InputError) as exc:
        load_profile(str(tmp_path / "p.yaml"))
    assert message in str(exc.value) and "p.yaml:4:" in str(exc.value)  # the step's own line


def test_bad_coil_health_checks_are_refused(tmp_path: Path) -> None:
    text = FC102.replace("equals: 0, description: no alarm", "min: 0, description: no alarm")
    (tmp_path / "p.yaml").write_text(text)
    with pytest.raises(InputError) as exc:
        load_profile(str(tmp_path / "p.yaml"))
    assert "a coil is one bit: 'min' does not apply" in str(exc.value)


def test_a_coil_commit_against_umodbus(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An independent device (umodbus) receives the commit as Function 05 on coil 65."""
    from tests.helpers import umodbus_server

    text = (
        FC102.replace("addressing: register-number\n", "")
        .replace("3411", "3410")
        .replace("3421", "3420")
        .replace("register: 66", "register: 65")
        .replace("health:\n  - {register: 67, register_type: coil, equals: 0, description: no alarm}\n", "")
    )
    _, recipe = files(tmp_path, profile=text)
    store = {3410: 0, 3411: 1000, 3420: 0, 3421: 1000}
    wire: list[tuple[int, int, int]] = []
    with umodbus_server(store, coils={65: 0}, wire=wire) as port:
        code, _, err = cli(
            capsys,
            "apply",
            str(recipe),
            "--device",
            f"tcp://127.0.0.1:{port}",
            "--yes",
            "--state-dir",
            str(tmp_path / "s"),
        )
    assert code == 0, err
    assert wire[-1] == (5, 65, 1) and store[3411] == 300
