"""One rule for every file deployer writes, one atomic write, a full disk said plainly (issue #17 items 5, 9, 11).

Every output option is run as a real `python -m deployer` process against each kind of path that is not a
regular file: a symbolic link, a FIFO (the run must not block on it), a device node, a folder.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import stat
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from deployer.errors import UsageError
from deployer.profile import builtin_profile
from deployer.state import durable, journal
from deployer.testing.simulator import Simulator, SimulatorThread

pytestmark = pytest.mark.timeout(180)

RECIPE = "recipe: r\nprofile: example-inverter\nparameters:\n  F07: 10 s\n"


def run(*args: str, cwd: Path | None = None) -> tuple[int, str]:
    p = subprocess.run(
        [sys.executable, "-m", "deployer", *args],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=cwd,
        env=os.environ | {"PYTHONPATH": str(Path(__file__).parent.parent)},
    )
    return p.returncode, p.stdout + p.stderr


@pytest.fixture(scope="module")
def sim() -> Iterator[Simulator]:
    with SimulatorThread(builtin_profile("example-inverter")) as s:
        yield s


def _plant(kind: str, path: Path, victim: Path) -> None:
    if kind == "symlink":
        path.symlink_to(victim)
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "folder":
        path.mkdir()


def _commands(tmp: Path, sim: Simulator, out: str) -> dict[str, list[str]]:
    recipe = tmp / "r.yaml"
    recipe.write_text(RECIPE)
    csv = tmp / "in.csv"
    csv.write_text("name,address,type\nspeed,0,uint16\n")
    return {
        "apply --report": [
            "apply",
            str(recipe),
            "--device",
            sim.url,
            "--yes",
            "--state-dir",
            str(tmp / "s"),
            "--report",
            out,
        ],
        "plan --out": ["plan", str(recipe), "--out", out, "--state-dir", str(tmp / "s")],
        "pull -o": ["pull", "--profile", "example-inverter", "--device", sim.url, "-o", out],
        "profiles import csv -o": ["profiles", "import", "csv", str(csv), "--id", "x", "-o", out],
        "profiles export csv -o": ["profiles", "export", "csv", "example-inverter", "-o", out],
        "profiles new": ["profiles", "new", out, "--id", "x"],
    }


@pytest.mark.parametrize("kind", ["symlink", "fifo", "folder", "device"])
def test_every_output_refuses_what_is_not_a_regular_file(kind: str, tmp_path: Path, sim: Simulator) -> None:
    victim = tmp_path / "precious.txt"
    victim.write_text("keep me\n")
    out = Path("/dev/null") if kind == "device" else tmp_path / "out"
    what = {"symlink": "a symbolic link", "fifo": "a FIFO", "folder": "a folder", "device": "a device"}[kind]
    for name, args in _commands(tmp_path, sim, str(out)).items():
        with contextlib.suppress(FileNotFoundError):
            if out.is_dir() and not out.is_symlink():
                out.rmdir()
            elif kind != "device":
                out.unlink()
        if kind != "device":
            _plant(kind, out, victim)
        writes = sum(1 for e in sim.log if e.function == 16)
        code, text = run(*args)  # a FIFO would block for ever: run()'s timeout fails the test
        assert code == 1, (name, text)
        assert f"{out}: it is {what}; deployer writes only regular files" in text or (
            kind == "folder" and f"'{out}' is a directory" in text
        ), (name, text)  # click's check first
        assert victim.read_text() == "keep me\n"
        assert sum(1 for e in sim.log if e.function == 16) == writes, name  # refused before anything was sent
    if kind == "symlink":
        assert out.is_symlink() and os.readlink(out) == str(victim)


def test_reports_plans_and_pulls_replace_a_file_imports_and_exports_need_force(tmp_path: Path, sim: Simulator) -> None:
    out = tmp_path / "out"
    for name, args in _commands(tmp_path, sim, str(out)).items():
        out.write_text("old\n")
        os.chmod(out, 0o640)
        code, text = run(*args)
        if name in ("apply --report", "plan --out", "pull -o"):
            assert code == 0 and out.read_text() != "old\n", (name, text)
            assert stat.S_IMODE(out.stat().st_mode) == 0o640  # the file keeps its permissions
        else:
            assert code == 1 and f"{out} exists; pass --force to overwrite it" in text, (name, text)
            assert out.read_text() == "old\n"
            code, text = run(*args, "--force")
            assert code == 0 and out.read_text() != "old\n", (name, text)
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []  # no temporary file left


def test_docs_rewrites_its_own_pages_and_refuses_other_files(tmp_path: Path) -> None:
    d = tmp_path / "ref"
    assert run("docs", "--out", str(d))[0] == 0
    page = d / "recipe.md"
    page.write_text(page.read_text().replace("# Recipe files", "# Old title"))  # a stale generated page
    code, text = run("docs", "--out", str(d))
    assert code == 0 and "1 page updated" in text and "# Recipe files" in page.read_text()
    page.write_text("my own notes\n")  # not a generated page
    code, text = run("docs", "--out", str(d))
    assert code == 1 and f"the page {page} exists; pass --force to overwrite it" in text
    assert page.read_text() == "my own notes\n"
    assert run("docs", "--out", str(d), "--force")[0] == 0 and "# Recipe files" in page.read_text()


def test_write_atomic_keeps_the_old_file_whole_when_the_write_fails(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "report.json"
    out.write_text("old\n")

    def full(fd: int, data: bytes) -> int:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "write", full)
    with pytest.raises(UsageError, match=re.escape(f"cannot write the report {out}: the disk is full")):
        durable.write_atomic(str(out), "new\n", what="the report")
    monkeypatch.undo()
    assert out.read_text() == "old\n" and sorted(p.name for p in tmp_path.iterdir()) == ["report.json"]


@pytest.fixture
def full_disk(tmp_path: Path) -> Iterator[Path]:
    """A 32 KiB tmpfs (root only), for a state directory on a full disk."""
    d = tmp_path / "small"
    d.mkdir()
    if sys.platform == "win32":
        pytest.skip("a small tmpfs is Linux's (Windows: no mount command)")
    if (
        os.getuid() != 0
        or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=32k", "tmpfs", str(d)], capture_output=True).returncode
        != 0
    ):
        pytest.skip("mounting a small tmpfs needs root")
    try:
        yield d
    finally:
        subprocess.run(["umount", str(d)], check=False)


def _fill(d: Path, leave: int) -> None:
    free = os.statvfs(d).f_bavail * os.statvfs(d).f_frsize
    with open(d / f"fill{len(list(d.iterdir()))}", "wb") as f, contextlib.suppress(OSError):
        f.write(b"x" * max(0, free - leave))


def test_a_full_state_directory_is_said_plainly(full_disk: Path, tmp_path: Path, sim: Simulator) -> None:
    recipe = tmp_path / "r.yaml"
    recipe.write_text(RECIPE.replace("10 s", "11 s"))
    _fill(full_disk, 0)
    code, text = run("apply", str(recipe), "--device", sim.url, "--yes", "--state-dir", str(full_disk / "s"))
    assert code == 1 and "error: cannot write the journal" in text and "the disk is full" in text, text
    assert "Traceback" not in text
    # room for the journal's first line, not for the snapshot: the device is not written
    for f in full_disk.glob("fill*"):
        f.unlink()
    (full_disk / "s").mkdir(exist_ok=True)
    _fill(full_disk, 4096)
    writes = sum(1 for e in sim.log if e.function == 16)
    code, text = run("apply", str(recipe), "--device", sim.url, "--yes", "--state-dir", str(full_disk / "s"), "--json")
    assert "Traceback" not in text
    if code == 4:
        # the report, then what could not be recorded (the audit trail's records too: the disk is full)
        dev = json.JSONDecoder().raw_decode(text[text.index("{") :])[0]["devices"][0]
        assert dev["status"] == "failed" and "cannot save the snapshot" in dev["error"]
        assert "the disk is full; nothing was written" in dev["error"]
        assert sum(1 for e in sim.log if e.function == 16) == writes
        assert list((full_disk / "s" / "snapshots").iterdir()) == []  # no partial snapshot left
    else:  # the whole run fitted after all (block sizes): it must then be complete and ok
        assert code == 0, text


def test_a_torn_journal_line_costs_only_itself(tmp_path: Path) -> None:
    path = tmp_path / "audit.jsonl"
    durable.append_lines(str(path), [{"event": "run-started", "run": "a"}])
    with open(path, "a") as f:
        f.write('{"event": "device-star')  # a crash in the middle of a line
    durable.append_lines(str(path), [{"event": "run-started", "run": "b"}])
    lines = path.read_text().splitlines()
    assert lines[1] == '{"event": "device-star' and json.loads(lines[2]) == {"event": "run-started", "run": "b"}


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.dictionaries(st.sampled_from(["event", "run", "x"]), st.text(max_size=8), max_size=3),
            st.text(alphabet='{}":,ab\n ', max_size=20),
        ),
        max_size=8,
    )
)
def test_every_record_is_read_back_whatever_fragments_lie_between(items: list[object]) -> None:
    """Records appended after any fragments (torn lines, garbage) each come back as a line of their own."""
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "audit.jsonl")
        records = []
        for it in items:
            if isinstance(it, dict):
                durable.append_lines(path, [it])
                records.append(it)
            else:
                assert isinstance(it, str)
                with open(path, "a") as f:
                    f.write(it)
        lines = Path(path).read_text().splitlines() if os.path.exists(path) else []
        parsed = []
        for ln in lines:
            with contextlib.suppress(ValueError):
                parsed.append(json.loads(ln))
        # every record is a line of its own, in order (a fragment may itself read as JSON, e.g. '{}')
        rest = iter(parsed)
        assert all(any(p == r for p in rest) for r in records), (records, lines)


def test_journal_errors_are_state_errors(tmp_path: Path) -> None:
    from deployer.errors import StateError

    (tmp_path / "audit.jsonl").mkdir()  # the journal cannot be opened for appending
    with pytest.raises(StateError, match="cannot write the journal"):
        journal.append(str(tmp_path), {"event": "x"})


def test_appends_racing_from_several_processes_leave_no_empty_line(tmp_path: Path) -> None:
    """Records longer than a page, appended at once by three processes: each comes back whole, and no line is
    empty (a process that looked at the file's last byte while another's append was half-way in added a
    newline for it: the CI's two-worker run read an empty journal line)."""
    path = tmp_path / "audit.jsonl"
    code = (
        "import sys\nfrom deployer.state import durable\n"
        "for i in range(60):\n"
        "    durable.append_lines(sys.argv[1], [{'k': sys.argv[2], 'i': i, 'pad': 'x' * 20000}])\n"
    )
    procs = [subprocess.Popen([sys.executable, "-c", code, str(path), str(k)]) for k in range(3)]
    assert all(p.wait(timeout=120) == 0 for p in procs)
    lines = path.read_bytes().split(b"\n")
    assert lines[-1] == b"" and b"" not in lines[:-1]
    got = sorted((r["k"], r["i"]) for r in map(json.loads, lines[:-1]))
    assert got == sorted((str(k), i) for k in range(3) for i in range(60))
