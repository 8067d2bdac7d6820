"""Hostile text on the terminal and the page (issue #28, items 10 and 13): a recipe named ``[/red]``,
an escape sequence in a label, a bidi override in a value, ``<!--<script>`` in a string register.

The real commands run against a simulator; what they print is checked character by character: no
markup is parsed, nothing a terminal acts on goes out raw, no name starts a line of its own.
"""

from __future__ import annotations

import json
import re
import sys
import unicodedata
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from deployer.load.messages import printable
from deployer.profile import load_profile
from deployer.state import journal
from deployer.testing.simulator import SimulatorThread
from tests.helpers import cli as run_cli

ESC = "\x1b"
FAKE = f"{ESC}[2K{ESC}[1Afake: ok"  # erase the line, go up one: a name that prints a line of its own
RECIPE_NAME = f"[/red]{FAKE}\u202e"
LABEL = f"[bold]{FAKE}"
PROFILE = (
    "profile: hostile\n"
    "parameters:\n"
    '  mode: {register: 1, type: uint16, values: {off: 0, "<!--<script>": 1, "'
    + LABEL.replace(ESC, "\\e")
    + '": 2, "x\\u202eko": 3}}\n'
    "  label: {register: 10, type: string, count: 32}\n"
)


def recipe_text(mode: str, label: str) -> str:
    return (
        f"recipe: {json.dumps(RECIPE_NAME)}\nprofile: prof.yaml\nparameters:\n"
        f"  mode: {json.dumps(mode)}\n  label: {json.dumps(label)}\n"
    )


# what a terminal acts on: every control (but the line breaks the program prints), bidi and format characters
_RAW = re.compile(r"[\x00-\x09\x0b-\x1f\x7f-\x9f\u200b-\u200f\u202a-\u202e\u2066-\u2069\u2028\u2029\ufeff]")


def assert_harmless(*texts: str) -> None:
    for text in texts:
        assert "Traceback" not in text, text
        assert not _RAW.search(text), ascii(text)
        assert not any(line.lstrip().startswith("fake: ok") for line in text.splitlines()), text


@pytest.mark.parametrize("category", ["Cc", "Cf", "Zl", "Zp", "Cs"])
def test_printable_escapes_every_character_a_terminal_acts_on(category: str) -> None:
    chars = [chr(c) for c in range(sys.maxunicode + 1) if unicodedata.category(chr(c)) == category]
    assert chars
    text = "".join(chars)
    shown = printable(text)
    assert all(unicodedata.category(c) not in ("Cc", "Cf", "Zl", "Zp", "Cs") for c in shown)
    assert printable("a\nb", newlines=True) == "a\nb" and printable("a\nb") == "a\\nb"
    assert printable(f"{ESC}[2K\u202e\r") == "\\e[2K\\u202e\\r"


def test_ordinary_text_is_shown_as_it_is() -> None:
    for text in ("press-001", "10 °C", "Drehzahl Sollwert", "ضغط", "压力", "naïve [x] {y}", "tab-free"):
        assert printable(text) == text


def test_hostile_names_through_the_real_commands(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    Path("prof.yaml").write_text(PROFILE)
    prof = load_profile("prof.yaml")
    Path("r.yaml").write_text(recipe_text(LABEL, f"<!--<script>\n{FAKE}"))
    hostile_file = f"r{ESC}[2K\u202e.yaml" if sys.platform != "win32" else "r\u202e.yaml"  # Windows: no controls
    Path(hostile_file).write_text(recipe_text("x\u202eko", "ok"))
    outputs: list[str] = []

    def run(*args: str) -> tuple[int, str, str]:
        code, out, err = run_cli(capsys, *args)
        outputs.extend((out, err))
        return code, out, err

    code, out, _ = run("validate", "r.yaml", hostile_file)
    assert code == 0 and "[/red]\\e[2K\\e[1Afake: ok\\u202e" in out and f"{printable(hostile_file)}: ok" in out
    with SimulatorThread(prof) as sim:
        code, out, _ = run("plan", "r.yaml", "--device", sim.url)
        assert code == 0 and "[bold]\\e[2K\\e[1Afake: ok" in out
        code, out, err = run(
            "apply",
            "r.yaml",
            "--device",
            sim.url,
            "--yes",
            "--report",
            "run.json",
            "--html",
            "run.html",
            "--state-dir",
            "st",
        )
        assert code == 0, err
        assert "[/red]\\e[2K\\e[1Afake: ok\\u202e " in out  # the name as it is, escaped, not a closing tag
        assert sim.read("mode") == (2,)  # the label's value reached the device
        code, out, _ = run("apply", hostile_file, "--device", sim.url, "--yes", "--state-dir", "st")
        assert code == 0 and "x\\u202eko" in out
        code, out, _ = run("diff", "r.yaml", "--device", sim.url)
        assert code == 2 and "[bold]\\e[2K\\e[1Afake: ok" in out
        code, out, _ = run_cli(capsys, "pull", "--profile", "prof.yaml", "--device", sim.url)
        assert code == 0 and "x\u202eko" in out  # a file's text, piped: exactly (YAML reads it back)
    code, out, _ = run("report", "run.json", "--html", "again.html")
    assert code == 0 and "[/red]\\e[2K\\e[1Afake: ok\\u202e " in out and "<!--<script>\\n\\e[2K\\e[1Afake: ok" in out
    # an unfinished run whose journal holds hostile text: status shows it escaped
    journal.append(
        "st",
        {
            "event": "run-started",
            "run": f"r1{ESC}[2K",
            "time": "t",
            "user": f"u{ESC}[1A",
            "pid": 1,
            "command": "apply",
            "via": "cli",
            "argv": ["--inventory", f"i{ESC}.yaml"],
            "recipe": None,
            "devices": [{"name": f"d\n{FAKE}", "url": "tcp://h:1", "unit": 1}],
        },
    )
    code, out, _ = run("status", "--state-dir", "st")
    assert code == 2 and "apply --inventory i\\e.yaml by u\\e[1A at t" in out, out
    code, _, err = run("report", f"missing{ESC}[2K.json")
    assert code == 1 and "missing\\e[2K.json" in err
    assert_harmless(*outputs)


def test_the_page_keeps_its_script_and_table_whole(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """An enum label and a string register holding ``<!--<script>``: the data block must not swallow the
    page's own script (the device table would stay empty), and nothing the data holds runs."""
    from tests.test_pages import CHROMIUM, Elements, dom

    if CHROMIUM is None:
        pytest.skip("no Chromium (CI installs it: apt-get install chromium)")
    monkeypatch.chdir(tmp_path)
    Path("prof.yaml").write_text(PROFILE)
    Path("r.yaml").write_text(recipe_text("<!--<script>", "<script>document.title='owned'</script>"))
    with SimulatorThread(load_profile("prof.yaml")) as sim:
        code, _, err = run_cli(
            capsys,
            "apply",
            "r.yaml",
            "--device",
            sim.url,
            "--yes",
            "--html",
            "run.html",
            "--report",
            "run.json",
            "--state-dir",
            "st",
        )
    assert code == 0, err
    page = Path("run.html").read_text()
    assert "<!--" not in page.split("<script type=application/json id=data>")[1].split("</script>")[0]
    doc = Elements(dom(tmp_path / "run.html", tmp_path))
    rows = doc.all("tr", "dev")
    assert len(rows) == 1 and str(rows[0]["cells"][0]).startswith("[/red]")  # type: ignore[index]
    record = str(doc.all("details", "device")[0]["text"])
    assert "<!--<script>" in record and "<script>document.title='owned'</script>" in record
    assert "owned" not in str(doc.all("title")[0]["text"])
    assert [s for s in doc.all("script") if not s.get("type")] and not [
        s for s in doc.all("script") if "owned" in str(s["text"]) and not s.get("type")
    ]
    # the name's U+202E is isolated: inside a <bdi>, closed before the page's own text goes on
    names = [b for b in doc.all("bdi") if str(b["text"]).startswith("[/red]")]
    assert names and all(str(b["text"]).endswith("\u202e\u202c") for b in names)


def test_every_line_the_command_line_prints_goes_through_the_escaping() -> None:
    """Commands print through base.echo, base.console() (text.SafeConsole) or tables.show: no command
    writes with click.echo, print or a console of its own (their text would reach the terminal raw)."""
    root = Path(__file__).resolve().parent.parent / "deployer" / "cli"
    allowed = {"base.py": 2, "text.py": 2, "demo.py": 99}  # base: echo, a file's text to a pipe; text: SafeConsole
    for f in sorted(root.glob("*.py")):
        text = f.read_text()
        raw = len(re.findall(r"\bclick\.s?echo\(|(?<![\w.])print\(|\bConsole\(|markup=True", text))
        assert raw <= allowed.get(f.name, 0), f"{f.name}: {raw} raw writes"


@given(st.text())
def test_printable_leaves_nothing_a_terminal_acts_on(text: str) -> None:
    shown = printable(text)
    assert all(unicodedata.category(c) not in ("Cc", "Cf", "Zl", "Zp", "Cs") for c in shown)
    assert "\n" not in shown and (printable(text, newlines=True).count("\n") == text.count("\n"))


def test_a_hostile_name_applied_to_a_device_of_another_library(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The same hostile recipe against umodbus (not our simulator): the device holds the label's value,
    the output shows every name escaped."""
    from tests.helpers import umodbus_server

    monkeypatch.chdir(tmp_path)
    Path("prof.yaml").write_text(PROFILE)
    Path("r.yaml").write_text(recipe_text(LABEL, f"<!--<script>\n{FAKE}"))
    store = {a: 0 for a in (1, *range(10, 42))}
    with umodbus_server(store) as port:
        code, out, err = run_cli(
            capsys,
            "apply",
            "r.yaml",
            "--device",
            f"tcp://127.0.0.1:{port}",
            "--yes",
            "--state-dir",
            "st",
            "--report",
            "run.json",
        )
    assert code == 0, err
    assert store[1] == 2 and store[10] == 0x3C21  # the label's raw value; '<!' the string's first register
    assert "[/red]\\e[2K\\e[1Afake: ok\\u202e " in out
    assert_harmless(out, err)
    code, out, err = run_cli(capsys, "report", "run.json")
    assert code == 0 and "[bold]\\e[2K\\e[1Afake: ok" in out
    assert_harmless(out, err)


def test_on_a_real_terminal_only_colours_go_out(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``deployer report`` of the hostile run with its output on a pseudo-terminal (rich draws its colours
    there): the only escape sequences that reach the terminal are colour changes (SGR, ``ESC [ ... m``),
    never the names' cursor movements or line erasures."""
    import os
    import subprocess

    pty = pytest.importorskip("pty", reason="no pseudo-terminals on Windows")

    monkeypatch.chdir(tmp_path)
    Path("prof.yaml").write_text(PROFILE)
    Path("r.yaml").write_text(recipe_text(LABEL, f"<!--<script>\n{FAKE}"))
    with SimulatorThread(load_profile("prof.yaml")) as sim:
        code, _, err = run_cli(
            capsys, "apply", "r.yaml", "--device", sim.url, "--yes", "--state-dir", "st", "--report", "run.json"
        )
    assert code == 0, err
    leader, follower = pty.openpty()
    proc = subprocess.Popen(
        [sys.executable, "-m", "deployer", "report", "run.json"],
        stdout=follower,
        stderr=follower,
        stdin=subprocess.DEVNULL,
        env={**os.environ, "COLUMNS": "200", "TERM": "xterm-256color"},
    )
    os.close(follower)
    chunks = []
    while True:
        try:
            data = os.read(leader, 65536)
        except OSError:  # EIO: the command ended and closed its side
            break
        if not data:
            break
        chunks.append(data)
    os.close(leader)
    assert proc.wait(timeout=60) == 0
    text = b"".join(chunks).decode()
    sequences = re.findall(r"\x1b\[[0-9;?]*[A-Za-z]", text)
    assert sequences and all(s.endswith("m") for s in sequences), sequences  # rich coloured it: a terminal
    plain = re.sub(r"\x1b\[[0-9;]*m", "", text)
    assert "\\e[2K\\e[1Afake: ok" in plain and "\x1b" not in plain
