"""The audit trail (docs/change-control.md): a hash chain that names the first record edited, removed, inserted
or reordered; appends from many processes at once; forwarded to syslog receivers (rsyslog, and a receiver
process killed for a while) without losing a record; the agent's backlog alarm on /metrics.

``DEPLOYER_TEST_SYSLOG_DOWN`` sets how long the receiver stays down in the outage test (seconds, default 3;
the issue's minute is 60): the forwarder's behaviour does not depend on it, only its back-off's length does.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from deployer.audit import record, trail
from deployer.audit.verify import verify
from tests.agent_helpers import until

ROOT = Path(__file__).resolve().parent.parent
DOWN = float(os.environ.get("DEPLOYER_TEST_SYSLOG_DOWN", "3"))


def _trail(folder: str, n: int) -> list[bytes]:
    for i in range(n):
        trail.append(
            folder,
            [
                record.event(
                    "applied",
                    device=f"d{i % 3}",
                    reason="ramps Ω",
                    detail={"parameters": [{"name": "accel", "old": "5 s", "new": f"{i} s"}]},
                )
            ],
        )
    return trail.lines(folder)


# ---- tampering is found, and named ---------------------------------------------------------------------

edits = st.one_of(
    st.tuples(st.just("edit"), st.integers(0, 10_000), st.integers(0, 10_000), st.sampled_from(b'0x"}{:,a ')),
    st.tuples(st.just("delete"), st.integers(0, 10_000), st.just(0), st.just(0)),
    st.tuples(st.just("insert"), st.integers(0, 10_000), st.integers(0, 10_000), st.just(0)),
    st.tuples(st.just("swap"), st.integers(0, 10_000), st.integers(0, 10_000), st.just(0)),
)


def _tamper(lines: list[bytes], op: tuple[str, int, int, int]) -> list[bytes] | None:
    kind, a, b, c = op
    out = list(lines)
    n = len(out)
    if kind == "edit":
        k = a % n
        at = b % len(out[k])
        if out[k][at] == c:
            return None
        out[k] = out[k][:at] + bytes([c]) + out[k][at + 1 :]
    elif kind == "delete":
        del out[a % n]
    elif kind == "insert":
        out.insert(a % (n + 1), out[b % n])
    else:
        i, j = sorted((a % n, b % n))
        if i == j:
            return None
        out[i], out[j] = out[j], out[i]
    return out


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(n=st.integers(2, 9), op=edits)
def test_any_edit_removal_insertion_or_reordering_is_found_and_the_first_such_record_named(
    n: int, op: tuple[str, int, int, int]
) -> None:
    with tempfile.TemporaryDirectory() as folder:
        lines = _trail(folder, n)
        assert verify(folder).holds
        changed = _tamper(lines, op)
        if changed is None:
            return
        Path(folder, trail.TRAIL).write_bytes(b"".join(x + b"\n" for x in changed))
        result = verify(folder)
        assert not result.holds, op
        first = next(
            i for i in range(len(changed) + 1) if i >= len(changed) or i >= len(lines) or changed[i] != lines[i]
        )
        named = result.problems[0].line - 1
        # the first line that differs is named (a duplicate next to its original: either of the two same lines)
        assert named == first or (first < len(changed) and named < len(changed) and changed[named] == changed[first]), (
            op,
            first,
            result.problems,
        )


def test_a_line_cut_by_a_crash_is_kept_and_the_chain_goes_on(tmp_path: Path) -> None:
    folder = str(tmp_path)
    _trail(folder, 3)
    with open(tmp_path / trail.TRAIL, "ab") as f:
        f.write(b'{"seq":4,"time":"2026')  # the process died in the middle of its write
    assert verify(folder).holds and "cut short" in verify(folder).notes[0]
    trail.append(folder, [record.event("confirmed")])
    result = verify(folder)
    assert result.holds and result.last_seq == 5 and not result.notes
    torn = json.loads(trail.lines(folder)[3])
    assert torn["event"] == "trail-torn" and "seq" in __import__("base64").b64decode(torn["detail"]["bytes"]).decode()


def test_a_cut_off_end_and_a_rewritten_head_are_told_apart(tmp_path: Path) -> None:
    folder = str(tmp_path)
    lines = _trail(folder, 4)
    (tmp_path / trail.TRAIL).write_bytes(b"".join(x + b"\n" for x in lines[:2]))
    assert "the end was cut off (seq 3 to 4 removed)" in str(verify(folder).problems[0])
    # cut and the head rewritten to match: only a head noted elsewhere (or a copy) tells
    head = f"4:{trail.line_hash(lines[3])}"
    (tmp_path / trail.HEAD).write_text(json.dumps({"seq": 2, "hash": trail.line_hash(lines[1])}))
    assert verify(folder).holds
    assert not verify(folder, head=head).holds


def _append_many(folder: str, who: int, count: int) -> None:
    for i in range(count):
        trail.append(folder, [record.event("applied", device=f"p{who}", detail={"i": i})])


def test_appends_from_several_processes_at_once_keep_one_chain(tmp_path: Path) -> None:
    folder = str(tmp_path / "audit")
    ctx = multiprocessing.get_context("spawn")
    procs = [ctx.Process(target=_append_many, args=(folder, w, 25)) for w in range(4)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout=120)
        assert p.exitcode == 0
    result = verify(folder)
    assert result.holds and result.last_seq == 100, result.problems
    recs = [json.loads(x) for x in trail.lines(folder)]
    for w in range(4):
        assert [r["detail"]["i"] for r in recs if r["device"] == f"p{w}"] == list(range(25))


# ---- syslog ---------------------------------------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def receiver(port: int, out: Path) -> Iterator[subprocess.Popen[str]]:
    proc = subprocess.Popen(
        [sys.executable, str(ROOT / "tests" / "syslog_receiver.py"), str(port), str(out)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "listening"
        yield proc
    finally:
        proc.kill()
        proc.wait(timeout=30)


def _received(out: Path) -> dict[int, bytes]:
    got: dict[int, bytes] = {}
    if not out.exists():
        return got
    for raw in out.read_bytes().splitlines():
        assert not raw.startswith(b"BAD"), raw
        at = raw.find(b'{"seq":')
        if at >= 0:
            got[json.loads(raw[at:])["seq"]] = raw[at:]
    return got


def test_with_the_receiver_down_for_a_while_nothing_is_lost(tmp_path: Path) -> None:
    folder = str(tmp_path / "audit")
    _trail(folder, 5)
    port, out = _free_port(), tmp_path / "received.log"
    fw = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "deployer",
            "audit",
            "forward",
            "--trail",
            folder,
            "--follow",
            "--syslog",
            f"tcp://127.0.0.1:{port}",
            "--settle",
            "0.2",
            "--retry-max",
            "1",
        ],
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        with receiver(port, out):
            until(lambda: len(_received(out)) == 5, why="the first five records at the receiver")
        down_until = time.monotonic() + DOWN  # the receiver is down: records keep coming
        while time.monotonic() < down_until:
            trail.append(folder, [record.event("drift-found", device="d1")])
            time.sleep(min(0.3, DOWN / 10))
        total = trail.read_head(folder)
        assert total is not None and total.seq > 5
        with receiver(port, out):
            until(
                lambda: set(_received(out)) >= set(range(1, total.seq + 1)),
                timeout=60,
                why="every record once the receiver is back",
            )
        got = _received(out)
        for i, line in enumerate(trail.lines(folder)):  # as they are in the trail, byte for byte
            assert got[i + 1] == line
        check = subprocess.run(
            [sys.executable, "-m", "deployer", "audit", "verify", "--trail", folder, "--copy", str(out)],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert check.returncode == 0 and f"{total.seq} records hold" in check.stdout, check.stdout + check.stderr
    finally:
        fw.terminate()
        fw.wait(timeout=30)


@pytest.mark.skipif(shutil.which("rsyslogd") is None, reason="rsyslog is not installed (apt-get install rsyslog)")
def test_rsyslog_gets_every_record_as_rfc5424_with_octet_counting(tmp_path: Path) -> None:
    folder = str(tmp_path / "audit")
    _trail(folder, 30)
    port, out = _free_port(), tmp_path / "rsyslog.log"
    conf = tmp_path / "rsyslog.conf"
    conf.write_text(f"""global(workDirectory="{tmp_path}" maxMessageSize="64k")
module(load="imtcp")
template(name="fields" type="string" string="%pri% %app-name% %msgid% %structured-data% %msg%\\n")
ruleset(name="audit") {{ action(type="omfile" file="{out}" template="fields") }}
input(type="imtcp" address="127.0.0.1" port="{port}" ruleset="audit")
""")
    rs = subprocess.Popen(
        ["rsyslogd", "-n", "-f", str(conf), "-i", str(tmp_path / "rsyslog.pid")],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:

        def listening() -> bool:
            with socket.socket() as s:
                return s.connect_ex(("127.0.0.1", port)) == 0

        until(listening, why="rsyslogd listening")
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "deployer",
                "audit",
                "forward",
                "--trail",
                folder,
                "--syslog",
                f"tcp://127.0.0.1:{port}",
                "--settle",
                "0.2",
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert r.returncode == 0 and "30 record(s) forwarded" in r.stderr, r.stderr
        until(lambda: out.exists() and len(out.read_bytes().splitlines()) >= 30, why="rsyslog's file")
    finally:
        rs.terminate()
        rs.wait(timeout=30)
    lines = out.read_text(encoding="utf-8").splitlines()
    assert len(lines) == 30
    for i, (got, mine) in enumerate(zip(lines, trail.lines(folder), strict=True), 1):
        m = re.fullmatch(r"(\d+) (\S+) (\S+) (\[[^\]]*\]) (.*)", got)
        assert m is not None, got
        pri, app, msgid, sd, msg = m.groups()
        rec = json.loads(mine)
        assert (pri, app, msgid) == ("109", "deployer", rec["event"])  # facility 13 (log audit), notice
        assert f'seq="{i}"' in sd and f'hash="{trail.line_hash(mine)}"' in sd
        assert msg.lstrip("\ufeff").encode() == mine  # the record itself, UTF-8 (Ω) intact
    check = subprocess.run(
        [sys.executable, "-m", "deployer", "audit", "verify", "--trail", folder, "--copy", str(out)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert check.returncode == 0, check.stdout + check.stderr


def _metrics(agent: Any) -> dict[str, float]:
    text = agent.client.metrics()  # with the token the agent made (every route but "/" needs a credential)
    return {ln.split(" ")[0]: float(ln.split(" ")[1]) for ln in text.splitlines() if ln.startswith("deployer_audit_")}


def test_the_agent_forwards_and_alarms_on_its_backlog(tmp_path: Path) -> None:
    from tests.agent_helpers import AgentProcess, write_site

    port, out = _free_port(), tmp_path / "received.log"
    inv = write_site(tmp_path, {"d1": "tcp://127.0.0.1:1"})
    text = inv.read_text()
    inv.write_text(f"change_control:\n  audit:\n    syslog: tcp://127.0.0.1:{port}\n    max_backlog: 3\n{text}")
    agent = AgentProcess(inv, tmp_path / "state")
    folder = str(tmp_path / "state" / "audit")
    try:
        _trail(folder, 6)  # the receiver is down: the backlog passes 3
        until(lambda: _metrics(agent).get("deployer_audit_forward_backlog_alarm") == 1, why="the alarm")
        assert _metrics(agent)["deployer_audit_forward_up"] == 0
        until(
            lambda: any(json.loads(x)["event"] == "forward-backlog" for x in trail.lines(folder)),
            why="the forward-backlog record",
        )
        with receiver(port, out):
            until(
                lambda: _metrics(agent).get("deployer_audit_forward_backlog_alarm") == 0,
                timeout=90,
                why="the backlog drained",
            )
            head = trail.read_head(folder)
            assert head is not None
            until(lambda: set(_received(out)) >= set(range(1, head.seq)), why="every record at the receiver")
        events = [json.loads(x)["event"] for x in trail.lines(folder)]
        assert "forward-restored" in events and events.count("forward-backlog") == 1
        assert _metrics(agent)["deployer_audit_forwarded_total"] >= head.seq - 1
    finally:
        assert agent.terminate() == 0


def test_show_chooses_by_device_user_and_time(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from tests.helpers import cli

    folder = str(tmp_path / "audit")
    trail.append(
        folder,
        [
            {**record.event("applied", user="ann", device="d1"), "time": "2026-01-01T10:00:00.000Z"},
            {**record.event("applied", user="ben", device="d2"), "time": "2026-01-02T10:00:00.000Z"},
            {**record.event("confirmed", user="ann"), "time": "2026-01-03T10:00:00.000Z"},
        ],
    )
    code, out, _ = cli(capsys, "audit", "show", "--trail", folder, "--json", "--user", "ann")
    assert code == 0 and [json.loads(x)["seq"] for x in out.splitlines()] == [1, 3]
    code, out, _ = cli(capsys, "audit", "show", "--trail", folder, "--device", "d2")
    assert code == 0 and out.startswith("2 2026-01-02T10:00:00.000Z applied ben device d2")
    code, out, _ = cli(
        capsys, "audit", "show", "--trail", folder, "--json", "--since", "2026-01-02", "--until", "2026-01-03T09:00Z"
    )
    assert [json.loads(x)["seq"] for x in out.splitlines()] == [2]
    code, _, err = cli(capsys, "audit", "show", "--trail", folder, "--since", "yesterday")
    assert code == 1 and "--since yesterday: expected an ISO 8601 date" in err
    code, out, _ = cli(capsys, "audit", "verify", "--trail", folder)
    assert code == 0 and "3 records hold; head seq 3" in out
