"""Group commit (deployer.durable): files and journal lines durable in as few fsyncs as the guarantees allow."""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import stat
import sys
from pathlib import Path
from typing import Any

import pytest

from deployer.state import durable, wal
from deployer.state.durable import Line, NewFile, _Pending, commit


def _file(folder: Path, stem: str, journal: Path | None = None, line: dict[str, Any] | None = None) -> NewFile:
    def text(path: str) -> str:
        return f"# I am {path}\n"

    first = str(folder / f"{stem}.yaml")
    later = (str(folder / f"{stem}-{n}.yaml") for n in itertools.count(2))
    return NewFile(later, text, (first, text(first)), str(journal) if journal else None, line)


def _lines(path: Path) -> list[dict[str, Any]]:
    return [json.loads(x) for x in path.read_text().splitlines()]


def test_a_batch_logs_its_files_with_one_fsync_then_the_journal_and_the_files_are_fsynced_at_the_settle(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The files' text goes to the folder's write-ahead log (one write, one fsync), then the journal lines (one
    write, one fsync): no fsync per file before the first write. Settling fsyncs each file, then the folder,
    and removes the log."""
    journal = tmp_path / "audit.jsonl"
    synced: list[str] = []
    real = os.fsync

    def fsync(fd: int) -> None:
        st = os.fstat(fd)
        synced.append(
            "dir"
            if stat.S_ISDIR(st.st_mode)
            else "journal"
            if st.st_ino == _ino(journal)
            else "log"
            if Path(tmp_path / ".wal").is_dir() and st.st_ino in _inos(tmp_path / ".wal")
            else "file"
        )
        real(fd)

    journal.touch()
    monkeypatch.setattr(os, "fsync", fsync)
    log = wal.Log()
    batch = [
        _Pending(_file(tmp_path, f"dev{i}", journal, {"event": "device-started", "name": f"dev{i}"})) for i in range(3)
    ]
    batch.append(_Pending(Line(str(journal), {"event": "device-finished", "name": "dev9"})))
    commit(batch, log)
    # the log's folder and its name made durable once, when the log is created; then one fsync each
    folders = [] if sys.platform == "win32" else ["dir", "dir"]  # Windows opens no folder to fsync
    assert synced == [*folders, "log", "journal"]  # the lines only after the files they name are logged
    assert [p.outcome() for p in batch] == [str(tmp_path / f"dev{i}.yaml") for i in range(3)] + [None]
    lines = _lines(journal)
    assert [x["name"] for x in lines] == ["dev0", "dev1", "dev2", "dev9"]  # submission order
    assert [x.get("snapshot") for x in lines[:3]] == [str(tmp_path / f"dev{i}.yaml") for i in range(3)]
    (segment,) = (tmp_path / ".wal").iterdir()
    logged = list(wal.records(segment.read_bytes()))
    assert [(path, body) for path, _, body in logged] == [
        (str(tmp_path / f"dev{i}.yaml"), f"# I am {tmp_path / f'dev{i}.yaml'}\n".encode()) for i in range(3)
    ]
    assert [digest for _, digest, _ in logged] == [x["snapshot_sha256"] for x in lines[:3]]

    synced.clear()
    commit([_Pending(_file(tmp_path, "dev3", journal, {"name": "dev3"}))], log)
    assert synced == ["log", "journal"]  # the log exists: one fsync for the file, one for its line
    synced.clear()
    log.settle()
    assert synced == ["file"] * 4 + folders[:1]
    assert not (tmp_path / ".wal").exists()  # settled: no log, and no empty folder beside the snapshots


def test_a_full_log_is_settled_beside_the_next_batches(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A long fleet's log does not grow without bound: a full segment is settled (its files fsync'ed, then it is
    removed) while the next batches go to a new one."""
    monkeypatch.setattr(wal, "MAX_BYTES", 1)
    log = wal.Log()
    batches = [[_Pending(_file(tmp_path, f"dev{b}-{i}")) for i in range(3)] for b in range(4)]
    for batch in batches:
        commit(batch, log)
    assert len(log.settling) == 3 and len(log.segments) == 1
    log.settle()
    assert not log.pending() and not (tmp_path / ".wal").exists()
    assert [p.outcome() for b in batches for p in b] == [
        str(tmp_path / f"dev{b}-{i}.yaml") for b in range(4) for i in range(3)
    ]


def _inos(folder: Path) -> set[int]:
    return {p.stat().st_ino for p in folder.iterdir()}


def _ino(path: Path) -> int:
    return os.stat(path).st_ino


def test_a_taken_name_moves_on_and_the_text_names_the_final_path(tmp_path: Path) -> None:
    (tmp_path / "dev.yaml").write_text("another run's snapshot\n")
    path = durable.durable_now(_file(tmp_path, "dev"))
    assert path == str(tmp_path / "dev-2.yaml")
    assert Path(path).read_text() == f"# I am {path}\n"
    assert (tmp_path / "dev.yaml").read_text() == "another run's snapshot\n"  # never overwritten


def test_a_failure_is_that_operations_own_and_its_line_is_not_written(tmp_path: Path) -> None:
    journal = tmp_path / "audit.jsonl"
    good = _Pending(_file(tmp_path, "good", journal, {"name": "good"}))
    (tmp_path / "a-file").write_text("not a folder")
    bad = _Pending(_file(tmp_path / "a-file", "bad", journal, {"name": "bad"}))
    commit([good, bad])
    assert good.outcome() == str(tmp_path / "good.yaml")
    with pytest.raises(NotADirectoryError):
        bad.outcome()
    assert [x["name"] for x in _lines(journal)] == ["good"]  # no line names a snapshot that is not there


def test_a_missing_folder_is_made_by_the_files_create(tmp_path: Path) -> None:
    """The first snapshot of a state folder makes its folder (a fleet does not ask for it once per device)."""
    journal = tmp_path / "audit.jsonl"
    new = _Pending(_file(tmp_path / "state" / "snapshots", "first", journal, {"name": "first"}))
    commit([new])
    assert new.outcome() == str(tmp_path / "state" / "snapshots" / "first.yaml")
    assert (tmp_path / "state" / "snapshots" / "first.yaml").read_text() == f"# I am {new.path}\n"


def test_a_folder_another_process_makes_meanwhile_is_used(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A fleet's workers make their first snapshots in a new folder together: when the folder appears between one
    worker's failed open and its look at the folder (another worker made it), that worker opens again; it used to
    raise the open's "No such file or directory" and fail its device. Here the other worker's mkdir comes right
    after the first open fails, as it did in a fleet on a loaded machine."""
    folder = tmp_path / "state" / "snapshots"
    real_open = os.open
    raced: list[str] = []

    def open_(path: Any, flags: int, mode: int = 0o777, **kw: Any) -> int:
        try:
            return real_open(path, flags, mode, **kw)
        except FileNotFoundError:
            if not raced and str(path).startswith(str(folder)):
                raced.append(str(path))
                folder.mkdir(parents=True)  # the other worker, a moment later
            raise

    monkeypatch.setattr(os, "open", open_)  # the one os module durable uses too
    new = _Pending(_file(folder, "d1", tmp_path / "audit.jsonl", {"name": "d1"}))
    commit([new])
    monkeypatch.undo()
    assert raced == [str(folder / "d1.yaml")]
    assert new.outcome() == str(folder / "d1.yaml") and (folder / "d1.yaml").is_file()
    if os.name == "nt":  # a symbolic link needs a privilege there
        return
    # a folder that is not one (a link to nowhere): an error, not a loop
    gone = tmp_path / "dangling"
    gone.symlink_to(tmp_path / "nowhere")
    with pytest.raises(NotADirectoryError):
        durable._open_in_folder(str(gone / "x.yaml"), os.O_WRONLY | os.O_CREAT | os.O_EXCL)


def test_many_devices_at_once_each_get_their_own_durable_file_and_line(tmp_path: Path) -> None:
    journal = tmp_path / "audit.jsonl"

    async def device(i: int) -> str | None:
        path = await durable.durable(_file(tmp_path, "same-second", journal, {"name": f"dev{i}"}))
        assert path is not None and os.path.exists(path)  # on disk when the device goes on to write
        await durable.durable(Line(str(journal), {"name": f"dev{i}", "event": "device-finished"}))
        return path

    async def main() -> list[str | None]:
        return await asyncio.gather(*(device(i) for i in range(40)))

    paths = asyncio.run(main())
    assert len(set(paths)) == 40  # one name collision after another, none overwritten
    lines = _lines(journal)
    started = {x["name"]: x["snapshot"] for x in lines if "snapshot" in x}
    assert sorted(started.values()) == sorted(p for p in paths if p)
    for name, snap in started.items():  # each device's finished line comes after its started line
        order = [i for i, x in enumerate(lines) if x["name"] == name]
        assert len(order) == 2 and lines[order[0]].get("snapshot") == snap
        assert Path(snap).read_text() == f"# I am {snap}\n"


def test_after_a_crowded_batch_the_writer_gathers_the_next_one_and_a_lone_operation_never_waits(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two operations committed together (a fleet): the next batch waits ``GATHER`` for the others, so operations
    queued meanwhile share its fsyncs; a writer whose batches hold one operation each (one device) never waits."""
    import threading
    import time

    monkeypatch.setattr(durable, "GATHER", 0.3)
    batches: list[int] = []
    real = durable.commit

    def counted(batch: list[_Pending], log: wal.Log | None = None) -> None:
        batches.append(len(batch))
        real(batch, log)

    monkeypatch.setattr(durable, "commit", counted)
    journal = str(tmp_path / "audit.jsonl")

    def line(i: int) -> _Pending:
        return _Pending(Line(journal, {"n": i}), event=threading.Event())

    lone = durable.GroupCommit()
    t = time.monotonic()
    for i in range(3):
        p = lone.submit(line(i))
        assert p.event is not None and p.event.wait(10) and p.outcome() is None
    assert time.monotonic() - t < 0.3 and batches == [1, 1, 1]  # never gathered: each alone, at once

    batches.clear()
    fleet = durable.GroupCommit()
    with fleet._cond:  # both queued before the writer takes any: one batch of two
        first = [fleet.submit(line(i)) for i in (10, 11)]
    assert all(p.event is not None and p.event.wait(10) for p in first)
    t = time.monotonic()
    late = [fleet.submit(line(20))]
    time.sleep(0.05)  # within the gathering: joins the batch of the one before
    late.append(fleet.submit(line(21)))
    assert all(p.event is not None and p.event.wait(10) for p in late)
    assert time.monotonic() - t >= 0.3
    assert batches == [2, 2]
    assert [json.loads(x)["n"] for x in Path(journal).read_text().splitlines()] == [0, 1, 2, 10, 11, 20, 21]


def test_write_atomic_from_pieces_more_than_one_writev_takes(tmp_path: Path) -> None:
    from deployer.state.durable import write_atomic

    pieces = [f"{i}:{'x' * (i % 7)}\n".encode() for i in range(5000)] + [b"", b"end\n"]  # beyond IOV_MAX
    write_atomic(str(tmp_path / "r.json"), pieces)
    assert (tmp_path / "r.json").read_bytes() == b"".join(pieces)
    write_atomic(str(tmp_path / "r.json"), "text too: \u00b0C\n")
    assert (tmp_path / "r.json").read_text(encoding="utf-8") == "text too: \u00b0C\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json"]  # no temporary file left


def test_an_unexpected_error_reaches_the_caller_and_the_writer_goes_on(tmp_path: Path) -> None:
    journal = tmp_path / "audit.jsonl"
    with pytest.raises(TypeError):
        durable.durable_now(Line(str(journal), {"not JSON": object()}))
    assert durable.durable_now(Line(str(journal), {"name": "next"})) is None
    assert _lines(journal) == [{"name": "next"}]


def test_a_failed_log_fsync_fails_its_batch_and_the_next_batch_gets_a_new_log(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The log is the files' durability: when its fsync fails, none of the batch's files is durable (their
    devices are not written) and no journal line names them; the log is not appended to again."""
    journal = tmp_path / "audit.jsonl"
    log = wal.Log()
    commit([_Pending(_file(tmp_path, "first", journal, {"name": "first"}))], log)
    real = os.fsync
    (old,) = (tmp_path / ".wal").iterdir()

    def fsync(fd: int) -> None:
        if os.fstat(fd).st_ino == _ino(old):
            raise OSError(5, "Input/output error")
        real(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    batch = [_Pending(_file(tmp_path, f"more{i}", journal, {"name": f"more{i}"})) for i in range(2)]
    commit(batch, log)
    for p in batch:
        with pytest.raises(OSError, match="Input/output"):
            p.outcome()
    assert [x["name"] for x in _lines(journal)] == ["first"]
    later = _Pending(_file(tmp_path, "later", journal, {"name": "later"}))
    commit([later], log)
    assert later.outcome() == str(tmp_path / "later.yaml")
    assert len(list((tmp_path / ".wal").iterdir())) == 2  # a new log; the broken one waits for the settle
    monkeypatch.setattr(os, "fsync", real)
    log.settle()
    assert not (tmp_path / ".wal").exists()


def test_a_file_that_cannot_be_fsynced_at_the_settle_leaves_its_log_for_recovery(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    log = wal.Log()
    commit([_Pending(_file(tmp_path, f"dev{i}", None, None)) for i in range(2)], log)
    real = os.fsync
    failing = _ino(tmp_path / "dev1.yaml")

    def fsync(fd: int) -> None:
        if os.fstat(fd).st_ino == failing:
            raise OSError(5, "Input/output error")
        real(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    log.settle()
    assert len(list((tmp_path / ".wal").iterdir())) == 1  # nothing lost: the log stays, unlocked, for recover
    monkeypatch.setattr(os, "fsync", real)
    assert wal.recover(str(tmp_path)) == []  # the files were intact: fsync'ed now, nothing rewritten
    assert not (tmp_path / ".wal").exists()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="workers (fleet.workers) are forked on Linux only")
def test_a_forked_process_writes_through_a_writer_of_its_own(tmp_path: Path) -> None:
    """A forked worker has none of its parent's threads: the parent's writer (its thread, its lock, its queue)
    is not used there, and a line written in the child is on disk when its wait ends."""
    durable.durable_now(Line(str(tmp_path / "parent.jsonl"), {"who": "parent"}))  # the parent's writer thread runs
    parent = durable._WRITER
    pid = os.fork()
    if pid == 0:  # the child: exit code 0 only if all of this holds
        ok = False
        try:
            ok = durable._WRITER is not parent and not durable._WRITER._queue
            durable.durable_now(Line(str(tmp_path / "child.jsonl"), {"who": "child"}))
            ok = ok and json.loads((tmp_path / "child.jsonl").read_text()) == {"who": "child"}
        finally:
            os._exit(0 if ok else 1)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0
    assert durable._WRITER is parent
