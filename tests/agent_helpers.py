"""A real agent process (``python -m deployer agent``) for the agent tests, and the files it watches."""

from __future__ import annotations

import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

from deployer.agent.client import Agent

T = TypeVar("T")

PROFILE = """\
profile: test-drive
identity:
  - {register: 0, raw: 0x0A21, description: model code}
endurance: 1000
commit:
  - {register: 30, raw: 1, description: store to EEPROM}
health:
  - {register: 40, equals: 0, description: fault code is zero}
parameters:
  model: {register: 0, type: uint16, access: read-only, default: 0x0A21}
  accel: {register: 10, type: uint16, unit: s, scale: 0.1, min: 0, max: 100, default: 5}
  decel: {register: 11, type: uint16, unit: s, scale: 0.1, min: 0, max: 100, default: 5}
  speed: {register: 12, type: uint16, unit: rpm, min: 0, max: 6000, default: 1500, tolerance: 10}
  address: {register: 20, type: uint16, min: 1, max: 247, default: 1, per_unit: true}
  store: {register: 30, type: uint16, access: write-only}
  fault: {register: 40, type: uint16, access: read-only, default: 0}
"""

RECIPE = """\
recipe: line
profile: drive.yaml
parameters:
  accel: 2 s
  decel: 3 s
  speed: 3000 rpm
  address: 7
"""


def write_site(tmp: Path, urls: dict[str, str], recipe: str = RECIPE, profile: str = PROFILE) -> Path:
    (tmp / "drive.yaml").write_text(profile)
    (tmp / "r.yaml").write_text(recipe)
    lines = ["devices:"] + [f'  {n}: {{url: "{u}", recipe: r.yaml}}' for n, u in urls.items()]
    inv = tmp / "inv.yaml"
    inv.write_text("\n".join(lines) + "\n")
    return inv


class AgentProcess:
    """``deployer agent INVENTORY --listen 127.0.0.1:0 ...`` as a child process; ``url`` once it listens."""

    def __init__(
        self, inventory: Path, state: Path, *args: str, check_every: str = "0.2s", first_restore_soak: str = "0"
    ) -> None:
        # the first restores' canary: its health read once after the write (the default watches it for 10 s)
        cmd = [
            sys.executable,
            "-m",
            "deployer",
            "agent",
            str(inventory),
            "--state-dir",
            str(state),
            "--listen",
            "127.0.0.1:0",
            "--check-every",
            check_every,
            "--first-restore-soak",
            first_restore_soak,
            *args,
        ]
        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=os.environ.copy()
        )
        self.lines: queue.Queue[str] = queue.Queue()
        self.stderr: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self.url = self._wait_listening()
        self.client = Agent(self.url, timeout=20)

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.stderr.append(line)
            self.lines.put(line)

    def _wait_listening(self, timeout: float = 30) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.2)
            except queue.Empty:
                if self.proc.poll() is not None:
                    break
                continue
            m = re.match(r"listening on (https?://\S+)", line)
            if m:
                return m.group(1)
        self.kill()
        raise AssertionError("the agent did not start:\n" + "".join(self.stderr))

    def terminate(self, timeout: float = 30, client: Agent | None = None) -> int:
        """Stopped as its system's service manager stops it: SIGTERM on POSIX; on Windows, which has no SIGTERM to
        send, ``POST /v1/stop`` with the agent's token (and, over TLS, its certificate as the CA)."""
        if sys.platform == "win32":
            (client or self.stop_route()).post("/v1/stop")
        else:
            self.proc.send_signal(signal.SIGTERM)
        rc = self.proc.wait(timeout=timeout)
        self._reader.join(timeout=5)
        return rc

    def stop_route(self) -> Agent:
        """A client with the credentials the agent was started with (``--token-file``, else the token it made in its
        state folder; ``--tls-cert``), on loopback."""
        args = self.proc.args
        assert isinstance(args, list)

        def option(name: str) -> str | None:
            return str(args[args.index(name) + 1]) if name in args else None

        token_file, cert = option("--token-file"), option("--tls-cert")
        state = option("--state-dir")
        if token_file is None and state is not None and "--users" not in args:  # the token it made itself
            token_file = str(Path(state) / "agent" / "token")
        token = Path(token_file).read_text(encoding="utf-8").splitlines()[0].strip() if token_file else None
        return Agent(self.url.replace("//0.0.0.0:", "//127.0.0.1:"), token=token, ca=cert, timeout=20)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=30)
        self._reader.join(timeout=5)

    def log(self) -> str:
        return "".join(self.stderr)


def until(what: Callable[[], T | None], timeout: float = 20, every: float = 0.05, why: str = "") -> T:
    """Poll ``what`` until it returns something true; fail with ``why`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        got = what()
        if got:
            return got
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting: {why}")
        time.sleep(every)


def kinds(agent: Agent, device: str | None = None) -> list[str]:
    return [e["kind"] for e in agent.events(device=device)]


def event(agent: Agent, kind: str, device: str | None = None) -> dict[str, Any] | None:
    found = [e for e in agent.events(device=device, kind=kind)]
    return found[-1] if found else None


def writes_in_log(log: Sequence[Any], unit: int = 1) -> dict[int, int]:
    """Write requests per register address from a simulator's request log."""
    out: dict[int, int] = {}
    for e in log:
        if e.unit == unit and e.function in (6, 16):
            for a in range(e.address, e.address + e.count):
                out[a] = out.get(a, 0) + 1
    return out
