"""Snapshots: what a device held before apply wrote to it, saved as a self-contained recipe.

A snapshot names its profile unambiguously (absolute path or built-in id, plus the SHA-256 of
the profile's text), the device it was read from (URL and unit), and the raw registers beside
the engineering values, so ``rollback`` restores the device bit for bit from any working
directory, and refuses when the profile it would decode with is not the one used to read.
Loading (the checks) lives with the recipe loader (``load_recipe`` knows the ``snapshot`` block);
this module writes snapshots (``run.rollback`` finds them again from a run's report and journal).
"""

from __future__ import annotations

import itertools
import os
import re
import time
from collections.abc import Mapping

from ..errors import UsageError
from ..portable import file_name
from ..profile import Profile, profile_ref
from ..recipe.loader import Recipe
from ..recipe.model import DeviceSpec, SnapshotInfo
from ..recipe.text import recipe_head
from ..recipe.text import values_text as recipe_values_text
from . import journal, wal
from .durable import NewFile, append_lines, disk_error, durable_now


def snapshot_dir(state_dir: str) -> str:
    return os.path.join(os.path.abspath(state_dir), "snapshots")


def state_of(snapshot: str) -> str:
    """The state folder a snapshot was written into (STATE/snapshots/NAME.yaml)."""
    return os.path.dirname(os.path.dirname(os.path.abspath(snapshot)))


def recover(state_dir: str) -> list[str]:
    """Settle what a process that died left in the snapshots' write-ahead log (``state.wal``): the snapshot
    files restored from it (missing, or cut by the crash), each named in a ``snapshots-restored`` journal line.
    Run before snapshots are read (a run's start, rollback); cheap when nothing was left (one folder listing).
    Raises OSError when a snapshot cannot be restored (the log stays for the next try)."""
    folder = snapshot_dir(state_dir)
    restored = wal.recover(folder)
    if restored:
        append_lines(
            journal.path_of(os.path.abspath(state_dir)),
            [journal.snapshots_restored(restored, os.path.join(folder, wal.FOLDER))],
        )
    return restored


def recovered(state_dir: str) -> list[str]:
    """``recover`` before anything is sent: a notice naming what it restored, if anything; UsageError (nothing
    was sent) when a snapshot cannot be restored."""
    try:
        restored = recover(state_dir)
    except OSError as e:
        raise UsageError(
            f"cannot restore the snapshots in {state_dir} from their write-ahead log: {disk_error(e)}; nothing was sent"
        ) from None
    if not restored:
        return []
    return [
        f"note: restored {len(restored)} snapshot(s) in {state_dir} from the write-ahead log a process left "
        f"when it ended before fsync'ing them: {', '.join(restored)}"
    ]


def snapshot_file(
    state_dir: str,
    name: str,
    recipe: Recipe,
    values: Mapping[str, tuple[int, ...]],
    url: str,
    unit: int,
    *,
    applied: str | None = None,
    identity: Mapping[str, str] | None = None,
    values_text: str | None = None,
) -> NewFile:
    """The snapshot of what the device held, ready for ``durable``: a new file (never overwriting
    another run's snapshot from the same second), rendered for its first candidate path.
    ``values_text``: ``snapshot_values(recipe.profile, values)``, when the caller has it already."""
    directory = snapshot_dir(state_dir)  # made by the file's create where it is missing (``durable``)
    now = time.gmtime()
    stamp = time.strftime("%Y%m%dT%H%M%SZ", now)
    safe = file_name(name)  # valid on every system: no CON or AUX, no 300-character name

    def text(path: str) -> str:
        return snapshot_text(
            recipe.profile,
            values,
            name=name,
            url=url,
            unit=unit,
            taken=now,
            applied=applied,
            label=recipe.name,
            path=path,
            identity=identity,
            values_text=values_text,
            safe=safe,
        )

    first = os.path.join(directory, f"{safe}-{stamp}.yaml")
    later = (os.path.join(directory, f"{safe}-{stamp}-{n}.yaml") for n in itertools.count(2))
    return NewFile(later, text, (first, text(first)))


def snapshot_text(
    prof: Profile,
    values: Mapping[str, tuple[int, ...]],
    *,
    name: str,
    url: str,
    unit: int,
    taken: time.struct_time,
    applied: str | None,
    label: str,
    path: str,
    identity: Mapping[str, str] | None = None,
    values_text: str | None = None,
    safe: str | None = None,
) -> str:
    """A snapshot's text: what device ``name`` (``url`` unit ``unit``) held at ``taken`` (UTC) before
    ``applied`` (a recipe's path; None: the recipe ``label`` given in code) was applied, to be saved as ``path``.
    ``values_text``: ``snapshot_values(prof, values)``, when the caller has it already (the devices of a fleet
    holding the same values share it); ``safe``: ``file_name(name)``, when the caller has it."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", taken)
    info = SnapshotInfo(prof.digest, values, time.strftime("%Y-%m-%dT%H:%M:%SZ", taken), applied, identity=identity)
    safe = file_name(name) if safe is None else safe
    head = recipe_head(
        profile_ref(prof),
        name=f"snapshot-{safe}-{stamp}",
        device=DeviceSpec(url, unit),
        comment=f"Snapshot: what {url} unit {unit} held before applying '{applied or label}'.\n"
        f"Restore with: deployer rollback {path}",
        snapshot=info,
    )
    return head + (snapshot_values(prof, values) if values_text is None else values_text)


def snapshot_values(prof: Profile, values: Mapping[str, tuple[int, ...]]) -> str:
    """A snapshot's text from its ``registers:`` on: the raw registers, their addresses and the values."""
    return recipe_values_text([(prof.parameter(k), v) for k, v in values.items()], snapshot=True)


_STAMPED = re.compile(r"^(.+)-\d{8}T\d{6}Z(?:-\d+)?\.yaml$")
# snapshot folder -> device (its file-name form) -> its snapshots' file names: the folder is listed once per
# process, and the snapshots this process writes are added (``written``); a fleet asked for every device, and
# listing a folder of every device's snapshots once per device was quadratic in the fleet
_FILES: dict[str, dict[str, list[str]]] = {}


def _snapshots_of(directory: str, safe: str) -> list[str] | None:
    files = _FILES.get(directory)
    if files is None:
        try:
            listed = os.listdir(directory)
        except OSError:
            return None
        files = _FILES[directory] = {}
        for n in listed:
            m = _STAMPED.match(n)
            if m is not None:
                files.setdefault(m.group(1), []).append(n)
    return files.get(safe, [])


def written(path: str) -> None:
    """A snapshot this process wrote (``last_identity`` finds it without listing the folder again)."""
    files = _FILES.get(os.path.dirname(path))
    m = _STAMPED.match(os.path.basename(path))
    if files is not None and m is not None:
        files.setdefault(m.group(1), []).append(os.path.basename(path))


def last_identity(state_dir: str, name: str) -> tuple[str, dict[str, str]] | None:
    """The newest snapshot of device ``name`` that recorded a Function 43 identity: (its path, the objects).

    Only the snapshot block's ``identity:`` line is read, in the newest files first; None when no snapshot
    recorded one. The folder is listed once per process (see ``_FILES``).
    """
    import json

    directory = snapshot_dir(state_dir)
    safe = file_name(name)
    found = _snapshots_of(directory, safe)
    if not found:
        return None
    names = sorted(found, reverse=True)
    for n in names[:20]:
        path = os.path.join(directory, n)
        try:
            with open(path, encoding="utf-8") as f:
                for line in f:
                    if line.startswith("  identity: "):
                        data = json.loads(line[len("  identity: ") :])
                        if isinstance(data, dict):
                            return path, {str(k): str(v) for k, v in data.items()}
                    if line.startswith("parameters:"):
                        break
        except (OSError, ValueError):
            continue
    return None


def save_snapshot(
    state_dir: str,
    name: str,
    recipe: Recipe,
    values: Mapping[str, tuple[int, ...]],
    url: str,
    unit: int,
    *,
    applied: str | None = None,
) -> str:
    """Write the values the device held as a snapshot, durable (its text in the write-ahead log, ``state.wal``)
    before any write; the file itself is fsync'ed when the log is settled (at the latest when the process ends).

    Returns the snapshot's absolute path. ``values``: parameter name -> registers as read.
    (``apply`` uses ``snapshot_file`` with ``durable``, which shares the fsyncs with other devices.)
    """
    path = durable_now(snapshot_file(state_dir, name, recipe, values, url, unit, applied=applied))
    assert path is not None
    return path
