"""deployer without POSIX: the command line and the Python API in processes that lack what Windows lacks.

Each process here starts with tests/posixless/sitecustomize.py: ``fcntl``, ``pwd``, ``grp``, ``resource``
and ``termios`` cannot be imported, ``os`` has no uids, ``fchmod``, O_NOFOLLOW/O_CLOEXEC/O_NONBLOCK,
``pread``, ``writev`` or ``sysconf``, and the event loop's ``add_signal_handler`` raises
NotImplementedError. Devices are simulators on 127.0.0.1 (TCP: pyserial itself needs ``termios`` on
Linux). Locks there use the ``range`` backend, Windows' backend (``state.oslock``), with Linux's
open-file-description locks under it where Windows has LockFileEx; the same tests run on Windows
itself, with LockFileEx, only in the public CI (.github/workflows/ci.yml; docs/windows.md).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from deployer.profile import builtin_profile
from deployer.state import lock
from deployer.testing.simulator import SimulatorThread
from deployer.transport import urls
from tests.helpers import wait_for

pytestmark = [pytest.mark.timeout(180),
              pytest.mark.skipif(not sys.platform.startswith("linux"),
                                 reason="the POSIX-less harness hides Linux's POSIX modules (Windows runs the "
                                        "suite itself in CI)")]

HARNESS = Path(__file__).parent / "posixless"
ROOT = Path(__file__).parent.parent
FIRST = "  F07: 10 s\n  F08: 8 s\n  stop_mode: coast\n  base_speed: 1750 rpm\n  preset[0]: {speed: 300, time: 2 s}\n"
SECOND = "  F07: 20 s\n  F08: 9 s\n  stop_mode: ramp\n  base_speed: 1600 rpm\n  preset[0]: {speed: 900, time: 3 s}\n"


def env(posixless: bool = True) -> dict[str, str]:
    e = dict(os.environ)
    path = [str(ROOT)] + ([e["PYTHONPATH"]] if e.get("PYTHONPATH") else [])
    e["PYTHONPATH"] = os.pathsep.join(([str(HARNESS)] if posixless else []) + path)
    return e


def deployer(cwd: Path, *args: str) -> tuple[int, str, str]:
    p = subprocess.run([sys.executable, "-m", "deployer", *args], capture_output=True, text=True, timeout=90,
                       cwd=cwd, env=env())
    return p.returncode, p.stdout, p.stderr


def start(cwd: Path, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "deployer", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=cwd, env=env())


def python(code: str, *args: str, posixless: bool = True, cwd: Path | None = None) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(code), *args], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env(posixless), cwd=cwd)


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
        import deployer.api, deployer.cli, deployer.agent.service, deployer.transport.clients
        from deployer.state import oslock
        from deployer.portable import user_name
        print(json.dumps({"gone": gone, "attrs": attrs, "handlers": handlers, "backend": oslock.backend().name,
                          "user": user_name(), "loaded": [m for m in ("fcntl", "pwd", "resource", "termios")
                                                          if sys.modules.get(m)]}))
    """)
    out, err = probe.communicate(timeout=60)
    assert probe.returncode == 0, err
    seen = json.loads(out)
    assert seen["gone"] == ["fcntl", "pwd", "grp", "resource", "termios", "serial"]
    assert seen["attrs"] == ["getuid", "fchmod", "O_NOFOLLOW", "O_CLOEXEC", "O_NONBLOCK", "pread", "writev"]
    assert seen["handlers"] == "NotImplementedError" and seen["backend"] == "range" and seen["loaded"] == []
    assert seen["user"]  # getpass's environment variables (Windows: USERNAME), else "unknown"


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

        api = python("""
            import json, sys
            from deployer import api
            r = api.load_recipe(sys.argv[2])
            plan = api.plan(r, sys.argv[1])
            rep = api.apply(r, sys.argv[1], options=api.ApplyOptions(state_dir="api-state"))
            print(json.dumps({"writes": len(plan.writes), "exit": rep.exit_code, "drift": len(api.diff(r, sys.argv[1])),
                              "status": rep.devices[0].status}))
        """, url, second, cwd=tmp_path)
        out, err = api.communicate(timeout=90)
        assert api.returncode == 0, err
        assert json.loads(out) == {"writes": json.loads(out)["writes"], "exit": 0, "drift": 0, "status": "ok"}
        assert json.loads(out)["writes"] > 0 and sim.read("base_speed") == (1600,)
        journal = (tmp_path / "api-state" / "audit.jsonl").read_text()
        assert '"via": "api"' in journal and journal.endswith("\n")


def test_one_writer_per_device_and_ctrl_c_without_posix(tmp_path: Path) -> None:
    first, second = recipe(tmp_path, "first", FIRST), recipe(tmp_path, "second", SECOND)
    with SimulatorThread(builtin_profile("example-inverter")) as sim:
        port = sim.url.rsplit(":", 1)[1]
        sim.faults.latency_ms = 300  # each answer takes 0.3 s: the first run holds its lock for seconds
        a = start(tmp_path, "apply", first, "--device", f"tcp://127.0.0.1:{port}", "--yes", "--state-dir", "sa")
        wait_for(lambda: a.pid in holders(), "the first run's lock")
        code, out, err = deployer(tmp_path, "apply", second, "--device", f"tcp://localhost:{port}", "--yes",
                                  "--state-dir", "sb")
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


# ---- the portable lock, each backend: flock (POSIX) and range (Windows' backend) ----------------------

HOLDER = """
    import asyncio, json, sys
    from deployer.state import lock, oslock
    from deployer.transport.urls import parse_url
    url, unit, hold = sys.argv[1], int(sys.argv[2]), sys.argv[3] == "hold"
    try:
        held = asyncio.run(lock.acquire_device(parse_url(url).lock_keys, unit, command="test"))
    except lock.Locked as e:
        print(json.dumps({"locked": str(e), "backend": oslock.backend().name}), flush=True)
        sys.exit(3)
    print(json.dumps({"held": True, "backend": oslock.backend().name,
                      "stale": [h.stale for h in held if h.stale]}), flush=True)
    if hold:
        sys.stdin.read()  # until the test closes stdin, or kills this process
    for h in held:
        h.release()
"""


def holder(url: str, unit: int, *, hold: bool, posixless: bool) -> tuple[subprocess.Popen[str], dict[str, object]]:
    p = python(HOLDER, url, str(unit), "hold" if hold else "once", posixless=posixless)
    assert p.stdout is not None
    line = p.stdout.readline()
    assert line, p.communicate()[1]
    return p, json.loads(line)


@pytest.mark.parametrize("backend", ["flock", "range"])
def test_portable_lock_two_processes_two_spellings_a_killed_holder(backend: str) -> None:
    posixless = backend == "range"
    a, said = holder("tcp://127.0.0.1:1502", 1, hold=True, posixless=posixless)
    assert said == {"held": True, "backend": backend, "stale": []}
    b, said = holder("tcp://localhost:1502", 1, hold=False, posixless=posixless)  # another spelling
    assert b.wait(timeout=30) == 3 and said["backend"] == backend
    assert f"locked by PID {a.pid}" in str(said["locked"])
    c, said = holder("tcp://127.1:1502", 2, hold=False, posixless=posixless)  # another unit of the bus
    assert c.wait(timeout=30) == 0 and said["held"] is True
    d, said = holder("tcp://2130706433:1502", 0, hold=False, posixless=posixless)  # a broadcast: the whole bus
    assert d.wait(timeout=30) == 3 and "the bus is in use" in str(said["locked"])
    a.kill()  # SIGKILL: no release, no clean-up; the system drops its locks
    a.wait(timeout=30)
    e, said = holder("tcp://localhost:1502", 1, hold=False, posixless=posixless)
    assert e.wait(timeout=30) == 0 and said["held"] is True
    assert any(f"stale lock of PID {a.pid}" in str(s) for s in said["stale"]), said  # type: ignore[attr-defined]
    for p in (a, b, c, d, e):
        for f in (p.stdin, p.stdout, p.stderr):
            if f is not None:
                f.close()


def test_com_ports_in_device_urls() -> None:
    for text, shown, key, opened in [
        ("rtu://COM3?baudrate=19200&parity=E", "rtu://COM3?baudrate=19200&parity=E", "serial:COM3", r"\\.\COM3"),
        ("rtu://com10", "rtu://COM10", "serial:COM10", r"\\.\COM10"),
        (r"rtu://\\.\COM10?baudrate=9600", "rtu://COM10?baudrate=9600", "serial:COM10", r"\\.\COM10"),
        ("ascii://COM4", "ascii://COM4", "serial:COM4", r"\\.\COM4"),
        (r"rtu://\\.\CNCA0", r"rtu://\\.\CNCA0", "serial:CNCA0", r"\\.\CNCA0"),
    ]:
        u = urls.parse_url(text)
        assert (urls.describe(u), u.lock_keys, u.serial_device) == (shown, (key,), opened), text
    # one port, however it is spelled: one lock
    assert len({urls.parse_url(t).lock_keys for t in ("rtu://COM10", "rtu://com10", r"rtu://\\.\COM10")}) == 1
    assert urls.parse_url("rtu:///dev/ttyUSB0").serial_device == "/dev/ttyUSB0"
