"""Shared test helpers: profiles from text, simulator runs, request counting from the device's log."""

from __future__ import annotations

import asyncio
import os
import socketserver
import subprocess
import threading
import time
from collections.abc import Awaitable, Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

import pytest

from deployer.profile import Profile, load_profile
from deployer.testing.simulator import LogEntry, Simulator

T = TypeVar("T")


def without_coverage() -> dict[str, str]:
    """This process's environment without make test's COVERAGE_* settings, for child processes that coverage would
    only slow down: Ansible's (ansible-playbook and a fork per task and host, each starting coverage: a third of
    test_ansible.py's CPU; what they run of deployer is its public API, measured in-process) and the hostile imports'
    bounded runs (their memory and their bounds must be the importer's)."""
    return {k: v for k, v in os.environ.items() if not k.startswith("COVERAGE_")}


def cli(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """Run the command line in-process: (exit code, stdout, stderr)."""
    from deployer.cli import main

    with pytest.raises(SystemExit) as exc:
        main(list(args))
    out, err = capsys.readouterr()
    return int(exc.value.code or 0), out, err


run_cli = cli  # its name in tests written before there was one cli(); new tests say cli


@contextmanager
def pty_pair(folder: Path, name: str = "tty") -> Iterator[tuple[str, str]]:
    """Two linked pseudo-terminals made by socat (a null-modem cable): (FOLDER/NAMEA, FOLDER/NAMEB)."""
    import shutil
    import signal

    if shutil.which("socat") is None:
        pytest.skip("socat is not installed (CI installs it: apt-get install socat)")
    a, b = str(folder / f"{name}A"), str(folder / f"{name}B")
    proc = subprocess.Popen(
        ["socat", "-d", "-d", f"pty,raw,echo=0,link={a}", f"pty,raw,echo=0,link={b}"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
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


@contextmanager
def reaped(proc: subprocess.Popen[str]) -> Iterator[subprocess.Popen[str]]:
    """A process of a test, killed if it still runs when the test ends (a failed test leaves none behind)."""
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def process_children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (Linux's /proc; none found elsewhere)."""
    out = []
    try:
        entries = [e for e in os.listdir("/proc") if e.isdigit()]
    except OSError:
        return []
    for entry in entries:
        try:
            with open(f"/proc/{entry}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        if ppid == pid:
            out.append(int(entry))
    return out


def process_alive(pid: int) -> bool:
    """Whether ``pid`` runs (Linux's /proc: a zombie has ended)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def wait_for(cond: Callable[[], bool], what: str = "the condition", timeout: float = 120) -> None:
    """Poll until ``cond()`` holds. The timeout is an upper bound for a loaded machine, not a timing assertion."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.02)


def profile_from(tmp: Path, text: str, name: str = "dev.yaml") -> Profile:
    p = tmp / name
    p.write_text(text)
    return load_profile(str(p))


def run_with(sim: Simulator, body: Callable[[Simulator], Awaitable[T]]) -> T:
    async def main() -> T:
        async with sim:
            return await body(sim)

    return asyncio.run(main())


def count(log: list[LogEntry], function: int, **where: Any) -> int:
    return sum(1 for e in log if e.function == function and all(getattr(e, k) == v for k, v in where.items()))


async def _cancel_the_rest() -> None:
    rest = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
    for t in rest:
        t.cancel()
    await asyncio.gather(*rest, return_exceptions=True)


class Simulators:
    """Many simulators served by one event loop in one background thread (fleet tests).

    with Simulators([Simulator(prof) for _ in range(50)]) as sims: ... sims[0].url ...
    """

    def __init__(self, sims: list[Simulator]) -> None:
        self.sims = sims
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="deployer-simulators", daemon=True)

    def _each(self, method: str) -> None:
        async def all_of() -> None:
            await asyncio.gather(*(getattr(s, method)() for s in self.sims))

        asyncio.run_coroutine_threadsafe(all_of(), self._loop).result(timeout=60)

    def __enter__(self) -> list[Simulator]:
        self._thread.start()
        self._each("start")
        return self.sims

    def __exit__(self, *exc: object) -> None:
        try:
            self._each("stop")
            # what the servers' connections still had running (an answer a fault delays): ended before the loop
            # closes, else each is reported at exit as a task destroyed while pending
            asyncio.run_coroutine_threadsafe(_cancel_the_rest(), self._loop).result(timeout=30)
        finally:
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=30)
            self._loop.close()


@contextmanager
def umodbus_server(
    store: dict[int, int],
    coils: dict[int, int] | None = None,
    *,
    maximum: dict[int, int] | None = None,
    max_write: int = 0,
    all_or_nothing: bool = False,
    fc06_only: bool = False,
    wire: list[tuple[int, int, int]] | None = None,
    connections: int = 1,
) -> Iterator[int]:
    """A device from another library (umodbus, Modbus/TCP on 127.0.0.1, unit 1); yields its port.

    Holding registers are ``store`` (functions 3, 6 and 16), coils ``coils`` (1, 5 and 15). It knows no
    Function 43 (umodbus answers 01). A real device's quirks, all off by default: ``maximum``: register ->
    the largest value it takes (more answers 03; umodbus writes an FC16's registers one by one, so the ones
    before the bad value stay written, unless ``all_or_nothing``); ``max_write``: FC16 requests carrying more
    registers answer 03; ``fc06_only``: FC16 answers 01. ``wire`` collects (function, address, count) of
    each request. ``connections`` > 1: each connection is served by a thread of its own (another client, such as
    mbpoll, connects while the run's connection is open); 1: a second connection waits until the first closes.
    """
    pytest.importorskip("umodbus", reason="umodbus is a test extra (pip install -e '.[test]')")
    import struct

    from umodbus import conf
    from umodbus.exceptions import IllegalDataValueError
    from umodbus.server.tcp import RequestHandler, get_server
    from umodbus.utils import pack_exception_pdu

    limits = maximum or {}
    seen = wire if wire is not None else []

    class Quirky(RequestHandler):  # type: ignore[misc]
        def execute_route(self, meta_data: dict[str, int], request_pdu: bytes) -> bytes:
            fc = request_pdu[0]
            address, count = struct.unpack(">HH", request_pdu[1:5]) if len(request_pdu) >= 5 else (0, 0)
            seen.append((fc, 0, 1) if fc == 43 else (fc, address, 1 if fc in (5, 6) else count))
            if fc == 16:
                if fc06_only:
                    return bytes(pack_exception_pdu(16, 1))
                if max_write and count > max_write:
                    return bytes(pack_exception_pdu(16, 3))
                values = struct.unpack(f">{count}H", request_pdu[6 : 6 + 2 * count])
                if all_or_nothing and any(v > limits.get(address + i, 0xFFFF) for i, v in enumerate(values)):
                    return bytes(pack_exception_pdu(16, 3))
            out: bytes = super().execute_route(meta_data, request_pdu)
            return out

    conf.SIGNED_VALUES = False
    socketserver.TCPServer.allow_reuse_address = True
    server = get_server(
        socketserver.ThreadingTCPServer if connections > 1 else socketserver.TCPServer, ("127.0.0.1", 0), Quirky
    )

    @server.route(slave_ids=[1], function_codes=[3], addresses=list(store))  # type: ignore[untyped-decorator]
    def read(slave_id: int, function_code: int, address: int) -> int:
        return store[address]

    @server.route(slave_ids=[1], function_codes=[6, 16], addresses=list(store))  # type: ignore[untyped-decorator]
    def write(slave_id: int, function_code: int, address: int, value: int) -> None:
        if value > limits.get(address, 0xFFFF):
            raise IllegalDataValueError()
        store[address] = value

    if coils:

        @server.route(slave_ids=[1], function_codes=[1], addresses=list(coils))  # type: ignore[untyped-decorator]
        def read_coil(slave_id: int, function_code: int, address: int) -> int:
            return coils[address]

        @server.route(slave_ids=[1], function_codes=[5, 15], addresses=list(coils))  # type: ignore[untyped-decorator]
        def write_coil(slave_id: int, function_code: int, address: int, value: int) -> None:
            coils[address] = value

    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield int(server.server_address[1])
    finally:
        server.shutdown()
        server.server_close()
