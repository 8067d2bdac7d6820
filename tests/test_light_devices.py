"""The benchmarks' light device farm (benchmarks/light_devices.py) is a real Modbus/TCP device: pymodbus's
client and mbpoll (libmodbus, a client we did not write) read what they wrote, get the exceptions a device
answers, and a fleet apply writes and verifies through it."""

from __future__ import annotations

import asyncio
import json
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from pymodbus.client import AsyncModbusTcpClient

pytestmark = pytest.mark.timeout(60)
MBPOLL = shutil.which("mbpoll")
ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def farm() -> Iterator[list[str]]:
    """Three devices in two processes of their own (as the benchmark runs them), 64 registers each."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "benchmarks.light_devices", "3", "0", "--processes", "2", "--registers", "64"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        assert proc.stdout is not None
        urls = json.loads(proc.stdout.readline())
        assert len(urls) == 3
        yield urls
    finally:
        assert proc.stdin is not None
        proc.stdin.close()
        proc.wait(timeout=20)


def _port(url: str) -> int:
    return int(url.rsplit(":", 1)[1])


def test_pymodbus_reads_what_it_wrote_and_gets_the_exceptions(farm: list[str]) -> None:
    async def main() -> None:
        a = AsyncModbusTcpClient("127.0.0.1", port=_port(farm[0]), retries=0, timeout=2)
        b = AsyncModbusTcpClient("127.0.0.1", port=_port(farm[1]), retries=0, timeout=2)
        assert await a.connect() and await b.connect()
        try:
            assert not (await a.write_registers(10, [1, 2, 65535], device_id=1)).isError()  # FC16
            assert not (await a.write_register(20, 513, device_id=1)).isError()  # FC06
            r = await a.read_holding_registers(9, count=5, device_id=1)
            assert r.registers == [0, 1, 2, 65535, 0]
            assert (await a.read_input_registers(20, count=1, device_id=1)).registers == [513]
            assert (await b.read_holding_registers(10, count=3, device_id=1)).registers == [0, 0, 0]  # its own
            beyond = await a.read_holding_registers(62, count=4, device_id=1)
            assert beyond.isError() and beyond.exception_code == 2
            refused = await a.write_registers(63, [7, 7], device_id=1)  # all or nothing
            assert refused.isError() and refused.exception_code == 2
            assert (await a.read_holding_registers(62, count=2, device_id=1)).registers == [0, 0]
            coils = await a.read_coils(0, count=1, device_id=1)
            assert coils.isError() and coils.exception_code == 1
        finally:
            a.close()
            b.close()

    asyncio.run(main())


@pytest.mark.skipif(MBPOLL is None, reason="mbpoll (libmodbus) is not installed")
def test_mbpoll_reads_what_it_wrote(farm: list[str]) -> None:
    assert MBPOLL is not None
    port = str(_port(farm[2]))
    base = [MBPOLL, "-m", "tcp", "-a", "1", "-0", "-t", "4", "-p", port]
    subprocess.run([*base, "-r", "30", "127.0.0.1", "11", "22", "33"], check=True, capture_output=True, timeout=20)
    out = subprocess.run(
        [*base, "-r", "29", "-c", "5", "-1", "127.0.0.1"], check=True, capture_output=True, text=True, timeout=20
    ).stdout
    assert "[29]: \t0\n[30]: \t11\n[31]: \t22\n[32]: \t33\n[33]: \t0\n" in out
    bad = subprocess.run([*base, "-r", "100", "-c", "2", "-1", "127.0.0.1"], capture_output=True, text=True, timeout=20)
    assert "Illegal data address" in bad.stdout + bad.stderr


def test_a_fleet_apply_writes_and_verifies_through_it(farm: list[str], tmp_path: Path) -> None:
    (tmp_path / "p.yaml").write_text(
        "profile: p\nparameters:\n  a: {register: 40, type: uint16}\n  b: {register: 41, type: uint32}\n"
    )
    (tmp_path / "r.yaml").write_text("recipe: r\nprofile: p.yaml\nparameters: {a: 5, b: 70000}\n")
    (tmp_path / "inv.yaml").write_text("devices:\n" + "".join(f"  d{i}: {{url: '{u}'}}\n" for i, u in enumerate(farm)))
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "deployer",
            "apply",
            "r.yaml",
            "--inventory",
            "inv.yaml",
            "--yes",
            "--report",
            "rep.json",
            "--state-dir",
            "st",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    report = json.loads((tmp_path / "rep.json").read_text())
    assert [d["status"] for d in report["devices"]] == ["ok"] * 3
    for d in report["devices"]:
        assert {p["name"]: p["after_raw"] for p in d["parameters"]} == {"a": [5], "b": [1, 4464]}
