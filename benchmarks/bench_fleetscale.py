"""Fleets at scale (issue #30): 1,000 / 4,000 / 10,000 devices x 100 parameters, and deployer side by side
with a bare pymodbus client.

The devices are the light farm (benchmarks/light_devices.py) in two processes of their own, so the
device side costs less CPU than deployer does. Every deployer run is the real command line,
``deployer apply RECIPE --inventory INV --yes --parallel P --report FILE``, started as a child and
measured from outside (benchmarks/child.py): wall time, CPU time, peak RSS, bytes written to disk;
the report's ``summary.seconds`` is its fleet phase (without start-up, loading and the final table).
Every run writes new values (the recipe alternates), so each device really is written and verified.

Each size runs twice: as the command line runs it by default (one worker process per CPU, forked on Linux,
``deployer.fleet.workers``) and with ``--workers 0`` (every device in the command's process). CPU time and
peak memory are the command's and its workers' together (the launcher's ``wait4`` counts the workers it
waited for; the resident memory of the process tree is summed, which counts the pages a forked worker still
shares with the command once in each: ``peak_rss_mb``; ``peak_pss_mb`` sums the proportional set size,
which counts a shared page once in all: the memory the run really takes).

Side by side: the bare client (benchmarks/bare_fleet.py, its own process) sends each device the
requests deployer sent one device of the run before it, with the same ``--parallel``, on the same
devices; deployer (default and one process) and the bare client alternate, ``repeats`` times, each in
turn the first of a round (a run measured right after another one's moved by up to a fifth), and the
best of each is compared (the machine is shared: a ratio from one run side by side is what is worth
anything). ``cpu_ratio`` is deployer's CPU over the bare client's for the same devices. The system CPU of
every run is listed too: the kernel's work on deployer's files (locks, snapshots and their log, journal,
report) is where a regression of the files shows first. Every run must write every device: a run that found
the values in place (another ``Bench`` wrote the same recipe just before) would measure no snapshot, no
journal and no write, and fails the benchmark (RESULTS.md, run I: such runs were once taken for a fast machine).

    python -m benchmarks.bench_fleetscale [--quick] [--sizes 1000,4000] [--repeats 2] [--no-side-by-side]
                                          [--before OLD-CHECKOUT]

``--before``: the scale runs alternate with the deployer package of another checkout (e.g. ``git worktree
add /tmp/old 679ca76``), on the same devices, for a before/after measured in one run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from benchmarks.bench_apply import as_installed
from benchmarks.bench_fleet import _profile, _recipe
from benchmarks.child import measured_all

PARAMETERS = 100
SIZES = (1000, 4000, 10000)
SIDE_BY_SIDE = ((20, 1000, (32, 128, 256)), (0, 2000, (32, 128, 256)))  # latency ms, devices, --parallel
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@contextmanager
def farm(
    devices: int, latency_ms: float, processes: int = 2, cost: dict[str, Any] | None = None
) -> Iterator[list[str]]:
    """The light farm's device URLs while it serves; ``cost`` gets its CPU per request when it ends."""
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "benchmarks.light_devices",
            str(devices),
            str(latency_ms),
            "--processes",
            str(processes),
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        assert proc.stdout is not None
        yield json.loads(proc.stdout.readline())
    finally:
        assert proc.stdin is not None and proc.stdout is not None
        proc.stdin.close()
        try:
            served = json.loads(proc.stdout.readline() or "{}")
            proc.wait(timeout=120)
        except subprocess.TimeoutExpired:
            proc.kill()
        else:
            if cost is not None and served.get("requests"):
                cost.update(
                    {
                        "requests": served["requests"],
                        "us_per_request": round(served["cpu"] / served["requests"] * 1e6, 1),
                    }
                )


class Bench:
    def __init__(self, work: str) -> None:
        self.work = work
        self.variant = 0
        self.deployer = os.path.join(os.path.dirname(sys.executable), "deployer")
        with open(os.path.join(work, "profile.yaml"), "w") as f:
            f.write(_profile(PARAMETERS))
        self.requests: list[list[int]] = []  # what deployer sent one device, for the bare client

    def inventory(self, urls: list[str]) -> str:
        path = os.path.join(self.work, f"inventory-{len(urls)}-{abs(hash(urls[0]))}.yaml")
        if not os.path.exists(path):
            with open(path, "w") as f:
                f.write("defaults: {timeout: 5.0, retries: 1}\ndevices:\n")
                f.writelines(f"  dev{i:05d}: {{url: '{u}'}}\n" for i, u in enumerate(urls))
        return path

    def apply(
        self, urls: list[str], parallel: int, report: bool = True, src: str | None = None, workers: int | None = None
    ) -> dict[str, Any]:
        """One ``deployer apply`` of ``urls``; ``src``: run the deployer package found in that folder (an older
        checkout, measured side by side) instead of this one; ``workers``: its ``--workers`` (None: the command
        line's default: forked workers, one per CPU, from 100 devices on Linux). Its device locks go to the
        benchmark's own folder: the machine's lock folder keeps a file per device ever written, which would
        carry one run's devices into the next benchmark's figures."""
        self.variant += 1
        recipe = os.path.join(self.work, f"recipe{self.variant % 2}.yaml")
        with open(recipe, "w") as f:
            f.write(_recipe(PARAMETERS, self.variant % 2 + 1))
        path = os.path.join(self.work, f"report-{self.variant}.json")
        cmd = [
            self.deployer,
            "apply",
            recipe,
            "--inventory",
            self.inventory(urls),
            "--yes",
            "--parallel",
            str(parallel),
            "--state-dir",
            os.path.join(self.work, "state"),
        ]
        if workers is not None:
            cmd += ["--workers", str(workers)]
        env = {**os.environ, "DEPLOYER_LOCK_DIR": os.path.join(self.work, "locks")}
        if src is not None:
            env["PYTHONPATH"] = src
        _settle()
        m, err = measured_all(cmd + (["--report", path] if report else []), self.work, env=env)
        common = {
            "wall": m["wall"],
            "cpu": m["cpu"],
            "sys": m.get("sys", 0.0),
            "rss_mb": m.get("tree_rss_kb", m["maxrss_kb"]) / 1024,
            "pss_mb": m.get("tree_pss_kb", 0) / 1024,
            "written": m["written_bytes"],
        }
        if not report:
            assert m["code"] == 0, err[-2000:]
            return common
        with open(path) as f:
            doc = json.load(f)
        summary = doc["summary"]
        assert m["code"] == 0 and summary["ok"] == len(urls), (m, summary, err[-2000:])
        # each device written: a run that found its values in place took no snapshot and sent no write
        assert summary["write_requests"] >= len(urls), ("a run that wrote nothing", summary)
        self.requests = [[r["function"], r["address"], r["count"]] for r in doc["devices"][0]["requests"]]
        size = os.path.getsize(path)
        del doc
        os.remove(path)
        return {
            **common,
            "fleet": summary["seconds"],
            "report_bytes": size,
            "requests": summary["write_requests"] + summary["read_requests"],
        }

    def bare(self, urls: list[str], parallel: int) -> dict[str, Any]:
        spec = os.path.join(self.work, "bare.json")
        out = os.path.join(self.work, "bare-out.json")
        with open(spec, "w") as f:
            json.dump({"urls": urls, "parallel": parallel, "requests": self.requests, "out": out}, f)
        _settle()
        m, err = measured_all([sys.executable, "-m", "benchmarks.bare_fleet", spec], ROOT)
        assert m["code"] == 0, err[-2000:]
        with open(out) as f:
            seconds = json.load(f)["seconds"]
        return {"wall": m["wall"], "cpu": m["cpu"], "sys": m.get("sys", 0.0), "fleet": seconds}


def _time_wait() -> int:
    """Sockets in TIME_WAIT on this machine (Linux; 0 elsewhere)."""
    try:
        with open("/proc/net/sockstat") as f:
            for line in f:
                if line.startswith("TCP:"):
                    fields = line.split()
                    return int(fields[fields.index("tw") + 1])
    except (OSError, ValueError, IndexError):
        pass
    return 0


def _settle(most: float = 70.0) -> None:
    """Before a measured run: the last run's dirty pages written out, and its closed connections gone from
    TIME_WAIT (a run leaves one per device for a minute; 20,000 of them made the next run's connects search
    the port range: a second 10,000-device run took 10-20% longer than the first)."""
    os.sync()
    until = time.monotonic() + most
    while _time_wait() > 5000 and time.monotonic() < until:
        time.sleep(1)


def request_cost(url: str, n: int = 2000, rounds: int = 3) -> dict[str, Any]:
    """CPU per request in this process: deployer's transport and session (``Session.read``, as a fleet's
    device sends it) against a bare pymodbus client, FC03 of 60 registers, one device of the light farm
    answering at once; alternating rounds, the best of each."""
    import asyncio

    from pymodbus.client import AsyncModbusTcpClient

    from deployer.execute.session import Session
    from deployer.transport.clients import open_transport, parse_url

    host, port = url.split("//", 1)[1].rsplit(":", 1)

    async def ours() -> float:
        t = open_transport(parse_url(url))
        await t.connect()
        session = Session(t, 1, retries=1, backoff=0.05, records=[])
        c = time.process_time()
        for _ in range(n):
            session.records.clear()
            await session.read(0, 60)
        c = time.process_time() - c
        await t.close()
        return c

    async def bare() -> float:
        client = AsyncModbusTcpClient(host, port=int(port), retries=0, timeout=3)
        await client.connect()
        c = time.process_time()
        for _ in range(n):
            r = await client.read_holding_registers(0, count=60, device_id=1)
            assert not r.isError()
        c = time.process_time() - c
        client.close()
        return c

    a, b = [], []
    for _ in range(rounds):
        a.append(asyncio.run(ours()))
        b.append(asyncio.run(bare()))
    return {
        "deployer_us_per_request": round(min(a) / n * 1e6, 1),
        "bare_us_per_request": round(min(b) / n * 1e6, 1),
        "ratio": round(min(a) / min(b), 2),
    }


def _turns(kinds: list[str], repeats: int) -> Iterator[str]:
    """``repeats`` rounds of every kind, each kind in turn the first of its round: a run measured right after
    another one's moved by up to a fifth, so no kind always comes first or last."""
    for i in range(repeats):
        for k in range(len(kinds)):
            yield kinds[(i + k) % len(kinds)]


def _row(m: dict[str, Any], n: int) -> dict[str, Any]:
    """One run's figures; CPU and peak memory are the command's and its worker processes' together."""
    row = {
        "wall_seconds": round(m["wall"], 2),
        "cpu_ms_per_device": round(m["cpu"] * 1000 / n, 2),
        "system_cpu_ms_per_device": round(m["sys"] * 1000 / n, 2),
        "peak_rss_mb": round(m["rss_mb"], 1),
        "peak_pss_mb": round(m["pss_mb"], 1),
        "written_mb": round(m["written"] / 1e6, 1),
    }
    if "fleet" in m:
        row.update(
            {
                "fleet_seconds": round(m["fleet"], 2),
                "report_mb": round(m["report_bytes"] / 1e6, 1),
                "report_bytes_per_device": round(m["report_bytes"] / n),
                "requests_per_device": round(m["requests"] / n, 1),
            }
        )
    return row


def run(
    quick: bool = False,
    sizes: tuple[int, ...] | None = None,
    repeats: int | None = None,
    side_by_side: bool = True,
    before: str | None = None,
) -> dict[str, Any]:
    sizes = sizes or ((10,) if quick else SIZES)
    repeats = repeats or (1 if quick else 2)
    pairs = ((20, 10, (4,)), (0, 10, (4,))) if quick else SIDE_BY_SIDE
    as_installed()
    if before:  # compiled as this one is: else its processes would compile it, and the figures favour this one
        as_installed(before)
    out: dict[str, Any] = {"parameters": PARAMETERS}
    with tempfile.TemporaryDirectory(prefix="bench-fleetscale-") as work:
        b = Bench(work)
        start = measured_all([b.deployer, "--version"], work)[0]
        out["version_seconds"] = round(start["wall"], 3)
        with farm(1, 0, processes=1) as single:
            out["request_cpu"] = request_cost(single[0], 200 if quick else 2000)
        if side_by_side:
            for latency, n, parallels in pairs:
                with farm(n, latency, cost=out.setdefault(f"farm_{latency}ms", {})) as urls:
                    b.apply(urls[:10], 4)  # warm: the first run of a fresh state folder; not measured
                    for p in parallels:
                        got: dict[str, list[dict[str, Any]]] = {"ours": [], "one": [], "bare": []}
                        for kind in _turns(list(got), repeats):  # the machine's load falls on all three alike
                            got[kind].append(
                                b.bare(urls, p)
                                if kind == "bare"
                                else b.apply(urls, p, workers=0 if kind == "one" else None)
                            )
                        ours, one, bare = got["ours"], got["one"], got["bare"]
                        best = min(ours, key=lambda m: m["fleet"])
                        alone = min(one, key=lambda m: m["fleet"])
                        fastest = min(bare, key=lambda m: m["fleet"])
                        out[f"side_{latency}ms_{n}_parallel_{p}"] = {
                            "deployer_fleet_seconds": [round(m["fleet"], 3) for m in ours],
                            "one_process_fleet_seconds": [round(m["fleet"], 3) for m in one],
                            "bare_seconds": [round(m["fleet"], 3) for m in bare],
                            "ratio": round(best["fleet"] / fastest["fleet"], 2),
                            "ratios_per_pair": [
                                round(a["fleet"] / c["fleet"], 2) for a, c in zip(ours, bare, strict=True)
                            ],
                            "one_process_ratio": round(alone["fleet"] / fastest["fleet"], 2),
                            "deployer_cpu_ms_per_device": round(best["cpu"] * 1000 / n, 2),
                            "one_process_cpu_ms_per_device": round(alone["cpu"] * 1000 / n, 2),
                            "bare_cpu_ms_per_device": round(fastest["cpu"] * 1000 / n, 2),
                            "cpu_ratio": round(min(m["cpu"] for m in ours) / min(m["cpu"] for m in bare), 2),
                            # each run's, in the order of its fleet seconds: the kernel's work on the files
                            "deployer_system_cpu_ms_per_device": [round(m["sys"] * 1000 / n, 2) for m in ours],
                            "bare_system_cpu_ms_per_device": [round(m["sys"] * 1000 / n, 2) for m in bare],
                        }
        with farm(max(sizes), 20, cost=out.setdefault("farm_scale", {})) as urls:
            b.apply(urls[:10], 4)
            for n in sizes:
                scaled: dict[str, list[dict[str, Any]]] = {"runs": [], "one": []}
                if before:  # the older checkout, alternating with this one on the same devices
                    scaled["old"] = []
                for kind in _turns(list(scaled), repeats):
                    scaled[kind].append(
                        b.apply(
                            urls[:n], 256, workers=0 if kind == "one" else None, src=before if kind == "old" else None
                        )
                    )
                runs, one, old = scaled["runs"], scaled["one"], scaled.get("old", [])
                best = min(runs, key=lambda m: m["wall"])
                out[f"scale_{n}"] = {
                    **_row(best, n),
                    "walls": [round(m["wall"], 2) for m in runs],
                    "cpu_ms_per_device_each": [round(m["cpu"] * 1000 / n, 2) for m in runs],
                    "start_and_end_seconds": round(best["wall"] - best["fleet"], 2),
                }
                alone = min(one, key=lambda m: m["wall"])
                out[f"scale_{n}_one_process"] = {**_row(alone, n), "walls": [round(m["wall"], 2) for m in one]}
                if old:
                    first = min(old, key=lambda m: m["wall"])
                    out[f"scale_{n}_before"] = {
                        **_row(first, n),
                        "walls": [round(m["wall"], 2) for m in old],
                        "cpu_ms_per_device_each": [round(m["cpu"] * 1000 / n, 2) for m in old],
                    }
            n = max(sizes)
            out[f"scale_{n}_no_report"] = _row(b.apply(urls[:n], 256, report=False), n)
        if len(sizes) > 1:  # what each further device adds to the peak (the run's fixed memory taken out);
            # the two largest sizes, which run alike (a small fleet runs in one process: see auto_count)
            lo, hi = sorted(sizes)[-2:]
            for key in ("", "_one_process"):
                grow = out[f"scale_{hi}{key}"]["peak_rss_mb"] - out[f"scale_{lo}{key}"]["peak_rss_mb"]
                out[f"kb_per_device{key}"] = round(grow * 1024 / (hi - lo), 2)
                grow = out[f"scale_{hi}{key}"]["peak_pss_mb"] - out[f"scale_{lo}{key}"]["peak_pss_mb"]
                out[f"kb_per_device_pss{key}"] = round(grow * 1024 / (hi - lo), 2)
    return out


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--sizes", default=None)
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--no-side-by-side", action="store_true")
    ap.add_argument("--before", metavar="DIR", help="also run the deployer package of this checkout (side by side)")
    a = ap.parse_args()
    print(
        json.dumps(
            run(
                a.quick,
                tuple(int(x) for x in a.sizes.split(",")) if a.sizes else None,
                a.repeats,
                not a.no_side_by_side,
                a.before,
            ),
            indent=2,
        )
    )
