"""One device, however it is spelled; lock files nobody can turn against a run (issue #17 items 3, 4, 11, 12).

Runs are real processes (`python -m deployer`) against simulators on 127.0.0.1.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
import stat
import subprocess
import sys
import time
import urllib.parse
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from deployer.errors import BadURL, Locked
from deployer.profile import builtin_profile
from deployer.state import lock
from deployer.testing.simulator import SimulatorThread
from deployer.transport import urls
from tests.helpers import wait_for
from tests.test_lock_journal import FIRST, SECOND, recipe, run, start

pytestmark = pytest.mark.timeout(180)


def test_spellings_of_one_address_are_one_lock_key() -> None:
    keys = {urls.parse_url(f"tcp://{h}:5020").lock_keys for h in ("127.0.0.1", "127.1", "2130706433", "0x7f.1")}
    assert keys == {("tcp:127.0.0.1:5020",)}
    assert "tcp:127.0.0.1:5020" in urls.parse_url("tcp://localhost:5020").lock_keys
    assert urls.parse_url("tcp://[::1]:5020").lock_keys == ("tcp:[::1]:5020",)
    assert urls.parse_url("tcp://[::ffff:127.0.0.1]:5020").lock_keys == ("tcp:127.0.0.1:5020",)
    assert urls.parse_url("rtu+tcp://127.1:9").lock_keys == ("gateway:127.0.0.1:9",)
    assert urls.parse_url("tcp://127.0.0.1:5021").lock_keys != urls.parse_url("tcp://127.0.0.1:5020").lock_keys


def test_serial_keys_follow_links(tmp_path: Path) -> None:
    real = tmp_path / "ttyUSB0"
    real.touch()
    (tmp_path / "by-id").symlink_to(real)
    assert urls.parse_url(f"rtu://{tmp_path}/by-id").lock_keys == urls.parse_url(f"rtu://{real}").lock_keys


def test_two_runs_by_two_spellings_exclude_each_other(tmp_path: Path) -> None:
    from deployer.window.confirm import awaiting

    with SimulatorThread(builtin_profile("example-inverter")) as sim:
        port = sim.url.rsplit(":", 1)[1]
        # the first run holds the device until it is confirmed, however long the second takes to start
        a = start(
            "apply",
            recipe(tmp_path, "first", FIRST),
            "--device",
            f"tcp://127.0.0.1:{port}",
            "--yes",
            "--state-dir",
            str(tmp_path / "sa"),
            "--confirm-within",
            "1h",
        )
        wait_for(lambda: bool(awaiting(str(tmp_path / "sa"))) or a.poll() is not None)
        assert any(r.get("pid") == a.pid for r in _records())
        code, out, err = run(
            "apply",
            recipe(tmp_path, "second", SECOND),
            "--device",
            f"tcp://localhost:{port}",
            "--yes",
            "--state-dir",
            str(tmp_path / "sb"),
        )
        assert run("confirm", "--state-dir", str(tmp_path / "sa"))[0] == 0
        assert a.wait(timeout=60) == 0
        assert code == 3 and f"locked by PID {a.pid}" in out + err, out + err
        assert sim.read("base_speed") == (1750,)  # only the first run wrote
        keys = urls.parse_url(sim.url).lock_keys
    for k in keys:  # released locks leave no record (their files stay for the next run: no inode churn)
        for path in (_lock_path(f"{k}#bus"), _lock_path(lock.device_key(k, 1))):
            assert not path.exists() or path.read_bytes().strip() == b""


def _records() -> list[dict[str, object]]:
    d = Path(lock.lock_dir())
    out = []
    for f in d.glob("*.lock") if d.exists() else []:
        text = f.read_text() if f.is_file() and not f.is_symlink() else ""
        if text.strip():
            out.append(json.loads(text))
    return out


def _lock_path(key: str) -> Path:
    return Path(lock.lock_dir()) / (hashlib.sha256(key.encode()).hexdigest()[:24] + ".lock")


@pytest.mark.parametrize("plant", ["symlink", "hardlink", "fifo"])
def test_a_planted_lock_file_is_refused_and_its_target_untouched(plant: str, tmp_path: Path) -> None:
    victim = tmp_path / "precious.conf"
    victim.write_text("keep me\n")
    with SimulatorThread(builtin_profile("example-inverter")) as sim:
        key = lock.device_key(urls.parse_url(sim.url).lock_keys[0], 1)
        path = _lock_path(key)
        path.parent.mkdir(parents=True, exist_ok=True)
        os.chmod(path.parent, 0o1777)
        path.unlink(missing_ok=True)  # a released lock's file stays: an earlier test's device may have had the port
        if plant == "symlink":
            path.symlink_to(victim)
        elif plant == "hardlink":
            os.link(victim, path)
        else:
            os.mkfifo(path)
        try:
            code, out, err = run(
                "apply",
                recipe(tmp_path, "first", FIRST),
                "--device",
                sim.url,
                "--yes",
                "--state-dir",
                str(tmp_path / "s"),
            )
        finally:
            path.unlink()
        assert code == 3, out + err
        why = {"symlink": "it is a symbolic link", "hardlink": "it has 2 names", "fifo": "not a regular file"}[plant]
        assert f"refusing the lock file {path}: {why}" in out + err
        assert victim.read_text() == "keep me\n"
        assert not any(e.function == 16 for e in sim.log)


def test_lock_folder_rules(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    d = tmp_path / "locks"
    monkeypatch.setenv(lock.ENV, str(d))
    held = lock.try_lock("k")
    assert stat.S_IMODE(d.stat().st_mode) == 0o1777  # sticky, every user's runs share it
    assert stat.S_IMODE(Path(held.path).stat().st_mode) == 0o666  # whatever the umask: others lock it too
    held.release()
    assert [(f.name, f.read_bytes().strip()) for f in d.iterdir()] == [(Path(held.path).name, b"")]  # kept, blank
    lock._ready.clear()
    link = tmp_path / "link"
    link.symlink_to(d)
    monkeypatch.setenv(lock.ENV, str(link))
    with pytest.raises(Locked, match="it is a symbolic link"):
        lock.try_lock("k")
    other = tmp_path / "open"
    other.mkdir()
    os.chmod(other, 0o777)
    os.chown(other, 1, 1) if os.getuid() == 0 else pytest.skip("chown needs root")
    monkeypatch.setenv(lock.ENV, str(other))
    with pytest.raises(Locked, match="not sticky"):
        lock.try_lock("k")


def test_a_shared_bus_lock_is_held_until_its_last_holder_lets_go() -> None:
    a = lock.try_lock("bus", shared=True)
    b = lock.try_lock("bus", shared=True)
    a.release()
    with pytest.raises(Locked, match="the bus is in use"):  # b still holds it: a broadcast must wait
        lock.try_lock("bus")
    b.release()
    alone = lock.try_lock("bus")
    alone.release()
    assert Path(alone.path).read_bytes().strip() == b""  # no record left behind: nothing to call stale


@pytest.mark.skipif(sys.platform == "win32", reason="Windows removes no file that is open: the race cannot happen")
def test_a_waiter_on_a_removed_file_locks_the_new_one() -> None:
    """An older deployer removes the file on release; a run that opened the old file must not think it holds
    the lock (both versions may run side by side on one machine)."""
    first = lock.try_lock("dev")
    old = os.open(first.path, os.O_RDWR)
    first.release()
    os.unlink(first.path)  # as an older deployer's release did
    second = lock.try_lock("dev")  # creates a new file at the path
    try:
        import fcntl

        fcntl.flock(old, fcntl.LOCK_EX | fcntl.LOCK_NB)  # the old inode is free: locking it means nothing
        with pytest.raises(Locked):
            lock.try_lock("dev")
    finally:
        os.close(old)
        second.release()


@pytest.mark.skipif(sys.platform == "win32", reason="Windows removes no file that is open: the race cannot happen")
def test_a_file_removed_between_the_open_and_the_lock_is_not_taken_for_the_lock(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The race itself: the holder (an older deployer) removes the file after this run opened it and before
    this run's lock; the lock taken must be the one of the file now at the path, never of the removed one."""
    from deployer.state import oslock

    first = lock.try_lock("dev")
    path = first.path
    first.release()
    backend = oslock.backend()
    real = backend.try_lock
    calls: list[int] = []

    def racing(fd: int, *, shared: bool = False) -> bool:
        if not calls:  # the first open's file goes before it is locked (the next open makes a new one)
            os.unlink(path)
        calls.append(fd)
        return real(fd, shared=shared)

    monkeypatch.setattr(backend, "try_lock", racing)
    held = lock.try_lock("dev")
    try:
        assert len(calls) == 2  # the removed file's lock was let go, and the path opened again
        here, mine = os.stat(path), os.fstat(held.fd)
        assert (mine.st_dev, mine.st_ino, mine.st_nlink) == (here.st_dev, here.st_ino, 1)
        assert json.loads(Path(path).read_text())["pid"] == os.getpid()  # the record went into the new file
    finally:
        held.release()


def test_a_refused_broadcast_names_who_writes_the_bus(tmp_path: Path) -> None:
    with SimulatorThread(builtin_profile("example-inverter")) as sim:
        keys = urls.parse_url(sim.url).lock_keys
        other = asyncio.run(lock.acquire_device(keys, 2, command="deployer apply line3.yaml"))
        try:
            code, out, err = run(
                "apply",
                recipe(tmp_path, "first", FIRST),
                "--device",
                sim.url,
                "--unit",
                "0",
                "--allow-broadcast",
                "--yes",
                "--state-dir",
                str(tmp_path / "s"),
            )
        finally:
            for h in other:
                h.release()
        assert code == 3
        assert f"the bus is in use: unit 2 by PID {os.getpid()} on " in out + err
        assert "(deployer apply line3.yaml) is being written" in out + err


INVENTORY = """\
devices:
  press-1: {{url: "tcp://127.0.0.1:{port}"}}
  press-1b: {{url: "tcp://localhost:{port}"}}
  press-2: {{url: "tcp://127.0.0.1:{port}", unit: 2}}
"""


def test_an_inventory_naming_one_device_twice_is_refused(tmp_path: Path) -> None:
    with SimulatorThread(builtin_profile("example-inverter"), units=(1, 2)) as sim:
        port = sim.url.rsplit(":", 1)[1]
        inv = tmp_path / "inv.yaml"
        inv.write_text(INVENTORY.format(port=port))
        code, out, err = run("validate", str(inv))
        msg = (
            f"{inv}:3:19: error: devices 'press-1' and 'press-1b' are one device (tcp://127.0.0.1:{port} and "
            f"tcp://localhost:{port}, unit 1): name each device once"
        )
        assert code == 1 and msg in out + err, out + err
        code, out, err = run(
            "apply",
            recipe(tmp_path, "first", FIRST),
            "--inventory",
            str(inv),
            "--yes",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 1 and msg in out + err, out + err
        assert not sim.log  # nothing was sent
        # --unit puts all three on one unit: press-2 is then press-1 too
        inv.write_text(INVENTORY.format(port=port).replace('  press-1b: {url: "tcp://localhost:' + port + '"}\n', ""))
        code, out, err = run(
            "apply",
            recipe(tmp_path, "first", FIRST),
            "--inventory",
            str(inv),
            "--unit",
            "1",
            "--yes",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 1 and "devices 'press-1' and 'press-2' are one device" in out + err, out + err


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "tcp://[::1",
            "'tcp://[::1' is not a valid URL (Invalid IPv6 URL; an IPv6 host is written in brackets: tcp://[::1]:502)",
        ),
        (
            "tcp://user:pw@10.0.0.1",
            "unexpected user name or password in 'tcp://user:pw@10.0.0.1' (Modbus has no "
            "login; TLS uses cert= and key=)",
        ),
        (
            "tcp://10.0.0.1#frag",
            "unexpected '#frag' in 'tcp://10.0.0.1#frag' (a device URL has no fragment; options go after ?)",
        ),
        (
            "tcp://h?timeout=1&timeout=2",
            "option 'timeout' given 2 times in 'tcp://h?timeout=1&timeout=2': give it once",
        ),
        ("tls://h?ca=/dev/zero", "tls option ca: '/dev/zero' is not a regular file (expected a PEM file)"),
    ],
)
def test_bad_urls_said_plainly(text: str, message: str, tmp_path: Path) -> None:
    with pytest.raises(BadURL) as e:
        urls.parse_url(text)
    assert str(e.value) == message
    r = tmp_path / "r.yaml"
    r.write_text(
        f"recipe: r\nprofile: example-inverter\ndevice: {{url: {json.dumps(text)}}}\nparameters:\n  F07: 1 s\n"
    )
    code, out, err = run("validate", str(r))
    assert code == 1 and f"{r}:3:15: error: {message}" in out + err, out + err


@settings(max_examples=400, deadline=None)
@given(st.text(alphabet=st.sampled_from(list("tcprusl+:/[]@#?&=.%1270x:abfe -")), max_size=40))
def test_any_url_text_parses_or_is_a_bad_url(text: str) -> None:
    """Whatever the text, parse_url returns a URL or raises BadURL (never another exception), and what it
    accepts has a host or a path and a lock key."""
    try:
        u = urls.parse_url(text)
    except BadURL:
        return
    assert (u.host or u.path) and u.lock_keys
    assert "@" not in (u.host or "") and "#" not in urllib.parse.urlsplit(text.strip()).geturl().split("?")[0][-1:]


def test_lock_records_say_who(tmp_path: Path) -> None:
    held = lock.try_lock("who", command="deployer apply x")
    try:
        rec = json.loads(Path(held.path).read_text())
        assert rec["pid"] == os.getpid() and rec["command"] == "deployer apply x" and rec["since"] <= time.time()
    finally:
        held.release()


def test_release_by_another_process_is_safe(tmp_path: Path) -> None:
    code = (
        "from deployer.state import lock; h = lock.try_lock('x'); import sys; sys.stdout.write(h.path); "
        "sys.stdout.flush(); h.release()"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0 and Path(p.stdout).read_bytes().strip() == b""  # released there: no record left
