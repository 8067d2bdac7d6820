"""The safe-change window is one transaction (issue 28): its lock is held from the first write to the commit or
rollback, the commit is sent only over values re-read, a failed commit step fails the device, and
--rollback-on-failure treats every batch alike. Real processes against the simulator and against devices of
another library (umodbus), with changes made by another client (mbpoll)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from deployer.state import holder
from deployer.testing.simulator import Faults, Simulator, SimulatorThread
from deployer.window.confirm import awaiting
from tests.helpers import Simulators, cli, profile_from, umodbus_server, wait_for
from tests.test_safe import COMMIT, F07, MBPOLL, PROFILE, deployer, inventory, reads_of, recipe, writes_to

pytestmark = pytest.mark.timeout(180)
F08 = PROFILE.parameter("F08").address


def journal(state: str | Path) -> list[dict[str, Any]]:
    return [json.loads(x) for x in Path(state, "audit.jsonl").read_text().splitlines()]


def mbpoll_write(port: int | str, address: int, *values: int) -> None:
    """Write holding registers with libmodbus's client (another tool changing the device by hand)."""
    assert MBPOLL is not None
    poke = subprocess.run(
        [
            MBPOLL,
            "-m",
            "tcp",
            "-p",
            str(port),
            "-a",
            "1",
            "-0",
            "-1",
            "-r",
            str(address),
            "-t",
            "4",
            "127.0.0.1",
            *map(str, values),
        ],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert poke.returncode == 0, poke.stdout + poke.stderr


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "deployer", *args], capture_output=True, text=True, timeout=120)


# a device of another library's (umodbus) with a health register, a commit register and one parameter
WATCHED = """profile: w
health:
  - {register: 0x20, equals: 0, description: fault code is zero}
commit:
  - {register: 0x30, raw: 1, description: store}
parameters:
  x: {register: 0x10, type: uint16}
"""


needs_mbpoll = pytest.mark.skipif(MBPOLL is None, reason="mbpoll (libmodbus) is not installed")


# ---- 1. the window holds the device's lock ------------------------------------------------------------


def test_a_second_run_is_refused_during_the_window_by_any_spelling_and_status_lists_the_lock(tmp_path: Path) -> None:
    """A waits for its confirmation; B (another state folder, the device spelled localhost) is refused with A's
    run id, window, deadline and command, sends nothing; `status` of B's folder lists A's lock; confirmed, A
    commits once."""
    state_a, state_b = str(tmp_path / "a"), str(tmp_path / "b")
    with SimulatorThread(PROFILE) as sim:
        port = sim.url.rsplit(":", 1)[1]
        a = deployer(
            "apply",
            recipe(tmp_path, "3 s", sim.url),
            "--yes",
            "--json",
            "--confirm-within",
            "1h",
            "--state-dir",
            state_a,
        )
        try:
            wait_for(lambda: bool(awaiting(state_a)) or a.poll() is not None)
            (waiting,) = awaiting(state_a)
            seen = [e for e in sim.log if e.function != 3 or e.address != PROFILE.health[0].address]
            b = run(
                "apply",
                recipe(tmp_path, "4 s", f"tcp://localhost:{port}", "r2.yaml"),
                "--yes",
                "--json",
                "--state-dir",
                state_b,
            )
            # B sent nothing at all (A watches the health register while it waits)
            assert [e for e in sim.log if e.function != 3 or e.address != PROFILE.health[0].address] == seen
            assert b.returncode == 3, b.stderr
            dev = json.loads(b.stdout)["devices"][0]
            assert dev["status"] == "unreachable" and dev["requests"] == [] and dev["snapshot"] is None
            assert f"run {waiting.run}, in its confirmation window until {waiting.until()}" in dev["error"]
            assert "--confirm-within 1h" in dev["error"] and dev["error"].endswith("nothing was sent")
            # the machine's lock folder, whatever the state folder
            code = run("status", "--state-dir", state_b, "--json")
            locks = json.loads(code.stdout)["locks"]
            mine = [rec for rec in locks if rec["run"] == waiting.run]
            assert {rec["window"] for rec in mine} == {"confirm"} and all(r["pid"] == a.pid for r in mine)
            assert any(rec["key"].endswith("#unit1") for rec in mine)
            assert mine[0]["format"] == "deployer.lock/1" and "agent" in mine[0]
            text = run("status", "--state-dir", state_b).stdout
            assert f"run {waiting.run}, in its confirmation window until" in text
            confirmed = run("confirm", "--state-dir", state_a)
            assert confirmed.returncode == 0, confirmed.stderr
            assert f"run {waiting.run}: the commit was sent to ramp" in confirmed.stdout
            out, err = a.communicate(timeout=120)
        finally:
            if a.poll() is None:
                a.kill()
        log = list(sim.log)
    assert a.returncode == 0, err
    assert json.loads(out)["devices"][0]["commit"] == "sent" and len(writes_to(log, COMMIT)) == 1
    assert sim.read("F07") == (0, 300)  # A's value: B never wrote
    assert holder.held(os.environ["DEPLOYER_LOCK_DIR"]) == [] or all(
        r["run"] != waiting.run for r in holder.held(os.environ["DEPLOYER_LOCK_DIR"])
    )


def test_a_second_run_with_lock_timeout_waits_for_the_window_to_end(tmp_path: Path) -> None:
    """B waits (--lock-timeout) while A soaks; it writes only after A's soak passed and A's commit went out."""
    with SimulatorThread(PROFILE) as sim:
        a = deployer(
            "apply",
            recipe(tmp_path, "3 s", sim.url),
            "--yes",
            "--soak",
            "1500ms",
            "--health-interval",
            "100ms",
            "--state-dir",
            str(tmp_path / "a"),
        )
        try:
            # the soak's first read: the second one (the first is the safe change's, before the write)
            wait_for(lambda: len(reads_of(list(sim.log), PROFILE.health[0].address)) >= 2 or a.poll() is not None)
            b = run(
                "apply",
                recipe(tmp_path, "4 s", sim.url, "r2.yaml"),
                "--yes",
                "--json",
                "--lock-timeout",
                "60",
                "--state-dir",
                str(tmp_path / "b"),
            )
            a.communicate(timeout=120)
        finally:
            if a.poll() is None:
                a.kill()
        log = list(sim.log)
    assert a.returncode == 0 and b.returncode == 0, b.stderr
    a_commit, b_commit = writes_to(log, COMMIT)
    b_write = writes_to(log, F07)[1]
    assert a_commit < b_write < b_commit  # B's first write after A's window ended
    assert sim.read("F07") == (0, 400)


def test_a_device_of_another_library_in_a_window_gets_nothing_from_a_second_run(tmp_path: Path) -> None:
    """Item 1 against umodbus (its own request log, not our simulator's): while A waits for its confirmation, B
    (the device spelled localhost, another state folder) is refused and the device receives no request of
    B's; confirmed, A's commit reaches the device once."""
    profile_from(tmp_path, WATCHED, "w.yaml")
    store = {0x10: 0, 0x20: 0, 0x30: 0}
    wire: list[tuple[int, int, int]] = []
    with umodbus_server(store, wire=wire, connections=2) as port:

        def recipe_for(name: str, host: str, x: int) -> str:
            r = tmp_path / f"{name}.yaml"
            r.write_text(
                f"recipe: {name}\nprofile: w.yaml\ndevice: {{url: 'tcp://{host}:{port}'}}\nparameters:\n  x: {x}\n"
            )
            return str(r)

        state_a = str(tmp_path / "a")
        a = deployer(
            "apply",
            recipe_for("a", "127.0.0.1", 5),
            "--yes",
            "--json",
            "--confirm-within",
            "1h",
            "--state-dir",
            state_a,
        )
        try:
            wait_for(lambda: bool(awaiting(state_a)) or a.poll() is not None)
            (waiting,) = awaiting(state_a)

            def others() -> list[tuple[int, int, int]]:
                return [w for w in list(wire) if w[:2] != (3, 0x20)]  # A reads its health register while it waits

            seen = others()
            b = run("apply", recipe_for("b", "localhost", 6), "--yes", "--json", "--state-dir", str(tmp_path / "b"))
            assert others() == seen  # not one request of B's reached the device
            assert b.returncode == 3, b.stderr
            dev = json.loads(b.stdout)["devices"][0]
            assert f"run {waiting.run}, in its confirmation window" in dev["error"]
            assert dev["error"].endswith("nothing was sent")
            confirmed = run("confirm", "--state-dir", state_a)
            assert confirmed.returncode == 0, confirmed.stderr
            out, err = a.communicate(timeout=120)
        finally:
            if a.poll() is None:
                a.kill()
    assert a.returncode == 0, err
    assert json.loads(out)["devices"][0]["commit"] == "sent"
    assert store[0x10] == 5 and store[0x30] == 1  # A's value, and its commit, on the device
    assert sum(1 for fc, addr, n in wire if fc in (6, 16) and addr <= 0x30 < addr + n) == 1


# ---- 2. the commit re-reads ------------------------------------------------------------------------------


@needs_mbpoll
@pytest.mark.parametrize("window", ["confirm", "soak"])
def test_a_parameter_changed_by_hand_during_the_window_is_never_committed(tmp_path: Path, window: str) -> None:
    """mbpoll changes F07 while the change waits: no commit; F08 (still the run's) is rolled back, F07 left as
    found; the device ends failed naming F07 (found and written); `deployer confirm` exits 4 saying so."""
    state = str(tmp_path / "s")
    held = ["--confirm-within", "1h"] if window == "confirm" else ["--soak", "1500ms", "--health-interval", "100ms"]
    with SimulatorThread(PROFILE) as sim:
        before = sim.registers()
        proc = deployer(
            "apply",
            recipe(tmp_path, "3 s", sim.url),
            "--yes",
            "--json",
            *held,
            "--state-dir",
            state,
            "--report",
            str(tmp_path / "run.json"),
        )
        try:
            if window == "confirm":
                wait_for(lambda: bool(awaiting(state)) or proc.poll() is not None)
            else:
                wait_for(
                    lambda: (
                        len(reads_of(list(sim.log), PROFILE.health[0].address)) >= 2  # the soak's first
                        or proc.poll() is not None
                    )
                )
            mbpoll_write(sim.url.rsplit(":", 1)[1], F07, 0, 999)
            if window == "confirm":
                confirmed = run("confirm", "--state-dir", state)
                assert confirmed.returncode == 4, confirmed.stdout + confirmed.stderr
                assert "the commit was not sent to ramp" in confirmed.stderr
                assert "F07 holds 9.99 s, the run wrote 3 s" in confirmed.stderr
            out, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
        log = list(sim.log)
        after = sim.registers()
    assert proc.returncode == 4, err
    report = json.loads(out)
    dev = report["devices"][0]
    assert dev["status"] == "failed" and dev["commit"] == "not sent"
    assert "commit not sent: F07 holds 9.99 s, the run wrote 3 s" in dev["error"]
    params = {p["name"]: p for p in dev["parameters"]}
    assert params["F07"]["status"] == "failed" and params["F07"]["after_raw"] == [0, 999]
    assert params["F08"]["status"] == "rolled-back" and params["F08"]["after_raw"] == params["F08"]["before_raw"]
    assert json.loads((tmp_path / "run.json").read_text())["devices"][0] == dev
    # the device: F07 as mbpoll left it, everything else as before, never committed
    assert after[F07 + 1] == 999 and writes_to(log, COMMIT) == []
    assert {a: v for a, v in after.items() if a not in (F07, F07 + 1)} == {
        a: v for a, v in before.items() if a not in (F07, F07 + 1)
    }
    lines = journal(state)
    (commit,) = [r for r in lines if r["event"] == "commit"]
    assert commit["result"] == "not sent" and "F07 holds 9.99 s" in commit["error"]
    assert any(r["event"] == "rolled-back" and r["status"] == "failed" for r in lines)
    status = run("status", "--state-dir", state)
    assert "no unfinished runs" in status.stdout


@needs_mbpoll
def test_an_independent_device_changed_by_an_independent_client_is_not_committed(tmp_path: Path) -> None:
    """umodbus as the device, mbpoll as the other hand: x changed during the soak stays as found, y is restored,
    the commit register is never written."""
    prof = profile_from(tmp_path, WATCHED + "  y: {register: 0x11, type: uint16}\n", "w.yaml")
    assert prof.commit
    store = {0x10: 0, 0x11: 0, 0x20: 0, 0x30: 0}
    wire: list[tuple[int, int, int]] = []
    with umodbus_server(store, wire=wire, connections=2) as port:  # the run and mbpoll
        r = tmp_path / "r.yaml"
        r.write_text(
            f"recipe: r\nprofile: w.yaml\ndevice: {{url: 'tcp://127.0.0.1:{port}'}}\nparameters:\n  x: 5\n  y: 6\n"
        )
        proc = deployer(
            "apply",
            str(r),
            "--yes",
            "--json",
            "--soak",
            "1500ms",
            "--health-interval",
            "100ms",
            "--state-dir",
            str(tmp_path / "s"),
        )
        try:
            wait_for(lambda: any(w[:2] == (3, 0x20) for w in list(wire)) or proc.poll() is not None)
            mbpoll_write(port, 0x10, 77)
            out, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
    assert proc.returncode == 4, err
    dev = json.loads(out)["devices"][0]
    assert dev["status"] == "failed" and dev["commit"] == "not sent" and "x holds 77, the run wrote 5" in dev["error"]
    assert {p["name"]: p["status"] for p in dev["parameters"]} == {"x": "failed", "y": "rolled-back"}
    assert store == {0x10: 77, 0x11: 0, 0x20: 0, 0x30: 0}
    assert not any(fc in (6, 16) and a <= 0x30 < a + n for fc, a, n in wire)


# ---- 3. a failed commit step fails the device ---------------------------------------------------------


@pytest.mark.parametrize("held", [[], ["--soak", "200ms", "--health-interval", "100ms"]])
def test_a_refused_commit_fails_the_device_and_a_retry_sends_it_with_nothing_to_write(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, held: list[str]
) -> None:
    with Simulators([Simulator(PROFILE, faults=Faults(fail_registers=frozenset({COMMIT})))]) as (sim,):
        inv, report = inventory(tmp_path, {"d0": sim.url}), str(tmp_path / "run.json")
        code, out, _ = cli(
            capsys,
            "apply",
            recipe(tmp_path, "3 s"),
            "--inventory",
            inv,
            "--yes",
            "--json",
            *held,
            "--report",
            report,
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 4
        dev = json.loads(out)["devices"][0]
        assert dev["status"] == "failed" and dev["commit"] == "failed"
        assert "commit 'store parameters to EEPROM' failed: exception 04" in dev["error"]
        assert {p["status"] for p in dev["parameters"]} == {"ok"}  # verified, in RAM
        assert len(writes_to(list(sim.log), COMMIT)) == 1
        sim.faults.fail_registers = frozenset()  # the device takes its commit again
        seen = len(sim.log)
        code, out, err = cli(
            capsys,
            "apply",
            recipe(tmp_path, "3 s"),
            "--inventory",
            inv,
            "--yes",
            "--json",
            "--limit",
            f"@{report}",
            *held,
            "--state-dir",
            str(tmp_path / "s"),
        )
        retry = list(sim.log)[seen:]
    assert code == 0, err
    dev = json.loads(out)["devices"][0]
    assert dev["status"] == "ok" and dev["commit"] == "sent"
    assert {p["status"] for p in dev["parameters"]} == {"unchanged"}
    assert [e.address for e in retry if e.function in (6, 16)] == [COMMIT]  # the commit, nothing else


def test_commit_steps_go_as_function_06_to_a_device_that_refuses_16(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """umodbus answering 01 to Function 16 (and 02 for a commit register it lacks, in the second run)."""
    prof = profile_from(
        tmp_path,
        """profile: w
commit:
  - {register: 0x30, raw: 1, description: store}
parameters:
  x: {register: 0x10, type: uint16}
""",
        "w.yaml",
    )
    assert prof.commit
    wire: list[tuple[int, int, int]] = []
    store = {0x10: 0, 0x30: 0}
    with umodbus_server(store, fc06_only=True, wire=wire) as port:
        r = tmp_path / "r.yaml"
        r.write_text(f"recipe: r\nprofile: w.yaml\ndevice: {{url: 'tcp://127.0.0.1:{port}'}}\nparameters:\n  x: 5\n")
        code, out, err = cli(capsys, "apply", str(r), "--yes", "--json", "--state-dir", str(tmp_path / "s"))
    assert code == 0, err
    assert json.loads(out)["devices"][0]["commit"] == "sent" and store == {0x10: 5, 0x30: 1}
    assert (6, 0x30, 1) in wire
    store = {0x10: 0}  # no commit register: umodbus answers 02 (illegal data address)
    with umodbus_server(store) as port:
        r.write_text(f"recipe: r\nprofile: w.yaml\ndevice: {{url: 'tcp://127.0.0.1:{port}'}}\nparameters:\n  x: 5\n")
        code, out, _ = cli(capsys, "apply", str(r), "--yes", "--json", "--state-dir", str(tmp_path / "s"))
        dev = json.loads(out)["devices"][0]
    assert code == 4 and dev["status"] == "failed" and dev["commit"] == "failed" and store == {0x10: 5}
    assert "commit 'store' failed: exception 02" in dev["error"]
    assert "ok - commit" not in out


# ---- 7. --rollback-on-failure: every batch alike --------------------------------------------------------


def test_rollback_on_failure_with_the_failure_in_the_last_batch_rolls_back(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    with Simulators([Simulator(PROFILE), Simulator(PROFILE, faults=Faults(fail_registers=frozenset({F07})))]) as sims:
        before = [s.registers() for s in sims]
        urls = {f"d{i}": s.url for i, s in enumerate(sims)}
        code, out, _ = cli(
            capsys,
            "apply",
            recipe(tmp_path, "3 s"),
            "--inventory",
            inventory(tmp_path, urls),
            "--yes",
            "--json",
            "--batch",
            "1",
            "--rollback-on-failure",
            "--state-dir",
            str(tmp_path / "s"),
        )
        after = [s.registers() for s in sims]
    assert code == 4
    d0, d1 = json.loads(out)["devices"]
    assert d0["status"] == "rolled-back" and "the rollout stopped (batch 2 failed" in d0["error"]
    assert d1["status"] in ("failed", "partial", "rolled-back")
    assert {a: v for a, v in after[0].items() if a != COMMIT} == {a: v for a, v in before[0].items() if a != COMMIT}
    assert after[1][F07 + 1] == before[1][F07 + 1] and after[1][F08 + 1] == before[1][F08 + 1]


# ---- 6. restoring a run that died in its window -----------------------------------------------------------


@pytest.mark.parametrize("held", [["--confirm-within", "1h"], ["--soak", "1h", "--health-interval", "100ms"]])
def test_the_restore_status_recommends_sends_no_commit_and_drops_the_run(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, held: list[str]
) -> None:
    import signal

    state = str(tmp_path / "s")
    with SimulatorThread(PROFILE) as sim:
        before = sim.registers()
        proc = deployer("apply", recipe(tmp_path, "3 s", sim.url), "--yes", *held, "--state-dir", state)
        try:
            # the window's first health read: the second (the first is before the write)
            wait_for(
                lambda: (
                    bool(awaiting(state))
                    or len(reads_of(list(sim.log), PROFILE.health[0].address)) >= 2
                    or proc.poll() is not None
                )
            )
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.communicate(timeout=60)
        code, out, _ = cli(capsys, "status", "--state-dir", state)
        restore = next(line.split("restore them with: ", 1)[1] for line in out.splitlines() if "restore them" in line)
        assert "rollback --from-report" in restore and "pending" in restore
        if held[0] == "--confirm-within":  # confirm names the same command, in today's words
            code, _, err = cli(capsys, "confirm", "--state-dir", state)
            assert code == 1 and "deployer rollback --from-report" in err and "--report " not in err
        code, _, err = cli(capsys, *restore.split()[1:])
        assert code == 0, err
        assert sim.registers() == before and writes_to(list(sim.log), COMMIT) == []  # restored; nothing stored
        code, out, _ = cli(capsys, "status", "--state-dir", state)
    assert code == 0 and "no unfinished runs" in out, out


# ---- 5. an interrupted window: one story -------------------------------------------------------------


def _page_devices(page: Path) -> list[dict[str, Any]]:
    """The devices embedded in a page's data block (what the page renders its table from)."""
    import re

    (data,) = re.findall(r"<script type=application/json id=data>(.*?)</script>", page.read_text(), re.S)
    devices: list[dict[str, Any]] = json.loads(data)["devices"]
    return devices


@pytest.mark.parametrize(
    ("sig", "held"),
    [("SIGINT", ["--soak", "1h", "--health-interval", "100ms"]), ("SIGTERM", ["--confirm-within", "1h"])],
)
def test_an_interrupted_window_tells_one_story_everywhere(tmp_path: Path, sig: str, held: list[str]) -> None:
    import signal

    state, report, page = str(tmp_path / "s"), tmp_path / "r.json", tmp_path / "r.html"
    with SimulatorThread(PROFILE) as sim:
        before = sim.registers()
        proc = deployer(
            "apply",
            recipe(tmp_path, "3 s", sim.url),
            "--yes",
            *held,
            "--report",
            str(report),
            "--html",
            str(page),
            "--state-dir",
            state,
        )
        try:
            # the window's first health read: the second (the first is before the write)
            wait_for(
                lambda: (
                    bool(awaiting(state))
                    or len(reads_of(list(sim.log), PROFILE.health[0].address)) >= 2
                    or proc.poll() is not None
                )
            )
            proc.send_signal(getattr(signal, sig))
            out, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert sim.registers() == before and writes_to(list(sim.log), COMMIT) == []
    assert proc.returncode == 4, err
    (dev,) = json.loads(report.read_text())["devices"]
    assert dev["status"] == "rolled-back" and dev["commit"] == "not sent"
    assert {p["status"] for p in dev["parameters"]} == {"rolled-back"}
    assert out.splitlines()[0].startswith(f"ramp {sim.url} unit 1 (example-inverter): rolled-back - ")
    assert "commit: not sent" in out and "commit: held" not in out
    assert f"interrupted ({sig}): ramp rolled back to what it held before (verified);" in err
    assert "nothing was written" not in err and "may hold" not in err
    (shown,) = _page_devices(page)
    assert (shown["status"], shown["commit"], shown["error"]) == (dev["status"], dev["commit"], dev["error"])
    assert [p[4] for p in shown["params"]] == [p["status"] for p in dev["parameters"]]
    finished = [r for r in journal(state) if r["event"] == "run-finished"]
    assert [d["status"] for d in finished[0]["devices"]] == ["rolled-back"]


# ---- 8, 9. a full disk: act on the device first, then write --------------------------------------------------


@pytest.fixture
def small_disk(tmp_path: Path) -> Any:
    """A real filesystem of 1 MiB (tmpfs), mounted for the test; skipped where mounting is not permitted."""
    import shutil as sh

    where = tmp_path / "disk"
    where.mkdir()
    if sh.which("mount") is None:
        pytest.skip("no mount command")
    got = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(where)], capture_output=True, text=True)
    if got.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here (needs root or CAP_SYS_ADMIN): {got.stderr.strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], capture_output=True)


def fill(disk: Path) -> None:
    """Take every free block of ``disk``."""
    fd = os.open(disk / "filler", os.O_WRONLY | os.O_CREAT | os.O_APPEND)
    try:
        while True:
            os.write(fd, bytes(4096))
    except OSError:
        pass
    finally:
        os.close(fd)


def test_a_soak_on_a_full_disk_still_rolls_back_and_records_it(tmp_path: Path, small_disk: Path) -> None:
    """The disk fills during the soak, then the drive faults: the rollback happens and is journaled (the run's
    reserved space), the device ends as it was, exit 4."""
    from tests.test_safe import FAULT

    state = small_disk / "s"
    with SimulatorThread(PROFILE) as sim:
        before = sim.registers()
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
            # the soak's first read: the second one (the first is the safe change's, before the write)
            wait_for(lambda: len(reads_of(list(sim.log), PROFILE.health[0].address)) >= 2 or proc.poll() is not None)
            fill(small_disk)
            sim.set_register(FAULT, 7)  # the drive trips
            out, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
        after = sim.registers()
        log = list(sim.log)
    assert proc.returncode == 4, err
    assert "Traceback" not in err
    dev = json.loads(out)["devices"][0]
    assert dev["status"] == "rolled-back" and dev["commit"] == "not sent", (dev["error"], dev.get("unrecorded"))
    assert {a: v for a, v in after.items() if a != FAULT} == {a: v for a, v in before.items() if a != FAULT}
    assert writes_to(log, COMMIT) == []
    events = [r["event"] for r in journal(state)]
    assert "health-failed" in events and "rolled-back" in events and events[-1] == "run-finished"


def test_a_state_folder_that_refuses_every_write_never_stops_a_rollback(tmp_path: Path, small_disk: Path) -> None:
    """The state folder turns read-only during the confirmation wait: `deployer confirm` cannot record the
    confirmation (said, exit 1, no traceback); the run's window expires, the device is rolled back all the same,
    and the run says each line it could not record (exit 4)."""
    state = small_disk / "s"
    report = tmp_path / "r.json"  # the report on another disk: it can say what the journal could not
    with SimulatorThread(PROFILE) as sim:
        before = sim.registers()
        proc = deployer(
            "apply",
            recipe(tmp_path, "3 s", sim.url),
            "--yes",
            "--confirm-within",
            "3s",
            "--state-dir",
            str(state),
            "--report",
            str(report),
        )
        try:
            wait_for(lambda: bool(awaiting(str(state))) or proc.poll() is not None)
            remount = subprocess.run(["mount", "-o", "remount,ro", str(small_disk)], capture_output=True, text=True)
            if remount.returncode != 0:
                pytest.skip(f"cannot remount read-only: {remount.stderr.strip()}")
            confirmed = run("confirm", "--state-dir", str(state))
            _, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
        after = sim.registers()
        log = list(sim.log)
    assert confirmed.returncode == 1 and "the confirmation was not recorded" in confirmed.stderr
    assert "Traceback" not in confirmed.stderr
    assert proc.returncode == 4, err[-3000:]
    assert after == before and writes_to(log, COMMIT) == []  # rolled back, never committed
    dev = json.loads(report.read_text())["devices"][0]
    assert dev["status"] == "rolled-back" and "not confirmed within 3s" in dev["error"]
    assert any("could not record the confirm-expired line" in u for u in dev["unrecorded"])
    assert any("could not record the rolled-back line" in u for u in dev["unrecorded"])
    assert "not recorded: ramp: the journal" in err


def test_a_disk_full_after_the_write_says_what_reached_the_device(tmp_path: Path, small_disk: Path) -> None:
    """The disk fills while the device is written: the device holds the new values (committed), and the run says
    so on stdout, names the report and page it could not write, exits 4; the snapshot stays named."""
    state, report = small_disk / "s", small_disk / "r.json"
    with SimulatorThread(PROFILE, faults=Faults(latency_ms=300)) as sim:
        proc = deployer(
            "apply",
            recipe(tmp_path, "3 s", sim.url),
            "--yes",
            "--state-dir",
            str(state),
            "--report",
            str(report),
            "--html",
            str(small_disk / "r.html"),
        )
        try:
            wait_for(
                lambda: (
                    ((state / "audit.jsonl").exists() and "device-started" in (state / "audit.jsonl").read_text())
                    or proc.poll() is not None
                )
            )
            fill(small_disk)
            out, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
        log = list(sim.log)
        f07 = sim.read("F07")
    assert proc.returncode == 4, err
    assert "Traceback" not in err
    assert f07 == (0, 300) and len(writes_to(log, COMMIT)) == 1  # it reached the device, and was stored
    assert out.splitlines()[0].endswith(": ok") and "snapshot: " in out
    assert f"not recorded: cannot write the report {report}: the disk is full" in err
    assert "not recorded: cannot write" in err and "r.html" in err
    # the report's stream kept the device's snapshot from before its first write
    assert any(json.loads(line).get("snapshot") for line in report.read_text().splitlines()[1:])


# ---- 4. deadlines on the monotonic clock, the waiting process by PID and start time ---------------------------


def test_a_wall_clock_step_back_does_not_delay_the_rollback(tmp_path: Path) -> None:
    """The waiting run's wall clock steps back 60 s while it waits 2 s for its confirmation: it rolls back when
    its 2 s are over (the monotonic clock), not 60 s later; the journal has the deadline on both clocks."""
    import time

    state, step = str(tmp_path / "s"), tmp_path / "step"
    shifted = (
        "import os, sys, time\n_t = time.time\n"
        f"time.time = lambda: _t() - (60 if os.path.exists({str(step)!r}) else 0)\n"
        "from deployer.cli import main\nmain(sys.argv[1:])\n"
    )
    with SimulatorThread(PROFILE) as sim:
        before = sim.registers()
        proc = subprocess.Popen(
            [
                sys.executable,
                "-c",
                shifted,
                "apply",
                recipe(tmp_path, "3 s", sim.url),
                "--yes",
                "--json",
                "--confirm-within",
                "2s",
                "--state-dir",
                state,
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            wait_for(lambda: bool(awaiting(state)) or proc.poll() is not None)
            (waiting,) = awaiting(state)
            step.touch()  # from now on the run's wall clock reads 60 s earlier
            t = time.monotonic()
            out, err = proc.communicate(timeout=40)  # 60 s later would be a failure here
            took = time.monotonic() - t
        finally:
            if proc.poll() is None:
                proc.kill()
        assert sim.registers() == before
    assert proc.returncode == 4, err
    assert took < 40 and json.loads(out)["devices"][0]["status"] == "rolled-back"
    (line,) = [r for r in journal(state) if r["event"] == "confirm-awaited"]
    assert {"deadline", "deadline_epoch", "deadline_monotonic", "boot_id", "pid_start"} <= set(line)
    assert waiting.deadline_monotonic == line["deadline_monotonic"]


def test_a_reused_pid_is_not_taken_for_the_waiting_run(tmp_path: Path) -> None:
    """A confirm-awaited line whose PID is alive now but belongs to a process started at another time (the PID
    was reused): `confirm` says the waiting process is gone and names the restore command."""
    state = tmp_path / "s"
    state.mkdir()
    now = holder.process_start(os.getpid())
    assert now is not None or sys.platform != "linux"
    if now is None:
        pytest.skip("this system does not say when a process started")
    line = {
        "event": "confirm-awaited",
        "run": "R1",
        "time": "2026-01-01T00:00:00Z",
        "pid": os.getpid(),
        "pid_start": now - 100.0,
        "deadline": "2099-01-01T00:00:00Z",
        "deadline_epoch": 4070908800.0,
        "report": str(state / "pending" / "R1.json"),
    }
    (state / "audit.jsonl").write_text(json.dumps(line) + "\n")
    (waiting,) = awaiting(str(state))
    assert not waiting.alive
    got = run("confirm", "--state-dir", str(state))
    assert got.returncode == 1 and "its process" in got.stderr and "is gone" in got.stderr
    assert "deployer rollback --from-report" in got.stderr


def test_the_documented_lock_record_is_the_one_written(tmp_path: Path) -> None:
    """docs/locks.md: its example and its table name exactly the fields a lock file holds."""
    import re

    from deployer.state import lock

    text = (Path(__file__).resolve().parent.parent / "docs" / "locks.md").read_text()
    (example,) = re.findall(r"```json\n(.*?)```", text, re.S)
    table = set(re.findall(r"^\| `(\w+)` \|", text, re.M))
    held = lock.try_lock("tcp:127.0.0.1:9#unit1", command="test", directory=str(tmp_path), run="R1")
    try:
        written = json.loads(Path(held.path).read_text())
    finally:
        held.release()
    assert set(json.loads(example)) == set(written) == table
    assert written["format"] == json.loads(example)["format"] == holder.FORMAT
    assert written["run"] == "R1" and written["pid"] == os.getpid()


def test_confirming_a_profile_without_a_commit_step_says_the_values_were_kept(tmp_path: Path) -> None:
    """`deployer confirm` says what happened: no commit step to send, so the values stay as written (it used to
    say "the commit was sent")."""
    plain = profile_from(tmp_path, "profile: plain\nparameters:\n  x: {register: 0x10, type: uint16}\n", "plain.yaml")
    (tmp_path / "r.yaml").write_text("recipe: r\nprofile: plain.yaml\nparameters:\n  x: 7\n")
    state = str(tmp_path / "s")
    with SimulatorThread(plain) as sim:
        a = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "deployer",
                "apply",
                str(tmp_path / "r.yaml"),
                "--device",
                sim.url,
                "--yes",
                "--confirm-within",
                "1h",
                "--state-dir",
                state,
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            wait_for(lambda: bool(awaiting(state)) or a.poll() is not None)
            confirmed = run("confirm", "--state-dir", state)
            assert confirmed.returncode == 0, confirmed.stderr
            assert "kept as written on r (its profile has no commit step: nothing to store)" in confirmed.stdout
            assert "the commit was sent" not in confirmed.stdout
            a.communicate(timeout=120)
        finally:
            if a.poll() is None:
                a.kill()
        assert sim.read("x") == (7,) and a.returncode == 0
