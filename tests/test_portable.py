"""Portability: what runs the same on POSIX, Windows and macOS (docs/windows.md).

The lock tests run the system's own backend everywhere (``flock`` on Linux and macOS, ``range`` through
LockFileEx on Windows: there only in the public CI), and on Linux also the ``range`` backend in
processes without POSIX (tests/posixless/sitecustomize.py).
"""

from __future__ import annotations

import errno
import json
import os
import re
import stat
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from deployer import portable
from deployer.errors import UsageError
from deployer.state import durable, lock
from deployer.transport import urls
from tests.helpers import cli

HARNESS = Path(__file__).parent / "posixless"
ROOT = Path(__file__).parent.parent
LINUX = sys.platform.startswith("linux")


def env(posixless: bool = True) -> dict[str, str]:
    """The environment of a child process; ``posixless``: one that lacks what Windows lacks (Linux only)."""
    e = dict(os.environ)
    path = [str(ROOT)] + ([e["PYTHONPATH"]] if e.get("PYTHONPATH") else [])
    e["PYTHONPATH"] = os.pathsep.join(([str(HARNESS)] if posixless else []) + path)
    return e


def python(code: str, *args: str, posixless: bool = True, cwd: Path | None = None) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(code), *args],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env(posixless),
        cwd=cwd,
    )


def test_the_lock_folder_does_not_follow_tmpdir(monkeypatch: pytest.MonkeyPatch) -> None:
    # a service, a login shell and each macOS user see other TMPDIRs: they must still share locks
    monkeypatch.delenv(lock.ENV, raising=False)
    monkeypatch.setenv("TMPDIR", os.path.join(os.sep, "somewhere", "else"))
    expected = (
        os.path.join(os.environ.get("PROGRAMDATA", r"C:\ProgramData"), "deployer", "locks")
        if sys.platform == "win32"
        else "/tmp/deployer-locks"
    )
    assert lock.lock_dir() == lock.default_lock_dir() == expected
    monkeypatch.setenv(lock.ENV, os.path.join(os.sep, "srv", "locks"))
    assert lock.lock_dir() == os.path.join(os.sep, "srv", "locks")


# ---- the portable lock: two processes, two spellings of one device, a killed holder ------------------

HOLDER = """
    import asyncio, json, sys
    from deployer.errors import Locked
    from deployer.state import lock, oslock
    from deployer.transport.urls import parse_url
    url, unit, hold, wait = sys.argv[1], int(sys.argv[2]), sys.argv[3] == "hold", float(sys.argv[4])
    try:
        held = asyncio.run(lock.acquire_device(parse_url(url).lock_keys, unit, command="test", timeout=wait))
    except Locked as e:
        print(json.dumps({"locked": str(e), "backend": oslock.backend().name}), flush=True)
        sys.exit(3)
    print(json.dumps({"held": True, "backend": oslock.backend().name,
                      "stale": [h.stale for h in held if h.stale]}), flush=True)
    if hold:
        sys.stdin.read()  # until the test closes stdin, or kills this process
    for h in held:
        h.release()
"""


def holder(
    url: str, unit: int, *, hold: bool, posixless: bool, wait: float = 0
) -> tuple[subprocess.Popen[str], dict[str, object]]:
    p = python(HOLDER, url, str(unit), "hold" if hold else "once", str(wait), posixless=posixless)
    assert p.stdout is not None
    line = p.stdout.readline()
    assert line, p.communicate()[1]
    return p, json.loads(line)


@pytest.mark.portable  # the Windows case that matters: LockFileEx, TerminateProcess
@pytest.mark.timeout(120)
@pytest.mark.parametrize("where", ["native", "posixless"])
def test_portable_lock_two_processes_two_spellings_a_killed_holder(where: str) -> None:
    posixless = where == "posixless"
    if posixless and not LINUX:
        pytest.skip("the POSIX-less harness hides Linux's POSIX modules; Windows runs the native case itself")
    backend = "range" if posixless or sys.platform == "win32" else "flock"
    procs = []
    try:
        a, said = holder("tcp://127.0.0.1:1502", 1, hold=True, posixless=posixless)
        procs.append(a)
        assert said == {"held": True, "backend": backend, "stale": []}
        b, said = holder("tcp://localhost:1502", 1, hold=False, posixless=posixless)  # another spelling
        procs.append(b)
        assert b.wait(timeout=30) == 3 and said["backend"] == backend
        assert f"locked by PID {a.pid}" in str(said["locked"])
        c, said = holder("tcp://127.1:1502", 2, hold=False, posixless=posixless)  # another unit of the bus
        procs.append(c)
        assert c.wait(timeout=30) == 0 and said["held"] is True
        d, said = holder("tcp://2130706433:1502", 0, hold=False, posixless=posixless)  # a broadcast: the whole bus
        procs.append(d)
        assert d.wait(timeout=30) == 3 and "the bus is in use" in str(said["locked"])
        a.kill()  # SIGKILL (TerminateProcess on Windows): no release, no clean-up; the system drops its locks
        a.wait(timeout=30)
        # Windows drops a dead process's locks "after a while" (LockFileEx's documentation): a run that
        # waits (--lock-timeout) gets it; POSIX drops them before the process is reaped
        e, said = holder("tcp://localhost:1502", 1, hold=False, posixless=posixless, wait=30)
        procs.append(e)
        assert e.wait(timeout=30) == 0 and said["held"] is True
        stale = said["stale"]
        assert isinstance(stale, list) and any(f"stale lock of PID {a.pid}" in str(s) for s in stale), said
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.communicate()


# ---- COM ports -------------------------------------------------------------------------------------


@pytest.mark.portable
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
    assert urls.windows_port("COM3x") is None and urls.windows_port("COM0") is None


@pytest.mark.skipif(sys.platform == "win32", reason="on Windows COM3 may exist")
def test_a_com_port_elsewhere_is_said_plainly(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rec = tmp_path / "r.yaml"
    rec.write_text("recipe: r\nprofile: example-inverter\nparameters:\n  F07: 10 s\n")
    code, out, err = cli(
        capsys, "apply", str(rec), "--device", "rtu://COM3", "--yes", "--state-dir", str(tmp_path / "s")
    )
    said = " ".join((out + err).split())  # the console wraps long lines
    assert code == 3 and "no such serial device 'COM3' (COM ports are Windows' names" in said, said
    assert "Traceback" not in said


def test_scan_lists_serial_ports(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = cli(capsys, "scan", "--list-ports", "--json")
    assert code in (0, 3), err
    ports = json.loads(out)
    from serial.tools import list_ports

    assert [p["device"] for p in ports] == sorted(
        (str(p.device) for p in list_ports.comports()),
        key=lambda d: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", d)],
    )
    assert all(p["url"].startswith("rtu://") for p in ports)
    code, out, err = cli(capsys, "scan", "tcp://127.0.0.1:1", "--list-ports")
    assert code == 1 and "without a URL" in err
    code, out, err = cli(capsys, "scan")
    assert code == 1 and "--list-ports" in err


# ---- file names and paths --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "safe"),
    [
        ("line3/drive 7", "line3_drive_7"),
        ("CON", "_CON"),
        ("aux", "_aux"),
        ("nul.old", "_nul.old"),
        ("COM1", "_COM1"),
        ("lpt9.x", "_lpt9.x"),
        ("COM10", "COM10"),
        ("CONSOLE", "CONSOLE"),
        ("con-1", "con-1"),
        ("drive.", "drive"),
        ("..", "_"),
        ("", "_"),
    ],
)
def test_file_names_from_device_and_recipe_names(name: str, safe: str) -> None:
    assert portable.file_name(name) == safe


def test_long_names_stay_apart_and_within_the_limit() -> None:
    a, b = portable.file_name("x" * 300 + "a"), portable.file_name("x" * 300 + "b")
    assert a != b and len(a) == len(b) == portable.NAME_LIMIT


def test_a_reserved_device_name_gets_a_snapshot_and_a_pulled_recipe(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from deployer.profile import builtin_profile
    from deployer.state.snapshot import last_identity, snapshot_file
    from deployer.testing.simulator import SimulatorThread

    inv = tmp_path / "inv.yaml"
    with SimulatorThread(builtin_profile("example-inverter")) as sim:
        inv.write_text(f"devices:\n  CON:\n    url: {sim.url}\n    profile: example-inverter\n")
        code, out, err = cli(capsys, "pull", "--inventory", str(inv), "-o", str(tmp_path / "pulled"))
        assert code == 0, out + err
    assert [p.name for p in (tmp_path / "pulled").iterdir()] == ["_CON.yaml"]
    from deployer.recipe.loader import load_recipe

    rec = load_recipe(str(tmp_path / "pulled" / "_CON.yaml"))
    new = snapshot_file(str(tmp_path / "state"), "CON", rec, {}, "tcp://127.0.0.1:1", 1)
    assert os.path.basename(new.first[0]).startswith("_CON-")
    assert last_identity(str(tmp_path / "state"), "CON") is None  # found by the same name (none recorded)


def test_a_path_too_long_is_said_plainly() -> None:
    e = OSError(errno.ENAMETOOLONG, "File name too long", "x" * 300)
    assert durable.disk_error(e).startswith("the path is too long (300 characters")
    win = OSError(errno.EINVAL, "The filename or extension is too long", "C:\\" + "y" * 300)
    win.winerror = 206  # type: ignore[attr-defined]  # what Windows sets beyond 260 characters
    assert "too long" in durable.disk_error(win)


@pytest.mark.skipif(sys.platform == "win32", reason="Windows cannot fsync a folder (docs/windows.md)")
def test_a_failed_folder_fsync_says_so(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    real = os.fsync

    def fsync(fd: int) -> None:  # the folder's fsync fails (a network file system refusing it), files work
        if stat.S_ISDIR(os.fstat(fd).st_mode):
            raise OSError(errno.EACCES, "Permission denied")
        real(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    with pytest.raises(UsageError) as e:
        durable.write_atomic(str(tmp_path / "r.json"), "{}")
    assert f"the fsync of its folder {tmp_path} failed: Permission denied" in str(e.value)


@pytest.mark.portable  # Windows' own case: signal.signal is all its event loops have
def test_signals_without_loop_handlers_reach_the_loop() -> None:
    # what Windows does: the loop has no add_signal_handler, so signal.signal hands the signal over
    import asyncio
    import signal

    async def main() -> list[str]:
        loop = asyncio.get_running_loop()
        got: list[str] = []
        done = asyncio.Event()

        def on(sig: signal.Signals) -> None:
            got.append(sig.name)
            done.set()

        def refuse(*a: object) -> None:
            raise NotImplementedError

        loop.add_signal_handler = refuse  # type: ignore[method-assign,assignment]
        before = signal.getsignal(signal.SIGINT)
        undo = portable.on_signals(loop, (signal.SIGINT,), on)
        assert signal.getsignal(signal.SIGINT) is not before
        signal.raise_signal(signal.SIGINT)
        await asyncio.wait_for(done.wait(), 10)
        undo()
        assert signal.getsignal(signal.SIGINT) is before
        return got

    assert asyncio.run(main()) == ["SIGINT"]


def test_liveness_never_signals() -> None:
    assert portable.pid_alive(os.getpid())
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    assert not portable.pid_alive(p.pid) and not portable.pid_alive(0) and not portable.pid_alive(-1)


# ---- the serial transport on every system ------------------------------------------------------------


@pytest.mark.portable
def test_the_serial_transport_through_a_port_over_tcp(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # pyserial's socket:// is a serial port whose wire is a TCP connection: pymodbus's serial transport runs
    # over it as over a COM port, and on Windows polls it (force_poll) as it polls a COM port. Where CI has
    # no virtual COM-port pair (Windows), this is the serial path's run there.
    from deployer.profile import builtin_profile
    from deployer.testing.simulator import SimulatorThread

    rec = tmp_path / "r.yaml"
    rec.write_text("recipe: r\nprofile: example-inverter\nparameters:\n  F07: 10 s\n  base_speed: 1750 rpm\n")
    with SimulatorThread(builtin_profile("example-inverter"), listen="rtu+tcp://127.0.0.1:0") as sim:
        port = sim.url.rsplit(":", 1)[1]
        device = f"rtu://socket://127.0.0.1:{port}?baudrate=19200&parity=E"
        code, out, err = cli(
            capsys,
            "apply",
            str(rec),
            "--device",
            device,
            "--yes",
            "--state-dir",
            str(tmp_path / "s"),
            "--report",
            str(tmp_path / "r.json"),
        )
        assert code == 0, out + err
        assert sim.read("base_speed") == (1750,) and sim.read("F07") == (0, 1000)
        writes = [e for e in sim.log if e.function in (6, 16)]
        assert writes and all(e.unit == 1 for e in sim.log)
        code, out, err = cli(
            capsys, "rollback", "--from-report", str(tmp_path / "r.json"), "--yes", "--state-dir", str(tmp_path / "s")
        )
        assert code == 0, out + err
        assert sim.read("base_speed") == (1500,)


@pytest.mark.skipif(sys.platform != "win32", reason="COM ports are Windows' (elsewhere: the test above this one)")
def test_a_com_port_that_is_not_there_on_windows(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # pyserial's Windows backend opens \\.\COM250: the device namespace, as COM10 and above need
    rec = tmp_path / "r.yaml"
    rec.write_text("recipe: r\nprofile: example-inverter\nparameters:\n  F07: 10 s\n")
    code, out, err = cli(
        capsys,
        "apply",
        str(rec),
        "--device",
        "rtu://COM250?baudrate=19200&parity=E",
        "--yes",
        "--state-dir",
        str(tmp_path / "s"),
    )
    said = " ".join((out + err).split())  # the console wraps long lines
    assert code == 3 and "rtu://COM250?baudrate=19200&parity=E: no such serial port COM250" in said, said
    assert "Traceback" not in said


@pytest.mark.portable
def test_output_in_a_code_page_without_the_character(tmp_path: Path) -> None:
    # Windows writes to pipes and files in cp1252: a name it cannot encode is a '?', not a traceback
    rec = tmp_path / "r.yaml"
    rec.write_text("recipe: Ωmega\nprofile: example-inverter\nparameters:\n  F07: 10 s\n", encoding="utf-8")
    p = subprocess.run(
        [sys.executable, "-m", "deployer", "validate", str(rec)],
        capture_output=True,
        env={**env(posixless=False), "PYTHONIOENCODING": "cp1252", "PYTHONUTF8": "0"},
        timeout=60,
    )
    # stdout: Python's default there is to fail on such a character (stderr would escape it)
    assert p.returncode == 0 and b"ok (recipe ?mega" in p.stdout and b"Traceback" not in p.stderr, p.stderr


def test_reserved_names_in_output_paths(tmp_path: Path) -> None:
    assert [
        portable.reserved_name(p)
        for p in ("CON", "out/con.json", "x\\Aux.txt", "COM1.yaml", "CONSOLE.json", "com10.json", "report.json")
    ] == ["CON", "CON", "AUX", "COM1", None, None, None]
    if sys.platform == "win32":  # the same name is an ordinary file elsewhere
        with pytest.raises(durable.OutputRefused, match="Windows reserves the name CON"):
            durable.check_output(str(tmp_path / "con.json"))
    else:
        durable.write_atomic(str(tmp_path / "con.json"), "{}")
        assert (tmp_path / "con.json").read_text() == "{}"


def test_replace_retries_while_windows_has_the_file_open(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Windows refuses to replace a file another program holds open; POSIX never does, so the refusal is
    # played here by os.replace itself (the retry is our logic, the refusal Windows')
    real, refusals = os.replace, [2]

    def replace(src: str, dst: str) -> None:
        if refusals[0]:
            refusals[0] -= 1
            raise PermissionError(13, "Permission denied")
        real(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    monkeypatch.setattr(portable, "WINDOWS", True)
    (tmp_path / "a").write_text("new")
    portable.replace(str(tmp_path / "a"), str(tmp_path / "b"), pause=0.001)
    assert (tmp_path / "b").read_text() == "new" and refusals == [0]
    refusals[0] = 100
    (tmp_path / "c").write_text("newer")
    with pytest.raises(PermissionError):
        portable.replace(str(tmp_path / "c"), str(tmp_path / "b"), pause=0.001)
    assert refusals[0] == 80 and (tmp_path / "b").read_text() == "new"  # 20 tries, then the error
    monkeypatch.setattr(portable, "WINDOWS", False)
    with pytest.raises(PermissionError):  # POSIX: a refusal is final at once
        portable.replace(str(tmp_path / "c"), str(tmp_path / "b"))
    assert refusals[0] == 79


@pytest.mark.portable
def test_pymodbus_polling_as_on_windows_keeps_the_gaps(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # On Windows pymodbus polls a serial port (force_poll) instead of waiting on it; here it is made to poll
    # the socket:// port the same way, and a device that ignores requests sooner than 40 ms after its last
    # answer (the simulator's quirk) must see none: the gaps deployer keeps start when a reply is seen.
    from pymodbus.transport import serialtransport

    from deployer.profile import builtin_profile
    from deployer.testing.simulator import Quirks, SimulatorThread

    polls = []
    real = serialtransport.SerialTransport.polling_task

    async def polling_task(self: serialtransport.SerialTransport) -> None:
        polls.append(self)
        await real(self)  # type: ignore[no-untyped-call]

    monkeypatch.setattr(serialtransport.SerialTransport, "force_poll", True)
    monkeypatch.setattr(serialtransport.SerialTransport, "polling_task", polling_task)
    rec = tmp_path / "r.yaml"
    rec.write_text(
        "recipe: r\nprofile: example-inverter\nparameters:\n  F07: 10 s\n  F08: 8 s\n  base_speed: 1750 rpm\n"
    )
    with SimulatorThread(
        builtin_profile("example-inverter"), listen="rtu+tcp://127.0.0.1:0", quirks=Quirks(request_gap_ms=40)
    ) as sim:
        port = sim.url.rsplit(":", 1)[1]
        code, out, err = cli(
            capsys,
            "apply",
            str(rec),
            "--device",
            f"rtu://socket://127.0.0.1:{port}?pause_between_requests=60ms",
            "--yes",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 0, out + err
        assert polls and sim.read("base_speed") == (1750,)
        assert [e for e in sim.log if e.result == "too soon"] == []
        assert sum(1 for e in sim.log if e.function in (6, 16)) >= 2


def test_what_mypy_cannot_see_goes_through_portable() -> None:
    # `mypy --platform win32` (make test) finds the os and signal names Windows lacks; these two exist there
    # but mean something else: os.kill(pid, 0) ends the process, add_signal_handler raises NotImplementedError
    package = ROOT / "deployer"
    found = [
        f"{p.relative_to(ROOT)}: {what}"
        for p in sorted(package.rglob("*.py"))
        if p.name != "portable.py"
        for what in ("os.kill(", ".add_signal_handler(")
        if what in p.read_text(encoding="utf-8")
    ]
    assert found == [], "use deployer.portable (pid_alive, on_signals)"


def test_pyserials_windows_open_errors_said_by_the_ports_name() -> None:
    """pyserial's Windows backend says ``could not open port '\\\\\\\\.\\\\COM7': FileNotFoundError(2, ...)``: deployer
    names the port as the user wrote it and says what to do (the Windows suite runs the real thing)."""
    from deployer.transport.clients import _windows_open_error

    gone = r"could not open port '\\\\.\\COM7': FileNotFoundError(2, 'The system cannot find the file.', None, 2)"
    busy = r"could not open port '\\\\.\\COM3': PermissionError(13, 'Access is denied.', None, 5)"
    assert _windows_open_error(gone, r"\\.\COM7") == (
        "no such serial port COM7 (deployer scan --list-ports shows this system's serial ports)"
    )
    assert _windows_open_error(busy, "com3") == (
        "COM3 is in use by another program (a terminal, a vendor's tool): close it and run again"
    )
    assert _windows_open_error("[Errno 2] could not open port /dev/ttyUSB9", "/dev/ttyUSB9") is None
