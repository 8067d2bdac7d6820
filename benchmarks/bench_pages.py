"""The run report as a page at fleet scale (issue #23): 1,000 devices x 100 parameters.

Measured: the page's size against the report JSON's (the file `--report` writes); the time to make
the page; and, where Chromium is installed, how long a browser takes to open it: the wall time of
headless Chromium loading the page and taking a screenshot of it (parsed, its script run, laid out,
painted), less the same for an empty page (the browser's own start); and the page script's own
clock, navigation start to its last table drawn (``data-ready``). The browser is the floor we cannot
go under. The targets: opened in 2 s or less, a page at most 1.1x the JSON.
"""

from __future__ import annotations

import os
import re
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

from deployer.pages import run_page
from deployer.profile import load_profile
from deployer.report import DeviceResult, ParameterResult, Report, RequestRecord, report_text, run_info

CHROMIUM = next((p for p in (shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome")) if p), None)


def _report(devices: int, parameters: int, folder: Path) -> Report:
    prof_file = folder / "drive.yaml"
    prof_file.write_text(
        "profile: drive\nparameters:\n"
        + "".join(
            f"  P{i:03d}: {{register: {100 + i}, type: uint16, unit: s, scale: 0.1, max: 6000}}\n"
            for i in range(parameters)
        )
    )
    prof = load_profile(str(prof_file))
    out = []
    for d in range(devices):
        res = DeviceResult(
            f"drive-{d:04d}",
            f"tcp://10.0.{d // 250}.{d % 250}:502",
            1,
            prof.id,
            profile_ref=str(prof_file),
            profile_sha256=prof.digest,
            batch=1 + d // 100,
            seconds=0.4 + (d % 7) / 10,
        )
        res.requests = [
            RequestRecord(3, 100, parameters),
            RequestRecord(16, 100, parameters),
            RequestRecord(3, 100, parameters),
        ]
        for i, p in enumerate(prof.parameters):
            failed = d % 97 == 0 and i == 5
            res.parameters.append(
                ParameterResult(
                    p.name,
                    p.address,
                    1,
                    f"{(i + d) % 600 / 10:g} s",
                    ((i + d) % 600,),
                    (i,),
                    (i,) if failed else ((i + d) % 600,),
                    "failed" if failed else "ok",
                    "exception 03 (illegal data value)" if failed else None,
                    parameter=p,
                )
            )
        res.settle()
        out.append(res)
    return Report("line.yaml", out, 412.0, run_info("deployer apply line.yaml --inventory line.yaml", time.time()))


def _browser_seconds(page: Path, folder: Path, runs: int) -> tuple[float, int | None]:
    assert CHROMIUM is not None
    times, ready = [], None
    flags = [
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--no-first-run",
        "--hide-scrollbars",
        f"--user-data-dir={folder / 'profile'}",
    ]
    for _ in range(runs):
        start = time.perf_counter()
        # a screenshot needs the page parsed, its script run, laid out and painted: what "opened" means
        subprocess.run(
            [CHROMIUM, *flags, f"--screenshot={folder / 'shot.png'}", "--window-size=1280,900", page.as_uri()],
            capture_output=True,
            timeout=300,
            check=True,
        )
        times.append(time.perf_counter() - start)
    if page.name != "blank.html":  # the page's own clock: navigation start to its last table drawn
        proc = subprocess.run(
            [CHROMIUM, *flags, "--dump-dom", page.as_uri()], capture_output=True, text=True, timeout=300
        )
        m = re.search(r'data-ready="(\d+)"', proc.stdout)
        ready = int(m.group(1)) if m else None
    return statistics.median(times), ready


def run(quick: bool = False) -> dict[str, Any]:
    devices = 100 if quick else 1000
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        report = _report(devices, 100, folder)
        json_bytes = len(report_text(report).encode())
        start = time.perf_counter()
        page_text = run_page(report)
        make = time.perf_counter() - start
        page = folder / "run.html"
        page.write_text(page_text, encoding="utf-8")
        res: dict[str, Any] = {
            "devices": devices,
            "parameters": 100,
            "json_mb": round(json_bytes / 1e6, 2),
            "page_mb": round(os.path.getsize(page) / 1e6, 2),
            "page_vs_json": round(os.path.getsize(page) / json_bytes, 3),
            "make_page_seconds": round(make, 3),
        }
        if CHROMIUM is not None:
            blank = folder / "blank.html"
            blank.write_text("<!DOCTYPE html><title>blank</title>")
            floor, _ = _browser_seconds(blank, folder, 3)
            wall, ready_ms = _browser_seconds(page, folder, 3)
            res.update(
                {
                    "browser_blank_seconds": round(floor, 3),
                    "browser_page_seconds": round(wall, 3),
                    "load_seconds": round(wall - floor, 3),
                    "script_ready_seconds": None if ready_ms is None else ready_ms / 1000,
                }
            )
        else:
            res["browser"] = "not measured: no Chromium"
        out[str(devices)] = res
    return out
