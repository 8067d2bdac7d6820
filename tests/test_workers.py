"""Worker processes for big fleets (``deployer.fleet.workers``): the same outcome as one process, and no device
left behind when a process of the run dies.

Real processes (``python -m deployer apply --workers 2``) against simulated devices on 127.0.0.1; the
interrupted-run tests of test_runs.py also run with workers.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from deployer.errors import UsageError
from deployer.execute.session import ApplyOptions
from deployer.fleet.workers import MIN_DEVICES, MIN_DEVICES_FORKED, START_ENV, auto_count, forkable
from deployer.profile import load_profile
from deployer.report import read_report
from deployer.run.runner import worker_count
from deployer.testing.simulator import Simulator
from tests.helpers import Simulators, process_alive, process_children, reaped, wait_for
from tests.test_runs import (
    N,
    audit,
    before,
    deployer,
    files,  # noqa: F401 (a fixture)
    fleet,  # noqa: F401 (a fixture)
    fleet_apply,
    half_way,
    holds,
    writes,
)

pytestmark = pytest.mark.timeout(300)
_WORKER = "from deployer.fleet.workers import main; main()"


def _children(pid: int, how: str) -> list[int]:
    """The worker processes of run ``pid`` (Linux's /proc), started as ``how`` says: "fork" (the command's own
    command line) or "spawn" (this Python started again)."""

    def cmdline(p: int) -> str:
        try:
            with open(f"/proc/{p}/cmdline", "rb") as f:
                return f.read().decode(errors="replace")
        except OSError:
            return ""

    parent = cmdline(pid)
    return [c for c in process_children(pid) if (cmdline(c) == parent if how == "fork" else _WORKER in cmdline(c))]


def _same(doc: dict[str, Any]) -> list[dict[str, Any]]:
    """A report's devices without what differs between two runs of the same change (times, snapshot files)."""
    out = []
    for d in doc["devices"]:
        d = {k: v for k, v in d.items() if k not in ("seconds", "snapshot", "snapshot_sha256", "seen")}
        # a connection tried again (a loaded machine) is the run's circumstance, as its times are
        d["notices"] = [n for n in d.get("notices", []) if not n.startswith("connecting failed")]
        out.append(d)
    return out


needs_proc = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the workers in Linux's /proc")


@pytest.fixture
def quick(files: Path) -> Iterator[list[Simulator]]:  # noqa: F811
    """Ten devices answering at once (``fleet``'s answer after 100 ms: for killing runs half-way)."""
    prof = load_profile(files / "slow.yaml")
    sims = [Simulator(prof, gap_reads=True) for _ in range(10)]
    with Simulators(sims):
        (files / "fleet.yaml").write_text(
            "defaults: {timeout: 5}\ndevices:\n" + "".join(f"  d{i}: {{url: '{s.url}'}}\n" for i, s in enumerate(sims))
        )
        yield sims


def test_two_workers_report_what_one_process_reports(files: Path, quick: list[Simulator]) -> None:  # noqa: F811
    reports = []
    for workers in (0, 2):
        for i, s in enumerate(quick):  # the same starting point for both runs
            for k, v in enumerate(before(i)):
                s.write(f"p{k}", (v,))
        code, out, err = deployer(
            "apply",
            "new.yaml",
            "--inventory",
            "fleet.yaml",
            "--parallel",
            "4",
            "--yes",
            "--report",
            f"run{workers}.json",
            "--state-dir",
            f"state{workers}",
            "--workers",
            str(workers),
            cwd=files,
        )
        assert code == 0, out + err
        assert all(holds(s) == (7,) * N for s in quick)
        reports.append(json.loads((files / f"run{workers}.json").read_text()))
        for d in reports[-1]["devices"]:
            assert os.path.isfile(d["snapshot"]) and d["status"] == "ok"
    one, two = reports
    assert _same(one) == _same(two)
    assert {k: v for k, v in one["summary"].items() if k != "seconds"} == {
        k: v for k, v in two["summary"].items() if k != "seconds"
    }
    assert one["profiles"] == two["profiles"]
    for workers in (0, 2):  # the journal: each device started (its snapshot named) and finished, then the run
        lines = audit(files / f"state{workers}")
        started = {x["name"]: x for x in lines if x["event"] == "device-started"}
        finished = {x["name"]: x for x in lines if x["event"] == "device-finished"}
        assert set(started) == set(finished) == {f"d{i}" for i in range(len(quick))}
        assert all(started[n]["snapshot"] == finished[n]["snapshot"] for n in started)
        assert lines[-1]["event"] == "run-finished" and lines[-1]["exit_code"] == 0
        assert [d["written"] for d in lines[-1]["devices"]] == [[f"p{k}" for k in range(N)]] * len(quick)


# on Linux the command forks its workers; DEPLOYER_WORKER_START=spawn (and other systems) start Python again
@needs_proc
@pytest.mark.parametrize("how", ["fork", "spawn"])
def test_a_killed_run_takes_its_workers_with_it(
    files: Path,  # noqa: F811
    fleet: list[Simulator],  # noqa: F811
    how: str,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    if how == "spawn":
        monkeypatch.setenv(START_ENV, "spawn")
    with reaped(fleet_apply(files, 2)) as proc:
        wait_for(lambda: half_way(fleet), "devices half-written")
        workers = _children(proc.pid, how)
        assert len(workers) == 2
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    wait_for(lambda: not any(process_alive(w) for w in workers), "the workers to end", timeout=30)
    sent = [writes(s) for s in fleet]
    time.sleep(0.5)  # nothing goes on behind the killed run's back
    assert [writes(s) for s in fleet] == sent
    code, out, err = deployer("rollback", "--from-report", "run.json", "--yes", "--state-dir", "state", cwd=files)
    assert code == 0, out + err
    for i, s in enumerate(fleet):
        assert holds(s) == before(i), f"d{i}"


@needs_proc
def test_a_worker_that_dies_ends_the_run_truthfully(files: Path, fleet: list[Simulator]) -> None:  # noqa: F811
    with reaped(fleet_apply(files, 2)) as proc:
        wait_for(lambda: half_way(fleet), "devices half-written")
        victim = _children(proc.pid, "fork")[0]
        os.kill(victim, signal.SIGKILL)
        out, err = proc.communicate(timeout=120)
    assert proc.returncode == 4, out + err
    report = json.loads((files / "run.json").read_text())
    statuses = {d["name"]: d for d in report["devices"]}
    lost = [d for d in statuses.values() if "worker process" in (d.get("error") or "")]
    assert lost and all(d["status"] in ("interrupted", "skipped") for d in lost)
    for i, s in enumerate(fleet):  # what the report says of each device is what it holds
        d = statuses[f"d{i}"]
        if d["status"] == "ok":
            assert holds(s) == (7,) * N
        elif d["status"] == "skipped":
            assert holds(s) == before(i) and not writes(s)
        elif writes(s):
            assert d["status"] == "interrupted" and d["snapshot"] and "deployer rollback" in d["error"]
    assert audit(files / "state")[-1]["event"] == "run-finished"
    code, out, err = deployer("rollback", "--from-report", "run.json", "--yes", "--state-dir", "state", cwd=files)
    assert code == 0, out + err
    for i, s in enumerate(fleet):
        assert holds(s) == before(i), f"d{i}"


def test_a_device_whose_worker_died_before_saying_it_writes_names_its_snapshot_from_the_journal(
    tmp_path: Path,
) -> None:
    """A worker says "writing" (its snapshot) to the run's process in a message sent after its first write went out
    to the device; killed in between, the message is lost. The device-started line its journal had on disk before
    that write names the snapshot: the report says the device may hold new values and how to restore it, never
    "nothing was written". A device that had not started writing says so."""
    from deployer.execute.job import Job
    from deployer.fleet.rollout import Budget, _Rollout
    from deployer.fleet.workers import Call
    from deployer.recipe.loader import load_recipe
    from deployer.state import journal
    from deployer.transport.urls import parse_url
    from deployer.window.rollout import Window

    (tmp_path / "r.yaml").write_text("recipe: r\nprofile: example-inverter\nparameters: {F07: 10 s}\n")
    rec = load_recipe(str(tmp_path / "r.yaml"))
    state, run = str(tmp_path / "state"), "20261129T000000Z-1"
    jobs = [Job(n, rec, parse_url(f"tcp://127.0.0.1:{port}"), 1) for n, port in (("d1", 1502), ("d2", 1503))]
    snapshot = str(tmp_path / "state" / "snapshots" / "d1-20261129T000000Z.yaml")
    line = journal.device_started(run, name="d1", url="tcp://127.0.0.1:1502", unit=1, plan_digest="0" * 64)
    os.makedirs(state)
    journal.append(state, {**line, "snapshot": snapshot, "snapshot_sha256": "a" * 64})
    opts = ApplyOptions(state_dir=state, run_id=run)
    why = "worker process 1 (PID 4242) ended unexpectedly"

    async def main() -> list[Any]:
        rollout = _Rollout(jobs, opts, "r", {}, Budget(None), Window(opts, "r"), on_done=None, on_start=None)
        return [rollout.lost(j, None, Call(i, None), why) for i, j in enumerate(jobs)]  # type: ignore[arg-type]

    d1, d2 = asyncio.run(main())
    assert (d1.status, d1.snapshot, d1.snapshot_sha256) == ("interrupted", snapshot, "a" * 64)
    assert d1.error == f"{why}; some parameters may hold new values: restore with: deployer rollback {snapshot}"
    assert (d2.status, d2.snapshot) == ("interrupted", None)
    assert d2.error == f"{why} before its first write; nothing was written"


def test_a_safe_change_keeps_its_devices_in_one_process(files: Path, fleet: list[Simulator]) -> None:  # noqa: F811
    code, _, err = deployer(
        "apply",
        "new.yaml",
        "--inventory",
        "fleet.yaml",
        "--parallel",
        "4",
        "--yes",
        "--workers",
        "2",
        "--rollback-on-failure",
        "--state-dir",
        "state",
        cwd=files,
    )
    assert code == 1 and "--workers 2: --rollback-on-failure rolls devices back from this process" in err, err
    assert all(not s.log for s in fleet)  # refused before anything was sent
    assert not (files / "state" / "audit.jsonl").exists()


def test_how_many_workers_a_run_takes(monkeypatch: pytest.MonkeyPatch) -> None:
    plain = ApplyOptions()
    cpus = os.cpu_count() or 1
    monkeypatch.setenv(START_ENV, "spawn")  # workers started as new processes: worth it from 1,000 devices
    assert worker_count(0, 10_000, 256, plain, rollback_on_failure=False) == 0
    assert worker_count(3, 10_000, 256, plain, rollback_on_failure=False) == 3
    assert worker_count(3, 2, 256, plain, rollback_on_failure=False) == 2  # never more than devices at once
    assert worker_count(3, 10_000, 1, plain, rollback_on_failure=False) == 1
    assert worker_count(None, MIN_DEVICES - 1, 256, plain, rollback_on_failure=False) == 0  # too few to gain
    assert (
        worker_count(None, 10_000, 256, plain, rollback_on_failure=False)
        == auto_count(10_000, 256)
        == (0 if cpus < 2 else min(cpus, 32))
    )
    assert auto_count(10_000, 8) == (0 if cpus < 2 else 1)  # eight devices at once per worker at least
    # forked ones start at once: from 100 devices
    assert auto_count(MIN_DEVICES_FORKED - 1, 256, forked=True) == 0
    assert (
        auto_count(MIN_DEVICES_FORKED, 256, forked=True)
        == auto_count(MIN_DEVICES, 256, forked=False)
        == (0 if cpus < 2 else min(cpus, 32))
    )
    assert MIN_DEVICES_FORKED < MIN_DEVICES - 1 and auto_count(MIN_DEVICES - 1, 256, forked=False) == 0
    for opts, rb in ((ApplyOptions(soak=5.0), False), (ApplyOptions(confirm_within=60.0), False), (plain, True)):
        assert worker_count(None, 10_000, 256, opts, rollback_on_failure=rb) == 0  # auto: stays in one process
        with pytest.raises(UsageError, match="in this process"):
            worker_count(2, 10_000, 256, opts, rollback_on_failure=rb)


def test_a_report_of_a_killed_worker_run_reads_back(files: Path, fleet: list[Simulator]) -> None:  # noqa: F811
    """The stream a worker run leaves when killed is what the readers take (--limit @REPORT works from it)."""
    with reaped(fleet_apply(files, 2)) as proc:
        wait_for(lambda: half_way(fleet), "devices half-written")
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    report = read_report(str(files / "run.json"))
    assert report["run"]["id"] and len(report["devices"]) == len(fleet)
    code, out, err = deployer(
        "apply",
        "new.yaml",
        "--inventory",
        "fleet.yaml",
        "--limit",
        "@run.json",
        "--yes",
        "--workers",
        "2",
        "--parallel",
        "4",
        "--state-dir",
        "state",
        cwd=files,
    )
    assert code == 0, out + err
    assert all(holds(s) == (7,) * N for s in fleet)


def test_what_the_rollout_keeps_of_a_workers_device_is_small(files: Path, quick: list[Simulator]) -> None:  # noqa: F811
    """The command's process keeps a count per finished device, not its parameters nor its 17 KB report line."""
    from deployer.run.request import RunRequest, execute, prepare

    request = RunRequest(
        str(files / "new.yaml"),
        inventory=str(files / "fleet.yaml"),
        parallel=4,
        workers=2,
        state_dir=str(files / "state"),
        report_path=str(files / "r.json"),
    )
    report = asyncio.run(execute(prepare(request), keep_results=False))
    assert [d.status for d in report.devices] == ["ok"] * len(quick), [(d.name, d.error) for d in report.devices]
    assert all(d.report_line is None and not d.parameters and not d.requests and d.tally for d in report.devices)
    doc = json.loads((files / "r.json").read_text())
    assert all(len(d["parameters"]) == N for d in doc["devices"])  # the file has them all


@pytest.mark.parametrize(
    "boot",
    [
        "import sys; sys.exit(3)",  # never connects
        "import socket, sys, time; p = int(sys.argv[1]); t = bytes.fromhex(sys.stdin.readline().strip()); "
        "s = socket.create_connection(('127.0.0.1', p)); s.sendall(t); time.sleep(0.2); sys.exit(4)",  # dies unready
    ],
)
def test_workers_that_cannot_start_are_said_before_anything_is_sent(boot: str, monkeypatch: pytest.MonkeyPatch) -> None:
    import asyncio

    from deployer.fleet import workers

    monkeypatch.setattr(workers, "_BOOT", boot)

    async def start() -> None:
        pool = await workers.Pool.launch(2, [], fork=False)
        await pool.setup(ApplyOptions(), lines=True, small_ok=True, files=100, timeout=30)

    with pytest.raises(
        UsageError,
        match=r"cannot start 2 worker processes: a worker process (exited at its start|"
        r"ended before it was ready).*nothing was sent.*--workers 0",
    ):
        asyncio.run(start())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="workers are forked on Linux only")
def test_forked_workers_that_die_unready_are_said_before_anything_is_sent(monkeypatch: pytest.MonkeyPatch) -> None:
    import asyncio

    from deployer.fleet import workers

    monkeypatch.setattr(workers, "_forked_main", lambda sock, inherited: os._exit(3))

    async def start() -> tuple[list[int | None], str]:
        pool = await workers.Pool.launch(2, [], fork=True)
        try:
            await pool.setup(ApplyOptions(), lines=True, small_ok=True, files=100, timeout=30)
        except UsageError as e:
            return [w.process.returncode for w in pool.workers], str(e)
        return [], "ready"

    codes, said = asyncio.run(start())
    assert codes == [3, 3]  # reaped
    assert re.search(
        r"cannot start 2 worker processes: a worker process ended before it was ready.*"
        r"nothing was sent.*--workers 0",
        said,
    ), said


def test_when_workers_are_forked(monkeypatch: pytest.MonkeyPatch) -> None:
    """Forked on Linux while this process has no other thread; else (and when told) Python is started again."""
    import threading

    monkeypatch.delenv(START_ENV, raising=False)
    alone = threading.active_count() == 1  # pytest-xdist's workers have threads of their own
    assert forkable() == (sys.platform.startswith("linux") and alone)
    stop = threading.Event()
    other = threading.Thread(target=stop.wait)
    other.start()
    try:
        assert not forkable()
    finally:
        stop.set()
        other.join()
    monkeypatch.setenv(START_ENV, "spawn")
    assert not forkable()


@needs_proc
def test_a_fleet_on_a_terminal_forks_its_workers_before_its_live_display(files: Path, fleet: list[Simulator]) -> None:  # noqa: F811
    """The live display's refresh thread starts with the first device, after the workers were forked (a process
    with threads would start Python again for them)."""
    import pty
    import subprocess
    import threading

    master, slave = pty.openpty()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "deployer",
            "apply",
            "new.yaml",
            "--inventory",
            "fleet.yaml",
            "--parallel",
            "4",
            "--yes",
            "--workers",
            "2",
            "--state-dir",
            "state",
        ],
        stdin=slave,
        stdout=slave,
        stderr=slave,
        cwd=files,
        close_fds=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).parent.parent)},
    )
    os.close(slave)
    shown = bytearray()

    def drain() -> None:  # the terminal is read all along: a full one would stop the run
        while True:
            try:
                chunk = os.read(master, 4096)
            except OSError:
                return
            if not chunk:
                return
            shown.extend(chunk)

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    with reaped(proc):
        wait_for(lambda: half_way(fleet), "devices half-written")
        assert len(_children(proc.pid, "fork")) == 2
        code = proc.wait(timeout=120)
    reader.join(timeout=10)
    os.close(master)
    text = shown.decode(errors="replace")
    assert code == 0, text[-4000:]  # what the terminal showed says which device did not end ok, and why
    assert "in flight" in text and "10 devices: 10 ok" in text, text[-2000:]
    assert all(holds(s) == (7,) * N for s in fleet)
