"""Shared fixtures: socat pseudo-terminal pairs for the serial tests."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.helpers import pty_pair

# the notes agents started without a token leave for their user's clients (deployer.agent.local_token): in a
# folder of this test session's own, not the user's home; child processes inherit it
if "DEPLOYER_RUNTIME_DIR" not in os.environ:
    import atexit
    import tempfile

    os.environ["DEPLOYER_RUNTIME_DIR"] = tempfile.mkdtemp(prefix="deployer-runtime-")
    atexit.register(shutil.rmtree, os.environ["DEPLOYER_RUNTIME_DIR"], True)


@pytest.fixture
def socat_pair(tmp_path: Path) -> Iterator[tuple[str, str]]:
    """Two linked serial ports (a null-modem cable): (port A, port B). socat's pseudo-terminals; on Windows under
    Wine (``make test-windows``) the same, seen as two COM ports (``tests/comports.py``)."""
    if sys.platform == "win32":
        from tests import comports

        if not comports.available():
            pytest.skip(
                "no virtual COM-port pair: make test-windows makes them under Wine; on a Windows machine "
                "none without com0com (an administrator's driver)"
            )
        with comports.ComPair() as pair:
            yield pair.a, pair.b
        return
    with pty_pair(tmp_path) as pair:
        yield pair


_HELD: list[socket.socket] = []


def simulate_process(*args: str) -> tuple[subprocess.Popen[str], str, int]:
    """``deployer simulate ARGS --listen tcp://127.0.0.1:0`` in a process of its own: (process, the URL
    and the port it reported). The server picks its port, so no two tests can be handed the same one."""
    import re
    import sys

    proc = subprocess.Popen(
        [sys.executable, "-m", "deployer", "simulate", *args, "--listen", "tcp://127.0.0.1:0"],
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stderr is not None
    line = proc.stderr.readline()
    found = re.search(r" on (tcp://127\.0\.0\.1:(\d+)) ", line)
    if found is None:
        proc.kill()
        raise AssertionError(f"the simulator did not report its port: {line!r}")
    return proc, found.group(1), int(found.group(2))


def dead_port() -> int:
    """A 127.0.0.1 TCP port where nothing listens, and nothing will while the tests run.

    The port stays bound (never listening) until the test process ends, so connections to it are
    refused and no other test or server can be handed it: a port guessed from a closed socket could
    be handed out twice (two "dead" devices on one port are one device) or taken by a server.
    A test that needs a server lets the server bind port 0 and reads back the port it got.
    """
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    _HELD.append(s)
    return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """Test certificates: a CA, a server certificate for 127.0.0.1, a client certificate, another CA."""
    from tests.certs import issue, make_ca

    d = tmp_path_factory.mktemp("pki")
    ca, ca_key, ca_cert = make_ca(d)
    server_crt, server_key = issue(d, "server", ca_key, ca_cert, server=True)
    client_crt, client_key = issue(d, "client", ca_key, ca_cert, server=False)
    other_ca, _, _ = make_ca(d, "other-ca")
    return {
        "ca": ca,
        "server_crt": server_crt,
        "server_key": server_key,
        "client_crt": client_crt,
        "client_key": client_key,
        "other_ca": other_ca,
    }


def _state_files(folder: Path) -> dict[str, tuple[int, int]]:
    out = {}
    for dirpath, _dirs, files in os.walk(folder):
        for name in files:
            try:
                st = os.stat(os.path.join(dirpath, name))
            except OSError:
                continue
            out[os.path.join(dirpath, name)] = (st.st_size, st.st_mtime_ns)
    return out


@pytest.fixture(autouse=True, scope="session")
def _repository_state_untouched() -> Iterator[None]:
    """No test writes into the checkout's own state folder (``.deployer``, the default ``--state-dir`` of a
    command run where the suite runs): a test leaves its journal, snapshots and audit records in its own folder."""
    folder = Path(__file__).resolve().parent.parent / ".deployer"
    before = _state_files(folder)
    yield
    changed = sorted(f for f, st in _state_files(folder).items() if before.get(f) != st)
    assert not changed, (
        f"tests wrote into {folder} (give the command a --state-dir of the test's own): {', '.join(changed)}"
    )


@pytest.fixture(autouse=True, scope="session")
def _own_lock_dir(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Device locks in a folder of this test session: parallel test runs on one machine stay apart. For the
    whole session, so that a module's fixtures (set up before any test's) run with it too; a test that
    changes it (monkeypatch) has it back afterwards."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("DEPLOYER_LOCK_DIR", str(tmp_path_factory.getbasetemp() / "locks"))
        yield


@pytest.fixture(autouse=True)
def _test_lock_dir(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """And a folder of each test's own: a test that kills a run leaves its lock records behind (as it should: the
    next run names the stale lock), and a later test's simulator given the same port would take that device's
    lock and be told of it."""
    monkeypatch.setenv("DEPLOYER_LOCK_DIR", str(tmp_path_factory.mktemp("locks")))


# ---- systems: tests whose subject is POSIX itself skip elsewhere, with the reason (docs/windows.md) ----

_WINDOWS_MODULES = {  # whole modules: Ansible has no Windows control node
    "test_ansible.py": "Ansible has no Windows control node (run playbooks from Linux or WSL)",
    "test_ansible_collection.py": "Ansible has no Windows control node (run playbooks from Linux or WSL)",
    "test_ansible_agent.py": "Ansible has no Windows control node (run playbooks from Linux or WSL)",
}
# what a test's own source uses that Windows lacks; tests/test_posixless.py runs the same code paths
# without these on Linux, and tests/test_portable.py runs the lock on Windows itself
_WINDOWS_LACKS = (
    ("SIGKILL", "sends SIGKILL (Windows: no signals to another process)"),
    ("SIGTERM", "sends SIGTERM (Windows: no signals to another process)"),
    ("SIGINT", "sends SIGINT (Windows: no signals to another process)"),
    ("SIGUSR1", "uses SIGUSR1 (POSIX only)"),
    ("send_signal", "signals another process (Windows: none but TerminateProcess)"),
    ("mkfifo", "makes a FIFO (POSIX only)"),
    ("symlink", "makes symbolic links (Windows: administrators or developer mode only)"),
    ("hardlink", "makes hard links at lock and output paths (a POSIX attack)"),
    ("os.link", "makes hard links at lock and output paths (a POSIX attack)"),
    ("chmod", "checks Unix permission modes (Windows: ACLs)"),
    ("getuid", "checks Unix user ids"),
    ("/dev/", "uses POSIX device files"),
    ("_run_on_a_terminal", "answers on a pseudo-terminal (pty, termios: POSIX; a Windows console is not one)"),
    ("pty.openpty", "answers on a pseudo-terminal (pty, termios: POSIX; a Windows console is not one)"),
    ("resource.", "uses POSIX resource limits"),
)


# Gaps of Wine (the Windows of `make test-windows`), not of Windows: under Wine these tests skip with the gap's name,
# on Windows itself they run. One entry per test; docs/windows.md reproduces this table (tests/test_docs.py checks).
WINE_GAPS = {
    "test_scan_lists_serial_ports": "Wine 8 lacks Cfgmgr32.CM_MapCrToWin32Err, which pyserial's list_ports calls",
    "test_port_held_by_another_process_is_unreachable_with_the_reason": (
        "Wine 8 opens a COM port for a second program, which Windows refuses (ERROR_ACCESS_DENIED)"
    ),
    "test_the_agents_own_token_is_kept_to_its_owner_on_windows": (
        "Wine 8 keeps no access list given to a file (SetNamedSecurityInfoW succeeds and changes nothing)"
    ),
}


def under_wine() -> bool:
    """Whether this Windows is Wine (its ntdll exports wine_get_version)."""
    if sys.platform != "win32":
        return False
    import ctypes

    return hasattr(ctypes.windll.ntdll, "wine_get_version")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "portable: runs on Windows too, whatever its source names (checked by hand)")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if sys.platform != "win32":
        return
    import inspect

    wine = under_wine()
    for item in items:
        gap = WINE_GAPS.get(item.name.split("[")[0]) if wine else None
        if gap is not None:
            item.add_marker(pytest.mark.skip(reason=f"a gap of Wine, not of Windows: {gap}"))
            continue
        if item.get_closest_marker("portable") is not None:
            continue
        reason = _WINDOWS_MODULES.get(item.path.name)
        fn = getattr(item, "function", None)
        if reason is None and fn is not None:
            try:
                source = inspect.getsource(fn)
            except (OSError, TypeError):
                source = ""
            reason = next((why for what, why in _WINDOWS_LACKS if what in source), None)
        if reason is not None:
            item.add_marker(pytest.mark.skip(reason=f"not on Windows: {reason}"))
