"""What a rollback restores: a snapshot to the device it was taken from, or every device an earlier run wrote.

A run's report names each device's snapshot; a run that was killed (``kill -9``, a power cut) may
not have said so in its report file before it died, but its journal did, before the first write:
the report names the run and its state folder, and the journal's ``device-started`` lines name the
snapshots of the devices it was writing. A device that may have been written and has no snapshot
anywhere is refused by name, nothing sent.
"""

from __future__ import annotations

import hashlib
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from ..errors import BadURL, Diagnostic, InputError, UsageError
from ..execute.job import Job
from ..fleet.inventory import FleetDevice, Inventory, select
from ..fleet.livereport import NOT_FINISHED
from ..recipe.loader import Recipe, load_recipe
from ..report import read_report
from ..state import journal
from ..state.snapshot import recovered, state_of
from ..transport.urls import DeviceURL, describe, overridden, parse_url


def _url(text: str, timeout: float | None, retries: int | None, *, recorded: bool = False) -> DeviceURL:
    """``recorded``: a snapshot's URL, which keeps the apply's timeout and retries; those given now go over them
    (a URL typed now keeps its own, as everywhere)."""
    try:
        url = parse_url(text, timeout=timeout, retries=retries)
    except BadURL as e:
        raise UsageError(str(e)) from None
    return overridden(url, timeout, retries) if recorded else url


def check_digest(path: str, expected: str | None, where: str, *, accept_edited: bool) -> str | None:
    """Is the snapshot file what was written? ``expected``: the SHA-256 a report or the journal recorded
    (``where`` says which). Returns a notice when nothing recorded it; raises UsageError when it differs
    (an edited snapshot restores values nobody read from the device), unless ``accept_edited``."""
    try:
        with open(path, "rb") as f:
            actual = hashlib.sha256(f.read()).hexdigest()
    except OSError:
        return None  # loading it says what is wrong
    if expected is None:
        return f"note: {path}: no report or journal records this snapshot's SHA-256, so it cannot be checked for edits"
    if actual == expected:
        return None
    if not accept_edited:
        raise UsageError(
            f"{path} was changed after it was written (SHA-256 {actual[:12]}..., {where} recorded "
            f"{expected[:12]}...): it may no longer hold what the device held. Nothing was sent; "
            "--accept-edited-snapshot restores it as it is now"
        )
    return f"warning: {path} was changed after it was written; restoring it as it is now (--accept-edited-snapshot)"


_SNAPSHOT_NAME = re.compile(r"^.+-\d{8}T\d{6}Z(-\d+)?\.yaml$")


def _not_a_snapshot_file(path: str) -> str | None:
    """Why a path a report (or its journal) names is not opened as a snapshot, or None: only a regular file
    named as deployer names snapshots (STATE/snapshots/NAME-YYYYMMDDTHHMMSSZ.yaml) is; a link is not."""
    import stat

    if os.path.basename(os.path.dirname(path)) != "snapshots" or not _SNAPSHOT_NAME.match(os.path.basename(path)):
        return (
            "not a snapshot file deployer writes (STATE/snapshots/NAME-YYYYMMDDTHHMMSSZ.yaml): not opened; "
            "restore a snapshot you chose with: deployer rollback SNAPSHOT"
        )
    try:
        st = os.lstat(path)
    except OSError as e:
        return f"cannot read it: {e.strerror}"
    if not stat.S_ISREG(st.st_mode):
        return "not a regular file (a link, a folder or a device): not opened"
    return None


def snapshot_job(
    path: str,
    *,
    device: str | None = None,
    unit: int | None = None,
    timeout: float | None = None,
    retries: int | None = None,
    force: bool = False,
    accept_edited: bool = False,
) -> tuple[Job, str | None, list[str]]:
    """The job restoring one snapshot; why it needs consent (``--to-other-device``) when ``device`` or
    ``unit`` is not the device the snapshot was taken from (else None); notices for the user.

    The snapshot's SHA-256 is checked against the journal of the state folder it lies in (``check_digest``)."""
    state = state_of(path)
    notices = recovered(state)
    note = check_digest(
        path,
        journal.snapshot_digest(state, os.path.abspath(path)),
        f"the journal {journal.path_of(state)}",
        accept_edited=accept_edited,
    )
    rec = load_recipe(path, force=force)
    taken = rec.device.url if rec.device is not None else None
    taken_unit = rec.device.unit if rec.device is not None and rec.device.unit is not None else 1
    text = device or taken
    if text is None:
        raise UsageError("no device: pass --device URL or set device.url in the recipe")
    url = _url(text, timeout, retries, recorded=device is None)
    u = unit if unit is not None else taken_unit
    moved = None
    if rec.snapshot is not None and taken is not None:
        was = _url(taken, timeout, retries)
        if (was.bus, taken_unit) != (url.bus, u):
            moved = f"{path} was taken from {describe(was)} unit {taken_unit}, not {describe(url)} unit {u}"
    return Job(rec.name, rec, url, u), moved, notices + ([note] if note else [])


@dataclass(frozen=True)
class RunSnapshot:
    """One device of an earlier run that may have been written, and the snapshot that restores it."""

    name: str
    url: str
    unit: int
    snapshot: str | None  # absolute path; None: may have been written, and no snapshot is known
    source: str  # "report" or "journal": who named the snapshot
    sha256: str | None = None  # the snapshot file's SHA-256 as the report or the journal recorded it
    where: str = ""  # which file recorded it
    wrote: tuple[tuple[str, tuple[int, ...]], ...] = ()  # what the run read back after writing: name, registers
    held: bool = False  # the run never sent its commit there (a soak or confirmation window): nor does the rollback


@dataclass
class Restores:
    """The devices of a report to restore, and what to tell the user about the others."""

    found: list[RunSnapshot] = field(default_factory=list)
    notices: list[str] = field(default_factory=list)
    nothing: list[str] = field(default_factory=list)  # nothing was written there
    undone: list[str] = field(default_factory=list)  # the run already rolled it back itself
    problem: str | None = None  # why devices that may have been written have no known snapshot
    started: str = ""  # when the run started (ISO 8601), to order several runs


def _absolute(snap: str, report: str) -> str:
    """Relative snapshot paths (reports before snapshots were absolute): the report's folder, then here."""
    if os.path.isabs(snap):
        return snap
    beside = os.path.join(os.path.dirname(os.path.abspath(report)), snap)
    return beside if os.path.exists(beside) else os.path.abspath(snap)


def read_run(path: str) -> Restores:
    """Every device of a report's run that may have been written, with its snapshot: the report's, else the
    one the run's journal names (a run killed before its report said so). Raises InputError for a file that
    is not a deployer report."""
    try:
        data = read_report(path)
    except FileNotFoundError:
        raise InputError([Diagnostic(path, 0, 0, "no such file")]) from None
    except OSError as e:
        raise InputError([Diagnostic(path, 0, 0, f"cannot read: {e.strerror}")]) from None
    info = data.get("run")
    run, state = (info.get("id"), info.get("state_dir")) if isinstance(info, dict) else (None, None)
    started: dict[str, dict[str, Any]] = {}
    journal_problem = None
    if isinstance(run, str) and isinstance(state, str):
        import stat

        try:  # the journal the report names: a regular file only (a link could point anywhere)
            st = os.lstat(journal.path_of(state))
        except OSError:
            st = None  # none there: journal.records says so below
        if st is not None and not stat.S_ISREG(st.st_mode):
            journal_problem = f"its journal {journal.path_of(state)} is not a regular file (not opened)"
        else:
            try:
                started = {
                    str(r.get("name")): r
                    for r in journal.records(state, run)
                    if r.get("event") == "device-started" and r.get("snapshot")
                }
            except OSError as e:
                journal_problem = f"its journal {journal.path_of(state)} cannot be read ({e.strerror})"
    else:
        journal_problem = "it names no run journal (made by an older deployer)"
    out = Restores(started=str(info.get("started") or "") if isinstance(info, dict) else "")
    nothing, undone = out.nothing, out.undone
    for dev in data["devices"]:
        if not isinstance(dev, dict) or "name" not in dev:
            continue
        name = str(dev["name"])
        if dev.get("status") == "rolled-back":  # that run restored it from this snapshot itself, verified
            undone.append(name)
            continue
        url, unit = str(dev.get("url", "")), int(dev.get("unit", 1))
        snap = dev.get("snapshot")
        rec = started.get(name)
        if snap:
            snap = _absolute(str(snap), path)
            digest, where = dev.get("snapshot_sha256"), path
            if digest is None and rec is not None and rec.get("snapshot") == snap:
                digest, where = rec.get("snapshot_sha256"), journal.path_of(str(state))
            if digest is None:
                digest = journal.snapshot_digest(state_of(snap), snap)
                where = journal.path_of(state_of(snap))
            out.found.append(
                RunSnapshot(
                    name,
                    url,
                    unit,
                    snap,
                    "report",
                    digest,
                    where,
                    _wrote(dev),
                    dev.get("commit") in ("held", "not sent"),
                )
            )
            continue
        if rec is not None:
            out.found.append(
                RunSnapshot(
                    name,
                    url,
                    unit,
                    str(rec["snapshot"]),
                    "journal",
                    rec.get("snapshot_sha256"),
                    journal.path_of(str(state)),
                )
            )
            out.notices.append(
                f"{name}: the report does not name its snapshot (the run ended before it could "
                f"say so); the journal does: {rec['snapshot']}"
            )
            continue
        unknown = dev.get("status") == "interrupted" or (
            dev.get("status") == "skipped" and dev.get("error") == NOT_FINISHED
        )
        if unknown and journal_problem is not None:
            out.found.append(RunSnapshot(name, url, unit, None, "report"))
        else:
            nothing.append(name)
    if nothing:
        out.notices.append(f"nothing to roll back on {', '.join(nothing)}: nothing was written there")
    if undone:
        out.notices.append(f"nothing to roll back on {', '.join(undone)}: that run already rolled it back")
    if journal_problem and any(f.snapshot is None for f in out.found):
        out.problem = f"{path}: the run did not finish and {journal_problem}"
    return out


def report_jobs(
    paths: Sequence[str],
    *,
    limit: str | None = None,
    force: bool = False,
    timeout: float | None = None,
    retries: int | None = None,
    accept_edited: bool = False,
    even_if_changed: bool = False,
    refused: list[str] | None = None,
) -> tuple[list[Job], list[str]]:
    """One job per device earlier runs (a rollout and its retries) may have written: the snapshot of the
    earliest run that wrote it, to its own device; and the notices for the user. ``limit`` selects among
    those devices by name or pattern. A device that no longer holds what the newest run that wrote it read
    back is refused (read before anything is written), unless ``even_if_changed``: with ``refused`` (a list)
    each such device is left out and named there, the others restored; without it one changed device refuses
    them all (``--all-or-nothing``).

    Raises UsageError naming the devices that may have been written but have no known snapshot,
    and when nothing at all was written."""
    notices: list[str] = []
    nothing = undone = 0
    problems: list[str] = []
    # a rollout and its retries: the earliest run that wrote a device has its snapshot of what it held before
    # any of them; the newest one says what it should hold now. Runs are ordered by when they started.
    runs = sorted(((read_run(p), i) for i, p in enumerate(paths)), key=lambda ri: (ri[0].started, ri[1]))
    first: dict[tuple[str, int], RunSnapshot] = {}
    last: dict[tuple[str, int], tuple[int, RunSnapshot]] = {}
    for order, (r, _) in enumerate(runs):
        notices.extend(r.notices)
        nothing += len(r.nothing)
        undone += len(r.undone)
        if r.problem is not None:
            problems.append(r.problem)
        for f in r.found:
            first.setdefault((f.url, f.unit), f)
            last[(f.url, f.unit)] = (order, f)
    # runs undone newest first: the devices the newest run wrote go first
    found = sorted(first.values(), key=lambda f: -last[(f.url, f.unit)][0])
    newest = {f.name: last[(f.url, f.unit)][1] for f in found}
    if limit:  # names and patterns select among that run's devices (it has no groups)
        chosen = {d.name for d in select(Inventory(paths[0], tuple(FleetDevice(f.name, f.url) for f in found)), limit)}
        found = [f for f in found if f.name in chosen]
    blind = [f.name for f in found if f.snapshot is None]
    if blind:
        raise UsageError(
            f"{', '.join(blind)} may have been written by the run of {', '.join(paths)}, and no "
            "snapshot of them is known (" + "; ".join(problems) + "): nothing was sent. Find their "
            "snapshots with deployer status, restore them with "
            "deployer rollback SNAPSHOT, and leave them out here with --limit '!NAME'"
        )
    if not found and undone and not nothing:
        raise UsageError(
            f"{', '.join(paths)}: every device of that run was already rolled back ("
            + "; ".join(notices)
            + "): nothing to roll back"
        )
    if not found:
        raise UsageError(
            f"{', '.join(paths)}: no device of that run has a snapshot (nothing was written): nothing to roll back"
        )
    jobs: list[Job] = []
    errors: list[Diagnostic] = []
    for state in dict.fromkeys(state_of(f.snapshot) for f in found if f.snapshot is not None):
        notices.extend(recovered(state))
    for f in found:
        assert f.snapshot is not None
        refused_file = _not_a_snapshot_file(f.snapshot)
        if refused_file is not None:
            errors.append(Diagnostic(f.snapshot, 0, 0, f"{f.name}: {refused_file}; named by {f.where}"))
            continue
        note = check_digest(f.snapshot, f.sha256, f.where, accept_edited=accept_edited)
        if note:
            notices.append(note)
        try:
            rec = load_recipe(f.snapshot, force=force)
        except InputError as e:  # what is wrong, where, but never the file's text: a report chose the file
            errors.extend(
                Diagnostic(
                    d.path,
                    d.line,
                    d.col,
                    f"{f.name}: not a snapshot deployer wrote (what it "
                    f"holds is not shown here; check it with: deployer validate {d.path})",
                )
                for d in e.diagnostics[:1]
            )
            continue
        if rec.snapshot is None:
            errors.append(
                Diagnostic(
                    f.snapshot,
                    1,
                    1,
                    f"{f.name}: not a snapshot (a recipe without its snapshot block); named by " + f.where,
                )
            )
            continue
        if not _has_device(rec):
            errors.append(
                Diagnostic(
                    f.snapshot,
                    1,
                    1,
                    f"{f.name}: not a snapshot with its device (made by an "
                    "older deployer?): roll it back with rollback SNAPSHOT "
                    "--device URL",
                )
            )
            continue
        assert rec.device is not None and rec.device.url is not None
        u = rec.device.unit if rec.device.unit is not None else 1
        jobs.append(Job(f.name, rec, _url(rec.device.url, timeout, retries, recorded=True), u, hold_commit=f.held))
    if errors:
        raise InputError(errors)
    if not even_if_changed:
        changed = _changed(jobs, {n: dict(f.wrote) for n, f in newest.items()})
        if changed and refused is not None:
            refused.extend(f"{why}: not restored (--even-if-changed restores it anyway)" for why in changed.values())
            jobs = [j for j in jobs if j.name not in changed]
        elif changed:
            raise UsageError(
                "; ".join(changed.values()) + ": changed since the run wrote it (someone else wrote it "
                "since?); nothing was sent. --even-if-changed restores the snapshot anyway, or leave it "
                "out with --limit '!NAME'"
            )
    # one device in the run twice (older deployers allowed it): its snapshots are restored last written
    # first, so the earliest one, what it held before the run, is the one that stays
    twice: dict[tuple[tuple[str, ...], int], list[int]] = {}
    for i, j in enumerate(jobs):
        twice.setdefault((j.url.lock_keys, j.unit), []).append(i)
    places = list(range(len(jobs)))
    for same in twice.values():
        for i, k in zip(same, reversed(same), strict=True):
            places[i] = k
    return [jobs[k] for k in places], notices


def _changed(jobs: Sequence[Job], wrote: dict[str, dict[str, tuple[int, ...]]]) -> dict[str, str]:
    """Devices that do not hold what their newest run read back after writing (unreachable ones are left to
    the run, which says so)."""
    import asyncio

    from ..fleet.rollout import ReadJob, read_many

    reads = [
        ReadJob(
            j.name, j.recipe.profile, tuple(n for n in wrote.get(j.name, {}) if j.recipe.profile.get(n)), j.url, j.unit
        )
        for j in jobs
        if wrote.get(j.name)
    ]
    now = asyncio.run(read_many(reads, parallel=8)) if reads else {}
    out = {}
    for name, values in now.items():
        if isinstance(values, Exception):
            continue
        diff = [p for p, regs in wrote[name].items() if p in values and values[p] != regs]
        if diff:
            out[name] = f"{name} no longer holds what the run wrote ({', '.join(diff)})"
    return out


def _wrote(dev: dict[str, Any]) -> tuple[tuple[str, tuple[int, ...]], ...]:
    """The values a run wrote and read back (``ok`` parameters): what the device should still hold."""
    out = []
    for p in dev.get("parameters") or []:
        if isinstance(p, dict) and p.get("status") == "ok" and isinstance(p.get("after_raw"), list):
            out.append((str(p["name"]), tuple(int(w) for w in p["after_raw"])))
    return tuple(out)


def _has_device(rec: Recipe) -> bool:
    return rec.snapshot is not None and rec.device is not None and rec.device.url is not None
