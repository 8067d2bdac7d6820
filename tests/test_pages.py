"""The HTML pages, opened by a real browser: headless Chromium loads pages made from real runs
against simulators (file:// URLs, no network) and the tests read the DOM its script built.

Chromium is the Debian package (CI installs it beside socat and mbpoll); without it these skip.
"""

from __future__ import annotations

import html.parser
import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from deployer.profile import builtin_profile
from deployer.testing.simulator import Faults, Simulator
from tests.conftest import dead_port
from tests.helpers import Simulators, cli

PROFILE = builtin_profile("example-inverter")
F08 = PROFILE.parameter("F08").address
RECIPE = "recipe: line\nprofile: example-inverter\nparameters:\n  F07: 10 s\n  F08: 12 s\n  stop_mode: coast\n"
CHROMIUM = next((p for p in (shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome")) if p), None)

pytestmark = [
    pytest.mark.timeout(300),
    pytest.mark.skipif(CHROMIUM is None, reason="no Chromium (CI installs it: apt-get install chromium)"),
]


def browser(*args: str, tmp: Path) -> subprocess.CompletedProcess[str]:
    assert CHROMIUM is not None
    return subprocess.run(
        [
            CHROMIUM,
            "--headless=new",
            "--no-sandbox",
            "--disable-gpu",
            "--no-first-run",
            f"--user-data-dir={tmp / 'chromium-profile'}",
            "--virtual-time-budget=10000",
            *args,
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )


def dom(page: Path, tmp: Path, fragment: str = "") -> str:
    """The page's DOM after its script ran, as Chromium serialises it."""
    proc = browser("--dump-dom", page.as_uri() + (f"#{fragment}" if fragment else ""), tmp=tmp)
    assert proc.returncode == 0, proc.stderr
    assert 'data-ready="' in proc.stdout, "the page's script did not finish"
    return proc.stdout


class Elements(html.parser.HTMLParser):
    """Elements by tag with their attributes and text (enough to read the tables the script built)."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.found: list[dict[str, object]] = []
        self._open: list[dict[str, object]] = []
        self.feed(text)

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        el: dict[str, object] = {"tag": tag, **{k: v or "" for k, v in attrs}, "text": "", "cells": []}
        self.found.append(el)
        row = next((o for o in reversed(self._open) if o["tag"] == "tr"), None)
        if tag in ("td", "th") and row is not None:
            cells = row["cells"]
            assert isinstance(cells, list)
            cells.append("")
        if tag not in ("input", "meta", "br", "img", "link"):
            self._open.append(el)

    def handle_endtag(self, tag: str) -> None:
        for i in range(len(self._open) - 1, -1, -1):
            if self._open[i]["tag"] == tag:
                del self._open[i:]
                break

    def handle_data(self, data: str) -> None:
        for el in self._open:
            el["text"] = str(el["text"]) + data
        row = next((o for o in reversed(self._open) if o["tag"] == "tr"), None)
        if row is not None and row["cells"]:
            cells = row["cells"]
            assert isinstance(cells, list)
            cells[-1] += data

    def all(self, tag: str, cls: str | None = None) -> list[dict[str, object]]:
        return [e for e in self.found if e["tag"] == tag and (cls is None or cls in str(e.get("class", "")).split())]


def visible_rows(doc: Elements) -> list[str]:
    """The device table's rows that show: their cells' texts joined by spaces."""
    return [
        " ".join(r["cells"])  # type: ignore[arg-type]
        for r in doc.all("tr", "dev")
        if "hidden" not in str(r.get("class", ""))
    ]


def fleet_files(tmp: Path, sims: list[Simulator], down_port: int) -> tuple[Path, Path]:
    rec = tmp / "line.yaml"
    rec.write_text(RECIPE)
    inv = tmp / "inventory.yaml"
    names = [f"press-{i}" for i in range(len(sims))]
    inv.write_text(
        "defaults: {timeout: 0.5, retries: 0}\ndevices:\n"
        + "".join(f"  {n}: {{url: '{s.url}'}}\n" for n, s in zip(names, sims, strict=True))
        + f"  press-down: {{url: 'tcp://127.0.0.1:{down_port}'}}\n"
    )
    return rec, inv


def test_a_fleet_run_as_a_page_failures_first_counts_filters(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    faults = [Faults(), Faults(), Faults(fail_registers=frozenset({F08})), Faults()]
    with Simulators([Simulator(PROFILE, faults=f) for f in faults]) as sims:
        rec, inv = fleet_files(tmp_path, sims, dead_port())
        page, report = tmp_path / "run.html", tmp_path / "run.json"
        code = cli(
            capsys,
            "apply",
            str(rec),
            "--inventory",
            str(inv),
            "--yes",
            "--batch",
            "1,100%",
            "--state-dir",
            str(tmp_path / "st"),
            "--report",
            str(report),
            "--html",
            str(page),
        )[0]
        assert code == 4
    text = page.read_text()
    assert "http://" not in text and "https://" not in text  # nothing to fetch: opens offline, from file://

    doc = Elements(dom(page, tmp_path))
    rows = visible_rows(doc)
    assert len(rows) == 5
    assert rows[0].startswith("press-2") and "partial" in rows[0]  # failures first
    assert rows[1].startswith("press-down") and "unreachable" in rows[1]
    counts = {str(b["data-status"]): str(b["text"]) for b in doc.all("button", "count")}
    assert counts == {"partial": "1partial", "unreachable": "1unreachable", "ok": "3ok"}
    # the device that needs a look is open, its parameters drawn: F08 failed with the device's exception
    opened = [d for d in doc.all("details", "device") if "open" in d]
    assert [str(d["text"]).split()[0] for d in opened] == ["press-2", "press-down"]
    assert "F08" in str(opened[0]["text"]) and "exception 04" in str(opened[0]["text"])
    assert "5 s" in str(opened[0]["text"]) and "10 s" in str(opened[0]["text"])  # as found, as left: units
    meta = " ".join(str(d["text"]) for d in doc.all("dd"))
    assert "deployer apply" in meta and "--html" in meta and "example-inverter" in meta
    batches = [o["text"] for o in doc.all("option") if o["text"] in ("1", "2")]
    assert batches == ["1", "2"]

    # filters: by status (a link carries it), by name, by batch
    assert [r.split()[0] for r in visible_rows(Elements(dom(page, tmp_path, "status=partial")))] == ["press-2"]
    assert [r.split()[0] for r in visible_rows(Elements(dom(page, tmp_path, "q=press-1")))] == ["press-1"]
    assert [r.split()[0] for r in visible_rows(Elements(dom(page, tmp_path, "batch=1")))] == ["press-0"]
    assert len(visible_rows(Elements(dom(page, tmp_path, "bad=1")))) == 2

    # the same run from its report file: deployer report, text and page
    code, out, _ = cli(capsys, "report", str(report), "--html", str(tmp_path / "again.html"))
    assert code == 0 and "press-2" in out and "F08" in out and "5 devices: 3 ok" in out
    again = Elements(dom(tmp_path / "again.html", tmp_path))
    assert visible_rows(again) == rows

    shot = tmp_path / "run.png"
    proc = browser(f"--screenshot={shot}", "--window-size=1280,900", page.as_uri(), tmp=tmp_path)
    assert proc.returncode == 0 and shot.stat().st_size > 10_000


def test_the_page_prints_as_the_commissioning_record(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    with Simulators([Simulator(PROFILE) for _ in range(2)]) as sims:
        rec, inv = fleet_files(tmp_path, sims, dead_port())
        inv.write_text("\n".join(inv.read_text().splitlines()[:-1]) + "\n")  # both devices answer
        page = tmp_path / "run.html"
        assert (
            cli(
                capsys,
                "apply",
                str(rec),
                "--inventory",
                str(inv),
                "--yes",
                "--state-dir",
                str(tmp_path / "st"),
                "--html",
                str(page),
            )[0]
            == 0
        )
    pdf = tmp_path / "record.pdf"
    proc = browser(f"--print-to-pdf={pdf}", "--no-pdf-header-footer", page.as_uri(), tmp=tmp_path)
    assert proc.returncode == 0 and pdf.read_bytes().startswith(b"%PDF")
    if shutil.which("pdftotext"):  # poppler-utils: read the printed words back
        words = subprocess.run(["pdftotext", "-layout", str(pdf), "-"], capture_output=True, text=True).stdout
        assert "press-0" in words and "press-1" in words and words.count("Commissioned by") == 1  # one sign-off
        assert "as found" in words and "as left" in words and "filter devices" not in words


def test_pull_writes_the_as_found_record(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    with Simulators([Simulator(PROFILE) for _ in range(2)]) as sims:
        _, inv = fleet_files(tmp_path, sims, dead_port())
        page = tmp_path / "found.html"
        code = cli(
            capsys,
            "pull",
            "--inventory",
            str(inv),
            "--profile",
            "example-inverter",
            "-o",
            str(tmp_path / "pulled"),
            "--html",
            str(page),
        )[0]
        assert code == 3  # press-down does not answer
    doc = Elements(dom(page, tmp_path))
    assert [r.split()[0] for r in visible_rows(doc)] == ["press-down", "press-0", "press-1"]
    sections = {str(d["text"]).split()[0]: str(d["text"]) for d in doc.all("details", "device")}
    assert "F07" in sections["press-0"] and "5 s" in sections["press-0"] and "500" in sections["press-0"]
    assert "as found" in dom(page, tmp_path)


def test_drift_matrix_page(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    with Simulators([Simulator(PROFILE) for _ in range(3)]) as sims:
        rec, inv = fleet_files(tmp_path, sims, dead_port())
        inv.write_text("\n".join(inv.read_text().splitlines()[:-1]) + "\n")
        assert (
            cli(capsys, "apply", str(rec), "--inventory", str(inv), "--yes", "--state-dir", str(tmp_path / "st"))[0]
            == 0
        )
        sims[1].write("F07", (0, 700))  # someone changed press-1 at its panel
        page = tmp_path / "drift.html"
        code = cli(capsys, "diff", str(rec), "--inventory", str(inv), "--html", str(page))[0]
        assert code == 2
    doc = Elements(dom(page, tmp_path))
    drift = doc.all("td", "drift")
    assert len(drift) == 1 and drift[0]["text"] == "7 s → 10 s"
    assert [
        r["cells"][0]  # type: ignore[index]
        for r in doc.all("tr")
        if "hidden" not in str(r.get("class", "")) and r.get("data-i") is not None
    ] == ["F07"]  # drifted only
    everything = Elements(dom(page, tmp_path)).all("tr")
    assert len([r for r in everything if r.get("data-i") is not None]) == 3


def test_hostile_names_and_an_old_report(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """Names and values are text, never markup; a report of an older version shows what it has."""
    old = {
        "schema": "deployer.report/1",
        "recipe": "line3.yaml",
        "devices": [
            {
                "name": "<script>document.title='owned'</script>",
                "url": "tcp://10.0.0.11:502",
                "unit": 1,
                "profile": "example-inverter",
                "status": "partial",
                "snapshot": None,
                "requests": [],
                "parameters": [
                    {
                        "name": "F07",
                        "address": 4354,
                        "count": 2,
                        "desired": "10 s </script><b>x",
                        "desired_raw": [0, 1000],
                        "before_raw": [0, 500],
                        "after_raw": [0, 500],
                        "status": "failed",
                        "error": "exception 03 (illegal data value)",
                    }
                ],
            }
        ],
        "summary": {
            "devices": 1,
            "ok": 0,
            "partial": 1,
            "failed": 0,
            "unreachable": 0,
            "write_requests": 1,
            "read_requests": 2,
            "seconds": 0.2,
        },
    }
    report = tmp_path / "old.json"
    report.write_text(json.dumps(old))
    page = tmp_path / "old.html"
    code, out, _ = cli(capsys, "report", str(report), "--html", str(page))
    assert code == 0 and "F07" in out
    text = dom(page, tmp_path)
    doc = Elements(text)
    assert "owned" not in str(doc.all("title")[0]["text"])
    assert not [s for s in doc.all("script") if "owned" in str(s["text"]) and not s.get("type")]
    assert "<script>document.title" in str(doc.all("details", "device")[0]["text"])
    assert "5 s" in str(doc.all("details", "device")[0]["text"])  # units from the profile, which still loads


def test_report_refuses_what_is_not_a_report(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    bad = tmp_path / "x.json"
    bad.write_text('{"hello": 1}')
    code, _, err = cli(capsys, "report", str(bad))
    assert code == 1 and "not a deployer report" in err
    code, _, err = cli(capsys, "report", str(tmp_path / "missing.json"))
    assert code == 1 and "missing.json" in err and "Traceback" not in err
    assert os.listdir(tmp_path) == ["x.json"]
