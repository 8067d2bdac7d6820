"""The run as the library's object: journaled whoever starts it, and interrupted runs that end truthfully.

Runs are real processes (``python -m deployer``, or a Python script using the API) against slow
simulated devices on 127.0.0.1, killed with SIGKILL, SIGINT or SIGTERM while they write; afterwards
every device's registers are read from the simulator and compared with what the report claims and
with what it held before.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from deployer.profile import load_profile
from deployer.report import read_report
from deployer.state import wal
from deployer.testing.simulator import Faults, Simulator, SimulatorThread
from tests.helpers import Simulators, process_alive, process_children, reaped, wait_for

pytestmark = pytest.mark.timeout(300)

N = 12  # parameters, each in its own write request (gaps between them), read in one request
PROFILE = "profile: slow\nlimits: {max_read_gap: 9}\nparameters:\n" + "".join(
    f"  p{i}: {{register: {10 * i}, type: uint16}}\n" for i in range(N)
)
RECIPE = "recipe: new\nprofile: slow.yaml\nparameters:\n" + "".join(f"  p{i}: 7\n" for i in range(N))


@pytest.fixture
def files(tmp_path: Path) -> Path:
    (tmp_path / "slow.yaml").write_text(PROFILE)
    (tmp_path / "new.yaml").write_text(RECIPE)
    return tmp_path


def before(i: int) -> tuple[int, ...]:
    """What device i holds before the run: its own values, so a restore to the wrong device shows."""
    return tuple(100 * (i + 1) + k for k in range(N))


def holds(sim: Simulator) -> tuple[int, ...]:
    return tuple(sim.read(f"p{k}")[0] for k in range(N))


def writes(sim: Simulator) -> int:
    return sum(1 for e in sim.log if e.function in (6, 16) and e.result == "ok")


def start(*args: str, cwd: Path) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "deployer", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).parent.parent)},
    )


def deployer(*args: str, cwd: Path) -> tuple[int, str, str]:
    p = subprocess.run(
        [sys.executable, "-m", "deployer", *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).parent.parent)},
    )
    return p.returncode, p.stdout, p.stderr


def audit(state: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (state / "audit.jsonl").read_text().splitlines()]


@pytest.fixture
def fleet(files: Path) -> Iterator[list[Simulator]]:
    """Ten devices answering after 100 ms each; an inventory of them."""
    prof = load_profile(files / "slow.yaml")
    sims = [Simulator(prof, faults=Faults(latency_ms=100), gap_reads=True) for _ in range(10)]
    with Simulators(sims):
        for i, s in enumerate(sims):
            for k, v in enumerate(before(i)):
                s.write(f"p{k}", (v,))
        (files / "fleet.yaml").write_text(
            "defaults: {timeout: 5}\ndevices:\n" + "".join(f"  d{i}: {{url: '{s.url}'}}\n" for i, s in enumerate(sims))
        )
        yield sims


def half_way(sims: list[Simulator]) -> bool:
    """The first devices are done writing and later ones are in the middle of it."""
    done = [writes(s) for s in sims]
    return any(n == N for n in done) and any(0 < n <= N - 5 for n in done)  # 5 writes (0.5 s) of margin


def fleet_apply(files: Path, workers: int = 0) -> subprocess.Popen[str]:
    return start(
        "apply",
        "new.yaml",
        "--inventory",
        "fleet.yaml",
        "--parallel",
        "4",
        "--yes",
        "--report",
        "run.json",
        "--state-dir",
        "state",
        "--workers",
        str(workers),
        cwd=files,
    )


# in this process, and in two worker processes (fleet.workers): the same outcome, the same report
@pytest.mark.parametrize("workers", [0, 2])
def test_kill_9_mid_fleet_then_rollback_from_the_report_restores_every_device(
    files: Path, fleet: list[Simulator], workers: int
) -> None:
    with reaped(fleet_apply(files, workers)) as proc:
        wait_for(lambda: half_way(fleet), "devices half-written")
        children = process_children(proc.pid)  # its workers (Linux)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    # what the run wrote is counted once its workers ended too: they stop their devices as soon as they see
    # the command gone, which takes them a few milliseconds more
    wait_for(lambda: not any(process_alive(c) for c in children), "the run's workers to end", timeout=30)
    half = [f"d{i}" for i, s in enumerate(fleet) if 0 < writes(s) < N]
    by_run = [writes(s) for s in fleet]
    assert half and any(holds(s) != before(i) for i, s in enumerate(fleet))
    assert (files / "run.json").read_text().startswith('{"schema": "deployer.report-stream/3"')  # killed: a stream
    report = read_report(str(files / "run.json"))
    assert report["run"]["id"] and report["run"]["state_dir"] == str(files / "state")
    by_name = {d["name"]: d for d in report["devices"]}
    for name in half:  # the file says not finished (or interrupted, if its writer got there): never ok
        assert by_name[name]["status"] in ("skipped", "interrupted")
    # --limit @REPORT retries the half-written devices too
    assert set(half) <= {d["name"] for d in report["devices"] if d["status"] not in ("ok", "sent")}

    # killed before its end, the run never fsync'ed its snapshot files themselves: their write-ahead log holds
    # them (state.wal), and a power loss now could cost any of them. Lose them all (one cut to nothing).
    # (Workers see the command gone and settle their own log first: nothing of theirs is left to lose.)
    logs = sorted((files / "state" / "snapshots" / ".wal").glob("*.jsonl"))
    logged = [path for f in logs for path, _, _ in wal.records(f.read_bytes())]
    if workers == 0:
        assert logged
    for k, path in enumerate(logged):
        Path(path).write_bytes(b"") if k == 0 else Path(path).unlink()

    code, out, err = deployer(
        "rollback", "--from-report", "run.json", "--yes", "--state-dir", "state", "--report", "back.json", cwd=files
    )
    assert code == 0, out + err
    if logged:
        assert f"restored {len(logged)} snapshot(s)" in err
        (event,) = [r for r in audit(files / "state") if r["event"] == "snapshots-restored"]
        assert event["snapshots"] == logged
    assert not (files / "state" / "snapshots" / ".wal").exists()
    for i, s in enumerate(fleet):
        assert holds(s) == before(i), f"d{i}"
    back = json.loads((files / "back.json").read_text())
    restored = {d["name"] for d in back["devices"]}
    assert set(half) <= restored
    # devices the run never wrote got no write from the rollback either (at most a snapshot taken right
    # before the kill, whose restore finds nothing to change)
    assert all(writes(s) == 0 for s, n in zip(fleet, by_run, strict=True) if n == 0)
    assert "nothing was written there" in err  # the devices never started (d9 at least)


@pytest.mark.parametrize("workers", [0, 2])
def test_sigint_mid_fleet_ends_with_an_exact_report_and_rolls_back(
    files: Path, fleet: list[Simulator], workers: int
) -> None:
    with reaped(fleet_apply(files, workers)) as proc:
        wait_for(lambda: half_way(fleet), "devices half-written")
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=120)
    assert proc.returncode == 4, out + err
    report = json.loads((files / "run.json").read_text())
    statuses = {d["name"]: d["status"] for d in report["devices"]}
    assert "interrupted" in statuses.values() and report["run"]["interrupted"] == "SIGINT"
    assert report["summary"]["interrupted"] == sum(1 for s in statuses.values() if s == "interrupted")
    for i, (s, d) in enumerate(zip(fleet, report["devices"], strict=True)):
        now = holds(s)
        if d["status"] == "skipped":  # skipped keeps meaning: nothing was sent
            assert not s.log and now == before(i) and d["error"] == "not started: the run was interrupted"
            continue
        assert d["status"] in ("ok", "interrupted"), json.dumps(d)[:4000]
        if d["status"] == "interrupted" and writes(s):
            assert d["snapshot"] and os.path.isfile(d["snapshot"])
            assert "rollback" in d["error"]
        for k, p in enumerate(d["parameters"]):  # the report says exactly what each register holds
            if p["status"] == "ok":
                assert now[k] == 7
            elif p["status"] == "skipped":
                assert now[k] == before(i)[k], (d["name"], p)
            else:
                assert p["status"] == "unverified" and p["error"], p
    assert "interrupted (SIGINT)" in err
    if sum(1 for d in report["devices"] if d["status"] == "interrupted" and d["snapshot"]) > 1:
        assert "undo with: deployer rollback --from-report run.json" in err
    lines = audit(files / "state")
    assert lines[-1]["event"] == "run-finished" and lines[-1]["interrupted"] == "SIGINT"
    assert lines[-1]["run"] == report["run"]["id"] and lines[-1]["exit_code"] == 4

    code, out, err = deployer("rollback", "--from-report", "run.json", "--yes", "--state-dir", "state", cwd=files)
    assert code == 0, out + err
    for i, s in enumerate(fleet):
        assert holds(s) == before(i), f"d{i}"


def test_sigterm_mid_apply_of_one_device(files: Path) -> None:
    prof = load_profile(files / "slow.yaml")
    with SimulatorThread(prof, faults=Faults(latency_ms=150), gap_reads=True) as sim:
        for k, v in enumerate(before(0)):
            sim.write(f"p{k}", (v,))
        proc = start(
            "apply", "new.yaml", "--device", sim.url, "--yes", "--report", "one.json", "--state-dir", "state", cwd=files
        )
        wait_for(lambda: 2 <= writes(sim) <= N - 6, "writes")
        # the report file was written before the first request, like a fleet's
        first = read_report(str(files / "one.json"))
        assert first["devices"][0]["status"] in ("skipped", "interrupted") and first["run"]["id"]
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 4, out + err
        dev = json.loads((files / "one.json").read_text())["devices"][0]
        assert dev["status"] == "interrupted" and dev["snapshot"] and os.path.isfile(dev["snapshot"])
        assert f"undo with: deployer rollback {dev['snapshot']}" in err and "interrupted (SIGTERM)" in err
        assert any(r["result"] == "interrupted" for r in dev["requests"]) or writes(sim) == sum(
            1 for r in dev["requests"] if r["function"] == 16
        )
        now = holds(sim)
        for k, p in enumerate(dev["parameters"]):
            if p["status"] == "skipped":
                assert now[k] == before(0)[k]
        assert audit(files / "state")[-1]["interrupted"] == "SIGTERM"
        code, out, err = deployer("status", "--state-dir", "state", cwd=files)
        assert code == 2 and "interrupted (SIGTERM)" in out and f"undo with: deployer rollback {dev['snapshot']}" in out
        assert f"deployer diff {files / 'new.yaml'} --device {sim.url} --unit 1" in out  # the run's own recipe
        code, out, err = deployer("rollback", dev["snapshot"], "--yes", "--state-dir", "state", cwd=files)
        assert code == 0, out + err
        assert holds(sim) == before(0)
        # restored from its snapshot: nothing left to look at
        code, out, err = deployer("status", "--state-dir", "state", cwd=files)
        assert "no unfinished runs" in out, out


API_RUN = """
import sys
import deployer
rec = deployer.load_recipe(sys.argv[1])
report = deployer.apply(rec, sys.argv[2], state_dir=sys.argv[3], name="press")
print(report.run_id, report.exit_code)
"""


def test_an_api_apply_is_journaled_and_status_sees_it_killed(files: Path) -> None:
    prof = load_profile(files / "slow.yaml")
    with SimulatorThread(prof, faults=Faults(latency_ms=100), gap_reads=True) as sim:
        script = files / "api_run.py"
        script.write_text(API_RUN)
        env = {**os.environ, "PYTHONPATH": str(Path(__file__).parent.parent)}
        p = subprocess.run(
            [sys.executable, str(script), "new.yaml", sim.url, "state"],
            capture_output=True,
            text=True,
            cwd=files,
            env=env,
            timeout=120,
        )
        assert p.returncode == 0, p.stderr
        run, exit_code = p.stdout.split()
        assert exit_code == "0"
        lines = [r for r in audit(files / "state") if r["run"] == run]
        assert [r["event"] for r in lines] == ["run-started", "device-started", "device-finished", "run-finished"]
        assert lines[0]["via"] == "api" and lines[0]["devices"][0]["name"] == "press"

        # killed mid-write: deployer status lists the API's run and the device it was writing
        for k, v in enumerate(before(0)):
            sim.write(f"p{k}", (v,))
        sim.log.clear()
        proc = subprocess.Popen(
            [sys.executable, str(script), "new.yaml", sim.url, "state"],
            cwd=files,
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        wait_for(lambda: writes(sim) >= 2, "writes")
        proc.kill()
        proc.wait(timeout=30)
        code, out, _ = deployer("status", "--state-dir", "state", "--json", cwd=files)
        (unfinished,) = json.loads(out)["unfinished"]
        assert unfinished["via"] == "api" and unfinished["interrupted"][0]["name"] == "press"
        code, out, _ = deployer("status", "--state-dir", "state", cwd=files)
        assert "apply (through the Python API)" in out and "interrupted while writing: press" in out
        # acknowledged after a look: recorded in the audit log, and no longer listed
        code, out, err = deployer("status", "--state-dir", "state", "--resolve", unfinished["run"], cwd=files)
        assert code == 0 and f"resolved run {unfinished['run']}" in out, out + err
        resolved = audit(files / "state")[-1]
        assert resolved["event"] == "run-resolved" and resolved["run"] == unfinished["run"] and resolved["user"]
        code, out, _ = deployer("status", "--state-dir", "state", "--json", cwd=files)
        assert json.loads(out)["unfinished"] == []
        code, out, err = deployer("status", "--state-dir", "state", "--resolve", unfinished["run"], cwd=files)
        assert code == 1 and "needs a look" in err


def test_a_stale_plan_is_refused_and_journaled_as_such(files: Path) -> None:
    prof = load_profile(files / "slow.yaml")
    with SimulatorThread(prof, gap_reads=True) as sim:
        code, out, err = deployer("plan", "new.yaml", "--device", sim.url, "--out", "plan.json", cwd=files)
        assert code == 0, out + err
        sim.write("p3", (55,))  # the device changes after the plan was made
        code, out, err = deployer("apply", "plan.json", "--yes", "--state-dir", "state", cwd=files)
        assert code == 1 and "make a new plan" in err
        assert not any(e.function in (6, 16) for e in sim.log)
        last = audit(files / "state")[-1]
        assert last["event"] == "run-finished" and "make a new plan" in last["refused"]
        code, out, err = deployer("status", "--state-dir", "state", "--json", cwd=files)
        assert json.loads(out)["unfinished"] == []


def test_an_edited_snapshot_is_refused_unless_accepted(files: Path) -> None:
    """The snapshot's SHA-256 is in the journal's device-started line and the report; rollback checks it."""
    prof = load_profile(files / "slow.yaml")
    with SimulatorThread(prof, gap_reads=True) as sim:
        for k, v in enumerate(before(0)):
            sim.write(f"p{k}", (v,))
        code, out, err = deployer(
            "apply", "new.yaml", "--device", sim.url, "--yes", "--report", "run.json", "--state-dir", "state", cwd=files
        )
        assert code == 0, out + err
        dev = json.loads((files / "run.json").read_text())["devices"][0]
        snap = Path(dev["snapshot"])
        import hashlib

        digest = hashlib.sha256(snap.read_bytes()).hexdigest()
        started = next(r for r in audit(files / "state") if r["event"] == "device-started")
        assert dev["snapshot_sha256"] == started["snapshot_sha256"] == digest
        # edited consistently (value and recorded registers alike): the recipe loader cannot tell
        text = snap.read_text()
        assert "  p0: 100\n" in text and "    p0: [100]\n" in text
        snap.write_text(text.replace("  p0: 100\n", "  p0: 555\n").replace("    p0: [100]\n", "    p0: [555]\n"))
        writes_before = writes(sim)
        for args in (["rollback", str(snap)], ["rollback", "--from-report", "run.json"]):
            code, out, err = deployer(*args, "--yes", "--state-dir", "state", cwd=files)
            assert code == 1 and "was changed after it was written" in err and "--accept-edited-snapshot" in err
        assert writes(sim) == writes_before  # nothing was sent
        # --force (the profile changed) is not that consent
        code, out, err = deployer("rollback", str(snap), "--yes", "--force", "--state-dir", "state", cwd=files)
        assert code == 1 and writes(sim) == writes_before
        code, out, err = deployer(
            "rollback", str(snap), "--yes", "--accept-edited-snapshot", "--state-dir", "state", cwd=files
        )
        assert code == 0 and "restoring it as it is now" in err, out + err
        assert holds(sim) == (555, *before(0)[1:])
        # a copy no report or journal knows: restored, with a plain notice that it could not be checked
        copy = files / "elsewhere" / "snapshots" / "copy.yaml"
        copy.parent.mkdir(parents=True)
        copy.write_text(text)
        code, out, err = deployer("rollback", str(copy), "--yes", "--state-dir", "state", cwd=files)
        assert code == 0 and "cannot be checked for edits" in err, out + err
        assert holds(sim) == before(0)


def test_a_rollout_and_its_retry_roll_back_in_one_command(files: Path) -> None:
    prof = load_profile(files / "slow.yaml")
    sims = [
        Simulator(prof, gap_reads=True, faults=Faults(fail_registers=frozenset({50}) if i == 1 else frozenset()))
        for i in range(3)
    ]
    with Simulators(sims):
        for i, s in enumerate(sims):
            for k, v in enumerate(before(i)):
                s.write(f"p{k}", (v,))
        (files / "fleet.yaml").write_text(
            "devices:\n" + "".join(f"  d{i}: {{url: '{s.url}'}}\n" for i, s in enumerate(sims))
        )
        run = ("apply", "new.yaml", "--inventory", "fleet.yaml", "--yes", "--state-dir", "state")
        code, out, err = deployer(*run, "--report", "run1.json", cwd=files)
        assert code == 4, out + err
        assert holds(sims[1])[5] == before(1)[5] and holds(sims[1])[4] == 7  # d1 half-written by run 1
        sims[1].faults.fail_registers = frozenset()
        code, out, err = deployer(*run, "--limit", "@run1.json", "--report", "retry2.json", cwd=files)
        assert code == 0, out + err
        assert all(holds(s) == (7,) * N for s in sims)
        # someone changed d0 since: with --all-or-nothing refused, nothing sent, unless --even-if-changed
        sims[0].write("p3", (42,))
        back = (
            "rollback",
            "--from-report",
            "run1.json",
            "--from-report",
            "retry2.json",
            "--yes",
            "--state-dir",
            "state",
        )
        code, out, err = deployer(*back, "--all-or-nothing", cwd=files)
        assert code == 1 and "d0 no longer holds what the run wrote (p3)" in err and "--even-if-changed" in err
        assert holds(sims[0])[3] == 42 and holds(sims[2]) == (7,) * N
        code, out, err = deployer(*back, "--even-if-changed", "--report", "back.json", cwd=files)
        assert code == 0, out + err
        # each device from the snapshot of the earliest run that wrote it: d1 as it was before run 1
        for i, s in enumerate(sims):
            assert holds(s) == before(i), f"d{i}"
        restored = {d["name"]: d["restored"] for d in json.loads((files / "back.json").read_text())["devices"]}
        first = {d["name"]: d["snapshot"] for d in json.loads((files / "run1.json").read_text())["devices"]}
        assert restored == first


def test_rollback_force_restores_only_where_the_snapshot_read(files: Path) -> None:
    prof = load_profile(files / "slow.yaml")
    with SimulatorThread(prof, gap_reads=True) as sim:
        for k, v in enumerate(before(0)):
            sim.write(f"p{k}", (v,))
        code, out, err = deployer(
            "apply", "new.yaml", "--device", sim.url, "--yes", "--json", "--state-dir", "state", cwd=files
        )
        assert code == 0, err
        snap = json.loads(out)["devices"][0]["snapshot"]
        assert "  addresses:\n    p0: [0, 1]\n    p1: [10, 1]\n" in Path(snap).read_text()
        # the profile moved p1 (10 -> 12): --force must not write the old value at the new address
        (files / "slow.yaml").write_text(PROFILE.replace("p1: {register: 10,", "p1: {register: 12,"))
        code, out, err = deployer("rollback", snap, "--yes", "--state-dir", "state", cwd=files)
        assert code == 1 and "changed since this snapshot was taken" in err
        writes_before = writes(sim)
        # with another parameter now at 10, restoring p1 there would write over it: refused, nothing sent
        (files / "slow.yaml").write_text(
            PROFILE.replace("p1: {register: 10,", "p1: {register: 12,") + "  q: {register: 10, type: uint16}\n"
        )
        code, out, err = deployer("rollback", snap, "--yes", "--force", "--state-dir", "state", cwd=files)
        assert code == 1 and "p1 moved: the snapshot read it at 10 (0x000A)" in err and "q at 10" in err, err
        assert writes(sim) == writes_before
        # --force restores every recorded register where the snapshot read it: p1 back at 10, nothing at 12
        (files / "slow.yaml").write_text(PROFILE.replace("p1: {register: 10,", "p1: {register: 12,"))
        sim.write("p1", (7,))
        code, out, err = deployer("rollback", snap, "--yes", "--force", "--json", "--state-dir", "state", cwd=files)
        assert code == 0, out + err
        assert holds(sim) == before(0)
        assert not any(e.function in (6, 16) and e.address <= 12 < e.address + e.count for e in sim.log)
        assert {p["name"]: p["address"] for p in json.loads(out)["devices"][0]["parameters"]}["p1"] == 10
        for k, v in enumerate(before(0)):  # the device as the run found it, for the next case
            sim.write(f"p{k}", (v,))
        # a profile changed elsewhere (every parameter where it was): --force restores the recorded registers
        (files / "slow.yaml").write_text(PROFILE + "# reviewed\n")
        code, out, err = deployer("rollback", snap, "--yes", "--force", "--state-dir", "state", cwd=files)
        assert code == 0, out + err
        assert holds(sim) == before(0)
