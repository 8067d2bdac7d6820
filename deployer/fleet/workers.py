"""Worker processes for a big fleet: the devices' work on every core, the rollout in this process.

A device costs a few milliseconds of Python (its requests, snapshot, journal lines, report line), and
one process runs Python on one core at a time (the GIL): 10,000 devices were CPU-bound on one core
while the others idled. With workers, the rollout (``fleet.rollout``: buses, batches, the failure
budget, progress, the report file) stays in this process and decides when each device starts, exactly
as without them; each device runs in a worker process (``execute.device``, unchanged: its lock, its
snapshot and journal lines, its read-back), which sends back its outcome and its report line.

Only plain runs use workers (``eligible``): a safe-change window (soak, confirmation, rollback on
failure) keeps devices' locks and acts on them after they finished, and a question per device needs
this process's terminal, so those runs stay in one process.

The workers are this Python started again (``python -c``); they connect to a listening socket of this
process on 127.0.0.1 and say a secret given to them on their stdin before anything else is read
(a local user who finds the port cannot feed this process data). Messages are pickled tuples, each
framed by its length. A worker whose parent goes away (killed, crashed) sees its connection close and
cancels its devices: each ends as an interrupted run's device does (its journal lines say where it was).
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import os
import pickle
import secrets
import struct
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

from ..errors import UsageError

if TYPE_CHECKING:
    from ..execute.job import Job
    from ..execute.session import ApplyOptions
    from ..report import DeviceResult

MIN_DEVICES = 2000  # below this, starting workers (about 0.5 s) costs more than they save (benchmarks/RESULTS.md)
MIN_PER_WORKER = 8  # devices in flight per worker at least: fewer, and one process keeps up
MAX_WORKERS = 64
_FRAME = struct.Struct(">I")
_BOOT = "from deployer.fleet.workers import main; main()"


def auto_count(devices: int, parallel: int) -> int:
    """How many workers ``workers=None`` (auto) takes: one per CPU for a fleet big enough to gain, else 0."""
    cpus = os.cpu_count() or 1
    if cpus < 2 or devices < MIN_DEVICES:
        return 0
    return max(0, min(cpus, parallel // MIN_PER_WORKER, MAX_WORKERS))


def ineligible(opts: ApplyOptions, *, rollback_on_failure: bool) -> str | None:
    """Why a run must keep its devices in this process (None: workers may run them)."""
    if opts.soak is not None or opts.confirm_within is not None:
        return "a soak or a confirmation window acts on devices after they finished"
    if rollback_on_failure:
        return "--rollback-on-failure rolls devices back from this process"
    if opts.confirm is not None:
        return "a question before each device's write needs this process's terminal"
    if opts.expected is not None:
        return "a saved plan is for one device"
    if opts.lock_held or opts.keep_lock is not None:
        return "this process holds the devices' locks"
    return None


# ---- framing ------------------------------------------------------------------------------------


async def _read(reader: asyncio.StreamReader) -> Any:
    """The next message (None at the end of the connection)."""
    try:
        head = await reader.readexactly(_FRAME.size)
        return pickle.loads(await reader.readexactly(_FRAME.unpack(head)[0]))
    except (asyncio.IncompleteReadError, ConnectionError):
        return None


def _frame(message: object) -> bytes:
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    return _FRAME.pack(len(data)) + data


# ---- results across processes ---------------------------------------------------------------------


def _bare(r: DeviceResult) -> DeviceResult:
    """A result to send: its parameters without their profile's ``Parameter`` (the other side has the job's)."""
    for p in r.parameters:
        p.parameter = None
    return r


_WRITTEN: dict[tuple[str, ...], tuple[str, ...]] = {}  # devices that wrote the same parameters share one tuple


def _dressed(r: DeviceResult, job: Job) -> DeviceResult:
    """A received result with its parameters' ``Parameter`` from the job's profile again (engineering texts)."""
    prof = job.recipe.profile
    for p in r.parameters:
        p.parameter = prof.get(p.name)
    if r.tally is not None:
        if len(_WRITTEN) > 1024:
            _WRITTEN.clear()
        r.tally = replace(r.tally, written=_WRITTEN.setdefault(r.tally.written, r.tally.written))
    return r


# ---- this process's side -------------------------------------------------------------------------


class WorkerGone(Exception):
    """A worker process ended (or broke its connection) while it ran devices."""


@dataclass
class Call:
    """One device sent to a worker: its outcome (``done``: the device's slot is free) and its report
    (``recorded``: its journal line on disk, its result and report line)."""

    index: int
    worker: _Worker
    started: float = field(default_factory=time.monotonic)
    done: asyncio.Future[tuple[Any, ...]] = field(default_factory=lambda: asyncio.get_running_loop().create_future())
    recorded: asyncio.Future[tuple[DeviceResult, bytes | None]] = field(
        default_factory=lambda: asyncio.get_running_loop().create_future())
    writing: DeviceResult | None = None  # what the device said when its writes started (its snapshot)


class _Worker:
    def __init__(self, process: asyncio.subprocess.Process) -> None:
        self.process = process
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None
        self.calls: dict[int, Call] = {}
        self.listening: asyncio.Task[None] | None = None
        self.gone: WorkerGone | None = None  # set once its connection ended: it takes no more devices

    def send(self, message: object) -> None:
        assert self.writer is not None
        if not self.writer.is_closing():
            self.writer.write(_frame(message))


class Pool:
    """Worker processes running a rollout's devices (``start``), each device when the rollout says (``run``)."""

    def __init__(self, jobs: Sequence[Job], on_writing: Callable[[DeviceResult], None] | None) -> None:
        self.jobs = jobs
        self.index = {j.name: i for i, j in enumerate(jobs)}
        self.on_writing = on_writing
        self.workers: list[_Worker] = []
        self._server: asyncio.AbstractServer | None = None

    @classmethod
    async def start(cls, count: int, jobs: Sequence[Job], opts: ApplyOptions, *, lines: bool, small_ok: bool,
                    files: int, timeout: float = 60.0) -> Pool:
        """``count`` workers, each given the jobs and the run's options; ready when this returns.

        ``lines``: the workers encode each device's report line; ``small_ok``: a device that ended ok comes
        back as its small result; ``files``: the open files each may need. Raises UsageError (nothing sent to
        any device) when they cannot start."""
        pool = cls(jobs, opts.on_writing)
        try:
            await asyncio.wait_for(pool._start(count, opts, lines=lines, small_ok=small_ok, files=files), timeout)
        except BaseException as e:
            await pool.close()
            if isinstance(e, (OSError, TimeoutError, WorkerGone, pickle.PicklingError)):
                raise UsageError(f"cannot start {count} worker processes: {e or type(e).__name__}; run the fleet in "
                                 "one process with --workers 0") from None
            raise
        return pool

    async def _start(self, count: int, opts: ApplyOptions, *, lines: bool, small_ok: bool, files: int) -> None:
        # a secret per worker: it says which process a connection is (they connect in any order)
        secrets_of = {secrets.token_bytes(32): i for i in range(count)}
        connected: list[asyncio.Future[tuple[asyncio.StreamReader, asyncio.StreamWriter]]] = [
            asyncio.get_running_loop().create_future() for _ in range(count)]

        async def accept(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            try:  # the secret first, as raw bytes: nothing from a connection is unpickled before it
                said = await asyncio.wait_for(reader.readexactly(32), 10)
            except (asyncio.IncompleteReadError, ConnectionError, TimeoutError):
                writer.close()
                return
            i = next((i for token, i in secrets_of.items() if hmac.compare_digest(said, token)), None)
            if i is None or connected[i].done():
                writer.close()
                return
            connected[i].set_result((reader, writer))

        self._server = await asyncio.start_server(accept, "127.0.0.1", 0)
        port = self._server.sockets[0].getsockname()[1]
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(
            [_package_root(), *filter(None, [os.environ.get("PYTHONPATH")])])}
        for token in secrets_of:
            proc = await asyncio.create_subprocess_exec(sys.executable, "-c", _BOOT, str(port),
                                                        stdin=asyncio.subprocess.PIPE, env=env)
            assert proc.stdin is not None
            proc.stdin.write(token.hex().encode() + b"\n")
            await proc.stdin.drain()
            proc.stdin.close()
            self.workers.append(_Worker(proc))
        setup = _frame(("setup", list(self.jobs), _portable(opts), sys.argv, lines, small_ok,
                        opts.on_writing is not None, files))
        for w, got in zip(self.workers, connected, strict=True):
            exited: asyncio.Future[Any] = asyncio.ensure_future(w.process.wait())
            await asyncio.wait([exited, got], return_when=asyncio.FIRST_COMPLETED)
            if not got.done():
                raise WorkerGone(f"a worker process exited at its start (exit code {exited.result()})")
            exited.cancel()
            w.reader, w.writer = got.result()
            w.writer.write(setup)
        for w in self.workers:  # each says it is ready once it has loaded the jobs
            assert w.reader is not None
            if await _read(w.reader) != ("ready",):
                raise WorkerGone("a worker process did not start")
            w.listening = asyncio.ensure_future(self._listen(w))
        self._server.close()
        self._server = None

    async def _listen(self, w: _Worker) -> None:
        """Messages from a worker, to the calls they are about; when it goes, its calls fail with WorkerGone."""
        assert w.reader is not None
        while True:
            message = await _read(w.reader)
            if message is None:
                break
            kind, index, *rest = message
            call = w.calls.get(index)
            if call is None:
                continue
            if kind == "writing":
                call.writing = _dressed(rest[0], self.jobs[index])
                if self.on_writing is not None:
                    self.on_writing(call.writing)
            elif kind in ("done", "interrupted", "failed"):
                if kind == "interrupted":
                    rest[0] = _dressed(rest[0], self.jobs[index])
                    del w.calls[index]
                elif kind == "failed":
                    del w.calls[index]
                if not call.done.done():
                    call.done.set_result((kind, *rest))
            elif kind == "recorded":
                del w.calls[index]
                if not call.recorded.done():
                    call.recorded.set_result((_dressed(rest[0], self.jobs[index]), rest[1]))
        code = await w.process.wait()
        gone = w.gone = WorkerGone(f"the worker process running it ended unexpectedly (exit code {code})")
        for call in w.calls.values():
            for fut in (call.done, call.recorded):
                if not fut.done():
                    fut.set_exception(gone)
                    fut.add_done_callback(_retrieved)  # a call may never wait for its "recorded"
        w.calls.clear()

    def run(self, job: Job, batch: int | None) -> Call:
        """Start ``job`` on the worker with the fewest devices in flight; its call to wait for (which fails with
        WorkerGone at once when no worker is left)."""
        alive = [w for w in self.workers if w.gone is None]
        w = min(alive or self.workers, key=lambda w: len(w.calls))
        call = Call(self.index[job.name], w)
        if w.gone is not None:
            call.done.set_exception(w.gone)
            call.recorded.set_exception(w.gone)
            call.recorded.add_done_callback(_retrieved)
            return call
        w.calls[call.index] = call
        w.send(("start", call.index, batch))
        return call

    def cancel(self, call: Call) -> None:
        """Interrupt a device (the run was interrupted): its worker answers ``interrupted`` (or ``done``)."""
        call.worker.send(("cancel", call.index))

    async def close(self) -> None:
        """The workers told to end (their connection closed) and waited for."""
        if self._server is not None:
            self._server.close()
        for w in self.workers:
            if w.writer is not None:
                w.writer.close()
        for w in self.workers:
            try:
                await asyncio.wait_for(w.process.wait(), 30)
            except TimeoutError:
                w.process.kill()
                await w.process.wait()
            if w.listening is not None:
                with contextlib.suppress(BaseException):
                    await w.listening


def _retrieved(fut: asyncio.Future[Any]) -> None:
    if not fut.cancelled():
        fut.exception()


def _package_root() -> str:
    """The folder holding this ``deployer`` package: the workers import the very same code."""
    return os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _portable(opts: ApplyOptions) -> ApplyOptions:
    """The run's options as a worker takes them: what calls back into this process is left out."""
    return replace(opts, confirm=None, on_writing=None, keep_lock=None)


# ---- the worker's side ---------------------------------------------------------------------------


def main() -> None:
    """A worker: ``python -c "from deployer.fleet.workers import main; main()" PORT``, the secret on stdin."""
    import signal

    port = int(sys.argv[1])
    token = bytes.fromhex(sys.stdin.readline().strip())
    # Ctrl-C reaches every process of the terminal: this process's devices are interrupted when the rollout
    # says so (it relays the interruption), never behind its back
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "SIGBREAK"):
        signal.signal(signal.SIGBREAK, signal.SIG_IGN)
    with asyncio.Runner(loop_factory=_loop_factory()) as runner:
        runner.run(_serve(port, token))


def _loop_factory() -> Callable[[], asyncio.AbstractEventLoop] | None:
    """uvloop's event loop where it is installed (not on Windows): a worker's loop carries its devices' sockets and
    its link to the rollout, and took 12-18% less CPU per device on it (benchmarks/RESULTS.md); else asyncio's."""
    if sys.platform == "win32":
        return None
    try:
        import uvloop
    except ImportError:
        return None
    factory: Callable[[], asyncio.AbstractEventLoop] = uvloop.new_event_loop
    return factory


async def _serve(port: int, token: bytes) -> None:
    import gc

    from ..execute.device import DeviceInterrupted, _apply_device, journal_line
    from ..portable import raise_open_files
    from ..report import device_json

    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(token)
    setup = await _read(reader)
    if setup is None:
        return
    _, jobs, opts, argv, lines, small_ok, writing, files = setup
    sys.argv = argv  # what lock records and messages name as the command: the run's, not this worker's
    raise_open_files(files)  # the rollout's process checked that the system allows them
    gc.freeze()  # what was loaded lives as long as the run (as the command line does for itself)
    gc.set_threshold(20_000, 20, 10)
    tasks: dict[int, asyncio.Task[None]] = {}

    def send(message: object) -> None:
        if not writer.is_closing():
            writer.write(_frame(message))

    index_of = {j.name: i for i, j in enumerate(jobs)}
    if writing:
        def on_writing(r: DeviceResult) -> None:  # what the report file says of it now: its snapshot
            send(("writing", index_of[r.name], replace(r, requests=[], parameters=[], notices=[])))

        opts = replace(opts, on_writing=on_writing)

    async def device(index: int, batch: int | None) -> None:
        try:
            await run(index, batch)
        finally:
            tasks.pop(index, None)

    async def run(index: int, batch: int | None) -> None:
        job = jobs[index]
        o = opts
        if job.commit_owed or job.hold_commit:
            o = replace(o, commit_owed=job.commit_owed, hold_commit=o.hold_commit or job.hold_commit)
        t = time.monotonic()
        try:
            res, finishing = await _apply_device(job.recipe, job.url, job.unit, name=job.name, options=o, batch=batch)
        except DeviceInterrupted as e:
            e.result.seconds = time.monotonic() - t
            send(("interrupted", index, _bare(e.result)))
            return
        except UsageError as e:
            send(("failed", index, str(e)))
            return
        except BaseException:
            import traceback

            send(("failed", index, f"an error in deployer (please report it): {traceback.format_exc()}"))
            return
        res.seconds = time.monotonic() - t
        send(("done", index, res.status))
        if finishing is not None:
            await journal_line(res, finishing)
        line = device_json(res) if lines else None
        send(("recorded", index, _bare(res.small() if small_ok and res.status == "ok" else res), line))

    send(("ready",))
    while True:
        message = await _read(reader)
        if message is None:  # the rollout's process went away (or ended the run): every device stops
            break
        if message[0] == "start":
            tasks[message[1]] = asyncio.ensure_future(device(message[1], message[2]))
        elif message[0] == "cancel":
            running = tasks.get(message[1])
            if running is not None:
                running.cancel()
    for task in list(tasks.values()):
        task.cancel()
    if tasks:
        await asyncio.gather(*tasks.values(), return_exceptions=True)
    writer.close()
    with contextlib.suppress(ConnectionError):
        await writer.wait_closed()
