"""One writer per device (the lock) and a journal that survives kill -9 (issue #11).

Runs are real processes (`python -m deployer`) against in-process simulators on 127.0.0.1.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from deployer.profile import builtin_profile
from deployer.state import lock
from deployer.testing.simulator import Faults, SimulatorThread
from tests.helpers import wait_for

pytestmark = pytest.mark.timeout(120)

FIRST = "  F07: 10 s\n  F08: 8 s\n  stop_mode: coast\n  base_speed: 1750 rpm\n  preset[0]: {speed: 300, time: 2 s}\n"
SECOND = "  F07: 20 s\n  F08: 9 s\n  stop_mode: ramp\n  base_speed: 1600 rpm\n  preset[0]: {speed: 900, time: 3 s}\n"


def recipe(tmp: Path, name: str, body: str) -> str:
    p = tmp / f"{name}.yaml"
    p.write_text(f"recipe: {name}\nprofile: example-inverter\nparameters:\n{body}")
    return str(p)


def start(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "deployer", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


def run(*args: str) -> tuple[int, str, str]:
    p = subprocess.run([sys.executable, "-m", "deployer", *args], capture_output=True, text=True, timeout=60)
    return p.returncode, p.stdout, p.stderr


def held_locks() -> list[dict[str, object]]:
    d = Path(lock.lock_dir())
    out = []
    for f in d.glob("*.lock") if d.exists() else []:
        text = f.read_text()
        if text.strip():
            out.append(json.loads(text))
    return out


def test_two_applies_on_one_device_one_is_refused(tmp_path: Path) -> None:
    from deployer.window.confirm import awaiting

    # the first run holds the lock in its confirm window until confirmed, however long the second takes to start
    with SimulatorThread(builtin_profile("example-inverter")) as sim:
        a = start(
            "apply",
            recipe(tmp_path, "first", FIRST),
            "--device",
            sim.url,
            "--yes",
            "--state-dir",
            str(tmp_path / "sa"),
            "--report",
            str(tmp_path / "a.json"),
            "--confirm-within",
            "1h",
        )
        wait_for(lambda: bool(awaiting(str(tmp_path / "sa"))) or a.poll() is not None)
        assert any(h.get("pid") == a.pid for h in held_locks())
        code, out, err = run(
            "apply",
            recipe(tmp_path, "second", SECOND),
            "--device",
            sim.url,
            "--yes",
            "--state-dir",
            str(tmp_path / "sb"),
            "--report",
            str(tmp_path / "b.json"),
        )
        assert run("confirm", "--state-dir", str(tmp_path / "sa"))[0] == 0
        assert a.wait(timeout=60) == 0, a.stderr.read() if a.stderr else ""
        assert code == 3, out + err
        assert f"locked by PID {a.pid} on " in out + err and " since " in out + err
        b = json.loads((tmp_path / "b.json").read_text())["devices"][0]
        assert b["status"] == "unreachable" and b["requests"] == [] and b["snapshot"] is None
        assert json.loads((tmp_path / "a.json").read_text())["devices"][0]["status"] == "ok"
        assert sim.read("F07") == (0, 1000) and sim.read("base_speed") == (1750,)  # the first run's recipe
        assert not (tmp_path / "sb" / "snapshots").exists()


def test_lock_timeout_waits_for_the_other_run(tmp_path: Path) -> None:
    with SimulatorThread(builtin_profile("example-inverter"), faults=Faults(latency_ms=40)) as sim:
        a = start(
            "apply", recipe(tmp_path, "first", FIRST), "--device", sim.url, "--yes", "--state-dir", str(tmp_path / "s")
        )
        wait_for(lambda: any(h.get("pid") == a.pid for h in held_locks()))
        code, out, err = run(
            "apply",
            recipe(tmp_path, "second", SECOND),
            "--device",
            sim.url,
            "--yes",
            "--state-dir",
            str(tmp_path / "s"),
            "--lock-timeout",
            "30",
            "--json",
        )
        assert a.wait(timeout=60) == 0
        assert code == 0, out + err
        # the second run read the device only after the first had verified: its "before" is the first's values
        f07 = next(p for p in json.loads(out)["devices"][0]["parameters"] if p["name"] == "F07")
        assert f07["before_raw"] == [0, 1000] and f07["status"] == "ok"
        assert sim.read("F07") == (0, 2000)


def test_stale_lock_of_a_dead_process_is_taken_over(tmp_path: Path) -> None:
    from deployer.transport.clients import parse_url

    with SimulatorThread(builtin_profile("example-inverter")) as sim:
        url = parse_url(sim.url)
        key = lock.device_key(url.bus, 1)
        held = lock.try_lock(key, command="crashed run")
        dead = subprocess.run(
            [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
        ).stdout.strip()
        os.ftruncate(held.fd, 0)
        os.lseek(held.fd, 0, os.SEEK_SET)
        os.write(
            held.fd,
            json.dumps(
                {
                    "pid": int(dead),
                    "host": socket.gethostname(),
                    "since": time.time() - 60,
                    "key": key,
                    "command": "crashed run",
                }
            ).encode(),
        )
        os.close(held.fd)  # the process "died": the kernel drops its flock, its record stays
        code, out, err = run(
            "apply",
            recipe(tmp_path, "first", FIRST),
            "--device",
            sim.url,
            "--yes",
            "--state-dir",
            str(tmp_path / "s"),
            "--json",
        )
        assert code == 0, err
        dev = json.loads(out)["devices"][0]
        assert any(f"stale lock of PID {dead}" in n for n in dev["notices"]), dev


def test_a_shorter_record_replaces_a_longer_one_whole(tmp_path: Path) -> None:
    # the record is written over the old one, padded with spaces (the file is never truncated: that waits for
    # the file system's journal): nothing of a longer old record may trail it
    key = "127.0.0.1:1502#unit1"
    held = lock.try_lock(key, command="x" * 3000, directory=str(tmp_path))
    long_text = Path(held.path).read_text()
    os.close(held.fd)  # gone without releasing: its long record stays, as a crashed run's does
    again = lock.try_lock(key, command="short", directory=str(tmp_path))
    try:
        text = Path(again.path).read_text()
        record = json.loads(text)
        assert record["command"] == "short" and record["pid"] == os.getpid()
        assert text.rstrip(" ") == json.dumps(record) and len(text) == len(long_text)  # spaces after it, no more
    finally:
        again.release()
    assert Path(again.path).read_text().strip() == ""  # released: blank, kept for the device's next run


def test_kill_9_mid_write_is_found_in_the_journal_and_retried(tmp_path: Path) -> None:
    state = tmp_path / "s"
    r = recipe(tmp_path, "first", FIRST)
    with SimulatorThread(builtin_profile("example-inverter"), faults=Faults(latency_ms=300)) as sim:
        proc = start("apply", r, "--device", sim.url, "--yes", "--state-dir", str(state))
        audit = state / "audit.jsonl"
        wait_for(lambda: audit.exists() and "device-started" in audit.read_text())
        wait_for(lambda: any(e.function == 16 for e in sim.log))  # it is writing now
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        assert any(e.function == 16 for e in sim.log)
        code, out, _ = run("status", "--state-dir", str(state), "--json")
        assert code == 2  # a run needs a look
        (unfinished,) = json.loads(out)["unfinished"]
        assert unfinished["pid"] == proc.pid and not unfinished["running"]
        (dev,) = unfinished["interrupted"]
        assert dev["url"] == sim.url and dev["unit"] == 1 and os.path.isfile(dev["snapshot"])
        code, out, _ = run("status", "--state-dir", str(state))
        assert "did not finish" in out and "interrupted while writing" in out and dev["snapshot"] in out
        # the retry takes over the dead run's lock (with a notice) and leaves the device verified
        sim.faults.latency_ms = 0
        code, out, err = run("apply", r, "--device", sim.url, "--yes", "--state-dir", str(state), "--json")
        assert code == 0, err
        retry = json.loads(out)["devices"][0]
        assert retry["status"] == "ok"
        assert any(f"stale lock of PID {proc.pid}" in n for n in retry["notices"])
        assert run("diff", r, "--device", sim.url)[0] == 0


def test_a_broadcast_and_a_unit_on_one_bus_exclude_each_other(tmp_path: Path) -> None:
    """Unit 0 writes every device of the bus: it takes the bus's lock exclusively, single units share it."""
    import asyncio

    from deployer.transport.clients import parse_url

    r = recipe(tmp_path, "first", FIRST)
    with SimulatorThread(builtin_profile("example-inverter")) as sim:
        bus = parse_url(sim.url).bus
        other = asyncio.run(lock.acquire_device(bus, 2, command="another run"))  # a run writing unit 2
        try:
            code, out, err = run(
                "apply",
                r,
                "--device",
                sim.url,
                "--unit",
                "0",
                "--allow-broadcast",
                "--yes",
                "--state-dir",
                str(tmp_path / "s"),
            )
            assert code == 3 and "the bus is in use" in out + err, out + err
            assert not any(e.function == 16 for e in sim.log)
            # another unit of the bus is not blocked by it
            code, _, err = run("apply", r, "--device", sim.url, "--yes", "--state-dir", str(tmp_path / "s"))
            assert code == 0, err
        finally:
            for h in other:
                h.release()
        broadcast = asyncio.run(lock.acquire_device(bus, 0, command="a broadcast"))
        try:
            code, out, err = run(
                "apply",
                recipe(tmp_path, "second", SECOND),
                "--device",
                sim.url,
                "--yes",
                "--state-dir",
                str(tmp_path / "s"),
            )
            assert code == 3 and f"locked by PID {os.getpid()}" in out + err and "a broadcast" in out + err
        finally:
            for h in broadcast:
                h.release()
