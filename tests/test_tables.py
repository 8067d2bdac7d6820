"""Tables: plain aligned text off a terminal or beyond a screenful, every row printed."""

from __future__ import annotations

import io
import subprocess
import sys
from pathlib import Path

from rich.console import Console

from benchmarks import drive
from deployer.cli.tables import RICH_ROWS, plain, show


def test_plain_columns_are_aligned_like_rich() -> None:
    text = plain(["parameter", "value"], [["F07", "10 s"], ["preset[0].speed", ("ok", "green")]])
    assert text.splitlines() == [" parameter        value", " F07              10 s", " preset[0].speed  ok"]


def test_rich_only_on_a_terminal_and_for_a_screenful() -> None:
    rows: list[list[str | tuple[str, str]]] = [[f"p{i}", "[bold]x[/bold]"] for i in range(RICH_ROWS + 1)]
    buf = io.StringIO()
    show(Console(file=buf, force_terminal=True, width=80), ["name", "value"], rows)
    assert buf.getvalue() == plain(["name", "value"], rows)  # too many rows for rich; markup stays text
    buf = io.StringIO()
    show(Console(file=buf, force_terminal=True, width=80, color_system=None), ["name", "value"], rows[:3])
    assert "[bold]x[/bold]" in buf.getvalue()  # rich, but a value is never read as markup


def test_plan_of_5000_parameters_prints_every_row(tmp_path: Path) -> None:
    files = drive.write(str(tmp_path), 5000, wide_every=4)
    proc = subprocess.run(
        [sys.executable, "-m", "deployer", "plan", files["recipe"]], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert sum(1 for ln in lines if ln.startswith(" P0")) == 5000
    # its write is the first step after the 125 snapshot reads and the Function 43 request
    assert " P00001     0x0002 (2)     0004       0.4 Hz    127" in lines
