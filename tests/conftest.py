"""Shared fixtures: socat pseudo-terminal pairs for the serial tests."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest


@pytest.fixture
def socat_pair(tmp_path: Path) -> Iterator[tuple[str, str]]:
    """Two linked pseudo-terminals (a null-modem cable): (path A, path B)."""
    if shutil.which("socat") is None:
        pytest.skip("socat is not installed (CI installs it: apt-get install socat)")
    a, b = str(tmp_path / "ttyA"), str(tmp_path / "ttyB")
    proc = subprocess.Popen(["socat", "-d", "-d", f"pty,raw,echo=0,link={a}", f"pty,raw,echo=0,link={b}"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 5
    while not (os.path.exists(a) and os.path.exists(b)):
        if time.monotonic() > deadline or proc.poll() is not None:
            proc.kill()
            pytest.fail("socat did not create the pty pair")
        time.sleep(0.02)
    try:
        yield a, b
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
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
    return {"ca": ca, "server_crt": server_crt, "server_key": server_key, "client_crt": client_crt,
            "client_key": client_key, "other_ca": other_ca}


@pytest.fixture(autouse=True)
def _own_lock_dir(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """Device locks in a folder of this test session: parallel test runs on one machine stay apart."""
    monkeypatch.setenv("DEPLOYER_LOCK_DIR", str(tmp_path_factory.getbasetemp() / "locks"))
