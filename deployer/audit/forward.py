"""Forwarding the trail to syslog: RFC 5424 messages over TCP or TLS, RFC 6587 octet-counting framing.

The trail is the queue: the forwarder reads it from the last record it knows the receiver got (``forward.json``:
its byte offset, seq and hash) and sends what follows, a bounded batch at a time. Nothing is lost while the
receiver is down, however long: the records wait on disk. A batch counts as received once the connection it
went out on is seen alive ``settle`` seconds later (a receiver that died closes its connection, and what was in
flight is sent again after the reconnect: a duplicate carries the same seq and hash). A backlog past
``max_backlog`` records is itself recorded (``forward-backlog``, once, then ``forward-restored``) and shown on
``/metrics``. The standard library's ``SysLogHandler`` speaks neither RFC 5424 nor octet counting: hence this.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import ssl
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

from ..errors import UsageError
from . import record, trail

CURSOR = "forward.json"
FACILITY = 13  # log audit (RFC 5424 table 1)
NOTICE, WARNING = 5, 4
SD_ID = "audit@32473"  # 32473: the enterprise number RFC 5612 reserves for examples and documentation
BOM = b"\xef\xbb\xbf"
BATCH = 256


def _sd_value(text: str) -> str:
    return text.replace("\\", "\\\\").replace('"', '\\"').replace("]", "\\]")


def _token(text: Any, limit: int) -> str:
    """A header field: printable US-ASCII without spaces, at most ``limit`` characters, else ``-``."""
    s = str(text) if text is not None else ""
    return s[:limit] if s and all(33 <= ord(c) <= 126 for c in s[:limit]) else "-"


def message(line: bytes, rec: Mapping[str, Any]) -> bytes:
    """The record as an RFC 5424 message: facility log audit, severity warning for a refusal, MSGID its event,
    structured data its seq, hash and prev, the message its line (UTF-8 with a BOM)."""
    event = str(rec.get("event") or "")
    severity = WARNING if event in record.REFUSALS or event in ("trail-torn", "forward-backlog") else NOTICE
    sd = (
        f'[{SD_ID} seq="{_sd_value(str(rec.get("seq")))}" hash="{trail.line_hash(line)}" '
        f'prev="{_sd_value(str(rec.get("prev")))}"]'
    )
    head = (
        f"<{FACILITY * 8 + severity}>1 {_token(rec.get('time'), 64)} {_token(rec.get('host'), 255)} deployer "
        f"{_token(rec.get('pid'), 128)} {_token(event, 32)} {sd} "
    )
    return head.encode("ascii") + BOM + line


def framed(msg: bytes) -> bytes:
    """RFC 6587 octet counting (as RFC 5425 requires over TLS): ``LENGTH SP MESSAGE``."""
    return str(len(msg)).encode() + b" " + msg


@dataclass
class Cursor:
    offset: int = 0
    seq: int = 0
    hash: str = trail.GENESIS
    alarmed: bool = False


def target(url: str, ca: str | None = None) -> tuple[str, int, ssl.SSLContext | None]:
    """``tcp://HOST:PORT`` or ``tls://HOST:PORT`` (port 6514 by default for TLS, 514 for TCP)."""
    parts = urlsplit(url)
    if parts.scheme not in ("tcp", "tls") or not parts.hostname:
        raise UsageError(f"syslog {url}: expected tcp://HOST:PORT or tls://HOST:PORT")
    try:
        port = parts.port or (6514 if parts.scheme == "tls" else 514)
    except ValueError:
        raise UsageError(f"syslog {url}: the port is not a number") from None
    ctx = None
    if parts.scheme == "tls":
        try:
            ctx = ssl.create_default_context(cafile=ca)
        except (OSError, ssl.SSLError) as e:
            raise UsageError(f"syslog CA {ca}: cannot load it: {e}") from None
        ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    return parts.hostname, port, ctx


class Forwarder:
    """One trail to one receiver. ``run`` until cancelled; ``up``, ``sent``, ``failures``, ``backlog`` for
    /metrics (``metrics.collector``)."""

    def __init__(
        self,
        folder: str,
        url: str,
        *,
        ca: str | None = None,
        max_backlog: int = 10_000,
        settle: float = 1.0,
        retry_max: float = 30.0,
        poll: float = 0.5,
    ) -> None:
        self.folder, self.url = folder, url
        self.host, self.port, self.ssl = target(url, ca)
        self.max_backlog, self.settle, self.retry_max, self.poll = max_backlog, settle, retry_max, poll
        self.up = False
        self.sent = 0
        self.failures = 0
        self.backlog = 0
        self.last_error: str | None = None
        self.cursor = self._load()
        self._writer: asyncio.StreamWriter | None = None
        self._reader: asyncio.StreamReader | None = None
        self._wake = asyncio.Event()

    # ---- the cursor ---------------------------------------------------------------------------------

    def _load(self) -> Cursor:
        try:
            with open(os.path.join(self.folder, CURSOR), "rb") as f:
                d = json.loads(f.read(4096))
            c = Cursor(int(d["offset"]), int(d["seq"]), str(d["hash"]), bool(d.get("alarmed")))
        except (OSError, ValueError, KeyError, TypeError):
            return Cursor()
        return c if self._still_there(c) else Cursor(alarmed=c.alarmed)

    def _still_there(self, c: Cursor) -> bool:
        """The record before the cursor is where it was (a trail replaced or cut: forward it all again)."""
        if c.offset == 0:
            return True
        try:
            with open(os.path.join(self.folder, trail.TRAIL), "rb") as f:
                f.seek(max(0, c.offset - 1))
                if f.read(1) != b"\n":
                    return False
            return True
        except OSError:
            return False

    def _save(self) -> None:
        from ..state.durable import write_atomic

        c = self.cursor
        with contextlib.suppress(UsageError, OSError):
            write_atomic(
                os.path.join(self.folder, CURSOR),
                json.dumps({"url": self.url, "offset": c.offset, "seq": c.seq, "hash": c.hash, "alarmed": c.alarmed})
                + "\n",
            )

    # ---- sending --------------------------------------------------------------------------------------

    def wake(self) -> None:
        """Records were appended: look now, not at the next poll."""
        self._wake.set()

    async def _connect(self) -> None:
        self._reader, self._writer = await asyncio.wait_for(
            asyncio.open_connection(
                self.host, self.port, ssl=self.ssl, server_hostname=self.host if self.ssl else None
            ),
            10,
        )
        self.up = True

    async def _close(self) -> None:
        w, self._writer, self._reader = self._writer, None, None
        self.up = False
        if w is not None:
            w.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(w.wait_closed(), 2)

    async def _alive(self) -> bool:
        """The receiver still holds the connection (it never writes to it: a read that ends means it closed)."""
        assert self._reader is not None
        try:
            got = await asyncio.wait_for(self._reader.read(1), 0.05)
        except TimeoutError:
            return True
        except (OSError, ssl.SSLError):
            return False
        return got != b"" and not self._reader.at_eof()

    async def send_pending(self) -> int:
        """Everything after the cursor, written batch after batch, then confirmed together by a live connection
        ``settle`` seconds later; the records confirmed (OSError when the connection failed: the unconfirmed ones
        go again next time)."""
        done = 0
        while True:
            offset, last = self.cursor.offset, None
            count = 0
            while count < BATCH * 32:
                batch = trail.read_from(self.folder, offset, BATCH)
                if not batch:
                    break
                if self._writer is None:
                    await self._connect()
                assert self._writer is not None
                self._writer.write(b"".join(framed(message(line, rec)) for _, line, rec in batch))
                await self._writer.drain()
                offset, last = batch[-1][0], batch[-1]
                count += len(batch)
            if last is None:
                self._count_backlog()
                return done
            await asyncio.sleep(self.settle)
            if not await self._alive():
                raise ConnectionError("the receiver closed the connection")
            _, line, rec = last
            self.cursor.offset, self.cursor.hash = offset, trail.line_hash(line)
            self.cursor.seq = rec["seq"] if isinstance(rec.get("seq"), int) else self.cursor.seq
            self._save()
            self.sent += count
            done += count
            self._count_backlog()

    def _count_backlog(self) -> None:
        head = trail.read_head(self.folder)
        self.backlog = max(0, (head.seq if head is not None else 0) - self.cursor.seq)
        over = self.backlog > self.max_backlog
        if over != self.cursor.alarmed and (over or self.backlog <= self.max_backlog // 2):
            self.cursor.alarmed = over
            self._save()
            name = "forward-backlog" if over else "forward-restored"
            with contextlib.suppress(OSError):
                trail.append(
                    self.folder,
                    [
                        record.event(
                            name,
                            via="forwarder",
                            result="alarm" if over else "ok",
                            detail={
                                "syslog": self.url,
                                "backlog": self.backlog,
                                "max_backlog": self.max_backlog,
                                "error": self.last_error,
                            },
                        )
                    ],
                )

    async def run(self, stop: asyncio.Event | None = None) -> None:
        """Forward until ``stop`` is set (or the task is cancelled); a failed connection is tried again with
        back-off up to ``retry_max`` seconds, the backlog counted meanwhile."""
        delay = 0.2
        stop = stop or asyncio.Event()
        try:
            while not stop.is_set():
                try:
                    await self.send_pending()
                    delay = 0.2
                    self.last_error = None
                except (OSError, TimeoutError, ssl.SSLError) as e:
                    self.failures += 1
                    self.last_error = f"{type(e).__name__}: {e}"
                    await self._close()
                    self._count_backlog()
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(stop.wait(), delay)
                    delay = min(self.retry_max, delay * 2)
                    continue
                self._wake.clear()
                waits = [asyncio.ensure_future(self._wake.wait()), asyncio.ensure_future(stop.wait())]
                await asyncio.wait(waits, timeout=self.poll, return_when=asyncio.FIRST_COMPLETED)
                for w in waits:
                    w.cancel()
        finally:
            await self._close()


def collector(fw: Forwarder) -> Any:
    """The forwarder on /metrics: is the receiver connected, the backlog and its alarm, records sent, failures."""
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

    class Collector:
        def collect(self) -> Iterator[Metric]:
            yield GaugeMetricFamily(
                "deployer_audit_forward_up", "1 while the syslog receiver is connected", value=1 if fw.up else 0
            )
            yield GaugeMetricFamily(
                "deployer_audit_forward_backlog",
                "audit records not yet confirmed by the syslog receiver",
                value=fw.backlog,
            )
            yield GaugeMetricFamily(
                "deployer_audit_forward_backlog_alarm",
                "1 while the backlog is past max_backlog (a forward-backlog record says when it began)",
                value=1 if fw.cursor.alarmed else 0,
            )
            yield CounterMetricFamily(
                "deployer_audit_forwarded", "audit records the syslog receiver confirmed", value=fw.sent
            )
            yield CounterMetricFamily(
                "deployer_audit_forward_failures", "connections to the syslog receiver that failed", value=fw.failures
            )

    return Collector()


def for_agent(inventory: str, state_dir: str, registry: Any) -> Forwarder | None:
    """The agent's forwarder, when its inventory's policy names ``audit.syslog`` (registered on /metrics)."""
    from ..change import policy

    pol = policy.load(inventory)
    if pol is None or pol.audit.syslog is None:
        return None
    fw = Forwarder(
        record.folder_of(state_dir, pol.audit.trail),
        pol.audit.syslog,
        ca=pol.audit.syslog_ca,
        max_backlog=pol.audit.max_backlog,
    )
    registry.register(collector(fw))
    return fw


async def forward(
    folder: str,
    url: str,
    *,
    ca: str | None = None,
    follow: bool = False,
    max_backlog: int = 10_000,
    settle: float = 1.0,
    retry_max: float = 30.0,
) -> Forwarder:
    """``audit forward``: send what is pending once (OSError when the receiver cannot take it), or follow the
    trail until SIGTERM/SIGINT."""
    fw = Forwarder(folder, url, ca=ca, max_backlog=max_backlog, settle=settle, retry_max=retry_max)
    if not follow:
        try:
            await fw.send_pending()
        finally:
            await fw._close()
        return fw
    from ..portable import interrupt_signals, on_signals

    stop = asyncio.Event()
    undo = on_signals(asyncio.get_running_loop(), interrupt_signals(), lambda _sig: stop.set())
    try:
        await fw.run(stop)
    finally:
        undo()
    return fw
