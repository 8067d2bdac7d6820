"""A late serial answer never becomes a value (issue #47 item 1): the matrix.

A device holding 1, 2, 3 at registers 100, 200, 300 answers at 0.5x, 1.5x, 2.5x and 4x the timeout, once
(one read in each phase: the snapshot's, the read-back's, the rollback's own before-read) or every time;
as the simulator and as umodbus's RTU server behind a relay of ours (an implementation we did not write),
on a pty and over rtu+tcp. Each point applies a recipe and rolls it back. The recipe is chosen so that an
answer taken for the next read's makes a wrong plan: shifted by one, the snapshot reads p2 = 1 and
p3 = 2, which are the recipe's own values, and the rollback's before-read p2 = 2, the snapshot's. Every
outcome must be the true values or nothing written: a snapshot holds what the device held, a parameter
the report calls ``ok`` or ``unchanged`` holds its value on the device, a device refused wrote nothing.
All 32 points run at once (they only wait); the agent's checks are tested at the end.
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import asynccontextmanager, contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import pytest
import yaml

from deployer.execute.device import apply_device
from deployer.execute.session import ApplyOptions
from deployer.recipe.loader import load_recipe
from deployer.report import DeviceResult
from deployer.testing.simulator import Faults, Simulator
from deployer.transport.urls import parse_url
from tests.helpers import profile_from, pty_pair
from tests.rtu_devices import SlowServer, on_pty, on_tcp

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="the devices sit on pseudo-terminals (POSIX)")

TIMEOUT = 0.2
FACTORS = (0.5, 1.5, 2.5, 4.0)
MODES = ("once", "always")
START_GAP = 0.02  # seconds between the points' starts: 32 connections at once would stall the loop beyond a timeout
ADDRESS = {"p1": 100, "p2": 200, "p3": 300}
HELD = {100: 1, 200: 2, 300: 3}
RECIPE = {"p1": 2, "p2": 1, "p3": 2}  # shifted by one read, the snapshot holds p2 = 1, p3 = 2: "unchanged"

PROFILE = """\
profile: late-matrix
parameters:
  p1: {register: 100, type: uint16}
  p2: {register: 200, type: uint16}
  p3: {register: 300, type: uint16}
"""


@dataclass(eq=False)
class Point:
    """One device of the matrix: how late it answers, its URL, what it holds now, how many writes reached
    it, and its arming (once: the next read is answered late)."""

    factor: float
    mode: str
    name: str
    url: str
    holds: Callable[[], dict[int, int]]
    writes: Callable[[], int]
    arm: Callable[[], None]
    folder: Path  # the profile's, and the points' state folders


def _check(res: DeviceResult, before: dict[int, int], point: Point, writes_before: int) -> str:
    """What the report says is so on the device; returns the outcome ("ok", "refused", ...)."""
    holds = point.holds()
    where = f"{point.name}: {res.status} {res.error or ''} {res.notices}"
    if res.snapshot is not None:
        snap = yaml.safe_load(Path(res.snapshot).read_text())["parameters"]
        assert snap == {n: before[a] for n, a in ADDRESS.items()}, where
    for p in res.parameters:
        if p.before_raw is not None:
            assert list(p.before_raw) == [before[p.address]], (p.name, where)
        if p.status in ("ok", "unchanged"):
            assert holds[p.address] == p.desired_raw[0], (p.name, p.status, holds, where)
    if res.snapshot is None:  # refused before the first write: nothing written
        assert point.writes() == writes_before and holds == before, where
        return f"refused ({res.status}: {res.error})"
    if res.status == "ok":
        assert all(p.status in ("ok", "unchanged") for p in res.parameters), where
    return res.status


async def _story(point: Point, start: float) -> tuple[str, str]:
    """Apply the recipe, then roll back from its snapshot; the outcome of each."""
    await asyncio.sleep(start)
    state = point.folder / point.name.replace(" ", "-")
    state.mkdir()
    recipe_file = state / "r.yaml"
    recipe_file.write_text(
        f"recipe: late\nprofile: {point.folder / 'dev.yaml'}\n"
        f"device: {{url: '{point.url}', unit: 1}}\n"
        "parameters: {" + ", ".join(f"{n}: {v}" for n, v in RECIPE.items()) + "}\n"
    )
    url = parse_url(point.url)
    opts = ApplyOptions(
        state_dir=str(state / "state"), lock_dir=str(state / "locks"), on_writing=lambda _r: point.arm()
    )  # once: the read-back's first read is late
    before, writes = point.holds(), point.writes()
    point.arm()
    res = await apply_device(load_recipe(str(recipe_file)), url, 1, name=point.name, options=opts)
    applied = _check(res, before, point, writes)
    if res.snapshot is None:
        return applied, "-"
    before, writes = point.holds(), point.writes()
    point.arm()
    back = await apply_device(
        load_recipe(res.snapshot), url, 1, name=point.name, options=replace(opts, hold_commit=True)
    )  # as `deployer rollback` does
    rolled = _check(back, before, point, writes)
    if rolled == "ok":
        assert point.holds() == HELD, point.name
    return applied, rolled


def _points() -> list[tuple[float, str]]:
    return [(f, m) for f in FACTORS for m in MODES]


@asynccontextmanager
async def _simulators(line: str, tmp: Path) -> AsyncIterator[list[Point]]:
    """The simulator at each point of the matrix, listening on a pty or as an rtu+tcp gateway."""
    prof = profile_from(tmp, PROFILE)  # the file the recipes name too
    points: list[Point] = []
    async with contextlib.AsyncExitStack() as stack:
        for factor, mode in _points():
            faults = Faults(latency_ms=factor * TIMEOUT * 1000, late_reads=None if mode == "always" else 0)
            if line == "rtu":
                a, b = stack.enter_context(pty_pair(tmp, f"{factor:g}{mode}"))
                sim = await stack.enter_async_context(
                    Simulator(prof, listen=f"rtu://{a}", init=dict(HELD), faults=faults)
                )
                url = f"rtu://{b}?timeout={TIMEOUT:g}"
            else:
                sim = await stack.enter_async_context(
                    Simulator(prof, listen="rtu+tcp://127.0.0.1:0", init=dict(HELD), faults=faults)
                )
                url = f"{sim.url}?timeout={TIMEOUT:g}"

            def arm(f: Faults = faults) -> None:
                if f.late_reads is not None:
                    f.late_reads = 1

            def holds(s: Simulator = sim) -> dict[int, int]:
                regs = s.registers()
                return {a: regs[a] for a in HELD}

            def writes(s: Simulator = sim) -> int:
                return sum(1 for e in s.log if e.function in (6, 16))

            points.append(Point(factor, mode, f"simulator {line} {factor:g}x {mode}", url, holds, writes, arm, tmp))
        yield points


@contextmanager
def _servers(line: str, tmp: Path) -> Iterator[list[Point]]:
    """umodbus's RTU server behind our slow relay at each point, on a pty or behind an rtu+tcp gateway."""
    profile_from(tmp, PROFILE)  # the file the recipes name
    points: list[Point] = []
    with contextlib.ExitStack() as stack:
        for factor, mode in _points():
            dev = stack.enter_context(SlowServer(dict(HELD), factor * TIMEOUT, always=mode == "always").running())
            if line == "rtu":
                a, b = stack.enter_context(pty_pair(tmp, f"{factor:g}{mode}"))
                stack.enter_context(on_pty(dev, a))
                url = f"rtu://{b}?timeout={TIMEOUT:g}"
            else:
                url = f"rtu+tcp://127.0.0.1:{stack.enter_context(on_tcp(dev))}?timeout={TIMEOUT:g}"

            def holds(d: SlowServer = dev) -> dict[int, int]:
                return {a: d.regs[a] for a in HELD}

            def writes(d: SlowServer = dev) -> int:
                return sum(1 for f in d.frames if f[1] in (6, 16))

            points.append(Point(factor, mode, f"umodbus {line} {factor:g}x {mode}", url, holds, writes, dev.arm, tmp))
        yield points


def test_a_late_answer_never_becomes_a_value(tmp_path: Path) -> None:
    """The whole matrix at once: the simulator and umodbus, on a pty and over rtu+tcp, 8 points each."""

    async def main() -> dict[Point, tuple[str, str] | BaseException]:
        async with contextlib.AsyncExitStack() as stack:
            points: list[Point] = []
            for group in ("simulator-rtu", "simulator-rtu+tcp", "umodbus-rtu", "umodbus-rtu+tcp"):
                kind, line = group.split("-", 1)
                folder = tmp_path / group
                folder.mkdir()
                points += (
                    await stack.enter_async_context(_simulators(line, folder))
                    if kind == "simulator"
                    else stack.enter_context(_servers(line, folder))
                )
            got = await asyncio.gather(
                *(_story(p, i * START_GAP) for i, p in enumerate(points)), return_exceptions=True
            )
            return {p: g for p, g in zip(points, got, strict=True)}

    outcomes = asyncio.run(main())
    wrong = [f"{p.name}: {g!r}" for p, g in outcomes.items() if isinstance(g, BaseException)]
    # a device early enough, or late once and answering within its request's retries (up to 2.5x), must also
    # be written and rolled back: a refusal there would be the rule refusing too much
    wrong += [
        f"{p.name}: {g} (must be written and rolled back)"
        for p, g in outcomes.items()
        if (p.factor < 1 or (p.mode == "once" and p.factor < 3)) and g != ("ok", "ok")
    ]
    assert not wrong, "\n".join(wrong)


class _LiveP2(SlowServer):
    """The slow device with a live p2: it counts its reads, so no two reads of it agree."""

    def handle(self, req: bytes) -> bytes | None:
        if req[1] == 3 and req[2:4] == b"\x00\xc8":
            self.regs[200] += 1
        return super().handle(req)


@pytest.mark.parametrize("live", [False, True], ids=["always-late", "live-value"])
def test_the_agent_takes_no_late_answer_for_drift(live: bool, tmp_path: Path) -> None:
    """The agent's first check (with --on-drift restore) of a device holding what the agent adopted.
    always-late: every answer 2.5x the timeout late; a shifted read would be drift (p2 reading p1's 1) and a
    restore: the device is ok, nothing written. live-value: the first answer late, and p2 changes at each
    read, so it is never confirmed: the check says the device cannot be read and why; no drift is seen and
    nothing is restored, though p2 differs from what was adopted."""
    from tests.agent_helpers import AgentProcess, kinds, until, write_site

    dev = (
        _LiveP2(dict(HELD), 2.5 * TIMEOUT, always=False) if live else SlowServer(dict(HELD), 2.5 * TIMEOUT, always=True)
    )
    dev.arm()  # live-value: the first read is late, the session is in doubt from then on
    with dev.running(), on_tcp(dev) as port:
        inv = write_site(
            tmp_path,
            {"d1": f"rtu+tcp://127.0.0.1:{port}?timeout={TIMEOUT:g}"},
            recipe="recipe: held\nprofile: drive.yaml\nparameters: {p1: 1, p2: 2, p3: 3}\n",
            profile=PROFILE,
        )
        agent = AgentProcess(inv, tmp_path / "state", "--on-drift", "restore", "--bus-share", "1", check_every="1h")
        try:
            c = agent.client
            d = until(lambda: (x := c.device("d1"))["status"] != "unknown" and x, timeout=60, why="the first check")
            if live:
                assert d["status"] == "unreachable" and "no read after" in d["unreachable"], d
            else:
                assert d["status"] == "ok", (d, c.events())
            assert not {"drift", "restored", "restore-failed", "replaced"} & set(kinds(c, "d1")), c.events()
            assert agent.terminate() == 0
        finally:
            agent.kill()
    assert not [f for f in dev.frames if f[1] in (6, 16)] and dev.regs[100] == 1 and dev.regs[300] == 3
