"""The audit trail's file: records appended under a lock, each chained to the one before (docs/change-control.md).

``FOLDER/trail.jsonl`` holds one JSON record per line; each carries ``seq`` (one more than the last) and
``prev`` (the SHA-256 of the previous line's bytes). ``FOLDER/head.json`` names the last record (its seq and
hash), rewritten after every append. Appends from several processes (command-line runs, the agent, a
forwarder) take ``FOLDER/trail.lock`` (``state.oslock``: the lock dies with its holder), write their records
in one write and fsync them before the head moves.
"""

from __future__ import annotations

import base64
import contextlib
import datetime
import hashlib
import json
import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from ..portable import O_BINARY, O_CLOEXEC

TRAIL = "trail.jsonl"
HEAD = "head.json"
LOCK = "trail.lock"
GENESIS = "0" * 64
KEYS = (
    "seq",
    "time",
    "event",
    "user",
    "role",
    "via",
    "host",
    "pid",
    "reason",
    "device",
    "result",
    "run",
    "plan",
    "detail",
)
_TAIL_CHUNK = 65536


def line_hash(line: bytes) -> str:
    """The SHA-256 (hex) of a record's line, without its newline: what the next record's ``prev`` says."""
    return hashlib.sha256(line).hexdigest()


def now_ms() -> str:
    return datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


def encode(record: Mapping[str, Any]) -> bytes:
    """One record's line (no newline): compact JSON in the record's key order, UTF-8."""
    return json.dumps(record, ensure_ascii=False, separators=(",", ":"), allow_nan=False).encode()


@dataclass(frozen=True)
class Head:
    seq: int
    hash: str


def read_head(folder: str) -> Head | None:
    try:
        with open(os.path.join(folder, HEAD), "rb") as f:
            d = json.loads(f.read(4096))
        return Head(int(d["seq"]), str(d["hash"]))
    except (OSError, ValueError, KeyError, TypeError):
        return None


@contextlib.contextmanager
def locked(folder: str) -> Iterator[None]:
    """The trail's lock, exclusive, waited for (appends are short)."""
    from ..state import oslock

    os.makedirs(folder, exist_ok=True)
    fd = os.open(os.path.join(folder, LOCK), os.O_RDWR | os.O_CREAT | O_CLOEXEC | O_BINARY, 0o640)
    try:
        oslock.backend().lock(fd)
        yield
    finally:
        os.close(fd)  # releases the lock


def _tail(fd: int, size: int) -> tuple[bytes | None, bytes]:
    """(the last complete line, the bytes after it that a crash left without their newline)."""
    if size == 0:
        return None, b""
    from ..portable import pread

    start = max(0, size - _TAIL_CHUNK)
    data = pread(fd, size - start, start)
    while True:
        end = data.rfind(b"\n")
        torn = data[end + 1 :] if end >= 0 else data
        body = data[:end] if end >= 0 else b""
        cut = body.rfind(b"\n")
        if cut >= 0 or start == 0:
            if end < 0 and start == 0:
                return None, torn
            return body[cut + 1 :], torn
        step = min(start, _TAIL_CHUNK * 16)
        start -= step
        data = pread(fd, step, start) + data


def _seq_of(line: bytes | None, folder: str) -> int:
    if line is None:
        return 0
    try:
        seq = json.loads(line)["seq"]
        if isinstance(seq, int):
            return seq
    except (ValueError, KeyError, TypeError):
        pass
    head = read_head(folder)  # a damaged last line: number on from the head (verify names the damage)
    return head.seq if head is not None else 0


def append(folder: str, records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Append ``records`` (their fields: ``record.event`` makes them) as the next ones of the chain, durable
    before this returns; the records as written. OSError when the folder cannot take them."""
    if not records:
        return []
    from ..state.durable import write_atomic

    path = os.path.join(folder, TRAIL)
    with locked(folder):
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_APPEND | O_BINARY | O_CLOEXEC, 0o640)
        try:
            size = os.fstat(fd).st_size
            last, torn = _tail(fd, size)
            todo = list(records)
            if torn:  # a line a crash cut short: kept whole in a record of its own, the chain goes on
                os.ftruncate(fd, size - len(torn))
                todo.insert(
                    0,
                    {
                        "event": "trail-torn",
                        "result": "kept",
                        "detail": {
                            "bytes": base64.b64encode(torn).decode(),
                            "why": "a record cut short by a crash while it was appended; its bytes are kept here",
                        },
                    },
                )
            seq = _seq_of(last, folder)
            prev = GENESIS if last is None else line_hash(last)
            out, lines = [], []
            for r in todo:
                seq += 1
                rec = {"seq": seq, **{k: r.get(k) for k in KEYS[1:]}, "prev": prev}
                rec["time"] = rec["time"] or now_ms()
                line = encode(rec)
                lines.append(line + b"\n")
                prev = line_hash(line)
                out.append(rec)
            os.write(fd, b"".join(lines))
            os.fsync(fd)
        finally:
            os.close(fd)
        write_atomic(os.path.join(folder, HEAD), json.dumps({"seq": seq, "hash": prev, "time": now_ms()}) + "\n")
    return out


def lines(folder: str) -> list[bytes]:
    """The trail's lines as they are on disk (the last one without a newline when a crash cut it)."""
    try:
        with open(os.path.join(folder, TRAIL), "rb") as f:
            data = f.read()
    except FileNotFoundError:
        return []
    parts = data.split(b"\n")
    if parts and parts[-1] == b"":
        parts.pop()
    return parts


def read_from(folder: str, offset: int, limit: int) -> list[tuple[int, bytes, dict[str, Any]]]:
    """Up to ``limit`` complete records from byte ``offset`` on (a forwarder's next batch): (the offset after
    the line, the line, the record). A line without its newline yet is left for the next call."""
    out: list[tuple[int, bytes, dict[str, Any]]] = []
    path = os.path.join(folder, TRAIL)
    if not os.path.exists(path):
        return out
    with open(path, "rb") as f:
        f.seek(offset)
        at = offset
        for raw in f:
            if not raw.endswith(b"\n"):
                break  # being appended, or cut by a crash: not a record yet
            at += len(raw)
            line = raw[:-1]
            try:
                rec = json.loads(line)
            except ValueError:
                rec = None
            if not isinstance(rec, dict) or not isinstance(rec.get("seq"), int):
                rec = {"seq": None, "event": "unreadable"}  # forwarded as it is: the receiver keeps the damage too
            out.append((at, line, rec))
            if len(out) >= limit:
                break
    return out
