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
from dataclasses import dataclass, field, replace
from typing import Any, NoReturn

from ..errors import Diagnostic, InputError, UsageError
from ..load.messages import clipped_repr
from ..portable import O_BINARY, O_CLOEXEC
from ..profile import Limits, Profile, profile_ref
from ..profile.model import PROTOCOL_MAX_WRITE
from ..recipe.loader import Recipe
from ..state.durable import write_atomic
from ..transport.urls import DeviceURL
from . import oslock

FILE = "learned.json"
SCHEMA = "deployer.learned/1"
LIMIT_KEYS = ("max_write_registers", "write_function", "device_identification")


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
        out: dict[str, Any] = {
            "profile": self.profile,
            "device": self.device,
            "url": self.url,
            "unit": self.unit,
            "limits": dict(self.limits),
            "seen": self.seen,
            "when": self.when,
        }
        if self.identity is not None:
            out["identity"] = dict(self.identity)
        return out

    @staticmethod
    def from_json(d: Mapping[str, Any]) -> Entry:
        return Entry(
            str(d["profile"]),
            str(d["device"]),
            {k: int(v) for k, v in dict(d.get("limits") or {}).items() if k in LIMIT_KEYS},
            str(d.get("seen", "")),
            str(d.get("when", "")),
            None if d.get("identity") is None else {str(k): str(v) for k, v in dict(d["identity"]).items()},
            str(d.get("url", "")),
            int(d.get("unit", 0)),
        )

    def describe_limits(self) -> str:
        return ", ".join(f"limits.{k}: {v}" for k, v in sorted(self.limits.items()))


def path_of(state_dir: str) -> str:
    return os.path.join(os.path.abspath(state_dir), FILE)


def _shown(v: Any) -> str:
    """A value as the file says it (``1E+400``, ``null``, ``true``, ``'x'``)."""
    if isinstance(v, bool) or v is None:
        return json.dumps(v)
    if isinstance(v, dict | list):
        return "a mapping" if isinstance(v, dict) else "a list"
    return clipped_repr(v) if isinstance(v, str) else str(v)


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number deployer writes")


_ENTRY_KEYS = {
    "profile": str,
    "device": str,
    "url": str,
    "unit": int,
    "limits": dict,
    "seen": str,
    "when": str,
    "identity": dict,
}


def _problems(data: Any) -> list[tuple[tuple[str | int, ...], str]]:
    """Where ``data`` is not a learned file as deployer writes it: (path, message) each."""
    if not isinstance(data, dict):
        return [((), 'expected a mapping with "schema" and "devices"')]
    out: list[tuple[tuple[str | int, ...], str]] = []
    if data.get("schema") != SCHEMA:
        out.append((("schema",), f'expected "schema": "{SCHEMA}"'))
    out.extend(((k,), f"unknown key {k!r}") for k in data if k not in ("schema", "devices"))
    devices = data.get("devices")
    if not isinstance(devices, list):
        return [*out, (("devices",), "expected a list of entries")]
    for i, d in enumerate(devices):
        if not isinstance(d, dict):
            out.append((("devices", i), "expected a mapping (an entry)"))
            continue
        for k, v in d.items():
            want = _ENTRY_KEYS.get(k)
            if want is None:
                out.append((("devices", i, k), f"unknown key {k!r}"))
            elif not (isinstance(v, want) and not isinstance(v, bool)) and not (k == "identity" and v is None):
                out.append((("devices", i, k), f"{k}: expected {want.__name__}, got {_shown(v)}"))
        for k in ("profile", "device", "limits"):
            if k not in d:
                out.append((("devices", i), f"missing {k!r}"))
        unit = d.get("unit", 0)
        if isinstance(unit, int) and not isinstance(unit, bool) and not 0 <= unit <= 247:
            out.append((("devices", i, "unit"), f"unit: {unit} is not a unit id (0-247)"))
        limits = d.get("limits")
        for k, v in limits.items() if isinstance(limits, dict) else ():
            at = ("devices", i, "limits", k)
            if k not in LIMIT_KEYS:
                out.append((at, f"unknown limit {k!r} (deployer learns {', '.join(LIMIT_KEYS)})"))
            elif not isinstance(v, int) or isinstance(v, bool):
                out.append((at, f"limits.{k}: expected a whole number, got {_shown(v)}"))
            elif k == "max_write_registers" and not 1 <= v <= PROTOCOL_MAX_WRITE:
                out.append((at, f"limits.{k}: {v} is not 1 to {PROTOCOL_MAX_WRITE}"))
            elif k == "write_function" and v not in (6, 16):
                out.append((at, f"limits.{k}: {v} is not 6 or 16"))
            elif k == "device_identification" and v != 0:
                out.append((at, f"limits.{k}: {v} is not 0 (the device does not answer Function 43)"))
        ident = d.get("identity")
        if isinstance(ident, dict):
            out.extend(
                (("devices", i, "identity", k), f"identity: expected text, got {_shown(v)}")
                for k, v in ident.items()
                if not isinstance(v, str)
            )
    return out


def load(state_dir: str) -> list[Entry]:
    """Every remembered entry; a missing file is none.

    A file that is not what deployer wrote (not JSON, a number out of range, ``1e400``, ``-Infinity``,
    a limit as text, ``null`` or ``true``) is refused: InputError at its position, naming the command
    that clears it. What devices taught changes what apply sends; a guess at a damaged file would not.
    """
    path = path_of(state_dir)
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except FileNotFoundError:
        return []
    except OSError as e:
        raise InputError([Diagnostic(path, 0, 0, f"cannot read it: {e.strerror or e}; {_clear(state_dir)}")]) from None
    try:
        data = json.loads(raw, parse_constant=_no_constant)
    except (ValueError, RecursionError):  # not JSON (or not UTF-8): the YAML reader below says where
        data = None
    else:
        problems = _problems(data)
        if not problems:
            return [Entry.from_json(d) for d in data["devices"]]
    _refuse(path, raw, data, state_dir)


def _clear(state_dir: str) -> str:
    there = "" if os.path.abspath(state_dir) == os.path.abspath(".deployer") else f" --state-dir {state_dir}"
    return (
        f"not a learned file deployer wrote: fix it, or clear it with: deployer learned forget --all{there} "
        "(devices teach their limits again on the next apply)"
    )


def _refuse(path: str, raw: bytes, data: Any, state_dir: str) -> NoReturn:
    """InputError for a damaged learned file, each problem at its position (the JSON read again, slowly,
    by the positioned reader: only ever for a file that is wrong)."""
    from ..load import yamlsrc

    hint = _clear(state_dir)
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        line = raw[: e.start].count(b"\n") + 1
        raise InputError(
            [Diagnostic(path, line, e.start - (raw.rfind(b"\n", 0, e.start) + 1) + 1, f"not UTF-8 text; {hint}")]
        ) from None
    try:
        json.loads(text, parse_constant=_no_constant)
    except json.JSONDecodeError as e:  # not JSON: where the JSON reader stopped
        raise InputError([Diagnostic(path, e.lineno, e.colno, f"invalid JSON: {e.msg}; {hint}")]) from None
    except (ValueError, RecursionError):  # NaN, Infinity (no position from the JSON reader)
        pass
    try:
        positioned, src = yamlsrc.load(path, text)
    except InputError as e:
        raise InputError([replace(d, message=f"{d.message}; {hint}") for d in e.diagnostics]) from None
    # the positioned reader reads 1e400 and 1.5 as decimals, NaN and -Infinity as text: each is flagged there
    found = [src.error(at, f"{message}; {hint}") for at, message in _problems(positioned)]
    if not found:  # pragma: no cover - both readers disagree on what is wrong
        found = [Diagnostic(path, 1, 1, f"{m}; {hint}") for _, m in _problems(data) or [((), "unreadable")]]
    raise InputError(found)


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
    write_atomic(
        path_of(state_dir), json.dumps({"schema": SCHEMA, "devices": [e.to_json() for e in entries]}, indent=2) + "\n"
    )
    _READ.pop(path_of(state_dir), None)  # this process's own change: seen by its next lookup


def remember(state_dir: str, entry: Entry) -> None:
    """Store ``entry``, replacing what was known of that profile on that device (limits merge: a device
    that taught both keeps both)."""
    with _locked(state_dir):
        entries = load(state_dir)
        old = next((e for e in entries if (e.profile, e.device) == (entry.profile, entry.device)), None)
        if old is not None and old.identity == entry.identity:
            entry = Entry(
                entry.profile,
                entry.device,
                {**old.limits, **entry.limits},
                entry.seen,
                entry.when,
                entry.identity,
                entry.url,
                entry.unit,
            )
        entries = [e for e in entries if (e.profile, e.device) != (entry.profile, entry.device)] + [entry]
        _save(state_dir, entries)


def forget(state_dir: str, *, profile: str | None = None, device: str | None = None) -> list[Entry]:
    """Remove the entries matching every filter given (none: all); returns what was removed.

    Forgetting everything clears a learned file deployer did not write too (what ``load`` refuses)."""
    with _locked(state_dir):
        if profile is None and device is None:
            try:
                entries = load(state_dir)
            except InputError:  # damaged: cleared whole
                os.unlink(path_of(state_dir))
                return [Entry("(a damaged learned file)", path_of(state_dir), {}, "", "")]
        else:
            entries = load(state_dir)
        gone = [
            e for e in entries if (profile is None or e.profile == profile) and (device is None or e.device == device)
        ]
        if gone:
            _save(state_dir, [e for e in entries if e not in gone])
        return gone


# path -> its file as last read (its identity; None: no file), and when its status was last asked of the system
_READ: dict[str, tuple[tuple[int, int, int] | None, dict[tuple[str, str], Entry], float]] = {}
# another process's changes are seen within this many seconds (this process's own at once: ``_save``): a fleet asks
# for every device, and each system call beside a worker's event loop is a moment its other thread takes the GIL
RECHECK = 1.0


def lookup(state_dir: str, profile: str, device: str) -> Entry | None:
    """What ``device`` taught of ``profile`` (None: nothing). The file is read again only when it changed (a new
    file, as every save makes one, or another size or time), and its status asked at most every ``RECHECK``
    seconds: a fleet asks this for every device, and parsing a file of thousands of entries per device was
    quadratic."""
    path = path_of(state_dir)
    now = time.monotonic()
    seen = _READ.get(path)
    if seen is not None and now - seen[2] < RECHECK:
        return seen[1].get((profile, device))
    try:
        st = os.stat(path)
    except FileNotFoundError:
        _READ[path] = (None, {}, now)
        return None
    except OSError:
        st = None  # ``load`` says why it cannot be read
    ident = None if st is None else (st.st_ino, st.st_size, st.st_mtime_ns)
    if ident is None or seen is None or seen[0] != ident:
        by_key: dict[tuple[str, str], Entry] = {}
        for e in load(state_dir):
            by_key.setdefault((e.profile, e.device), e)
        if ident is None:
            return by_key.get((profile, device))
        seen = (ident, by_key, now)
    _READ[path] = (seen[0], seen[1], now)
    return seen[1].get((profile, device))


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
    if entry.limits.get("device_identification") == 0 and lim.device_identification:
        changes["device_identification"] = False
    if not changes:
        return profile
    new_limits: Limits = replace(lim, **changes)
    return replace(profile, limits=new_limits)


def note(entry: Entry) -> str:
    """The visible note of a plan or apply that uses what a device taught."""
    return (
        f"using what this device taught on {entry.when}: {entry.describe_limits()} "
        f"({entry.seen.split(';')[0]}); 'deployer learned forget' drops it"
    )


def refusal(recipe: Recipe, over: Recipe) -> UsageError | None:
    """Why no plan can carry ``recipe`` over the limits a device taught (``over``: the recipe over them) where its
    profile alone allows one (a string longer than the writes the device takes): the planner's refusal, or None.
    A recipe the profile alone refuses raises that refusal, as it is."""
    from ..planning.planner import plan_writes

    try:
        plan_writes(over.desired, over.profile.limits)
    except UsageError as e:
        plan_writes(recipe.desired, recipe.profile.limits)
        return e
    return None


def taught(e: UsageError, entry: Entry) -> UsageError:
    """``refusal`` said with where the limit came from, and how to drop it: the profile does not say it, so the user
    would look there in vain."""
    return UsageError(
        f"{e}, which this device taught on {entry.when} (not its profile: {entry.describe_limits()}); "
        "'deployer learned forget' drops what it taught"
    )


def device_id(url: DeviceURL, unit: int) -> str:
    """The key a device's entries are kept under: its resolved address (as its lock's), and unit.

    tcp://localhost:P, tcp://127.0.0.1:P, tcp://127.1:P and tcp://2130706433:P are one device and share
    what it taught; a name with several addresses is kept under the first of them (sorted)."""
    from .lock import device_key

    return device_key(url.lock_keys[0], unit)


def for_recipe(recipe: Recipe, state_dir: str, url: DeviceURL, unit: int) -> tuple[Recipe, Entry | None]:
    """``recipe`` with what its device taught in force (and the entry used), else unchanged. Raises UsageError
    where no plan can carry it over those limits (``refusal``)."""
    from dataclasses import replace

    entry = lookup(state_dir, profile_ref(recipe.profile), device_id(url, unit))
    if entry is None:
        return recipe, None
    prof = with_limits(recipe.profile, entry)
    if prof is recipe.profile:
        return recipe, None
    over = replace(recipe, profile=prof)
    e = refusal(recipe, over)
    if e is not None:
        raise taught(e, entry)
    return over, entry
