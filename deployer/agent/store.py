"""The agent's database: SQLite (standard library) in WAL mode, a schema version and migrations.

What the agent keeps beyond the journal and the snapshots: events, the write ledger, identities,
as-left values, adoptions, windows, runs. Every write is one transaction, committed (``synchronous=FULL``:
durable across a power cut) before the agent acts on it or answers for it. The journal stays the audit log.
"""

from __future__ import annotations

import json
import os
import sqlite3
import time
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from ..errors import StateError
from ..window.state import WindowState

# each entry migrates the schema from its index to index + 1; applied in order, in one transaction each
MIGRATIONS: tuple[str, ...] = (
    """
    CREATE TABLE events (id INTEGER PRIMARY KEY AUTOINCREMENT, time REAL NOT NULL, device TEXT,
                         kind TEXT NOT NULL, message TEXT NOT NULL, detail TEXT NOT NULL DEFAULT '{}');
    CREATE INDEX events_device ON events (device, id);
    CREATE TABLE ledger (device TEXT NOT NULL, register INTEGER NOT NULL, writes INTEGER NOT NULL DEFAULT 0,
                         commits INTEGER NOT NULL DEFAULT 0, first REAL NOT NULL, last REAL NOT NULL,
                         PRIMARY KEY (device, register));
    CREATE TABLE identities (device TEXT PRIMARY KEY, objects TEXT, registers TEXT NOT NULL DEFAULT '{}',
                             fc43 INTEGER, time REAL NOT NULL);
    CREATE TABLE asleft (device TEXT PRIMARY KEY, "values" TEXT NOT NULL, source TEXT NOT NULL, time REAL NOT NULL);
    CREATE TABLE adopted (device TEXT PRIMARY KEY, recipe TEXT NOT NULL, sha256 TEXT NOT NULL, run TEXT,
                          time REAL NOT NULL);
    CREATE TABLE windows (run TEXT NOT NULL, kind TEXT NOT NULL, devices TEXT NOT NULL, deadline REAL NOT NULL,
                          boot_id TEXT NOT NULL, report TEXT, state TEXT NOT NULL DEFAULT 'open',
                          options TEXT NOT NULL DEFAULT '{}', time REAL NOT NULL, PRIMARY KEY (run, kind));
    CREATE TABLE runs (id TEXT PRIMARY KEY, command TEXT NOT NULL, options TEXT NOT NULL, state TEXT NOT NULL,
                       exit_code INTEGER, report TEXT, started REAL NOT NULL, finished REAL);
    """,
)
SCHEMA_VERSION = len(MIGRATIONS)


def boot_id() -> str:
    """This boot of the machine (Linux); a reboot (power loss) gives another. Elsewhere: the boot time."""
    try:
        with open("/proc/sys/kernel/random/boot_id", encoding="ascii") as f:
            return f.read().strip()
    except OSError:  # not Linux: the boot time estimated from the clocks (a reboot changes it)
        return f"boot-{round(time.time() - time.monotonic(), -1):.0f}"


class Store:
    """One agent's database (one connection, used from the agent's event loop thread only)."""

    def __init__(self, path: str) -> None:
        self.path = path
        try:
            os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
            self.db = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
            self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute("PRAGMA synchronous=FULL")  # a committed transaction survives a power cut
            self.db.execute("PRAGMA busy_timeout=5000")
            self._migrate()
        except sqlite3.Error as e:
            raise StateError(f"cannot use the agent database {path}: {e}") from None

    def _migrate(self) -> None:
        (version,) = self.db.execute("PRAGMA user_version").fetchone()
        if version > SCHEMA_VERSION:
            raise StateError(
                f"the agent database {self.path} has schema version {version}, newer than this "
                f"deployer knows ({SCHEMA_VERSION}): upgrade deployer (an older one never writes it)"
            )
        for v in range(version, SCHEMA_VERSION):
            self.db.execute("BEGIN IMMEDIATE")
            try:
                for stmt in MIGRATIONS[v].split(";"):
                    if stmt.strip():
                        self.db.execute(stmt)
                self.db.execute(f"PRAGMA user_version = {v + 1}")
                self.db.execute("COMMIT")
            except BaseException:
                self.db.execute("ROLLBACK")
                raise

    def version(self) -> int:
        return int(self.db.execute("PRAGMA user_version").fetchone()[0])

    def close(self) -> None:
        self.db.close()

    # ---- events -------------------------------------------------------------------------------

    def event(
        self,
        kind: str,
        message: str,
        *,
        device: str | None = None,
        detail: Mapping[str, Any] | None = None,
        when: float | None = None,
    ) -> dict[str, Any]:
        t = time.time() if when is None else when
        cur = self.db.execute(
            "INSERT INTO events (time, device, kind, message, detail) VALUES (?, ?, ?, ?, ?)",
            (t, device, kind, message, json.dumps(dict(detail or {}))),
        )
        return {
            "id": cur.lastrowid,
            "time": _iso(t),
            "device": device,
            "kind": kind,
            "message": message,
            "detail": dict(detail or {}),
        }

    def events(
        self, *, after: int = 0, limit: int = 1000, device: str | None = None, kind: str | None = None
    ) -> list[dict[str, Any]]:
        sql = "SELECT id, time, device, kind, message, detail FROM events WHERE id > ?"
        args: list[Any] = [after]
        if device is not None:
            sql += " AND device = ?"
            args.append(device)
        if kind is not None:
            sql += " AND kind = ?"
            args.append(kind)
        # the newest ``limit`` after ``after``, oldest first
        rows = self.db.execute(f"SELECT * FROM ({sql} ORDER BY id DESC LIMIT ?) ORDER BY id", (*args, limit))
        return [
            {"id": i, "time": _iso(t), "device": d, "kind": k, "message": m, "detail": json.loads(x)}
            for i, t, d, k, m, x in rows
        ]

    def prune_events(self, older_than: float) -> None:
        self.db.execute("DELETE FROM events WHERE time < ?", (time.time() - older_than,))

    # ---- the write ledger ----------------------------------------------------------------------

    def count_writes(self, device: str, writes: Mapping[int, int], commits: Mapping[int, int]) -> None:
        """Add write and commit requests per register key (one transaction)."""
        now = time.time()
        self.db.execute("BEGIN IMMEDIATE")
        try:
            for key in sorted(set(writes) | set(commits)):
                self.db.execute(
                    "INSERT INTO ledger (device, register, writes, commits, first, last) VALUES (?, ?, ?, ?, ?, ?) "
                    "ON CONFLICT (device, register) DO UPDATE SET writes = writes + excluded.writes, "
                    "commits = commits + excluded.commits, last = excluded.last",
                    (device, key, writes.get(key, 0), commits.get(key, 0), now, now),
                )
            self.db.execute("COMMIT")
        except BaseException:
            self.db.execute("ROLLBACK")
            raise

    def ledger(self, device: str | None = None) -> dict[str, dict[int, tuple[int, int]]]:
        """device -> register key -> (writes, commits)."""
        out: dict[str, dict[int, tuple[int, int]]] = {}
        sql = "SELECT device, register, writes, commits FROM ledger"
        rows = self.db.execute(sql + " WHERE device = ?", (device,)) if device else self.db.execute(sql)
        for d, r, w, c in rows:
            out.setdefault(d, {})[int(r)] = (int(w), int(c))
        return out

    # ---- identities, as-left values, adoptions ---------------------------------------------------

    def set_identity(
        self, device: str, objects: Mapping[str, str] | None, registers: Mapping[str, int], fc43: bool | None
    ) -> None:
        self.db.execute(
            "INSERT OR REPLACE INTO identities (device, objects, registers, fc43, time) VALUES (?, ?, ?, ?, ?)",
            (
                device,
                None if objects is None else json.dumps(dict(objects)),
                json.dumps(dict(registers)),
                None if fc43 is None else int(fc43),
                time.time(),
            ),
        )

    def identity(self, device: str) -> tuple[dict[str, str] | None, dict[str, int], bool | None] | None:
        row = self.db.execute("SELECT objects, registers, fc43 FROM identities WHERE device = ?", (device,)).fetchone()
        if row is None:
            return None
        objects, registers, fc43 = row
        return (
            None if objects is None else json.loads(objects),
            json.loads(registers),
            None if fc43 is None else bool(fc43),
        )

    def set_asleft(self, device: str, values: Mapping[str, Sequence[int]], source: str) -> None:
        self.db.execute(
            'INSERT OR REPLACE INTO asleft (device, "values", source, time) VALUES (?, ?, ?, ?)',
            (device, json.dumps({k: list(v) for k, v in values.items()}), source, time.time()),
        )

    def asleft(self, device: str) -> tuple[dict[str, tuple[int, ...]], str, float] | None:
        row = self.db.execute('SELECT "values", source, time FROM asleft WHERE device = ?', (device,)).fetchone()
        if row is None:
            return None
        return {k: tuple(v) for k, v in json.loads(row[0]).items()}, row[1], row[2]

    def adopt(self, device: str, recipe: str, sha256: str, run: str | None) -> None:
        self.db.execute(
            "INSERT OR REPLACE INTO adopted (device, recipe, sha256, run, time) VALUES (?, ?, ?, ?, ?)",
            (device, recipe, sha256, run, time.time()),
        )

    def adopted(self) -> dict[str, tuple[str, str, str | None, float]]:
        return {
            d: (r, s, run, t)
            for d, r, s, run, t in self.db.execute("SELECT device, recipe, sha256, run, time FROM adopted")
        }

    def forget(self, devices: Iterable[str]) -> None:
        for d in devices:
            self.db.execute("DELETE FROM adopted WHERE device = ?", (d,))

    # ---- windows ---------------------------------------------------------------------------------

    def open_window(self, w: WindowState) -> None:
        self.db.execute(
            "INSERT OR REPLACE INTO windows (run, kind, devices, deadline, boot_id, report, state, "
            "options, time) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
            (
                w.run,
                w.kind,
                json.dumps(w.devices),
                w.deadline_epoch,
                w.boot_id,
                w.report,
                w.state,
                json.dumps(w.options),
                time.time(),
            ),
        )

    def close_window(self, w: WindowState, state: str) -> None:
        """An open window ends (``state``: how); one already closed stays as it closed."""
        if w.state != "open":
            return
        w.state = state
        self.db.execute(
            "UPDATE windows SET state = ? WHERE run = ? AND kind = ? AND state = 'open'", (state, w.run, w.kind)
        )

    def windows(self, *, state: str | None = "open") -> list[WindowState]:
        sql = "SELECT run, kind, devices, deadline, boot_id, report, state, options FROM windows"
        rows = (
            self.db.execute(sql + " WHERE state = ? ORDER BY time", (state,))
            if state
            else self.db.execute(sql + " ORDER BY time")
        )
        return [
            WindowState(r, k, json.loads(d), dl, report=rep or "", boot_id=b, state=s, options=json.loads(o))
            for r, k, d, dl, b, rep, s, o in rows
        ]

    # ---- runs ------------------------------------------------------------------------------------

    def run_started(self, run: str, command: str, options: Mapping[str, Any]) -> None:
        self.db.execute(
            "INSERT OR REPLACE INTO runs (id, command, options, state, started) VALUES (?, ?, ?, ?, ?)",
            (run, command, json.dumps(dict(options)), "running", time.time()),
        )

    def run_ended(self, run: str, state: str, exit_code: int | None, report: str | None) -> None:
        self.db.execute(
            "UPDATE runs SET state = ?, exit_code = ?, report = ?, finished = ? WHERE id = ?",
            (state, exit_code, report, time.time(), run),
        )

    def runs(self, limit: int = 100) -> list[dict[str, Any]]:
        rows = self.db.execute(
            "SELECT id, command, options, state, exit_code, report, started, finished FROM runs "
            "ORDER BY started DESC LIMIT ?",
            (limit,),
        )
        return [
            {
                "id": i,
                "command": c,
                "options": json.loads(o),
                "state": s,
                "exit_code": x,
                "report_path": r,
                "started": _iso(st),
                "finished": None if f is None else _iso(f),
            }
            for i, c, o, s, x, r, st, f in rows
        ]


def _iso(t: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t)) + f".{int(t % 1 * 1000):03d}Z"
