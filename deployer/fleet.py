"""Fleets: an inventory of devices, which of them a run selects, and how a rollout is staged.

Pure decisions (selection, batch sizes, failure budget, one job per device) plus the live
report file that a fleet run keeps current on disk. Talking to devices is the executor's job.
"""

from __future__ import annotations

import contextlib
import fnmatch
import json
import math
import os
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

from . import yamlsrc
from .diagnostics import Diagnostic, InputError, UsageError
from .profile import is_profile_path
from .recipe import Entry, Recipe, expand, load_recipe, with_overrides

if TYPE_CHECKING:
    from .executor import Job
    from .profile import Profile
    from .report import DeviceResult, Report


@dataclass(frozen=True)
class FleetDevice:
    name: str
    url: str
    unit: int = 1
    profile: str | None = None  # built-in id or a path (relative to the inventory)
    groups: tuple[str, ...] = ()
    timeout: float | None = None
    retries: int | None = None
    overrides: tuple[Entry, ...] = field(default=(), compare=False)  # per-device parameter values
    where: tuple[int, int] = (0, 0)  # line and column of the device's url in the inventory


@dataclass(frozen=True)
class Inventory:
    path: str
    devices: tuple[FleetDevice, ...]

    def select(self, limit: str | None) -> tuple[FleetDevice, ...]:
        """The devices ``limit`` selects, in inventory order (see ``select``)."""
        return select(self, limit)


def select(inv: Inventory, limit: str | None) -> tuple[FleetDevice, ...]:
    """``--limit``: comma-separated names, groups and glob patterns (on both); ``!x`` excludes;
    ``@REPORT.json`` selects the devices of that report whose status is not ok.

    A word that matches nothing is an error (a typo must not silently shrink a rollout).
    """
    if not limit or not limit.strip():
        return inv.devices
    chosen: set[str] = set()
    excluded: set[str] = set()
    retried: list[str] = []  # reports named with @
    positive = False
    for word in (w.strip() for w in limit.split(",")):
        if not word:
            continue
        exclude = word.startswith("!")
        word = word[1:] if exclude else word
        if word.startswith("@"):
            retried.append(word[1:])
            names = set(not_ok(word[1:]))
            unknown = sorted(names - {d.name for d in inv.devices})
            if unknown:
                raise UsageError(f"--limit {word}: devices {', '.join(unknown)} are not in {inv.path} "
                                 "(a report of another inventory?)")
        else:
            names = {d.name for d in inv.devices
                     if fnmatch.fnmatchcase(d.name, word) or any(fnmatch.fnmatchcase(g, word) for g in d.groups)}
            if not names:
                raise UsageError(f"--limit: '{word}' matches no device name or group in {inv.path}")
        if exclude:
            excluded |= names
        else:
            positive = True
            chosen |= names
    if not positive:  # only exclusions: everything else
        chosen = {d.name for d in inv.devices}
    out = tuple(d for d in inv.devices if d.name in chosen and d.name not in excluded)
    if not out and retried:
        raise UsageError(f"--limit {limit}: nothing to retry (every device of {', '.join(retried)} ended ok)")
    return out


def not_ok(report_path: str) -> list[str]:
    """Names of the devices of a report (``--report`` of an earlier run) whose status is not ok.

    A ``sent`` broadcast succeeded as far as anything can tell (exit 0): it is not retried.
    """
    from .report import read_report

    try:
        data = read_report(report_path)
    except OSError as e:
        raise UsageError(f"--limit @{report_path}: cannot read the report: {e.strerror}") from None
    return [str(d.get("name")) for d in data["devices"]
            if isinstance(d, dict) and d.get("status") not in ("ok", "sent")]


# ---- staged rollouts ---------------------------------------------------------------------------


def _count(word: str, total: int, what: str) -> int:
    """``N`` or ``P%`` of ``total`` (a percentage rounds down, but never to zero)."""
    w = word.strip()
    try:
        if w.endswith("%"):
            pct = float(w[:-1])
            if not 0 < pct <= 100:
                raise ValueError
            return max(1, math.floor(total * pct / 100))
        n = int(w)
        if n < 1:
            raise ValueError
        return n
    except ValueError:
        raise UsageError(f"{what}: '{word}' is not a positive count or a percentage (e.g. 1, 10%, 100%)") from None


def batch_sizes(spec: str | None, total: int) -> list[int]:
    """``--batch 1,10%,100%``: Ansible's ``serial``; the last size repeats until every device had its turn."""
    if not spec:
        return [total] if total else []
    sizes = [_count(w, total, "--batch") for w in spec.split(",")]
    out: list[int] = []
    left = total
    i = 0
    while left > 0:
        n = min(sizes[min(i, len(sizes) - 1)], left)
        out.append(n)
        left -= n
        i += 1
    return out


def failure_budget(spec: str | None, total: int) -> int | None:
    """``--max-failures N|P%``: after this many failed or partial devices no new device starts."""
    return None if spec is None else _count(spec, total, "--max-failures")


# ---- jobs --------------------------------------------------------------------------------------


def load_inventory(path: str | os.PathLike[str]) -> Inventory:
    p = os.fspath(path)
    data, src = yamlsrc.load(p)
    if not isinstance(data, dict):
        raise InputError([src.error((), "an inventory must be a mapping (defaults: ..., devices: ...)")])
    errors: list[Diagnostic] = yamlsrc.validate(data, "inventory", src)
    if errors:
        raise InputError(errors)
    defaults: dict[str, Any] = data.get("defaults") or {}
    devices = []
    for name, spec in data["devices"].items():
        prof = spec.get("profile", defaults.get("profile"))
        if prof is not None and is_profile_path(prof):
            prof = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(p)), prof))
        overrides = tuple(e for k, v in (spec.get("parameters") or {}).items()
                          for e in expand(k, v, src, ("devices", name, "parameters", k)))
        devices.append(FleetDevice(
            name=name, url=spec["url"], unit=int(spec.get("unit", defaults.get("unit", 1))), profile=prof,
            groups=tuple(spec.get("groups", ())),
            timeout=float(spec.get("timeout", defaults.get("timeout", 0)) or 0) or None,
            retries=spec.get("retries", defaults.get("retries")),
            overrides=overrides,
            where=src.pos(("devices", name, "url")),
        ))
    return Inventory(p, tuple(devices))


def _overrides_key(entries: Iterable[Entry]) -> str:
    return json.dumps([[e.name, e.value] for e in entries], default=str)


class RecipeCache:
    """Each distinct (recipe, profile, overrides) is parsed and checked once, however many devices share it."""

    def __init__(self, recipe: Recipe) -> None:
        self.recipe = recipe
        self._by_profile: dict[str, Recipe] = {}
        self._profiles: dict[str, Profile] = {}
        self._by_key: dict[tuple[str, str], Recipe] = {}

    def profile(self, ref: str) -> Profile:
        from .profile import resolve_profile

        if ref not in self._profiles:
            self._profiles[ref] = resolve_profile(ref)
        return self._profiles[ref]

    def for_device(self, profile_ref: str | None, overrides: Sequence[Entry]) -> Recipe:
        base = self.recipe
        if profile_ref and profile_ref != self.recipe.profile_ref:
            if profile_ref not in self._by_profile:
                assert self.recipe.path is not None
                self._by_profile[profile_ref] = load_recipe(self.recipe.path, profile=self.profile(profile_ref))
            base = self._by_profile[profile_ref]
        if not overrides:
            return base
        key = (profile_ref or "", _overrides_key(overrides))
        if key not in self._by_key:
            self._by_key[key] = with_overrides(base, overrides)
        return self._by_key[key]


def fleet_jobs(inv: Inventory, recipe: Recipe, limit: str | None, *, timeout: float | None = None,
               retries: int | None = None, unit: int | None = None) -> list[Job]:
    """One job per selected device: the recipe with the device's profile and overrides, its URL parsed.

    Everything is checked before any device is touched; all problems at once as an InputError.
    """
    from .executor import Job
    from .transport import BadURL, parse_url

    jobs: list[Job] = []
    errors: list[Diagnostic] = []
    cache = RecipeCache(recipe)
    for dev in inv.select(limit):
        try:
            r = cache.for_device(dev.profile, dev.overrides)
            url = parse_url(dev.url, timeout=timeout or dev.timeout,
                            retries=retries if retries is not None else dev.retries)
            jobs.append(Job(dev.name, r, url, unit if unit is not None else dev.unit))
        except InputError as e:
            errors.extend(e.diagnostics)
        except (BadURL, UsageError) as e:
            errors.append(Diagnostic(inv.path, *dev.where, f"{dev.name}: {e}"))
    if errors:
        raise InputError(errors)
    return jobs


# ---- the report file of a running fleet ------------------------------------------------------

NOT_FINISHED = "not finished (interrupted run)"


def not_finished(jobs: Sequence[Job]) -> list[DeviceResult]:
    """Every job as ``skipped``, "not finished": the report file's first state. The devices of one
    recipe share one (read-only) parameter list, so its JSON is made once (``LiveReport``)."""
    from .executor import skipped_result
    from .transport import describe

    first: dict[int, DeviceResult] = {}
    out = []
    for j in jobs:
        proto = first.get(id(j.recipe))
        if proto is None:
            proto = first[id(j.recipe)] = skipped_result(j, NOT_FINISHED)
        out.append(replace(proto, name=j.name, url=describe(j.url), unit=j.unit, requests=[], notices=[]))
    return out


def _device_json(d: DeviceResult, made: dict[int, str]) -> bytes:
    """``json.dumps(d.to_json())``, with the JSON of a parameter list shared by several devices made once."""
    params = made.get(id(d.parameters))
    if params is None:
        params = made[id(d.parameters)] = json.dumps([p.to_json() for p in d.parameters])
    # no string value can hold this text unescaped, so the first match is the key itself
    return json.dumps(replace(d, parameters=[]).to_json()).replace('"parameters": []', f'"parameters": {params}',
                                                                   1).encode()


def _report_parts(recipe: str | None, devices: Sequence[bytes], summary: dict[str, Any]) -> list[bytes]:
    # one device per line, each encoded by the C encoder (the pure-Python indenting one took a second
    # for 200 devices x 100 parameters), kept as the devices' own bytes: the live report file is
    # rewritten from these pieces with one gathering write, never joined into one big string
    head = json.dumps({"schema": "deployer.report/1", "recipe": recipe})[:-1]
    out = [f'{head}, "devices": [\n'.encode()]
    for i, d in enumerate(devices):
        if i:
            out.append(b",\n")
        out.append(d)
    out.append(f'\n], "summary": {json.dumps(summary)}}}\n'.encode())
    return out


def report_text(report: Report) -> str:
    """A fleet's report as JSON text, one device per line (``--json`` and the ``--report`` file)."""
    return b"".join(_report_parts(report.recipe, [json.dumps(d.to_json()).encode() for d in report.devices],
                                  report.summary())).decode()


class LiveReport:
    """The ``--report`` file of a fleet run, true at every moment, even after a ``kill -9``.

    Before the first device starts, every selected device is in it as ``skipped`` with the error
    "not finished (interrupted run)"; as devices finish the file is rewritten atomically
    (``report.write_atomic``: temporary file, fsync, rename) so ``--limit @FILE`` retries exactly
    the devices that did not end ok. Each device's JSON is built once; a writer thread rewrites
    the file while the run goes on, taking in every device that finished meanwhile, so a big
    fleet does not wait for its own report: for a small report that is a write per device, for a
    huge one the file lags the run by at most a few write times (devices that ended ok in that
    window would be retried by ``@FILE``, which writes nothing to a device that already matches).
    """

    def __init__(self, path: str, recipe: str | None, skeleton: Sequence[DeviceResult]) -> None:
        self.path = path
        self.recipe = recipe
        self._order = [d.name for d in skeleton]
        made: dict[int, str] = {}  # the skeleton's devices share their parameter lists (not_finished)
        self._parts = {d.name: _device_json(d, made) for d in skeleton}
        self._finished: list[DeviceResult] = []
        self._cond = threading.Condition()
        self._dirty = False
        self._closing = False
        self._started = time.monotonic()
        self._write(self._document())  # on disk before the first device starts
        self._thread = threading.Thread(target=self._loop, name="deployer-report", daemon=True)
        self._thread.start()

    def finished(self, result: DeviceResult) -> None:
        part = json.dumps(result.to_json()).encode()  # ASCII (ensure_ascii)
        with self._cond:
            self._parts[result.name] = part
            self._finished.append(result)
            self._dirty = True
            self._cond.notify()

    def stop(self) -> None:
        """Stop the writer thread (what is on disk stays: at worst one write behind)."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join()

    def close(self, report: Report) -> None:
        """Write the final report: the devices' JSON as built when they finished, the final summary."""
        from .report import write_atomic

        self.stop()
        with self._cond:
            done = {r.name for r in self._finished}
            for d in report.devices:
                if d.name not in done:  # skipped by the rollout: never reported as finished
                    self._parts[d.name] = json.dumps(d.to_json()).encode()
        write_atomic(self.path, self._document(report.summary()))

    def _document(self, summary: dict[str, Any] | None = None) -> list[bytes]:
        from .report import Report

        with self._cond:
            parts = [self._parts[n] for n in self._order]
            finished = list(self._finished)
        if summary is None:  # finished devices count for real, the rest as skipped, like the file says
            summary = Report(self.recipe, finished, time.monotonic() - self._started).summary()
            summary["devices"] = len(self._order)
            summary["skipped"] += len(self._order) - len(finished)
        return _report_parts(self.recipe, parts, summary)

    def _write(self, text: list[bytes]) -> None:
        from .report import write_atomic

        write_atomic(self.path, text)

    def _loop(self) -> None:
        while True:
            with self._cond:
                while not self._dirty and not self._closing:
                    self._cond.wait()
                if not self._dirty:  # closing, and the file already says everything
                    return
                self._dirty = False
            t = time.monotonic()
            with contextlib.suppress(OSError):  # keep the fleet running; close() raises if the disk stays bad
                self._write(self._document())
            # pace: a write that took d seconds is followed by at least 4d of run, so a huge report
            # (36 MB for 1,000 devices x 100 parameters) costs the run at most a fifth of its time
            with self._cond:
                self._cond.wait_for(lambda: self._closing, timeout=4 * (time.monotonic() - t))
