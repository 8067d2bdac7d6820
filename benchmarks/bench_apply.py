"""apply on the issue-#9 drive, end to end, against a device answering after 0, 5 and 20 ms.

The drive: 500 parameters, every 3rd 32-bit, one undeclared register after every 40 (679
registers, 13 runs). The device is the simulator in its own process (`deployer simulate
--latency-ms D`), so its CPU is not ours. Each contender runs as a fresh process, timed from
spawn to exit (interpreter start-up and imports included), with new values each run so
everything is written:

* ``deployer``: ``deployer apply RECIPE --yes`` (snapshot read, writes, read-back, report);
  ``deployer_gap_reads``: the same with ``limits: {max_read_gap: 1}`` and a device that answers
  reads of its gaps;
* ``naive``: a pymodbus script doing one FC16 and one FC03 per parameter;
* ``skilled``: a pymodbus script writing the same 13 contiguous blocks and reading them back
  once (no snapshot, no checks, values precomputed);
* ``floor``: requests x answer delay, and ``floor_plus_startup``: that plus a bare
  ``python -c pass``.

Also the time split by phase (the library's own calls, step by step, in one process: load,
validate, plan, connect, snapshot read, writes, read-back, report), and the CPU per parameter
at 0 ms (process CPU of those phases / parameters).
"""

from __future__ import annotations

import asyncio
import compileall
import io
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from benchmarks import drive
from benchmarks.child import measured

N = 500
ROOT = Path(__file__).resolve().parent.parent

# naive: one FC16 and one FC03 per parameter; skilled: the same contiguous blocks as deployer's writes
SCRIPT = """
import json, sys
from pymodbus.client import ModbusTcpClient
host, port, plan, kind = sys.argv[1], int(sys.argv[2]), json.load(open(sys.argv[3])), sys.argv[4]
c = ModbusTcpClient(host, port=port, retries=0, timeout=3)
c.connect()
for address, regs in plan[kind]:
    assert not c.write_registers(address, regs, device_id=1).isError()
for address, regs in plan[kind]:
    assert c.read_holding_registers(address, count=len(regs), device_id=1).registers == regs
c.close()
"""


def as_installed(checkout: str | Path | None = None) -> None:
    """Byte-compile the package (of this checkout, or of another one measured beside it), as `pip install` does:
    a checkout run with PYTHONDONTWRITEBYTECODE (set on this machine) would otherwise compile every module of ours
    in every run (30-50 ms), and a worker process the modules it imports late, during its devices."""
    compileall.compile_dir(str(Path(checkout or ROOT) / "deployer"), quiet=1)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def device(profile: str, latency_ms: float, log: str, gap_reads: bool = False) -> Any:
    port = _free_port()
    args = [
        sys.executable,
        "-m",
        "deployer",
        "simulate",
        profile,
        "--listen",
        f"tcp://127.0.0.1:{port}",
        "--latency-ms",
        str(latency_ms),
        "--log",
        log,
    ] + (["--gap-reads"] if gap_reads else [])
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=ROOT)
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
                break
            except OSError:
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise RuntimeError("the simulator did not start") from None
                time.sleep(0.05)
        yield port
    finally:
        proc.terminate()
        proc.wait(10)


def timed(args: list[str], cwd: Path = ROOT) -> tuple[float, float, int, int]:
    """Wall seconds, CPU seconds, peak RSS (KB) and exit code of one child process (its own peak: see child.py)."""
    wall, cpu, rss, code, err = measured(args, str(cwd))
    if code != 0:
        raise RuntimeError(f"{' '.join(args[:4])} exited {code}: {err[-800:]}")
    return wall, cpu, rss, code


def _log_lines(log: str) -> list[str]:
    return Path(log).read_text().splitlines() if os.path.exists(log) else []


def _requests(lines: list[str]) -> dict[str, int]:
    out = {"fc16": 0, "fc03": 0}
    for line in lines:
        out["fc16" if json.loads(line)["function"] == 16 else "fc03"] += 1
    return out


def _plan_file(work: str, recipe_path: str) -> str:
    """The registers a hand-written script would hard-code: per parameter and per contiguous block."""
    from deployer.planning.model import Target
    from deployer.planning.steps import make_plan
    from deployer.recipe.loader import load_recipe

    rec = load_recipe(recipe_path)
    plan = make_plan(rec, Target(None, 1, "x"), write_all=True)
    data = {
        "parameters": [[d.parameter.address, list(d.registers)] for d in rec.desired],
        "blocks": [[w.address, list(w.registers)] for w in plan.writes],
    }
    path = os.path.join(work, "plan.json")
    Path(path).write_text(json.dumps(data))
    return path


def _contenders(work: str, latency: float, rounds: int) -> dict[str, Any]:
    out: dict[str, Any] = {}
    script = os.path.join(work, "script.py")
    Path(script).write_text(SCRIPT)
    startup = min(timed([sys.executable, "-c", "pass"])[0] for _ in range(5))
    for name, gap in (("deployer", 0), ("deployer_gap_reads", 1), ("skilled", 0), ("naive", 0)):
        files = drive.write(os.path.join(work, name), N, max_read_gap=gap)
        log = os.path.join(work, f"{name}.log")
        walls, cpus, reqs = [], [], {}
        with device(files["profile"], latency, log, gap_reads=bool(gap)) as port:
            for r in range(rounds if name != "naive" or latency < 20 else 1):
                files = drive.write(os.path.join(work, name), N, max_read_gap=gap, salt=r + 1)
                if name.startswith("deployer"):
                    args = [
                        sys.executable,
                        "-m",
                        "deployer",
                        "apply",
                        files["recipe"],
                        "--device",
                        f"tcp://127.0.0.1:{port}",
                        "--yes",
                        "--state-dir",
                        os.path.join(work, "state"),
                    ]
                else:
                    args = [
                        sys.executable,
                        script,
                        "127.0.0.1",
                        str(port),
                        _plan_file(work, files["recipe"]),
                        "parameters" if name == "naive" else "blocks",
                    ]
                seen = len(_log_lines(log))
                wall, cpu, _rss, _ = timed(args)
                walls.append(wall)
                cpus.append(cpu)
                time.sleep(0.2)  # the simulator's log line for the last answer
                reqs = _requests(_log_lines(log)[seen:])
        requests = reqs["fc16"] + reqs["fc03"]
        floor = requests * latency / 1000
        out[name] = {
            "seconds": round(min(walls), 3),
            "median_seconds": round(statistics.median(walls), 3),
            "cpu_seconds": round(min(cpus), 3),
            "fc16": reqs["fc16"],
            "fc03": reqs["fc03"],
            "floor_seconds": round(floor, 3),
            "vs_floor_plus_startup": round(min(walls) / (floor + startup), 2),
        }
    out["python_startup_seconds"] = round(startup, 3)
    out["deployer_vs_naive"] = round(out["naive"]["seconds"] / out["deployer"]["seconds"], 1)
    out["deployer_vs_skilled"] = round(out["deployer"]["seconds"] / out["skilled"]["seconds"], 2)
    return out


async def _phases(work: str, port: int, salt: int) -> dict[str, float]:
    """The apply pipeline step by step with the library's calls, timed (wall) per phase, plus process CPU."""
    from deployer.cli.outcome import print_report
    from deployer.execute.session import Session
    from deployer.execute.verify import values_of
    from deployer.load import yamlsrc
    from deployer.planning.model import Target
    from deployer.planning.steps import make_plan
    from deployer.recipe.loader import load_recipe
    from deployer.report import DeviceResult, Report
    from deployer.state.snapshot import save_snapshot
    from deployer.transport.clients import open_transport, parse_url

    files = drive.write(os.path.join(work, "phases"), N, salt=salt)
    ph: dict[str, float] = {}
    cpu0 = time.process_time()
    t = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal t
        now = time.perf_counter()
        ph[name] = round(now - t, 4)
        t = now

    yamlsrc.load(files["recipe"])
    yamlsrc.load(files["profile"])
    lap("load")
    rec = load_recipe(files["recipe"])  # loads again, then schema, units, ranges: validate = this - load
    ph["validate"] = round(time.perf_counter() - t - ph["load"], 4)
    t = time.perf_counter()
    url = parse_url(f"tcp://127.0.0.1:{port}")
    target = Target("tcp://127.0.0.1", 1, "bench")
    offline = make_plan(rec, target)
    lap("plan")
    transport = open_transport(url)
    await transport.connect()
    res = DeviceResult("bench", "tcp://127.0.0.1", 1, "bench")
    session = Session(transport, 1, retries=0, backoff=0.01, records=res.requests)
    lap("connect")
    params = [d.parameter for d in rec.desired]
    before = values_of(params, await session.read_blocks(offline.reads, rec.profile))
    plan = make_plan(rec, target, before)
    save_snapshot(os.path.join(work, "state"), "bench", rec, before, "tcp://127.0.0.1", 1)
    lap("snapshot_read")
    for w in plan.writes:
        await session.write(w)
    lap("writes")
    after = values_of(params, await session.read_blocks(plan.reads, rec.profile))
    lap("read_back")
    await transport.close()
    assert all(after[d.name] == d.registers for d in rec.desired)
    from deployer.report import ParameterResult

    res.parameters = [
        ParameterResult(
            d.name, d.parameter.address, d.parameter.count, d.text, d.registers, before.get(d.name), after[d.name], "ok"
        )
        for d in rec.desired
    ]
    report = Report(files["recipe"], [res])
    json.dumps(report.to_json())
    from rich.console import Console

    print_report(report, Console(file=io.StringIO(), width=200))
    lap("report")
    ph["total"] = round(sum(v for k, v in ph.items()), 4)
    ph["cpu_seconds"] = round(time.process_time() - cpu0, 4)
    ph["cpu_ms_per_parameter"] = round(ph["cpu_seconds"] / N * 1000, 3)
    return ph


def run(quick: bool = False) -> dict[str, Any]:
    latencies = [5.0] if quick else [0.0, 5.0, 20.0]
    rounds = 2 if quick else 3
    out: dict[str, Any] = {"parameters": N}
    as_installed()
    with tempfile.TemporaryDirectory() as work:
        for lat in latencies:
            out[f"{lat:g}ms"] = _contenders(work, lat, rounds)
        files = drive.write(os.path.join(work, "phases"), N)
        with device(files["profile"], 0.0, os.path.join(work, "ph.log")) as port:
            runs = [asyncio.run(_phases(work, port, salt)) for salt in range(1, rounds + 2)]
        best = min(runs, key=lambda r: r["total"])
        out["phases_0ms"] = best
    return out


if __name__ == "__main__":
    print(json.dumps(run("--quick" in sys.argv), indent=2))
