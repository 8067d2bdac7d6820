"""``audit verify``: walk the chain and name the first record that does not hold.

Each record must parse, carry the next ``seq`` and the hash of the line before it; the last must be the one the
head names. Which record is to blame when a link breaks between lines i-1 and i: line i-1 when the chain
from line i on holds (its successor pins line i, so line i-1 was edited); records removed when ``seq`` jumps
and the chain from line i on holds; line i-1 inserted when line i links to line i-2; else line i itself
(edited, inserted or moved). A forwarded copy (``--copy``) and a head noted elsewhere (``--head``) catch a
trail rewritten together with its head.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from .trail import GENESIS, Head, line_hash, lines, read_head


@dataclass(frozen=True)
class Finding:
    line: int  # 1-based; one past the last line for a cut-off tail
    what: str

    def __str__(self) -> str:
        return f"line {self.line}: {self.what}"


@dataclass
class Result:
    records: int = 0
    last_seq: int = 0
    last_hash: str = GENESIS
    problems: list[Finding] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def holds(self) -> bool:
        return not self.problems


def _parse(line: bytes) -> dict[str, Any] | None:
    try:
        rec = json.loads(line)
    except ValueError:
        return None
    if (
        not isinstance(rec, dict)
        or not isinstance(rec.get("seq"), int)
        or isinstance(rec.get("seq"), bool)
        or not isinstance(rec.get("prev"), str)
    ):
        return None
    return rec


def _blame(ls: Sequence[bytes], recs: Sequence[dict[str, Any] | None], i: int, head: Head | None) -> Finding:
    """The link into line i (0-based) breaks: which record is to blame. The last line is pinned by the head."""
    rec = recs[i]
    assert rec is not None
    prev_rec = recs[i - 1] if i > 0 else None
    expected_seq = 1 if prev_rec is None else int(prev_rec["seq"]) + 1

    def holds_from(k: int) -> bool:  # line k links to line k-1 (past the end: the head names the last line)
        if k >= len(ls):
            last = recs[-1]
            return head is not None and last is not None and head.seq == last["seq"] and head.hash == line_hash(ls[-1])
        return (
            recs[k] is not None
            and recs[k]["prev"] == line_hash(ls[k - 1])  # type: ignore[index]
            and recs[k]["seq"] == recs[k - 1]["seq"] + 1  # type: ignore[index]
        )

    if rec["prev"] == (GENESIS if i == 0 else line_hash(ls[i - 1])):
        return Finding(i + 1, f"seq {rec['seq']} where {expected_seq} was due (its seq was changed)")
    if i > 0 and rec["seq"] == expected_seq and holds_from(i + 1):
        return Finding(
            i,
            f"record seq {prev_rec['seq']} was changed: the next record's prev no longer "  # type: ignore[index]
            "matches it",
        )
    if rec["seq"] > expected_seq and holds_from(i + 1):
        gone = f"seq {expected_seq}" if rec["seq"] == expected_seq + 1 else f"seq {expected_seq} to {rec['seq'] - 1}"
        return Finding(i + 1, f"records are missing before it ({gone} removed)")
    if i > 1 and recs[i - 1] is not None and rec["prev"] == line_hash(ls[i - 2]):
        return Finding(i, f"record seq {recs[i - 1]['seq']} was inserted: the records around it link past it")  # type: ignore[index]
    if rec["seq"] < expected_seq:
        return Finding(i + 1, f"record seq {rec['seq']} is out of place (moved, or inserted)")
    return Finding(i + 1, f"record seq {rec['seq']} does not follow the line before it (changed, inserted or moved)")


def verify(folder: str, *, copy: str | None = None, head: str | None = None) -> Result:
    """The trail in ``folder`` checked whole; ``copy``: a syslog receiver's file; ``head``: ``SEQ:HASH``."""
    ls = lines(folder)
    out = Result()
    torn = False
    try:
        with open(f"{folder}/trail.jsonl", "rb") as f:
            f.seek(0, 2)
            size = f.tell()
            if size:
                f.seek(size - 1)
                torn = f.read(1) != b"\n"
    except FileNotFoundError:
        pass
    if torn:  # a crash's cut line: set aside here as the next append does
        out.notes.append(
            f"line {len(ls)} is cut short (a crash while it was appended); the next append keeps its "
            "bytes in a trail-torn record"
        )
        ls = ls[:-1]
    recs = [_parse(x) for x in ls]
    for i, rec in enumerate(recs):
        if rec is None:
            out.problems.append(Finding(i + 1, "not a record (not JSON with seq and prev): changed"))
            break
        expected_prev = GENESIS if i == 0 else line_hash(ls[i - 1])
        expected_seq = 1 if i == 0 else (recs[i - 1] or {}).get("seq", 0) + 1
        if rec["prev"] != expected_prev or rec["seq"] != expected_seq:
            out.problems.append(_blame(ls, recs, i, read_head(folder)))
            break
    out.records = len(ls)
    if ls and recs[-1] is not None:
        out.last_seq, out.last_hash = int(recs[-1]["seq"]), line_hash(ls[-1])
    if not out.problems:
        _check_head(out, read_head(folder), "its head (head.json)", ls, recs)
    if head is not None and not out.problems:
        _check_head(out, _parse_head(head), f"the head {head}", ls, recs, exact=False)
    if copy is not None and not out.problems:
        _check_copy(out, copy, ls, recs)
    return out


def _parse_head(text: str) -> Head | None:
    seq, _, h = text.partition(":")
    return Head(int(seq), h.lower()) if seq.isdigit() and re.fullmatch(r"[0-9a-fA-F]{64}", h) else None


def _check_head(
    out: Result,
    head: Head | None,
    what: str,
    ls: Sequence[bytes],
    recs: Sequence[dict[str, Any] | None],
    *,
    exact: bool = True,
) -> None:
    if head is None:
        if ls:
            out.notes.append(f"{what} cannot be read: a cut-off tail cannot be told")
        return
    if head.seq > out.last_seq:
        gone = f"seq {out.last_seq + 1}" + (f" to {head.seq}" if head.seq > out.last_seq + 1 else "")
        out.problems.append(
            Finding(
                len(ls) + 1,
                f"the trail ends at seq {out.last_seq} but {what} names seq "
                f"{head.seq}: the end was cut off ({gone} removed)",
            )
        )
        return
    at = next((i for i, r in enumerate(recs) if r is not None and r["seq"] == head.seq), None)
    if at is None:
        out.problems.append(Finding(1, f"{what} names seq {head.seq}, which the trail does not hold"))
    elif line_hash(ls[at]) != head.hash:
        out.problems.append(Finding(at + 1, f"record seq {head.seq} was changed: it no longer matches {what}"))
    elif exact and head.seq < out.last_seq:
        out.notes.append(
            f"{what} is {out.last_seq - head.seq} record(s) behind the trail (a crash between an "
            "append and its head's update)"
        )


def _check_copy(out: Result, copy: str, ls: Sequence[bytes], recs: Sequence[dict[str, Any] | None]) -> None:
    """Every record the syslog receiver got (the JSON after each line's structured data) is in the trail."""
    by_seq = {int(r["seq"]): line_hash(ls[i]) for i, r in enumerate(recs) if r is not None}
    seen = 0
    with open(copy, "rb") as f:
        for n, raw in enumerate(f, 1):
            at = raw.find(b'{"seq":')
            if at < 0:
                continue
            line = raw[at:].rstrip(b"\r\n")
            rec = _parse(line)
            if rec is None:
                continue
            seen += 1
            mine = by_seq.get(int(rec["seq"]))
            if mine is None:
                where = len(ls) + 1 if rec["seq"] > out.last_seq else 1
                out.problems.append(
                    Finding(
                        where, f"record seq {rec['seq']} of the copy ({copy} line {n}) is not in the trail: removed"
                    )
                )
                return
            if mine != line_hash(line):
                i = next(k for k, r in enumerate(recs) if r is not None and r["seq"] == rec["seq"])
                out.problems.append(
                    Finding(i + 1, f"record seq {rec['seq']} differs from the copy ({copy} line {n}): changed")
                )
                return
    out.notes.append(f"{seen} record(s) of the copy {copy} are in the trail as they were sent")
