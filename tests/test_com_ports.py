"""COM ports on Windows, byte for byte: ``rtu://COM5``, ``ascii://COM5`` and ``rtu://\\\\.\\COM10`` against the
simulator on the other end of a null-modem pair, the bytes on the line as socat recorded them
(not as deployer says it sent them), one lock whatever the port's spelling, and a port that is not there
refused with its name.

``make test-windows`` runs these on a Windows Python under Wine, its COM ports socat's pseudo-terminals
(``tests/comports.py``); elsewhere they skip: COM ports are Windows' names.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from deployer.profile import builtin_profile
from deployer.testing.simulator import SimulatorThread
from deployer.transport import urls
from deployer.window.confirm import awaiting
from tests import comports
from tests.helpers import wait_for

pytestmark = [
    pytest.mark.timeout(180),
    pytest.mark.skipif(sys.platform != "win32", reason="COM ports are Windows' names (docs/windows.md)"),
]

# the Omron M1 manual's example: F07 (0x1102, two registers) = 1000, i.e. 10.00 s, by FC16, and its CRC
OMRON_QUERY = bytes.fromhex("01 10 11 02 00 02 04 00 00 03 E8 B2 98")
OMRON_ASCII = b":01101102000204000003E8EB\r\n"  # the same request in ASCII: LRC EB


@pytest.fixture
def pair_5_6() -> Iterator[comports.ComPair]:
    if not comports.available():
        pytest.skip("no virtual COM-port pair: make test-windows makes them under Wine (com0com on a Windows machine)")
    with comports.ComPair((5, 6)) as pair:
        yield pair


def deployer(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "deployer", *args], capture_output=True, text=True, timeout=120, cwd=cwd
    )


def recipe(tmp_path: Path) -> Path:
    path = tmp_path / "r.yaml"
    path.write_text("recipe: r\nprofile: omron-m1\nparameters: {F07: 10 s}\n")
    return path


def test_rtu_com5_the_omron_query_byte_for_byte(pair_5_6: comports.ComPair, tmp_path: Path) -> None:
    assert (pair_5_6.a, pair_5_6.b) == ("COM5", "COM6")
    with SimulatorThread(builtin_profile("omron-m1"), listen="rtu://COM6") as sim:
        done = deployer(
            "apply",
            str(recipe(tmp_path)),
            "--device",
            "rtu://COM5?timeout=1",
            "--yes",
            "--json",
            "--state-dir",
            "s",
            cwd=tmp_path,
        )
        assert done.returncode == 0, done.stdout + done.stderr
        assert sim.read("F07") == (0, 1000)
    sent, answered = pair_5_6.wire()
    assert OMRON_QUERY in sent, sent.hex(" ")
    assert bytes.fromhex("01 10 11 02 00 02") in answered  # the device's answer: address and count echoed
    dev = json.loads(done.stdout)["devices"][0]
    assert dev["url"] == "rtu://COM5" and dev["status"] == "ok"


def test_ascii_com5_the_same_request_with_its_lrc(pair_5_6: comports.ComPair, tmp_path: Path) -> None:
    with SimulatorThread(builtin_profile("omron-m1"), listen="ascii://COM6") as sim:
        done = deployer(
            "apply",
            str(recipe(tmp_path)),
            "--device",
            "ascii://COM5?timeout=1",
            "--yes",
            "--state-dir",
            "s",
            cwd=tmp_path,
        )
        assert done.returncode == 0, done.stdout + done.stderr
        assert sim.read("F07") == (0, 1000)
    sent, _ = pair_5_6.wire()
    assert OMRON_ASCII in sent, sent


def test_the_device_namespace_spelling_com10(tmp_path: Path) -> None:
    if not comports.available():
        pytest.skip("no virtual COM-port pair: make test-windows makes them under Wine (com0com on a Windows machine)")
    with (
        comports.ComPair((10, 11)) as pair,
        SimulatorThread(builtin_profile("omron-m1"), listen=r"rtu://\\.\COM11") as sim,
    ):
        done = deployer(
            "apply",
            str(recipe(tmp_path)),
            "--device",
            r"rtu://\\.\COM10?timeout=1",
            "--yes",
            "--json",
            "--state-dir",
            "s",
            cwd=tmp_path,
        )
        assert done.returncode == 0, done.stdout + done.stderr
        assert sim.read("F07") == (0, 1000)
        sent, _ = pair.wire()
    assert OMRON_QUERY in sent, sent.hex(" ")
    assert json.loads(done.stdout)["devices"][0]["url"] == "rtu://COM10"  # shown by its name


def test_one_lock_whatever_the_spelling_of_the_port(pair_5_6: comports.ComPair, tmp_path: Path) -> None:
    """COM5, com5 and \\\\.\\COM5 are one port: a run holding it in its confirm window refuses the others."""
    assert len({urls.parse_url(u).lock_keys for u in ("rtu://COM5", "rtu://com5", r"rtu://\\.\COM5")}) == 1
    with SimulatorThread(builtin_profile("omron-m1"), listen="rtu://COM6"):
        first = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "deployer",
                "apply",
                str(recipe(tmp_path)),
                "--device",
                "rtu://COM5?timeout=1",
                "--yes",
                "--confirm-within",
                "1h",
                "--state-dir",
                "a",
            ],
            cwd=tmp_path,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            wait_for(lambda: bool(awaiting(str(tmp_path / "a"))) or first.poll() is not None, "the confirm window")
            for spelling in ("rtu://com5", r"rtu://\\.\COM5"):
                second = deployer(
                    "apply", str(recipe(tmp_path)), "--device", spelling, "--yes", "--state-dir", "b", cwd=tmp_path
                )
                assert second.returncode == 3, second.stdout + second.stderr
                assert f"PID {first.pid}" in second.stdout + second.stderr, second.stdout + second.stderr
            assert deployer("confirm", "--state-dir", "a", cwd=tmp_path).returncode == 0
            out, err = first.communicate(timeout=120)
        finally:
            if first.poll() is None:
                first.kill()
        assert first.returncode == 0, out + err


def test_a_port_that_is_not_there_is_refused_with_its_name(tmp_path: Path) -> None:
    done = deployer(
        "apply", str(recipe(tmp_path)), "--device", "rtu://COM7?timeout=0.5", "--yes", "--state-dir", "s", cwd=tmp_path
    )
    said = done.stdout + done.stderr
    assert done.returncode == 3, said
    assert "rtu://COM7" in said and "no such serial port COM7" in said and "Traceback" not in said, said
    assert not (tmp_path / "s" / "snapshots").exists()  # nothing read, nothing written
