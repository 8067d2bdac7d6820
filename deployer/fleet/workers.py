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

How a worker starts (``Pool.launch``). On Linux, while this process has no other thread, it is forked:
it has every module and the run's recipes already, and talks over a socket pair made before the fork. Started
so, two workers were ready in a few milliseconds where starting Python again took 0.2-0.3 s, all inside the
fleet's phase, and two imports' CPU on a two-core machine (benchmarks/RESULTS.md). Elsewhere (Windows, macOS,
whose system libraries are not safe to fork; a process with threads, such as a program that embeds deployer;
``DEPLOYER_WORKER_START=spawn``) it is this Python started again (``python -c``): it connects to a listening
socket of this process on 127.0.0.1 and says a secret given to it on its stdin before anything else is read
(a local user who finds the port cannot feed this process data). The run launches its workers before its
journal line and report file (``run.runner``): the report's thread must not exist when they are forked, and
spawned ones import their modules meanwhile.

Messages are pickled tuples, each framed by its length. A worker whose parent goes away (killed, crashed) sees
its connection close and cancels its devices: each ends as an interrupted run's device does (its journal lines
say where it was).
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import os
import pickle
import secrets
import signal
import socket
import struct
import sys
import threading
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from typing import TYPE_CHECKING, Any, NoReturn, Protocol, cast

from .. import portable
from ..errors import UsageError

if TYPE_CHECKING:
    from ..execute.job import Job
    from ..execute.session import ApplyOptions
    from ..recipe.loader import Recipe
    from ..report import DeviceResult

# below these, workers cost what they save (benchmarks/RESULTS.md): spawned ones take 0.2-0.3 s to start;
# forked ones start at once, and two made 100 devices answering after 20 ms 20% faster at --parallel 256
MIN_DEVICES = 1000
MIN_DEVICES_FORKED = 100
MIN_PER_WORKER = 8  # devices in flight per worker at least: fewer, and one process keeps up
MAX_WORKERS = 64
_FRAME = struct.Struct(">I")
_BOOT = "from deployer.fleet.workers import main; main()"
START_ENV = "DEPLOYER_WORKER_START"  # "spawn": start Python again even where forking is possible


def auto_count(devices: int, parallel: int, *, forked: bool | None = None) -> int:
    """How many workers ``workers=None`` (auto) takes: one per CPU for a fleet big enough to gain, else 0;
    ``forked``: whether they would be forked (None: ``forkable()`` now)."""
    cpus = os.cpu_count() or 1
    if forked is None:
        forked = forkable()
    if cpus < 2 or devices < (MIN_DEVICES_FORKED if forked else MIN_DEVICES):
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
    if opts.lock_held or opts.keep_lock is not None:
        return "this process holds the devices' locks"
    return None


# ---- the link between the rollout and a worker ---------------------------------------------------


class _Link(asyncio.Protocol):
    """One end of a connection between the rollout's process and a worker: messages are pickled tuples, each
    framed by its length. Each message received is handed to ``on_message`` as soon as its frame is whole
    (no coroutine woken per message); those sent within one turn of the event loop go out in one write.

    ``tokens`` (the rollout's end): the secrets of the workers it started; nothing a connection sends is
    unpickled before it has said one of them, and ``on_token(i, link)`` tells which worker it is."""

    def __init__(
        self,
        on_message: Callable[[Any], None] | None = None,
        on_lost: Callable[[], None] | None = None,
        *,
        tokens: dict[bytes, int] | None = None,
        on_token: Callable[[int, _Link], None] | None = None,
    ) -> None:
        self.on_message = on_message
        self.on_lost = on_lost
        self.tokens = tokens
        self.on_token = on_token
        self.transport: asyncio.Transport | None = None
        self._in = bytearray()
        self._out: list[bytes] = []

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)  # uvloop's transports do not subclass asyncio's

    def data_received(self, data: bytes) -> None:
        buf = self._in
        buf += data
        pos = 0
        if self.tokens is not None:  # not yet said who it is
            if len(buf) < 32:
                return
            i = next((i for token, i in self.tokens.items() if hmac.compare_digest(bytes(buf[:32]), token)), None)
            if i is None or self.on_token is None:
                self.close()
                return
            self.tokens = None
            pos = 32
            self.on_token(i, self)
            if self.transport is None or self.transport.is_closing():  # refused (a second connection of one worker)
                return
        while len(buf) - pos >= _FRAME.size:
            (size,) = _FRAME.unpack_from(buf, pos)
            end = pos + _FRAME.size + size
            if len(buf) < end:
                break
            message = pickle.loads(buf[pos + _FRAME.size : end])
            pos = end
            if self.on_message is not None:
                self.on_message(message)
        del buf[:pos]

    def connection_lost(self, exc: Exception | None) -> None:
        self.transport = None
        if self.on_lost is not None:
            self.on_lost()

    def send(self, message: object) -> None:
        if self.transport is None or self.transport.is_closing():
            return
        data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        self._out += (_FRAME.pack(len(data)), data)
        if len(self._out) == 2:
            asyncio.get_running_loop().call_soon(self._flush)

    def send_raw(self, data: bytes) -> None:
        assert self.transport is not None
        self.transport.write(data)

    def _flush(self) -> None:
        out, self._out = self._out, []
        if self.transport is not None and not self.transport.is_closing():
            self.transport.write(b"".join(out))

    def close(self) -> None:
        if self.transport is not None:
            if self._out:
                self._flush()
            self.transport.close()


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
    t = r.tally
    if t is not None:
        if len(_WRITTEN) > 1024:
            _WRITTEN.clear()
        # its fields given, not ``replace``d: a fleet does this for every device
        r.tally = type(t)(
            write_requests=t.write_requests,
            read_requests=t.read_requests,
            requests=t.requests,
            changed=t.changed,
            failed=t.failed,
            written=_WRITTEN.setdefault(t.written, t.written),
        )
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
        default_factory=lambda: asyncio.get_running_loop().create_future()
    )
    writing: DeviceResult | None = None  # what the device said when its writes started (its snapshot)


class NotStarted(UsageError):
    """The workers could not start (or died before they were ready): nothing was sent to any device."""


def _not_started(count: int, why: str) -> NotStarted:
    return NotStarted(
        f"cannot start {count} worker processes: {why}; nothing was sent to any device (run the fleet "
        "in one process with --workers 0)"
    )


class _Process(Protocol):
    """What the pool needs of a worker process: asyncio's for a spawned one, ``_Forked`` for a forked one."""

    @property
    def returncode(self) -> int | None: ...

    async def wait(self) -> int: ...

    def kill(self) -> None: ...


class _Forked:
    """A worker forked from this process (``Pool._fork``); reaped here, not by asyncio's child watcher."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self._code: int | None = None

    @property
    def returncode(self) -> int | None:
        if self._code is None:
            self._code = portable.child_exit_code(self.pid)
        return self._code

    async def wait(self) -> int:
        # polled: a worker ends within milliseconds of its link closing, and this runs once per worker and run
        while (code := self.returncode) is None:
            await asyncio.sleep(0.005)
        return code

    def kill(self) -> None:
        if self.returncode is None:
            portable.kill_child(self.pid)


class _Worker:
    def __init__(self, process: _Process) -> None:
        self.process = process
        self.link: _Link | None = None
        self.connected: asyncio.Future[_Link] = asyncio.get_running_loop().create_future()
        self.ready: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self.calls: dict[int, Call] = {}
        self.gone: WorkerGone | None = None  # set once its connection ended: it takes no more devices

    def send(self, message: object) -> None:
        assert self.link is not None
        self.link.send(message)


def forkable() -> bool:
    """Whether workers are forked (see the module's docstring): Linux, no other thread in this process, and not
    turned off with ``DEPLOYER_WORKER_START=spawn``."""
    return portable.can_fork() and os.environ.get(START_ENV, "").lower() != "spawn" and threading.active_count() == 1


class Pool:
    """Worker processes running a rollout's devices: ``launch`` them, then ``setup`` the run in them; each device
    when the rollout says (``run``)."""

    def __init__(self, jobs: Sequence[Job]) -> None:
        self.jobs = jobs
        self.index = {j.name: i for i, j in enumerate(jobs)}
        # the recipes the workers are given once; each device is sent with its own start (its job's fields and the
        # number of its recipe): a worker holds only the devices it runs (10,000 jobs held twice cost 6 KB a device)
        self.recipes: dict[int, int] = {}  # a recipe's number: its place in setup_recipes
        self.setup_recipes: list[Recipe] = []
        for j in jobs:
            if id(j.recipe) not in self.recipes:
                self.recipes[id(j.recipe)] = len(self.setup_recipes)
                self.setup_recipes.append(j.recipe)
        self.on_writing: Callable[[DeviceResult], None] | None = None
        self.workers: list[_Worker] = []
        self.set_up = False  # every worker had its setup and said it is ready
        self.seconds = 0.0  # what launching took (the fleet's phase counts it: it runs before the journal's line)
        self._server: asyncio.AbstractServer | None = None

    @classmethod
    async def launch(cls, count: int, jobs: Sequence[Job], *, fork: bool | None = None) -> Pool:
        """``count`` workers started, forked where ``forkable()`` (``fork``: decide here), else spawned; ``setup``
        makes them ready. Raises NotStarted (nothing sent to any device) when they cannot be started."""
        t = time.monotonic()
        pool = cls(jobs)
        forked = forkable() if fork is None else fork
        try:
            await (pool._fork(count) if forked else pool._spawn(count))
        except OSError as e:
            await pool.close(kill=True)
            raise _not_started(count, str(e)) from None
        pool.seconds = time.monotonic() - t
        return pool

    async def setup(
        self, opts: ApplyOptions, *, lines: bool, small_ok: bool, files: int, timeout: float = 60.0
    ) -> None:
        """Give every worker the recipes and the run's options, and wait until each is ready. ``lines``: the
        workers encode each device's report line; ``small_ok``: a device that ended ok comes back as its small
        result; ``files``: the open files each may need. Raises NotStarted (the workers ended; nothing sent to
        any device) when they cannot start."""
        self.on_writing = opts.on_writing
        setup = (
            "setup",
            self.setup_recipes,
            _portable(opts),
            sys.argv,
            lines,
            small_ok,
            opts.on_writing is not None,
            files,
        )
        try:
            await asyncio.wait_for(self._setup(setup), timeout)
        except BaseException as e:
            await self.close(kill=True)
            why = f"they were not ready within {timeout:g} s" if isinstance(e, TimeoutError) else str(e)
            if isinstance(e, (OSError, TimeoutError, WorkerGone, pickle.PicklingError)):
                raise _not_started(len(self.workers), why) from None
            raise

    async def _fork(self, count: int) -> None:
        """Fork the workers, each with its end of a socket pair (no secret: nobody else has the pair)."""
        pairs = [socket.socketpair() for _ in range(count)]
        for stream in (sys.stdout, sys.stderr):  # a worker's traceback must not repeat what this process had buffered
            with contextlib.suppress(OSError, ValueError, AttributeError):
                stream.flush()
        handed = 0  # our ends given to a transport, which closes them
        try:
            try:
                for _, theirs in pairs:
                    pid = portable.fork()
                    if pid == 0:
                        _forked_main(theirs, [s for pair in pairs for s in pair if s is not theirs])
                    self.workers.append(_Worker(_Forked(pid)))
            finally:
                for _, theirs in pairs:
                    theirs.close()
            loop = asyncio.get_running_loop()
            for (ours, _), w in zip(pairs, self.workers, strict=True):
                _, link = await loop.connect_accepted_socket(partial(self._link, w), ours)
                handed += 1
                w.link = link
                w.connected.set_result(link)
        finally:
            for ours, _ in pairs[handed:]:
                ours.close()

    async def _spawn(self, count: int) -> None:
        """Start Python again ``count`` times; each connects to this process and says its secret."""
        tokens = {secrets.token_bytes(32): i for i in range(count)}  # which process a connection is

        def connected(i: int, link: _Link) -> None:
            w = self.workers[i]
            if w.connected.done():
                link.close()
                return
            link.on_message, link.on_lost = (lambda m: self._received(w, m)), (lambda: self._lost(w))
            w.link = link
            w.connected.set_result(link)

        loop = asyncio.get_running_loop()
        self._server = await loop.create_server(lambda: _Link(tokens=tokens, on_token=connected), "127.0.0.1", 0)
        port = self._server.sockets[0].getsockname()[1]
        env = {
            **os.environ,
            "PYTHONPATH": os.pathsep.join([_package_root(), *filter(None, [os.environ.get("PYTHONPATH")])]),
        }
        for token in tokens:
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-c", _BOOT, str(port), stdin=asyncio.subprocess.PIPE, env=env
            )
            self.workers.append(_Worker(proc))
            assert proc.stdin is not None
            proc.stdin.write(token.hex().encode() + b"\n")
            await proc.stdin.drain()
            proc.stdin.close()

    def _link(self, w: _Worker) -> _Link:
        return _Link(on_message=lambda m: self._received(w, m), on_lost=lambda: self._lost(w))

    async def _setup(self, setup: tuple[Any, ...]) -> None:
        for w in self.workers:
            exited: asyncio.Future[Any] = asyncio.ensure_future(w.process.wait())
            await asyncio.wait([exited, w.connected], return_when=asyncio.FIRST_COMPLETED)
            if not w.connected.done():
                raise WorkerGone(f"a worker process exited at its start (exit code {exited.result()})")
            exited.cancel()
            w.send(setup)
        for w in self.workers:  # each says it is ready once it has loaded the recipes
            await w.ready
        self.set_up = True
        if self._server is not None:
            self._server.close()
            self._server = None

    def _received(self, w: _Worker, message: Any) -> None:
        """A message from a worker, to the call it is about."""
        kind, index, *rest = message
        if kind == "ready":
            if not w.ready.done():
                w.ready.set_result(None)
            return
        call = w.calls.get(index)
        if call is None:
            return
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

    def _lost(self, w: _Worker) -> None:
        """A worker's connection ended: its devices in flight fail with WorkerGone, it takes no new one."""
        code = f" (exit code {w.process.returncode})" if w.process.returncode is not None else ""
        w.gone = WorkerGone(
            f"the worker process running it ended unexpectedly{code}"
            if w.ready.done()
            else f"a worker process ended before it was ready{code}"
        )
        if not w.ready.done():
            w.ready.set_exception(w.gone)
            w.ready.add_done_callback(_retrieved)
        for call in w.calls.values():
            for fut in (call.done, call.recorded):
                if not fut.done():
                    fut.set_exception(w.gone)
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
        w.send(
            (
                "start",
                call.index,
                batch,
                job.name,
                job.url,
                job.unit,
                self.recipes[id(job.recipe)],
                job.group,
                job.hold_commit,
                job.commit_owed,
            )
        )
        return call

    def cancel(self, call: Call) -> None:
        """Interrupt a device (the run was interrupted): its worker answers ``interrupted`` (or ``done``)."""
        call.worker.send(("cancel", call.index))

    async def close(self, *, kill: bool = False) -> None:
        """The workers told to end (their connection closed) and waited for; ``kill``: ended at once (as are
        workers never set up: nothing of theirs is in flight). Closing again does nothing more."""
        kill = kill or not self.set_up
        if self._server is not None:
            self._server.close()
        for w in self.workers:
            if w.link is not None:
                w.link.on_lost = None
                w.link.close()
            if kill and w.process.returncode is None:
                w.process.kill()
        for w in self.workers:
            try:
                await asyncio.wait_for(w.process.wait(), 30)
            except TimeoutError:
                w.process.kill()
                await w.process.wait()


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
    """A spawned worker: ``python -c "from deployer.fleet.workers import main; main()" PORT``, the secret on stdin."""
    port = int(sys.argv[1])
    token = bytes.fromhex(sys.stdin.readline().strip())
    _ignore_interrupts()

    async def connect(link: _Link) -> None:
        await asyncio.get_running_loop().create_connection(lambda: link, "127.0.0.1", port)
        link.send_raw(token)

    with asyncio.Runner(loop_factory=_loop_factory()) as runner:
        runner.run(_serve(connect))


def _forked_main(sock: socket.socket, inherited: Sequence[socket.socket]) -> NoReturn:
    """A forked worker (``Pool._fork``): serves on its end of the socket pair, then ends this process. It never
    returns into the rollout's code it was forked from, and leaves no handler of it to run (``os._exit``)."""
    try:
        import gc

        gc.freeze()  # the rollout's objects are never collected here: a finalizer would close a descriptor of ours
        for s in inherited:  # the other workers' pairs: a copy of their ends here would keep their links open
            s.close()
        signal.set_wakeup_fd(-1)  # the rollout's event loop's, not ours
        asyncio._set_running_loop(None)  # Python 3.12+ does this itself at a fork
        _ignore_interrupts()
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        null = os.open(os.devnull, os.O_RDONLY)  # a question of the command's is never read here
        os.dup2(null, 0)
        os.close(null)

        async def connect(link: _Link) -> None:
            await asyncio.get_running_loop().connect_accepted_socket(lambda: link, sock)

        with asyncio.Runner(loop_factory=_loop_factory()) as runner:
            runner.run(_serve(connect))
    except KeyboardInterrupt:  # Ctrl-C before it ignored it: the rollout's process had it too, and says so
        os._exit(1)
    except BaseException:
        try:
            import traceback

            traceback.print_exc()
        finally:
            os._exit(1)
    os._exit(0)


def _ignore_interrupts() -> None:
    """Ctrl-C reaches every process of the terminal: a worker's devices are interrupted when the rollout says
    so (it relays the interruption), never behind its back."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "SIGBREAK"):
        signal.signal(signal.SIGBREAK, signal.SIG_IGN)


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


async def _serve(connect: Callable[[_Link], Awaitable[None]]) -> None:
    import gc

    from ..execute.device import DeviceInterrupted, Planners, apply_job, journal_line
    from ..execute.job import Job
    from ..portable import raise_open_files
    from ..report import device_json
    from ..state import durable

    loop = asyncio.get_running_loop()
    setup: asyncio.Future[Any] = loop.create_future()
    ended = asyncio.Event()
    tasks: dict[int, asyncio.Task[None]] = {}
    link = _Link()

    def first(message: Any) -> None:
        if not setup.done():
            setup.set_result(message)

    def lost() -> None:  # the rollout's process went away (or ended the run): every device stops
        if not setup.done():
            setup.set_result(None)
        ended.set()

    link.on_message, link.on_lost = first, lost
    await connect(link)
    given = await setup
    if given is None:
        return
    _, recipes, opts, argv, lines, small_ok, writing, files = given
    sys.argv = argv  # what lock records and messages name as the command: the run's, not this worker's
    raise_open_files(files)  # the rollout's process checked that the system allows them
    gc.freeze()  # what was loaded lives as long as the run (as the command line does for itself)
    gc.set_threshold(20_000, 20, 10)
    send = link.send

    index_of: dict[str, int] = {}  # the devices in flight here, by name
    if writing:

        def on_writing(r: DeviceResult) -> None:  # what the report file says of it now: its snapshot
            send(("writing", index_of[r.name], r.head()))

        opts = replace(opts, on_writing=on_writing)

    async def device(index: int, batch: int | None, job: Job) -> None:
        index_of[job.name] = index
        try:
            await run(index, batch, job)
        finally:
            tasks.pop(index, None)
            index_of.pop(job.name, None)

    planners = Planners()  # the devices of one recipe share its planner and their plans

    async def run(index: int, batch: int | None, job: Job) -> None:
        t = time.monotonic()
        try:
            res, finishing = await apply_job(job, opts, batch=batch, planners=planners)
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

    def received(message: Any) -> None:
        if message[0] == "start":
            _, index, batch, name, url, unit, recipe, group, hold_commit, commit_owed = message
            job = Job(name, recipes[recipe], url, unit, group, hold_commit=hold_commit, commit_owed=commit_owed)
            tasks[index] = asyncio.ensure_future(device(index, batch, job))
        elif message[0] == "cancel":
            running = tasks.get(message[1])
            if running is not None:
                running.cancel()

    link.on_message = received
    send(("ready", None))
    await ended.wait()
    for task in list(tasks.values()):
        task.cancel()
    if tasks:
        await asyncio.gather(*tasks.values(), return_exceptions=True)
    # the snapshots written here fsync'ed and their write-ahead log removed: the process ends by os._exit, and
    # the rollout's run-finished line comes after its workers ended
    await durable.settled()
    link.close()
