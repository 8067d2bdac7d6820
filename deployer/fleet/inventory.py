"""Fleets: an inventory of devices, which of them a run selects, and how a rollout is staged.

Pure decisions (selection, batch sizes, failure budget, one job per device) plus the live
report file that a fleet run keeps current on disk. Talking to devices is the executor's job.
"""

from __future__ import annotations

import fnmatch
import json
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from ..load import schema, yamlsrc
from ..load.diagnostics import Diagnostic, InputError, UsageError
from ..profile import is_profile_path
from ..recipe.loader import Entry, Recipe, expand, load_recipe, with_overrides

if TYPE_CHECKING:
    from ..profile import Profile
    from .rollout import Job


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
    from ..report import read_report

    try:
        data = read_report(report_path)
    except OSError as e:
        raise UsageError(f"--limit @{report_path}: cannot read the report: {e.strerror}") from None
    return [str(d.get("name")) for d in data["devices"]
            if isinstance(d, dict) and d.get("status") not in ("ok", "sent")]


# ---- jobs --------------------------------------------------------------------------------------


def load_inventory(path: str | os.PathLike[str]) -> Inventory:
    p = os.fspath(path)
    data, src = yamlsrc.load(p)
    if not isinstance(data, dict):
        raise InputError([src.error((), "an inventory must be a mapping (defaults: ..., devices: ...)")])
    errors: list[Diagnostic] = schema.validate(data, "inventory", src)
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
    errors = _same_devices(p, [(d, d.unit) for d in devices], check_urls=False)  # bad URLs: said with the rest
    if errors:
        raise InputError(errors)
    return Inventory(p, tuple(devices))


def url_problems(inv: Inventory) -> list[Diagnostic]:
    """Every device URL that does not parse, at its position (``validate``; a run says so in fleet_jobs)."""
    return _same_devices(inv.path, [(d, d.unit) for d in inv.devices], check_urls=True)


def _same_devices(path: str, devices: Sequence[tuple[FleetDevice, int]], *, check_urls: bool) -> list[Diagnostic]:
    """Devices named twice (one address and unit, however spelled), and with ``check_urls`` bad URLs.

    Two entries for one device would write it twice in one run, and their snapshots would hold each
    other's in-between values: one device, one entry.
    """
    from ..transport.urls import BadURL, parse_url

    errors: list[Diagnostic] = []
    seen: dict[tuple[str, int], FleetDevice] = {}
    for dev, unit in devices:
        try:
            keys = parse_url(dev.url).lock_keys
        except BadURL as e:
            if check_urls:
                errors.append(Diagnostic(path, *dev.where, f"{dev.name}: {e}"))
            continue
        for k in keys:
            first = seen.setdefault((k, unit), dev)
            if first is not dev:
                errors.append(Diagnostic(path, *dev.where, f"devices {first.name} and {dev.name} are one device "
                                         f"({first.url} and {dev.url}, unit {unit}): name each device once"))
                break
    return errors


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
        from ..profile import resolve_profile

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
    from ..transport.clients import parse_url
    from .rollout import Job

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
        except UsageError as e:  # BadURL too
            errors.append(Diagnostic(inv.path, *dev.where, f"{dev.name}: {e}"))
    if unit is not None:  # --unit puts every selected device on one unit id
        errors += _same_devices(inv.path, [(d, unit) for d in inv.select(limit)], check_urls=False)
    if errors:
        raise InputError(errors)
    return jobs
