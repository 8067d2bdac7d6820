"""The runs a state folder knows: confirming one that waits (``confirm``), what needs a look (``status``), and
acknowledging one after a look (``resolve_run``, the command line's)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from ..calls import checked
from ..errors import UsageError
from .checks import kind, need_flag, need_path

if TYPE_CHECKING:
    import os

    from ..state.journal import Unfinished
    from ..window.confirm import Awaiting


@dataclass(frozen=True)
class RunStatus:
    """What ``deployer status`` shows of a state folder (``status``), read only: the ``runs`` that need a
    look (never finished, interrupted while writing, or waiting for a confirmation; oldest first, each with
    who ran what and its devices), ``unreadable`` lines of the audit log (cut off by a crash), the runs
    ``awaiting`` a confirmation (run id -> when and whether its process still waits) and those that died
    ``soaking`` (run id -> its report file), the device ``locks`` held on this machine now (in ``lock_folder``,
    every run's whatever its state folder; ``held`` says them one line per holder), the devices site agents of this
    machine own (``owned``: their marks' records in ``owner_folder``, which no setting moves; ``owners`` says them
    one line per agent; empty where the lock folder is that folder: its locks are the marks), and the ``journal``
    read."""

    journal: str
    runs: list[Unfinished]
    unreadable: int
    awaiting: dict[str, Awaiting]
    soaking: dict[str, str | None]
    lock_folder: str
    locks: list[dict[str, Any]]
    held: list[str]
    owner_folder: str = ""
    owned: list[dict[str, Any]] = field(default_factory=list)
    owners: list[str] = field(default_factory=list)


def _run_id(run: object, call: str) -> str | None:
    if run is not None and not isinstance(run, str):
        raise UsageError(f"{call} takes the run id as a str, got {kind(run)}")
    return run


@checked("deployer.confirm")
def confirm(run: str | None = None, *, state_dir: str | os.PathLike[str] = ".deployer", wait: bool = False) -> str:
    """Confirm a run that waits (``apply(..., confirm_within=...)``): its held-back commit is sent. Returns the
    run id. ``run`` None: the one run that waits in ``state_dir``. ``wait``: return once the run said what its
    commit did (raising ``NotCommitted`` when it did not reach every device).

    Raises:
        UsageError: no run (or several, and ``run`` is None) waits in ``state_dir``, or the waiting process is
            gone, or its time ran out; ``run`` or ``state_dir`` of the wrong type.
        NotCommitted: with ``wait``, the commit did not reach every device (each named, and why), or the run's
            process ended without saying (``deployer.errors.NotCommitted``).
    """
    run = _run_id(run, "confirm")
    folder = need_path(state_dir, "confirm", "state_dir")
    wait = need_flag(wait, "wait")
    from ..window.confirm import confirm_run, outcome

    target = confirm_run(folder, run)
    if wait:
        outcome(folder, target)
    return target.run


def confirm_outcome(
    run: str | None = None, *, state_dir: str = ".deployer", on_confirmed: Callable[[str], None] | None = None
) -> dict[str, Any]:
    """Confirm a run that waits, as ``confirm`` does, and wait for what it did: its outcome record
    (``committed``: the devices its commit reached). ``on_confirmed(run)`` is called once the confirmation is
    given, before the wait (the run reads its parameters again first).

    Raises:
        UsageError: as ``confirm``.
        NotCommitted: the commit did not reach every device (each named, and why), or the run's process ended
            without saying.
    """
    run = _run_id(run, "confirm_outcome")
    folder = need_path(state_dir, "confirm_outcome", "state_dir")
    from ..window.confirm import confirm_run, outcome

    target = confirm_run(folder, run)
    if on_confirmed is not None:
        on_confirmed(target.run)
    return outcome(folder, target)


@checked("deployer.status")
def status(state_dir: str | os.PathLike[str] = ".deployer") -> RunStatus:
    """The runs of ``state_dir`` that need a look, and the devices held on this machine now, as
    ``deployer status`` shows them (a ``RunStatus``); read only.

    Raises:
        UsageError: ``state_dir`` is not a path.
    """
    folder = need_path(state_dir, "status", "state_dir")
    from ..state import holder, journal, lock
    from ..window.confirm import awaiting, soaking

    runs, torn = journal.unfinished(folder)
    locks_in = lock.lock_dir()
    locks = holder.held(locks_in)
    owners_in = lock.owner_dir()
    same = lock.same_folder(owners_in, locks_in)
    seen = {(r.get("key"), r.get("pid")) for r in locks}  # an agent given this lock folder: said there already
    owned = (
        []
        if same
        else [r for r in holder.held(owners_in) if r.get("agent") and (r.get("key"), r.get("pid")) not in seen]
    )
    return RunStatus(
        journal.path_of(folder),
        runs,
        torn,
        {a.run: a for a in awaiting(folder)},
        soaking(folder),
        locks_in,
        locks,
        holder.summary(locks) if locks else [],
        owners_in,
        owned,
        holder.summary(owned) if owned else [],
    )


def resolve_run(run: str, *, state_dir: str = ".deployer") -> Unfinished:
    """Acknowledge a run ``status`` lists, after a look: recorded in the audit log (by whom, when); it is
    listed no more. Returns the run as it was listed.

    Raises:
        UsageError: no such run needs a look in ``state_dir``.
    """
    folder = need_path(state_dir, "resolve_run", "state_dir")
    from ..load.messages import printable
    from ..state import journal

    try:
        return journal.resolve(folder, run)
    except KeyError:
        raise UsageError(
            f"no run {printable(str(run))} needs a look in {journal.path_of(folder)} (deployer status lists them)"
        ) from None
