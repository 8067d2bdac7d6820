"""deployer without POSIX: the command line and the Python API in processes that lack what Windows lacks.

Each process here starts with tests/posixless/sitecustomize.py: ``fcntl``, ``pwd``, ``grp``, ``resource``
and ``termios`` cannot be imported, ``os`` has no uids, ``fchmod``, O_NOFOLLOW/O_CLOEXEC/O_NONBLOCK,
``pread``, ``writev`` or ``sysconf``, and the event loop's ``add_signal_handler`` raises
NotImplementedError. Devices are simulators on 127.0.0.1 (TCP: pyserial itself needs ``termios`` on
Linux). Locks there use the ``range`` backend, Windows' backend (``state.oslock``), with Linux's
open-file-description locks under it where Windows has LockFileEx. On Windows itself the suite, with
the lock test of tests/test_portable.py on LockFileEx, runs only in the public CI (docs/windows.md).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from deployer.profile import builtin_profile
from deployer.state import lock
from deployer.testing.simulator import SimulatorThread
from tests.helpers import wait_for
from tests.test_portable import env, python

pytestmark = [
    pytest.mark.timeout(180),
    pytest.mark.skipif(
        not sys.platform.startswith("linux"),
        reason="the POSIX-less harness hides Linux's POSIX modules (Windows runs the suite itself in CI)",
    ),
]

FIRST = "  F07: 10 s\n  F08: 8 s\n  stop_mode: coast\n  base_speed: 1750 rpm\n  preset[0]: {speed: 300, time: 2 s}\n"
SECOND = "  F07: 20 s\n  F08: 9 s\n  stop_mode: ramp\n  base_speed: 1600 rpm\n  preset[0]: {speed: 900, time: 3 s}\n"


def deployer(cwd: Path, *args: str) -> tuple[int, str, str]:
    p = subprocess.run(
        [sys.executable, "-m", "deployer", *args], capture_output=True, text=True, timeout=90, cwd=cwd, env=env()
    )
    return p.returncode, p.stdout, p.stderr


def start(cwd: Path, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "deployer", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=cwd,
        env=env(),
    )


def recipe(tmp: Path, name: str, body: str) -> str:
    p = tmp / f"{name}.yaml"
    p.write_text(f"recipe: {name}\nprofile: example-inverter\nparameters:\n{body}")
    return p.name


def holders() -> list[object]:
    d = Path(lock.lock_dir())
    out = []
    for f in d.glob("*.lock") if d.exists() else []:
        text = f.read_text()
        if text.strip():
            out.append(json.loads(text).get("pid"))
    return out


def test_the_harness_takes_away_what_windows_lacks() -> None:
    probe = python("""
        import asyncio, json, os, sys
        gone = []
        for m in ("fcntl", "pwd", "grp", "resource", "termios", "serial"):
            try:
                __import__(m)
            except ImportError:
                gone.append(m)
        attrs = [a for a in ("getuid", "fchmod", "O_NOFOLLOW", "O_CLOEXEC", "O_NONBLOCK", "pread", "writev")
                 if not hasattr(os, a)]
        loop = asyncio.new_event_loop()
        try:
            loop.add_signal_handler(2, print)
            handlers = "work"
        except NotImplementedError:
            handlers = "NotImplementedError"
        import importlib, pkgutil, deployer
        modules = [m.name for m in pkgutil.walk_packages(deployer.__path__, "deployer.")
                   if not m.name.endswith("__main__")]
        refused = []
        for name in modules:  # every module of the package, not only those the command line loads
            try:
                importlib.import_module(name)
            except Exception as e:
                refused.append(f"{name}: {e!r}")
        from deployer.state import oslock
        from deployer.portable import user_name
        print(json.dumps({"gone": gone, "attrs": attrs, "handlers": handlers, "backend": oslock.backend().name,
                          "user": user_name(), "modules": len(modules), "refused": refused,
                          "loaded": [m for m in ("fcntl", "pwd", "resource", "termios") if sys.modules.get(m)]}))
    """)
    out, err = probe.communicate(timeout=60)
    assert probe.returncode == 0, err
    seen = json.loads(out)
    assert seen["gone"] == ["fcntl", "pwd", "grp", "resource", "termios", "serial"]
    assert seen["attrs"] == ["getuid", "fchmod", "O_NOFOLLOW", "O_CLOEXEC", "O_NONBLOCK", "pread", "writev"]
    assert seen["handlers"] == "NotImplementedError" and seen["backend"] == "range" and seen["loaded"] == []
    assert seen["user"]  # getpass's environment variables (Windows: USERNAME), else "unknown"
    assert seen["refused"] == [] and seen["modules"] > 90


def test_command_line_and_api_over_tcp_without_posix(tmp_path: Path) -> None:
    first, second = recipe(tmp_path, "first", FIRST), recipe(tmp_path, "second", SECOND)
    with SimulatorThread(builtin_profile("example-inverter")) as sim:
        before = sim.read("base_speed")
        url = sim.url
        code, out, err = deployer(tmp_path, "validate", first)
        assert code == 0, out + err
        code, out, err = deployer(tmp_path, "plan", first, "--device", url)
        assert code == 0 and "base_speed" in out, out + err
        code, out, err = deployer(tmp_path, "apply", first, "--device", url, "--yes", "--report", "a.json")
        assert code == 0, out + err
        assert sim.read("base_speed") == (1750,)
        report = json.loads((tmp_path / "a.json").read_text())
        assert report["devices"][0]["status"] == "ok" and report["run"]["user"]
        assert os.path.isfile(report["devices"][0]["snapshot"])
        code, out, err = deployer(tmp_path, "diff", first, "--device", url)
        assert code == 0, out + err
        code, out, err = deployer(tmp_path, "diff", second, "--device", url)
        assert code == 2, out + err
        code, out, err = deployer(tmp_path, "rollback", "--from-report", "a.json", "--yes")
        assert code == 0, out + err
        assert sim.read("base_speed") == before
        code, out, err = deployer(tmp_path, "status")
        assert code == 0, out + err
        # a worker process without os.fork: this Python started again, as on Windows
        (tmp_path / "inv.yaml").write_text(f"devices:\n  one: {{url: '{url}'}}\n")
        code, out, err = deployer(
            tmp_path, "apply", second, "--inventory", "inv.yaml", "--workers", "1", "--yes", "--report", "w.json"
        )
        assert code == 0 and sim.read("base_speed") == (1600,), out + err
        assert json.loads((tmp_path / "w.json").read_text())["devices"][0]["status"] == "ok"
        # a safe-change window: the lock held through a soak, then a confirmation from another process
        code, out, err = deployer(
            tmp_path, "apply", first, "--device", url, "--yes", "--soak", "1s", "--health-interval", "200ms"
        )
        assert code == 0 and sim.read("base_speed") == (1750,), out + err
        w = start(tmp_path, "apply", second, "--device", url, "--yes", "--confirm-within", "60s")
        wait_for(lambda: "confirm-awaited" in (tmp_path / ".deployer" / "audit.jsonl").read_text(), "the wait")
        code, out, err = deployer(tmp_path, "confirm")
        assert code == 0, out + err
        assert w.wait(timeout=60) == 0, w.communicate()
        assert sim.read("base_speed") == (1600,)

        api = python(
            """
            import json, sys
            from deployer import api
            r = api.load_recipe(sys.argv[2])
            plan = api.plan(r, sys.argv[1])
            rep = api.apply(r, sys.argv[1], state_dir="api-state")
            print(json.dumps({"writes": len(plan.writes), "exit": rep.exit_code, "drift": len(api.diff(r, sys.argv[1])),
                              "status": rep.devices[0].status}))
        """,
            url,
            first,
            cwd=tmp_path,
        )
        out, err = api.communicate(timeout=90)
        assert api.returncode == 0, err
        assert json.loads(out) == {"writes": json.loads(out)["writes"], "exit": 0, "drift": 0, "status": "ok"}
        assert json.loads(out)["writes"] > 0 and sim.read("base_speed") == (1750,)
        journal = (tmp_path / "api-state" / "audit.jsonl").read_text()
        assert '"via": "api"' in journal and journal.endswith("\n")


def test_one_writer_per_device_and_ctrl_c_without_posix(tmp_path: Path) -> None:
    first, second = recipe(tmp_path, "first", FIRST), recipe(tmp_path, "second", SECOND)
    with SimulatorThread(builtin_profile("example-inverter")) as sim:
        port = sim.url.rsplit(":", 1)[1]
        sim.faults.latency_ms = 300  # each answer takes 0.3 s: the first run holds its lock for seconds
        a = start(tmp_path, "apply", first, "--device", f"tcp://127.0.0.1:{port}", "--yes", "--state-dir", "sa")
        wait_for(lambda: a.pid in holders(), "the first run's lock")
        code, out, err = deployer(
            tmp_path, "apply", second, "--device", f"tcp://localhost:{port}", "--yes", "--state-dir", "sb"
        )
        assert a.wait(timeout=60) == 0, a.communicate()[1]
        assert code == 3 and f"locked by PID {a.pid}" in out + err, out + err
        assert sim.read("base_speed") == (1750,)  # only the first run wrote

        # Ctrl-C: SIGINT through signal.signal (no add_signal_handler), the report and journal still written
        sim.log.clear()
        c = start(tmp_path, "apply", second, "--device", sim.url, "--yes", "--state-dir", "sc", "--report", "c.json")
        wait_for(lambda: any(e.function in (6, 16) for e in list(sim.log)), "the first write")
        c.send_signal(signal.SIGINT)
        out, err = c.communicate(timeout=60)
        assert c.returncode == 4, out + err
        report = json.loads((tmp_path / "c.json").read_text())
        assert report["run"]["interrupted"] == "SIGINT" and report["devices"][0]["status"] == "interrupted"
        assert "interrupted (SIGINT)" in err
        lines = [json.loads(x) for x in (tmp_path / "sc" / "audit.jsonl").read_text().splitlines()]
        assert lines[-1]["event"] == "run-finished" and lines[-1]["interrupted"] == "SIGINT"
        sim.faults.latency_ms = 0
        code, out, err = deployer(tmp_path, "rollback", "--from-report", "c.json", "--yes", "--state-dir", "sc")
        assert code == 0, out + err
        assert sim.read("base_speed") == (1750,)  # what the interrupted run found


def test_the_demo_without_posix(tmp_path: Path) -> None:
    # the first command a new Windows user types
    code, out, err = deployer(tmp_path, "demo")
    assert code == 0 and "demo finished: every step behaved as described." in out + err, out + err
    assert "Traceback" not in out + err


def test_the_agent_without_posix(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # the site agent on a Windows-like Python: its folder lock (range backend), its device locks, a restore,
    # a plain apply refused, and SIGTERM through signal.signal (no loop handlers, no SIGHUP)
    from deployer.profile import load_profile
    from tests.agent_helpers import PROFILE, AgentProcess, event, until, write_site

    monkeypatch.setenv("PYTHONPATH", env()["PYTHONPATH"])  # AgentProcess passes the environment on
    (tmp_path / "drive.yaml").write_text(PROFILE)
    with SimulatorThread(load_profile(str(tmp_path / "drive.yaml"))) as sim:
        inv = write_site(tmp_path, {"d1": sim.url})
        agent = AgentProcess(inv, tmp_path / "state", "--on-drift", "restore")
        try:
            until(lambda: event(agent.client, "restored", "d1"), why="the first restore")
            assert sim.read("accel") == (20,) and sim.read("speed") == (3000,)
            # its folder lock is Windows' backend: a lock on byte 1 GiB of agent.lock, an OFD lock here
            ino = next((tmp_path / "state").rglob("agent.lock")).stat().st_ino
            held = [ln.split() for ln in Path("/proc/locks").read_text().splitlines()]
            assert any(f[1] == "OFDLCK" and f[5].endswith(f":{ino}") and f[6] == str(1 << 30) for f in held), held
            code, out, err = deployer(tmp_path, "apply", "r.yaml", "--device", sim.url, "--yes", "--state-dir", "other")
            assert code == 3 and "owned by the deployer agent" in " ".join((out + err).split()), out + err
            assert agent.terminate() == 0, agent.log()
        finally:
            agent.kill()


def test_ctrl_c_during_a_soak_rolls_back_without_posix(tmp_path: Path) -> None:
    # Ctrl-C while a change soaks is a no: restored at once, through signal.signal as on Windows
    second = recipe(tmp_path, "second", SECOND)
    with SimulatorThread(builtin_profile("example-inverter")) as sim:
        before = sim.registers()
        c = start(
            tmp_path,
            "apply",
            second,
            "--device",
            sim.url,
            "--yes",
            "--soak",
            "1h",
            "--health-interval",
            "100ms",
            "--state-dir",
            "s",
        )
        try:
            audit = tmp_path / "s" / "audit.jsonl"
            wait_for(lambda: audit.exists() and "soak-started" in audit.read_text(), "the soak")
            c.send_signal(signal.SIGINT)
            out, err = c.communicate(timeout=60)
        finally:
            if c.poll() is None:
                c.kill()
        assert c.returncode == 4, out + err
        assert sim.registers() == before
    events = [json.loads(x)["event"] for x in (tmp_path / "s" / "audit.jsonl").read_text().splitlines()]
    assert "rolled-back" in events and events[-1] == "run-finished"
