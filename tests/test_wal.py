"""The snapshots' write-ahead log (deployer.state.wal): what a process that died before fsync'ing its snapshot
files leaves is enough to restore every one of them, and nothing else is ever written from it."""

from __future__ import annotations

import hashlib
import itertools
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from deployer.state import durable, oslock, snapshot, wal
from deployer.state.durable import NewFile
from tests.helpers import wait_for


def _snapshot(folder: Path, stem: str, text: str) -> NewFile:
    first = str(folder / f"{stem}.yaml")
    later = (str(folder / f"{stem}-{n}.yaml") for n in itertools.count(2))
    return NewFile(later, lambda path: text, (first, text))


def _died_after_logging(folder: Path, texts: dict[str, str]) -> list[str]:
    """A forked process writes these snapshots through the group commit and dies before settling them
    (``os._exit``: no exit handler runs), as a killed run does: the paths it wrote."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            paths = [durable.durable_now(_snapshot(folder, stem, text)) for stem, text in texts.items()]
            os.write(w, json.dumps(paths).encode())
            code = 0
        finally:
            os._exit(code)
    os.close(w)
    with os.fdopen(r) as f:
        paths = json.loads(f.read())
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0
    return [str(p) for p in paths]


linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the dead process is forked")


@linux_only
def test_a_dead_process_log_restores_lost_and_cut_snapshots_and_leaves_intact_ones(tmp_path: Path) -> None:
    state = tmp_path / "state"
    folder = state / "snapshots"
    folder.mkdir(parents=True)
    texts = {f"dev{i}-20261127T120000Z": f"recipe: dev{i}\n# \u00b0C and all\n" + "x: 1\n" * i for i in range(4)}
    paths = _died_after_logging(folder, texts)
    assert [Path(p).read_text() for p in paths] == list(texts.values())
    (log,) = (folder / wal.FOLDER).iterdir()
    Path(paths[0]).unlink()  # what a power loss can do to a file written but not fsync'ed
    Path(paths[1]).write_bytes(b"")
    Path(paths[2]).write_bytes(b"\0" * 10)

    assert snapshot.recover(str(state)) == paths[:3]
    assert [Path(p).read_text() for p in paths] == list(texts.values())
    assert not log.exists() and not (folder / wal.FOLDER).exists()
    (event,) = [json.loads(x) for x in (state / "audit.jsonl").read_text().splitlines()]
    assert event["event"] == "snapshots-restored" and event["snapshots"] == paths[:3]
    assert snapshot.recover(str(state)) == []  # done once


def test_a_living_writers_log_is_left_alone(tmp_path: Path) -> None:
    log = wal.Log()
    p = durable._Pending(_snapshot(tmp_path, "dev-20261127T120000Z", "recipe: dev\n"))
    durable.commit([p], log)
    (segment,) = (tmp_path / wal.FOLDER).iterdir()
    Path(p.outcome() or "").unlink()
    assert wal.recover(str(tmp_path)) == []  # locked: its process is alive (this one), and settles it itself
    assert segment.exists()
    log.settle()  # the file it named is gone (its owner removed it): nothing to fsync, the log removed
    assert not (tmp_path / wal.FOLDER).exists()


@linux_only
def test_only_whole_records_restore_and_only_snapshot_files_of_the_logs_own_folder(tmp_path: Path) -> None:
    folder = tmp_path / "snapshots"
    folder.mkdir()
    paths = _died_after_logging(folder, {"a-20261127T120000Z": "recipe: a\n", "b-20261127T120000Z": "recipe: b\n"})
    (log,) = (folder / wal.FOLDER).iterdir()

    def rec(path: str, text: str) -> bytes:
        body = text.encode()
        return b"".join(wal.record(path, hashlib.sha256(body).hexdigest(), body))

    outside = tmp_path / "elsewhere.yaml"
    with open(log, "ab") as f:
        f.write(rec(str(outside), "recipe: planted\n"))  # another folder: at most restored into this one
        f.write(rec(str(folder / "notes.txt"), "not a snapshot\n"))  # never written: not a snapshot's name
        f.write(rec(str(folder / "c-20261127T120000Z.yaml"), "recipe: c\n").replace(b"recipe: c", b"recipe: X"))
        f.write(rec(str(folder / "d-20261127T120000Z.yaml"), "recipe: d\n")[:-3])  # cut by the crash
        f.write(rec(str(folder / "e-20261127T120000Z.yaml"), "recipe: e\n"))  # after a cut: never acknowledged
    Path(paths[0]).unlink()
    os.symlink(tmp_path / "target", paths[0])  # a link planted where a snapshot was lost: not written through

    assert wal.recover(str(folder)) == [str(folder / "elsewhere.yaml")]
    assert not (tmp_path / "target").exists() and os.path.islink(paths[0])
    assert not outside.exists() and not (folder / "notes.txt").exists()
    assert not any((folder / f"{x}-20261127T120000Z.yaml").exists() for x in "cde")
    assert Path(paths[1]).read_text() == "recipe: b\n"


def test_a_process_that_ends_settles_its_log_and_one_that_lives_on_settles_it_when_idle(tmp_path: Path) -> None:
    """The Python API's ``save_snapshot`` in a script that simply ends: no log is left behind (the exit handler
    settles it); in a process that lives on (the agent), the writer settles it once idle for ``wal.IDLE``."""
    script = (
        "import sys\n"
        "from deployer.recipe.loader import load_recipe\n"
        "from deployer.state.snapshot import save_snapshot\n"
        "rec = load_recipe(sys.argv[2])\n"
        "values = {d.name: d.registers for d in rec.desired}\n"
        "print(save_snapshot(sys.argv[1], 'press-1', rec, values, 'tcp://127.0.0.1:1502', 1))\n"
    )
    (tmp_path / "r.yaml").write_text("recipe: r\nprofile: example-drive\nparameters:\n  motor_poles: 4\n")
    out = subprocess.run(
        [sys.executable, "-c", script, str(tmp_path / "state"), str(tmp_path / "r.yaml")],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).parent.parent)},
    ).stdout
    assert Path(out.strip()).is_file()
    assert not (tmp_path / "state" / "snapshots" / wal.FOLDER).exists()

    path = durable.durable_now(_snapshot(tmp_path, "dev-20261127T120000Z", "recipe: dev\n"))
    assert path is not None and (tmp_path / wal.FOLDER).is_dir()
    wait_for(lambda: not (tmp_path / wal.FOLDER).exists(), "the idle writer to settle its log", timeout=wal.IDLE + 10)
    assert Path(path).read_text() == "recipe: dev\n"


@pytest.mark.skipif(sys.platform == "win32", reason="Windows removes no file that is open: the race cannot happen")
def test_a_new_segment_taken_and_removed_by_a_recover_before_its_lock_is_made_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Between a segment's create and its lock, another process's recover can take it for a dead process's (it
    has no records yet) and remove it: the writer's lock would then hold a file nobody finds after a crash. The
    writer sees its path gone and makes another one."""
    real = oslock.backend()
    taken: list[str] = []

    class Recovering:
        def try_lock(self, fd: int, *, shared: bool = False) -> bool:
            if not taken:  # the recover got there first: removed, then let go
                (new,) = (tmp_path / wal.FOLDER).iterdir()
                taken.append(str(new))
                new.unlink()
            return bool(real.try_lock(fd, shared=shared))

    monkeypatch.setattr(oslock, "backend", lambda: Recovering())
    seg = wal.Segment(str(tmp_path))
    assert taken and seg.path != taken[0] and os.path.exists(seg.path)
    body = b"recipe: dev\n"
    seg.append(wal.record(str(tmp_path / "dev-20261127T120000Z.yaml"), hashlib.sha256(body).hexdigest(), body), [])
    assert [p for p, _, _ in wal.records(Path(seg.path).read_bytes())] == [str(tmp_path / "dev-20261127T120000Z.yaml")]
    seg.settle()
    assert not (tmp_path / wal.FOLDER).exists()
