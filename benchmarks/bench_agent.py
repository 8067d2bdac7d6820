"""The site agent watching 1,000 devices at --check-every 10s: its CPU and memory (issue 32).

The devices run in another process (benchmarks/fleet_devices.py, one port each, answering at once);
the agent is the real command (`deployer agent INVENTORY --check-every 10s`) in a child process. After
it is ready and its first round is done, its CPU time (utime + stime from /proc/PID/stat) and resident
memory (VmRSS, peak VmHWM) are sampled over a whole number of rounds; the agent's own /v1/agent says
how many rounds it completed and how long the last one took.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
import time
import urllib.request
from typing import Any

DEVICES = 1000
PARAMETERS = 10
CHECK_EVERY = 10.0
ROUNDS = 6


def _profile(n: int) -> str:
    lines = ["profile: bench-agent-drive", "parameters:"]
    lines += [
        f"  p{i}: {{register: {i}, type: uint16, unit: s, scale: 0.1, min: 0, max: 600, default: 1}}" for i in range(n)
    ]
    return "\n".join(lines) + "\n"


def _cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat", encoding="ascii") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _memory_mb(pid: int) -> tuple[float, float]:
    with open(f"/proc/{pid}/status", encoding="ascii") as f:
        text = f.read()
    rss = int(re.search(r"VmRSS:\s+(\d+)", text).group(1))  # type: ignore[union-attr]
    hwm = int(re.search(r"VmHWM:\s+(\d+)", text).group(1))  # type: ignore[union-attr]
    return rss / 1024, hwm / 1024


def _agent(url: str, token: str) -> dict[str, Any]:
    req = urllib.request.Request(url + "/v1/agent", headers={"Authorization": f"Bearer {token}"})
    with urllib.request.urlopen(req, timeout=30) as r:
        return dict(json.loads(r.read()))


def run(quick: bool = False) -> dict[str, Any]:
    devices = 100 if quick else DEVICES
    rounds = 2 if quick else ROUNDS
    every = 2.0 if quick else CHECK_EVERY
    work = tempfile.mkdtemp(prefix="bench-agent-")
    with open(os.path.join(work, "drive.yaml"), "w") as f:
        f.write(_profile(PARAMETERS))
    with open(os.path.join(work, "r.yaml"), "w") as f:
        f.write(
            "recipe: bench\nprofile: drive.yaml\nparameters:\n" + "".join(f"  p{i}: 0.1 s\n" for i in range(PARAMETERS))
        )
    server = subprocess.Popen(
        [sys.executable, "-m", "benchmarks.fleet_devices", os.path.join(work, "drive.yaml"), str(devices), "0"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    agent = None
    try:
        assert server.stdout is not None
        urls = json.loads(server.stdout.readline())
        with open(os.path.join(work, "inv.yaml"), "w") as f:
            f.write("devices:\n" + "".join(f'  d{i}: {{url: "{u}", recipe: r.yaml}}\n' for i, u in enumerate(urls)))
        env = {**os.environ, "DEPLOYER_LOCK_DIR": os.path.join(work, "locks")}
        agent = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "deployer",
                "agent",
                os.path.join(work, "inv.yaml"),
                "--state-dir",
                os.path.join(work, "state"),
                "--listen",
                "127.0.0.1:0",
                "--check-every",
                f"{every}s",
            ],
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        assert agent.stderr is not None
        started = time.monotonic()
        url = ""
        for line in agent.stderr:
            m = re.match(r"listening on (http://\S+)", line)
            if m:
                url = m.group(1)
                break
        ready = time.monotonic() - started
        with open(os.path.join(work, "state", "agent", "token"), encoding="utf-8") as f:  # the one it made itself
            token = f.readline().strip()
        # the device logs go to stderr (one line per event): drain them so the agent never blocks on the pipe
        import threading

        threading.Thread(target=lambda: [None for _ in agent.stderr], daemon=True).start()  # type: ignore[union-attr]
        while _agent(url, token)["checks"] < 1:
            time.sleep(0.2)
        first = _agent(url, token)["last_check_seconds"]
        cpu0, t0 = _cpu_seconds(agent.pid), time.monotonic()
        time.sleep(rounds * every)
        cpu1, t1 = _cpu_seconds(agent.pid), time.monotonic()
        rss, hwm = _memory_mb(agent.pid)
        info = _agent(url, token)
        return {
            "devices": devices,
            "parameters": PARAMETERS,
            "check_every_seconds": every,
            "ready_seconds": round(ready, 2),
            "first_round_seconds": round(first, 2),
            "last_round_seconds": round(info["last_check_seconds"], 2),
            "rounds_measured": rounds,
            "cpu_percent_of_one_core": round(100 * (cpu1 - cpu0) / (t1 - t0), 1),
            "cpu_ms_per_device_check": round(1000 * (cpu1 - cpu0) / (devices * (t1 - t0) / every), 2),
            "rss_mb": round(rss, 1),
            "peak_rss_mb": round(hwm, 1),
            "rss_kb_per_device": round(rss * 1024 / devices, 1),
        }
    finally:
        if agent is not None:
            agent.terminate()
            agent.wait(timeout=120)
        assert server.stdin is not None
        server.stdin.close()
        server.wait(timeout=120)


if __name__ == "__main__":
    print(json.dumps(run("--quick" in sys.argv), indent=2))
