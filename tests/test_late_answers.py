"""Answers that come late, or wrong: never taken as the answer to another request (issue #17 items 1, 12).

The devices here are our own small RTU/TCP servers on a socat pty pair and on 127.0.0.1 sockets, built
on umodbus's CRC (an implementation we did not write), answering after the client's timeout or with a
wrong unit, byte count or echo; plus the simulator over rtu+tcp with a latency longer than the timeout.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import struct
import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import yaml

from deployer.errors import BadAnswer
from deployer.testing.simulator import Faults, Simulator
from deployer.transport import clients as tp
from tests.helpers import count, profile_from
from tests.rtu_devices import Answer, Device, crc, on_pty, on_tcp, read_frame

TIMEOUT = 0.2
LATE = 0.3  # after the timeout, before the line has been silent for another whole timeout


def _url(kind: str, where: str, port: int = 0) -> str:
    if kind == "rtu":
        return f"rtu://{where}?timeout={TIMEOUT:g}&retries=2"
    return f"rtu+tcp://127.0.0.1:{port}?timeout={TIMEOUT:g}&retries=2"


@contextmanager
def device_at(kind: str, dev: Device, socat_pair: tuple[str, str]) -> Iterator[str]:
    if kind == "rtu":
        with on_pty(dev, socat_pair[0]):
            yield _url(kind, socat_pair[1])
    else:
        with on_tcp(dev) as port:
            yield _url(kind, "", port)


Reads = tuple[list[list[int]], list[float], list[bytes]]


async def _two_reads(url: str, session_reads: list[tuple[int, int]]) -> Reads:
    """The executor's own retry loop (Session) over a real transport: reads in order; their values, the late
    answers, and the request frames the session says it sent (confirming reads included)."""
    from deployer.execute.session import Session

    t = tp.open_transport(url)
    await t.connect()
    try:
        s = Session(t, 1, retries=t.url.retries, backoff=0.05, records=[])
        values = [await s.read(a, n) for a, n in session_reads]
        return values, t.late_answers, [read_frame(r.address, r.count) for r in s.records]
    finally:
        await t.close()


@pytest.mark.parametrize("kind", ["rtu", "rtu+tcp"])
def test_a_late_answer_is_never_the_next_requests_answer(kind: str, socat_pair: tuple[str, str]) -> None:
    """The issue's case: two same-size reads, the first answered after the timeout. Before, the
    late answer of the first read's first copy answered its retry, and the retry's answer the second read."""
    regs = {100 + i: 1 for i in range(10)} | {200 + i: 2 for i in range(10)}
    dev = Device(regs, delay=lambda i: LATE if i == 0 else 0.0)
    with device_at(kind, dev, socat_pair) as url:
        values, late, sent = asyncio.run(_two_reads(url, [(100, 10), (200, 10)]))
    assert values == [[1] * 10, [2] * 10]
    # each request reached the device once; after the late answer each value was read again to confirm it
    assert dev.frames == sent == [read_frame(100, 10)] * 2 + [read_frame(200, 10)] * 2
    assert len(late) == 1 and late[0] > TIMEOUT


@pytest.mark.parametrize("kind", ["rtu", "rtu+tcp"])
def test_a_device_always_late_gets_every_request_once_and_right(kind: str, socat_pair: tuple[str, str]) -> None:
    regs = {100 + i: 1 for i in range(10)} | {200 + i: 2 for i in range(10)}
    dev = Device(regs, delay=lambda i: LATE)
    with device_at(kind, dev, socat_pair) as url:
        values, late, sent = asyncio.run(_two_reads(url, [(100, 10), (200, 10), (100, 10)]))
    assert values == [[1] * 10, [2] * 10, [1] * 10]
    assert dev.frames == sent == [read_frame(a, 10) for a in (100, 100, 200, 200, 100, 100)]
    assert len(late) == 6  # every answer came late, each was taken by its own request's retry


def test_bytes_nobody_asked_for_are_drained_before_the_next_request(socat_pair: tuple[str, str]) -> None:
    """A stray answer (e.g. to another master, or a device answering twice) after a good answer: the next
    request waits until the line is quiet, and takes only its own answer."""
    regs = {100 + i: 1 for i in range(10)} | {200 + i: 2 for i in range(10)}
    # answer 0 comes twice: the second copy (same shape as read 2's answer) arrives while the client settles
    dev = Device(regs, answer=lambda i, req, good: good + good if i == 0 else good)
    with device_at("rtu", dev, socat_pair) as url:
        values, late, sent = asyncio.run(_two_reads(url, [(100, 10), (200, 10)]))
    assert values == [[1] * 10, [2] * 10]
    # the second read came after bytes nobody asked for: it is read again once the line was silent
    assert dev.frames == sent == [read_frame(100, 10), read_frame(200, 10), read_frame(200, 10)] and late == []


def _bad(
    answer: Answer, request: Callable[[tp.Transport], Any], kind: str = "rtu", socat_pair: tuple[str, str] = ("", "")
) -> str:
    dev = Device({100 + i: 7 for i in range(4)}, answer=answer)

    async def main() -> str:
        t = tp.open_transport(url.replace("retries=2", "retries=0"))
        await t.connect()
        try:
            with pytest.raises(BadAnswer) as e:
                await request(t)
            return str(e.value)
        finally:
            await t.close()

    with device_at(kind, dev, socat_pair) as url:
        return asyncio.run(main())


def _unit(n: int) -> Answer:
    return lambda i, req, good: bytes(crc.add_crc(bytes([n]) + good[1:-2]))


@pytest.mark.parametrize("kind", ["rtu", "rtu+tcp"])
def test_wrong_answers_are_named_not_called_silence(kind: str, socat_pair: tuple[str, str]) -> None:
    read = lambda t: t.read_holding_registers(100, 4, 1)  # noqa: E731
    assert _bad(_unit(2), read, kind, socat_pair) == "an answer from unit 2 to a request for unit 1"

    def short(i: int, req: bytes, good: bytes) -> bytes:
        return bytes(crc.add_crc(bytes([1, 3, 6]) + good[3:9]))

    assert (
        _bad(short, read, kind, socat_pair) == "an answer with 6 bytes of registers to a read of 4 registers (8 bytes)"
    )

    def echo(i: int, req: bytes, good: bytes) -> bytes:
        return bytes(crc.add_crc(bytes([1, 16]) + struct.pack(">HH", 101, 2)))

    assert (
        _bad(echo, lambda t: t.write_registers(100, [1, 2], 1), kind, socat_pair)
        == "an answer echoing address 101, count 2 to a write of address 100, count 2"
    )

    def other_fc(i: int, req: bytes, good: bytes) -> bytes:
        return bytes(crc.add_crc(bytes([1, 4, 8]) + bytes(8)))

    assert _bad(other_fc, read, kind, socat_pair) == "an answer with function code 4 to a function 3 request"

    def garbled(i: int, req: bytes, good: bytes) -> bytes:
        return good[:-1] + bytes([good[-1] ^ 0xFF])

    assert _bad(garbled, read, kind, socat_pair) == "a garbled answer (CRC error)"


def test_a_wrong_answer_is_reported_as_such_after_the_retries(socat_pair: tuple[str, str]) -> None:
    dev = Device({100: 7}, answer=_unit(9))
    with device_at("rtu", dev, socat_pair) as url, pytest.raises(Exception) as e:
        asyncio.run(_two_reads(url, [(100, 1)]))
    assert str(e.value) == "an answer from unit 9 to a request for unit 1 (after 3 attempts)"


PROFILE = """\
profile: late-dev
parameters:
  p1: {register: 100, type: uint16}
  p2: {register: 200, type: uint16}
"""


def _deployer(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "deployer", *args],
        capture_output=True,
        text=True,
        timeout=300,
        env=os.environ | {"NO_COLOR": "1"},
    )


def _late_recipe(tmp_path: Path, port: str) -> Path:
    profile_from(tmp_path, PROFILE)
    recipe = tmp_path / "r.yaml"
    recipe.write_text(
        f"recipe: late\nprofile: dev.yaml\ndevice: {{url: 'rtu://{port}?timeout={TIMEOUT:g}', "
        "unit: 1}\nparameters:\n  p1: 11\n  p2: 22\n"
    )
    return recipe


def test_apply_to_an_always_late_device_snapshots_the_truth(socat_pair: tuple[str, str], tmp_path: Path) -> None:
    """A real `deployer apply` process: the snapshot holds what the device held, every request reached
    it once, the report says the device answered late."""
    recipe = _late_recipe(tmp_path, socat_pair[1])
    dev = Device({100: 1, 200: 2}, delay=lambda i: LATE)
    with on_pty(dev, socat_pair[0]):
        run = _deployer(
            "apply",
            str(recipe),
            "--yes",
            "--report",
            str(tmp_path / "report.json"),
            "--state-dir",
            str(tmp_path / "state"),
        )
    assert run.returncode == 0, run.stdout + run.stderr
    report = json.loads((tmp_path / "report.json").read_text())
    d = report["devices"][0]
    snap = yaml.safe_load(Path(d["snapshot"]).read_text())
    assert snap["parameters"] == {"p1": 1, "p2": 2}
    assert dev.regs[100] == 11 and dev.regs[200] == 22
    # register requests (the device's identification, FC43, is asked once too and answered exception 01)
    sent = [(r["function"], r["address"], r["count"]) for r in d["requests"] if r["function"] in (3, 6, 16)]
    got = [
        (f[1], struct.unpack(">H", f[2:4])[0], 1 if f[1] == 6 else struct.unpack(">H", f[4:6])[0])
        for f in dev.frames
        if f[1] in (3, 6, 16)
    ]
    assert len(dev.frames) - len(got) == len(d["requests"]) - len(sent) <= 1
    # every request the report lists reached the device, and nothing else: a retry goes out only when the
    # late answer to its first copy did not come first (a loaded machine), never more often than counted
    attempts = sum(r["attempts"] for r in d["requests"] if r["function"] in (3, 6, 16))
    assert sorted(set(got)) == sorted(set(sent)) and len(sent) <= len(got) <= attempts
    assert [g for g in sent if g[0] != 3] == [(16, 100, 1), (16, 200, 1)]  # each write once
    # after the first late answer every value read (snapshot, read-back) was read again to confirm it
    reads = [g[1] for g in sent if g[0] == 3]
    assert reads[:2] == [100, 100] and reads.count(100) >= 4 and reads.count(200) >= 4, reads
    assert any("after the timeout" in n and "confirming reads" in n for n in d["notices"]), d["notices"]


class _Counter(Device):
    """A device whose register 200 counts its reads (a live value): no two reads agree."""

    def handle(self, req: bytes) -> bytes | None:
        if req[1] == 3 and req[2:4] == b"\x00\xc8":
            self.regs[200] += 1
        return super().handle(req)


def test_a_value_no_second_read_confirms_is_not_written(socat_pair: tuple[str, str], tmp_path: Path) -> None:
    """After a late answer every value must be confirmed; p2's never is (it changes at each read): the
    device is failed with nothing written, and the report names the late answer and the timeout that serves."""
    recipe = _late_recipe(tmp_path, socat_pair[1])
    dev = _Counter({100: 1, 200: 2}, delay=lambda i: 2.5 * TIMEOUT if i == 0 else 0.0)
    with on_pty(dev, socat_pair[0]):
        run = _deployer(
            "apply",
            str(recipe),
            "--yes",
            "--report",
            str(tmp_path / "report.json"),
            "--state-dir",
            str(tmp_path / "state"),
        )
    assert run.returncode == 4, run.stdout + run.stderr
    d = json.loads((tmp_path / "report.json").read_text())["devices"][0]
    assert d["status"] == "failed" and d["snapshot"] is None
    assert "no read after" in d["error"] and d["error"].endswith("nothing was written"), d["error"]
    served = re.search(r"timeout=([0-9.]+) would have served", d["error"])
    assert served and float(served[1]) >= 0.75, d["error"]  # 1.5 times the 0.5 s the device took, or more
    assert "1 request went unanswered within the timeout (0.2 s)" in d["error"], d["error"]
    assert any("went unanswered" in n and "would have served" in n for n in d["notices"]), d["notices"]
    assert not [f for f in dev.frames if f[1] in (6, 16)] and dev.regs[100] == 1
    reads = [r["address"] for r in d["requests"] if r["function"] == 3]
    assert reads == [100, 100, 200, 200, 200, 200], reads  # p2: read, then three reads that never agreed
    assert "nothing was written" in run.stdout + run.stderr


def test_diff_of_a_value_no_second_read_confirms_says_it_cannot_be_read(
    socat_pair: tuple[str, str], tmp_path: Path
) -> None:
    recipe = _late_recipe(tmp_path, socat_pair[1])
    dev = _Counter({100: 1, 200: 2}, delay=lambda i: 2.5 * TIMEOUT if i == 0 else 0.0)
    with on_pty(dev, socat_pair[0]):
        run = _deployer("diff", str(recipe))
    assert run.returncode == 3, run.stdout + run.stderr
    assert "went out of step" in run.stderr and "no read after" in run.stderr, run.stderr
    assert "Traceback" not in run.stderr


class _LiveAfterWrite(Device):
    """Answers at once until it is written; then its first read answer comes late, and p2 reads one more
    at every other read (a value that moves on its own)."""

    written = late_done = False
    flip = 0

    def handle(self, req: bytes) -> bytes | None:
        self.written = self.written or req[1] == 16
        if not (self.written and req[1] == 3 and req[2:4] == b"\x00\xc8"):
            return super().handle(req)
        self.flip ^= 1
        self.regs[200] += self.flip
        try:
            return super().handle(req)
        finally:
            self.regs[200] -= self.flip

    def late(self, i: int, req: bytes) -> float:
        if self.written and not self.late_done and req[1] == 3:
            self.late_done = True
            return 2.5 * TIMEOUT
        return 0.0


def test_a_read_back_no_second_read_confirms_is_not_ok(socat_pair: tuple[str, str], tmp_path: Path) -> None:
    recipe = _late_recipe(tmp_path, socat_pair[1])
    dev = _LiveAfterWrite({100: 1, 200: 2})
    with on_pty(dev, socat_pair[0]):
        run = _deployer(
            "apply",
            str(recipe),
            "--yes",
            "--report",
            str(tmp_path / "report.json"),
            "--state-dir",
            str(tmp_path / "state"),
        )
    assert run.returncode == 4, run.stdout + run.stderr
    d = json.loads((tmp_path / "report.json").read_text())["devices"][0]
    assert dev.regs == {100: 11, 200: 22} and d["snapshot"] is not None  # written, then not verified
    p2 = next(p for p in d["parameters"] if p["name"] == "p2")
    assert p2["status"] != "ok" and "read-back failed" in p2["error"] and "no read after" in p2["error"], p2


def test_simulator_over_rtu_tcp_slower_than_the_timeout(tmp_path: Path) -> None:
    prof = profile_from(tmp_path, PROFILE)
    sim = Simulator(prof, listen="rtu+tcp://127.0.0.1:0", init={100: 1, 200: 2}, faults=Faults(latency_ms=LATE * 1000))

    async def main() -> Reads:
        async with sim:
            return await _two_reads(f"{sim.url}?timeout={TIMEOUT:g}&retries=2", [(100, 1), (200, 1)])

    values, late, sent = asyncio.run(main())
    assert values == [[1], [2]] and len(late) == 4
    assert count(sim.log, 3, address=100) == 2 and count(sim.log, 3, address=200) == 2 and len(sent) == 4


def test_an_answer_in_the_same_turn_as_its_timeout_is_kept_for_the_retry() -> None:
    """The timer gave up on the request (its future holds TimeoutError) and the answer came in the same
    turn of the event loop, before the request's task resumed: the answer is not lost, the retry of that
    very request takes it instead of sending again."""
    from pymodbus.framer import FramerRTU

    async def run() -> None:
        rx = tp._Receiver("rtu", lambda _out, chunk: chunk)
        want = tp._Expect(unit=1, function=3, address=100, count=1)
        rx.start(want)
        assert rx.future is not None
        tp._too_late(rx.future)  # the timeout fires first...
        pdu = bytes([1, 3, 2, 0x12, 0x34])
        rx.feed(pdu + FramerRTU.compute_CRC(pdu).to_bytes(2, "big"))  # ...then the answer, same turn
        with pytest.raises(TimeoutError):
            await tp._answer(rx.future, 1.0)
        rx.unanswered()
        late = rx.take_late(want)
        assert late is not None and late[0] == bytes([3, 2, 0x12, 0x34])

    asyncio.run(run())
