"""The pure-Python CPU one fleet device costs between its requests (issue #30), in-process, no devices.

A fleet device of the benchmark recipe (benchmarks/bench_fleet.py: 100 parameters, every 4th 32-bit)
holds the values of one recipe variant and is given the other: its results, its values read, the plan
(shared by the devices holding the same values), the snapshot's text, the journal's lines, the writes'
bookkeeping, the read-back's verification, the report line and the small result a fleet keeps.

Two measurements, CPU time (``time.process_time``) per device, the best of several rounds:

- ``stages``: each stage of ``execute/device.py``'s apply (and of ``executor.py``'s changes) on its own, run for every
  device of a round before the next stage starts (so no clock is read per device), fed with the register maps the
  reads would have answered. The stages call the same functions the apply calls.
- ``end_to_end``: ``apply_job`` itself, then the report line and ``small()``, over a fake transport
  that answers at once from a register map (no sockets), with the file system left out (the lock is
  taken as held; the snapshot file and the journal lines are encoded, hashed and dropped: what
  ``state/durable.py`` does in the caller's thread, without its system calls). What it measures beyond the
  stages is the session (request records, retries' bookkeeping) and the coroutines.

    python -m benchmarks.bench_device_cpu [--devices 500] [--rounds 7]
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import hashlib
import json
import os
import tempfile
import time
from collections.abc import Callable, Coroutine, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

from benchmarks.bench_fleet import _profile, _recipe
from deployer.errors import ExceptionResponse
from deployer.execute import device as dev
from deployer.execute.executor import Execution
from deployer.execute.job import Job
from deployer.execute.session import ApplyOptions, Session
from deployer.planning.model import Pacing, Target
from deployer.profile import profile_ref
from deployer.recipe.loader import Recipe, load_recipe
from deployer.report import DeviceResult, ParameterResult, RequestRecord, device_json
from deployer.state import durable, journal
from deployer.state.snapshot import snapshot_file
from deployer.transport import clients as tp

PARAMETERS = 100
RUN = "20250101T000000Z-1"


def _sync(coro: Coroutine[Any, Any, Any]) -> Any:
    """A coroutine that never waits (the fake session answers at once), run to its end."""
    try:
        coro.send(None)
    except StopIteration as e:
        return e.value
    raise AssertionError("the coroutine waited")


def _line(record: dict[str, Any]) -> bytes:
    """A journal line as ``state/durable.py`` encodes it (in the caller's thread)."""
    return (json.dumps(record) + "\n").encode()


def _registers(recipe: Recipe) -> dict[int, int]:
    """What a device holding ``recipe``'s values answers its reads: register key -> word."""
    regs = {}
    for d in recipe.desired:
        for i, w in enumerate(d.registers):
            regs[d.parameter.key + i] = w
    return regs


@dataclass
class _Device:
    """One device's state between the stages."""

    name: str
    url: str
    res: DeviceResult
    results: dict[str, ParameterResult] = field(default_factory=dict)
    before: dict[str, tuple[int, ...]] = field(default_factory=dict)
    plan: Any = None
    entry: Any = None
    snap: Any = None
    line: bytes = b""


class _Bench:
    def __init__(self, work: str) -> None:
        with open(os.path.join(work, "profile.yaml"), "w") as f:
            f.write(_profile(PARAMETERS))
        for variant in (1, 2):
            with open(os.path.join(work, f"recipe{variant}.yaml"), "w") as f:
                f.write(_recipe(PARAMETERS, variant))
        self.old = load_recipe(os.path.join(work, "recipe1.yaml"))
        self.recipe = load_recipe(os.path.join(work, "recipe2.yaml"))
        self.state = os.path.join(work, "state")
        self.opts = ApplyOptions(state_dir=self.state, run_id=RUN, applied=self.recipe.path, lock_held=True)
        self.regs_before = _registers(self.old)
        self.regs_after = _registers(self.recipe)
        self.start_after = [self.regs_after.get(a, 0) for a in range(max(self.regs_after) + 1)]
        self.planners = dev.Planners()
        self.shared = self.planners.shared(self.recipe, write_all=False, commit=True, pacing=Pacing())

    # ---- the stages, in the order an apply runs them ------------------------------------------------

    def results(self, d: _Device) -> None:
        """The device's result and its 100 parameter results (``apply_job``)."""
        prof = self.recipe.profile
        d.res = DeviceResult(
            d.name,
            d.url,
            1,
            prof.id,
            profile_ref=profile_ref(prof),
            recipe=self.recipe.path,
            batch=None,
            profile_sha256=prof.digest,
        )
        d.results = self.shared.results()
        d.res.parameters = list(d.results.values())

    def values_before(self, d: _Device) -> None:
        """The reads' registers as values by name, into the results (``Execution.checks``, ``_Device._apply``)."""
        d.before = self.shared.values(self.regs_before)
        for n, regs in d.before.items():
            d.results[n].before_raw = regs

    def plan(self, d: _Device) -> None:
        """The plan of the devices holding these values, for this device (``Shared.plan``, ``_Device._apply``)."""
        prof = self.recipe.profile
        d.plan, d.entry = self.shared.plan(Target(d.url, 1, profile_ref(prof)), d.before, False)
        dev.planned_results(d.results, d.plan, d.entry, prof)

    def snapshot(self, d: _Device) -> None:
        """The snapshot file's text (``_save_snapshot``)."""
        d.snap = snapshot_file(
            self.state,
            d.name,
            self.recipe,
            d.before,
            d.url,
            1,
            applied=self.opts.applied,
            identity=None,
            values_text=d.entry.snapshot_values(self.recipe.profile, d.before),
        )

    def journal_started(self, d: _Device) -> None:
        """The plan's digest and the ``device-started`` line, encoded (``_save_snapshot``)."""
        digest = d.entry.digest(d.plan.device)
        line = journal.device_started(
            RUN, name=d.name, url=d.url, unit=1, plan_digest=digest, batch=None, restoring=None
        )
        path = d.snap.first[0]
        d.line = _line({**line, "snapshot": path, "snapshot_sha256": "0" * 64})
        d.res.snapshot = path

    def execute(self, d: _Device) -> None:
        """The plan's changes (writes, read-back and its verification) on a session whose transport answers at once
        (``Execution.changes``: the session's request records, the writes' bookkeeping, ``_verify``); run in an
        event loop (the session asks it whether the run was cancelled), one loop for the round's devices."""
        raise NotImplementedError  # ``stages`` runs ``_execute`` in a loop

    async def _execute(self, d: _Device) -> None:
        transport = _FakeTransport(None, self.start_after)
        session = Session(transport, 1, retries=0, backoff=0.0, records=d.res.requests)  # type: ignore[arg-type]
        ex = Execution(session, self.recipe, d.res, d.results, self.opts, self.shared.values)
        ex.before = d.before
        await transport.connect()
        await ex.changes(d.plan)

    def notices(self, d: _Device) -> None:
        """The read-back's time, the power-cycle notices (``_Device._apply``) and the device's status."""
        d.res.seen = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        d.res.notices.extend(
            [f"{n} takes effect after a power cycle" for n in self.shared.restart if d.results[n].status == "ok"]
        )
        d.res.settle()
        assert d.res.status == "ok", (d.res.status, d.res.error)

    def journal_finished(self, d: _Device) -> None:
        """The ``device-finished`` line, encoded (``_locked``)."""
        d.line = _line(journal.device_finished(RUN, d.res))

    def report_line(self, d: _Device) -> None:
        """The device's line of the report file (``fleet/livereport.py``)."""
        d.line = device_json(d.res)

    def small(self, d: _Device) -> None:
        """What a fleet keeps of a device that ended ok (``fleet/rollout.py``)."""
        d.res = d.res.small()

    STAGES = (
        "results",
        "values_before",
        "plan",
        "snapshot",
        "journal_started",
        "execute",
        "notices",
        "journal_finished",
        "report_line",
        "small",
    )

    def stages(self, devices: int) -> dict[str, float]:
        """Seconds of CPU per device of each stage, this round."""
        ds = [
            _Device(f"dev{i:05d}", f"tcp://127.0.0.1:{20000 + i}", DeviceResult("", "", 1, "")) for i in range(devices)
        ]
        for d in ds:  # what the session recorded before the changes: the reads and Function 43
            d.res.requests = _requests()
        out = {}
        for stage in self.STAGES:
            gc.collect()  # each stage from a clean heap: a collection it triggers is its own
            if stage == "execute":

                async def each() -> float:
                    t = time.process_time()
                    for d in ds:
                        await self._execute(d)
                    return time.process_time() - t

                out[stage] = asyncio.run(each()) / devices
                continue
            run: Callable[[_Device], None] = getattr(self, stage)
            t = time.process_time()
            for d in ds:
                run(d)
            out[stage] = (time.process_time() - t) / devices
        return out

    # ---- the whole of it ------------------------------------------------------------------------------

    def end_to_end(self, devices: int) -> float:
        """Seconds of CPU per device of ``apply_job``, its report line and ``small()``."""
        urls = [tp.parse_url(f"tcp://127.0.0.1:{20000 + i}") for i in range(devices)]

        async def main() -> float:
            t = time.process_time()
            planners = dev.Planners()
            for i, url in enumerate(urls):
                res, finishing = await dev.apply_job(
                    Job(f"dev{i:05d}", self.recipe, url, 1), self.opts, planners=planners
                )
                assert finishing is not None
                await finishing
                assert res.status == "ok", (res.status, res.error)
                device_json(res)
                res.small()
            return (time.process_time() - t) / devices

        gc.collect()
        with _fakes(self.regs_before):
            return asyncio.run(main())


def _requests() -> list[RequestRecord]:
    return [
        RequestRecord(3, 0, 60, step=1),
        RequestRecord(3, 65, 65, step=2),
        RequestRecord(43, 0, 1, "exception", 1, step=3),
    ]


class _FakeTransport:
    """Answers at once from the holding registers ``start`` (the old recipe's values), sliced (so that it costs
    next to nothing beside deployer)."""

    def __init__(self, url: Any, start: list[int]) -> None:
        self.url = url
        self.start = start
        self.regs: list[int] = []
        self.late_answers: list[float] = []
        self.shifts = False  # as Modbus/TCP: answers tell their request (the session never doubts them)
        self.desyncs = 0
        self.connect_failures = 0
        self.backoff = 0.0

    def set_pacing(self, after_connect: float, between: float) -> None:
        pass

    async def connect(self) -> None:
        self.regs = self.start.copy()

    async def close(self) -> None:
        pass

    async def read(self, function: int, address: int, count: int, unit: int) -> list[int]:
        return self.regs[address : address + count]

    async def write_registers(self, address: int, values: list[int], unit: int) -> None:
        self.regs[address : address + len(values)] = values

    async def write_register(self, address: int, value: int, unit: int) -> None:
        self.regs[address] = value

    async def read_device_identification(self, unit: int, read_code: int = 1) -> dict[int, bytes]:
        raise ExceptionResponse(43, 1)  # as the light farm: no identification objects


@contextmanager
def _fakes(regs: dict[int, int]) -> Iterator[None]:
    """The transport and the durable writes replaced, in this process, while the benchmark runs."""

    async def written(op: durable.NewFile | durable.Line) -> str | None:
        assert isinstance(op, durable.NewFile)
        path, text = op.first
        op.digest = hashlib.sha256(text.encode()).hexdigest()
        if op.line is not None:
            _line({**op.line, op.path_key: path, f"{op.path_key}_sha256": op.digest})
        return path

    def queued(op: durable.NewFile | durable.Line) -> asyncio.Future[str | None]:
        assert isinstance(op, durable.Line)
        _line(op.record)
        done: asyncio.Future[str | None] = asyncio.get_running_loop().create_future()
        done.set_result(None)
        return done

    start = [regs.get(a, 0) for a in range(max(regs) + 1)]
    fakes: list[tuple[object, str, object]] = [
        (tp, "open_transport", lambda url: _FakeTransport(url, start)),
        (dev, "durable", written),
        (dev, "queue", queued),
    ]
    saved = [(module, name, getattr(module, name)) for module, name, _ in fakes]
    for module, name, fake in fakes:
        setattr(module, name, fake)
    try:
        yield
    finally:
        for module, name, real in saved:
            setattr(module, name, real)


def run(quick: bool = False, devices: int = 500, rounds: int = 7) -> dict[str, Any]:
    if quick:
        devices, rounds = 50, 2
    with tempfile.TemporaryDirectory(prefix="bench-device-cpu-") as work:
        bench = _Bench(work)
        best: dict[str, float] = {}
        whole = float("inf")
        gc.collect()
        for _ in range(rounds):  # best of several: the machine is shared
            for stage, seconds in bench.stages(devices).items():
                best[stage] = min(best.get(stage, float("inf")), seconds)
            whole = min(whole, bench.end_to_end(devices))
    us = {stage: round(s * 1e6, 1) for stage, s in best.items()}
    return {
        "devices": devices,
        "parameters": PARAMETERS,
        "rounds": rounds,
        "stages_us_per_device": us,
        "stages_total_us": round(sum(best.values()) * 1e6, 1),
        "end_to_end_us_per_device": round(whole * 1e6, 1),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--devices", type=int, default=500)
    ap.add_argument("--rounds", type=int, default=7)
    args = ap.parse_args(argv)
    res = run(args.quick, args.devices, args.rounds)
    print(json.dumps(res, indent=2))
    print(
        f"\nCPU per device, {res['parameters']} parameters, best of {res['rounds']} rounds of {res['devices']} devices"
    )
    for stage, us in res["stages_us_per_device"].items():
        print(f"  {stage:<18}{us:>9.1f} us")
    print(f"  {'stages, total':<18}{res['stages_total_us']:>9.1f} us")
    print(
        f"  {'end to end':<18}{res['end_to_end_us_per_device']:>9.1f} us  (apply_job over a fake transport, "
        "report line, small())"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
