"""What devices taught: profile limits found by their refusals, remembered per profile and device.

An apply that had to split refused writes, or fall back from Function 16 to 06, stores the limits
that would have avoided it in ``STATE/learned.json``, keyed by the profile (its file's absolute path
or built-in id) and the device key the locks use (bus and unit), with the device's Function 43
identity where it has one. ``plan`` and ``apply`` of that profile on that device use them with a
visible note; a device that answers with another identity has been replaced, and what its
predecessor taught is not used. ``deployer learned list|forget`` shows and removes entries.

The file is small JSON, rewritten whole (temporary file, fsync, rename) under an OS file lock (``state.oslock``) of a
companion lock file, so two runs finishing at once each keep their entry.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from ..portable import O_BINARY, O_CLOEXEC
from ..profile import Limits, Profile, profile_ref
from ..recipe.loader import Recipe
from ..report import write_atomic
from ..transport.urls import DeviceURL
from . import oslock

FILE = "learned.json"
SCHEMA = "deployer.learned/1"
LIMIT_KEYS = ("max_write_registers", "write_function")


@dataclass(frozen=True)
class Entry:
    profile: str  # profile_ref: a file's absolute path or a built-in id
    device: str  # the lock key: bus and unit
    limits: dict[str, int]
    seen: str  # what the device did, as the run's notice said it
    when: str  # UTC, ISO 8601
    identity: dict[str, str] | None = None
    url: str = ""  # the device's URL as the run used it (for people; the key is ``device``)
    unit: int = 0
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"profile": self.profile, "device": self.device, "url": self.url, "unit": self.unit,
                               "limits": dict(self.limits), "seen": self.seen, "when": self.when}
        if self.identity is not None:
            out["identity"] = dict(self.identity)
        return out

    @staticmethod
    def from_json(d: Mapping[str, Any]) -> Entry:
        return Entry(str(d["profile"]), str(d["device"]),
                     {k: int(v) for k, v in dict(d.get("limits") or {}).items() if k in LIMIT_KEYS},
                     str(d.get("seen", "")), str(d.get("when", "")),
                     None if d.get("identity") is None else {str(k): str(v) for k, v in dict(d["identity"]).items()},
                     str(d.get("url", "")), int(d.get("unit", 0)))

    def describe_limits(self) -> str:
        return ", ".join(f"limits.{k}: {v}" for k, v in sorted(self.limits.items()))


def path_of(state_dir: str) -> str:
    return os.path.join(os.path.abspath(state_dir), FILE)


def load(state_dir: str) -> list[Entry]:
    """Every remembered entry; a missing file is none, an unreadable one is ignored (it is a cache of
    what devices said, never the only record: the reports and the audit log keep it too)."""
    try:
        with open(path_of(state_dir), encoding="utf-8") as f:
            data = json.load(f)
        return [Entry.from_json(d) for d in data.get("devices", [])]
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        return []


@contextlib.contextmanager
def _locked(state_dir: str) -> Iterator[None]:
    os.makedirs(os.path.abspath(state_dir), exist_ok=True)
    fd = os.open(path_of(state_dir) + ".lock", os.O_RDWR | os.O_CREAT | O_BINARY | O_CLOEXEC, 0o666)
    try:
        oslock.lock_exclusive(fd)
        yield
    finally:
        os.close(fd)


def _save(state_dir: str, entries: list[Entry]) -> None:
    write_atomic(path_of(state_dir), json.dumps({"schema": SCHEMA, "devices": [e.to_json() for e in entries]},
                                                indent=2) + "\n")


def remember(state_dir: str, entry: Entry) -> None:
    """Store ``entry``, replacing what was known of that profile on that device (limits merge: a device
    that taught both keeps both)."""
    with _locked(state_dir):
        entries = load(state_dir)
        old = next((e for e in entries if (e.profile, e.device) == (entry.profile, entry.device)), None)
        if old is not None and old.identity == entry.identity:
            entry = Entry(entry.profile, entry.device, {**old.limits, **entry.limits}, entry.seen, entry.when,
                          entry.identity, entry.url, entry.unit)
        entries = [e for e in entries if (e.profile, e.device) != (entry.profile, entry.device)] + [entry]
        _save(state_dir, entries)


def forget(state_dir: str, *, profile: str | None = None, device: str | None = None) -> list[Entry]:
    """Remove the entries matching every filter given (none: all); returns what was removed."""
    with _locked(state_dir):
        entries = load(state_dir)
        gone = [e for e in entries
                if (profile is None or e.profile == profile) and (device is None or e.device == device)]
        if gone:
            _save(state_dir, [e for e in entries if e not in gone])
        return gone


def lookup(state_dir: str, profile: str, device: str) -> Entry | None:
    return next((e for e in load(state_dir) if (e.profile, e.device) == (profile, device)), None)


def now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def with_limits(profile: Profile, entry: Entry) -> Profile:
    """``profile`` with the learned limits in force (only ever tighter than the profile's own)."""
    from dataclasses import replace

    lim = profile.limits
    changes: dict[str, Any] = {}
    if "max_write_registers" in entry.limits and entry.limits["max_write_registers"] < lim.max_write_registers:
        changes["max_write_registers"] = entry.limits["max_write_registers"]
    if entry.limits.get("write_function") == 6 and lim.write_function != 6:
        changes["write_function"] = 6
    if not changes:
        return profile
    new_limits: Limits = replace(lim, **changes)
    return replace(profile, limits=new_limits)


def note(entry: Entry) -> str:
    """The visible note of a plan or apply that uses what a device taught."""
    return (f"using what this device taught on {entry.when}: {entry.describe_limits()} "
            f"({entry.seen.split(';')[0]}); 'deployer learned forget' drops it")


def device_id(url: DeviceURL, unit: int) -> str:
    """The key a device's entries are kept under: its resolved address (as its lock's), and unit.

    tcp://localhost:P, tcp://127.0.0.1:P, tcp://127.1:P and tcp://2130706433:P are one device and share
    what it taught; a name with several addresses is kept under the first of them (sorted)."""
    from .lock import device_key

    return device_key(url.lock_keys[0], unit)


def for_recipe(recipe: Recipe, state_dir: str, url: DeviceURL, unit: int) -> tuple[Recipe, Entry | None]:
    """``recipe`` with what its device taught in force (and the entry used), else unchanged."""
    from dataclasses import replace

    entry = lookup(state_dir, profile_ref(recipe.profile), device_id(url, unit))
    if entry is None:
        return recipe, None
    prof = with_limits(recipe.profile, entry)
    if prof is recipe.profile:
        return recipe, None
    return replace(recipe, profile=prof), entry
