"""Fleets: an inventory of devices, which of them a run selects, and how a rollout is staged.

Pure decisions (selection, batch sizes, failure budget, one job per device) plus the live
report file that a fleet run keeps current on disk. Talking to devices is the executor's job.
"""

from __future__ import annotations

import fnmatch
import json
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from ..errors import Diagnostic, InputError, UsageError
from ..load import schema, yamlsrc
from ..profile import is_profile_path
from ..recipe.loader import Entry, Recipe, expand, load_recipe, with_overrides

if TYPE_CHECKING:
    from ..execute.job import Job
    from ..profile import Profile


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
    recipe: str | None = None  # the recipe file this device gets, from the inventory
    # where the device's recipe and profile were said (its own entry, a group or the defaults), and its name
    at: Mapping[str, tuple[int, int]] = field(default_factory=dict, compare=False)
    # the site agent's settings for it (check_every in seconds, on_drift, on_replace), merged over its layers
    agent: Mapping[str, Any] = field(default_factory=dict, compare=False)


@dataclass(frozen=True)
class Inventory:
    path: str
    devices: tuple[FleetDevice, ...]
    groups: tuple[str, ...] = ()  # the groups that have settings (the top-level ``groups:``)
    meta: tuple[tuple[str, str], ...] = ()  # site, project, customer, line ...: the commissioning record's header

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
                raise UsageError(
                    f"--limit {word}: devices {', '.join(unknown)} are not in {inv.path} "
                    "(a report of another inventory?)"
                )
        else:
            names = {
                d.name
                for d in inv.devices
                if fnmatch.fnmatchcase(d.name, word) or any(fnmatch.fnmatchcase(g, word) for g in d.groups)
            }
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
    return [
        str(d.get("name")) for d in data["devices"] if isinstance(d, dict) and d.get("status") not in ("ok", "sent")
    ]


def commits_owed(limit: str | None) -> set[str]:
    """The devices of ``--limit @REPORT`` reports whose commit failed (or was never sent) while their write was
    verified: a retry sends their commit even when nothing is left to write."""
    from ..report import read_report

    out: set[str] = set()
    for word in (limit or "").split(","):
        word = word.strip()
        if not word.startswith("@"):
            continue
        try:
            data = read_report(word[1:])
        except OSError:
            continue  # select() says why it cannot be read
        out |= {
            str(d.get("name"))
            for d in data["devices"]
            if isinstance(d, dict)
            and d.get("status") not in ("ok", "sent")
            and d.get("commit") in ("failed", "not sent", "held")
        }
    return out


# ---- jobs --------------------------------------------------------------------------------------


# the settings a device takes from its own entry, its groups (in the order it lists them) and the defaults
_LAYERED = ("recipe", "profile", "unit", "timeout", "retries")


def load_inventory(path: str | os.PathLike[str]) -> Inventory:
    """Load and check an inventory file (profile and recipe paths in it are relative to it).

    Each device's settings: its own entry, else its groups (in the order it lists them, the later
    winning), else ``defaults``; ``parameters`` merge per name in that order (defaults < groups <
    device), over the recipe's own values. Raises InputError."""
    p = os.fspath(path)
    data, src = yamlsrc.load(p)
    return _inventory(p, data, src, os.path.dirname(os.path.abspath(p)))


def inventory_from(devices: Iterable[Mapping[str, Any]], name: str = "<devices>") -> Inventory:
    """An inventory from devices given in code (each a mapping with ``name``, ``url`` and the keys of an
    inventory file's device), checked as a file is; profile paths are relative to the working directory."""
    src = yamlsrc.Source(name)
    errors: list[Diagnostic] = []
    table: dict[str, Any] = {}
    for i, spec in enumerate(devices):
        rest = {k: v for k, v in spec.items() if k != "name" and v is not None}
        dev = spec.get("name")
        if not isinstance(dev, str) or not dev:
            errors.append(src.error((i,), f"device {i + 1}: a device needs a name"))
        elif dev in table:
            errors.append(src.error((i,), f"device {dev!r} is listed twice"))
        else:
            table[dev] = rest
    if errors:
        raise InputError(errors)
    return _inventory(name, {"devices": table}, src, os.getcwd())


def _inventory(p: str, data: Any, src: yamlsrc.Source, here: str) -> Inventory:
    if not isinstance(data, dict):
        raise InputError([src.error((), "an inventory must be a mapping (defaults: ..., devices: ...)")])
    errors: list[Diagnostic] = schema.validate(data, "inventory", src)
    if errors:
        raise InputError(errors)
    defaults: dict[str, Any] = data.get("defaults") or {}
    groups: dict[str, Any] = data.get("groups") or {}
    devices = []
    for name, spec in data["devices"].items():
        layers: list[tuple[yamlsrc.Path_, dict[str, Any]]] = [(("defaults",), defaults)]
        layers += [(("groups", g), groups[g]) for g in spec.get("groups", ()) if g in groups]
        layers.append((("devices", name), spec))
        got: dict[str, Any] = {}
        at: dict[str, tuple[int, int]] = {"device": src.pos(("devices", name), key=True)}
        params: dict[str, Entry] = {}
        agent: dict[str, Any] = {}
        for base, layer in layers:
            for key, value in (layer.get("agent") or {}).items():
                if key == "check_every":
                    from ..load.durations import parse_duration

                    try:
                        value = parse_duration(value)
                        if value <= 0:
                            raise ValueError("must be more than 0")
                    except ValueError as why:
                        errors.append(src.error((*base, "agent", key), f"check_every: {why}"))
                        continue
                agent[key] = value
            for key in _LAYERED:
                if key in layer:
                    got[key] = layer[key]
                    at[key] = src.pos((*base, key))
            for k, v in (layer.get("parameters") or {}).items():
                for e in expand(k, v, src, (*base, "parameters", k)):
                    params.pop(e.name, None)  # a later layer decides the order too
                    params[e.name] = e
        prof = got.get("profile")
        if prof is not None and is_profile_path(prof):
            prof = os.path.normpath(os.path.join(here, prof))
        rec = got.get("recipe")
        devices.append(
            FleetDevice(
                name=name,
                url=spec["url"],
                unit=int(got.get("unit", 1)),
                profile=prof,
                groups=tuple(spec.get("groups", ())),
                timeout=float(got.get("timeout", 0) or 0) or None,
                retries=got.get("retries"),
                overrides=tuple(params.values()),
                where=src.pos(("devices", name, "url")),
                # relative to the inventory, spelled as the inventory's own path is (as a RECIPE argument would be)
                recipe=None if rec is None else os.path.normpath(os.path.join(os.path.dirname(p), rec)),
                at=at,
                agent=agent,
            )
        )
    if errors:
        raise InputError(errors)
    meta = tuple((str(k), str(v)) for k, v in (data.get("meta") or {}).items())
    return Inventory(p, tuple(devices), tuple(groups), meta)


def _same_devices(path: str, devices: Sequence[tuple[FleetDevice, int]], *, check_urls: bool) -> list[Diagnostic]:
    """Devices named twice (one address and unit, however spelled), and with ``check_urls`` bad URLs.

    Two entries for one device would write it twice in one run, and their snapshots would hold each
    other's in-between values: one device, one entry.
    """
    from ..errors import BadURL
    from ..transport.urls import parse_url

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
                errors.append(
                    Diagnostic(
                        path,
                        *dev.where,
                        f"devices '{first.name}' and '{dev.name}' are one device "
                        f"({first.url} and {dev.url}, unit {unit}): name each device once",
                    )
                )
                break
    return errors


def _overrides_key(entries: Iterable[Entry]) -> str:
    return json.dumps([[e.name, e.value] for e in entries], default=str)


class RecipeCache:
    """Each distinct (recipe file, profile, overrides) is parsed and checked once, however many devices share it.

    ``recipe``: the command line's RECIPE, for every device; None: each device's own (the inventory's).
    A failure is remembered too: its errors are said once, naming every device they concern.
    """

    def __init__(self, recipe: Recipe | None, inventory: str | None = None) -> None:
        self.recipe = recipe
        self.inventory = inventory  # where the profile references come from (for the messages)
        self._profiles: dict[str, Profile | Exception] = {}
        self._bases: dict[tuple[str, str | None], Recipe | InputError] = {}
        self._by_key: dict[tuple[str, str | None, str], Recipe | InputError] = {}

    def profile(self, ref: str) -> Profile:
        from ..profile import resolve_profile

        if ref not in self._profiles:
            try:
                self._profiles[ref] = (
                    resolve_profile(ref)
                    if self.inventory is None
                    else resolve_profile(ref, relative_to=self.inventory, kind="inventory")
                )
            except (InputError, UsageError) as e:
                self._profiles[ref] = e
        got = self._profiles[ref]
        if isinstance(got, Exception):
            raise got
        return got

    def base(self, path: str | None, profile_ref: str | None) -> Recipe:
        """The recipe at ``path`` (None: the command line's) for a device of ``profile_ref`` (None: the recipe's)."""
        given = self.recipe
        if (
            given is not None
            and (path is None or path == given.path)
            and (profile_ref is None or profile_ref == given.profile_ref)
        ):
            return given
        if path is None:
            assert given is not None and given.path is not None  # a recipe built in code has no file to reload
            path = given.path
        key = (path, profile_ref)
        if key not in self._bases:
            try:
                prof = None if profile_ref is None else self.profile(profile_ref)
                self._bases[key] = load_recipe(path, profile=prof)
            except InputError as e:
                self._bases[key] = e
        got = self._bases[key]
        if isinstance(got, InputError):
            raise got
        return got

    def for_device(self, profile_ref: str | None, overrides: Sequence[Entry], path: str | None = None) -> Recipe:
        base = self.base(path, profile_ref)
        if not overrides:
            return base
        key = (base.path or "", profile_ref, _overrides_key(overrides))
        if key not in self._by_key:
            try:
                self._by_key[key] = with_overrides(base, overrides)
            except InputError as e:
                self._by_key[key] = e
        got = self._by_key[key]
        if isinstance(got, InputError):
            raise got
        return got


def fleet_jobs(
    inv: Inventory,
    recipe: Recipe | None,
    limit: str | None,
    *,
    timeout: float | None = None,
    retries: int | None = None,
    unit: int | None = None,
    require_recipe: bool = True,
) -> list[Job]:
    """One job per selected device: its recipe (``recipe``, else the one the inventory gives it) with the
    device's profile and overrides, its URL parsed.

    Everything is checked before any device is touched; all problems at once as an InputError, each
    said once and naming the devices it concerns. ``require_recipe`` False (validate): a device without
    a recipe is checked for what it has (profile, URL) and gets no job.
    """
    from ..execute.job import Job
    from ..transport.clients import parse_url

    jobs: list[Job] = []
    concerns: dict[Diagnostic, list[str]] = {}  # each problem, and the devices it stops
    cache = RecipeCache(recipe, inv.path)
    owed = commits_owed(limit)
    for dev in inv.select(limit):
        found: list[Diagnostic] = []
        try:
            if dev.profile is not None:
                cache.profile(dev.profile)
        except UsageError as e:  # an unknown built-in id
            found = [Diagnostic(inv.path, *dev.at.get("profile", dev.where), str(e))]
        except InputError as e:  # the profile file's own errors, and where the inventory names it
            where = dev.at.get("profile", dev.where)
            if all(d.line == 0 and d.path == dev.profile for d in e.diagnostics):  # cannot be read at all
                found = [Diagnostic(inv.path, *where, f"profile {dev.profile}: {d.message}") for d in e.diagnostics]
            else:
                found = [*e.diagnostics, Diagnostic(inv.path, *where, f"profile {dev.profile} is invalid")]
        if not found:
            try:
                if recipe is None and dev.recipe is None and not require_recipe:
                    parse_url(dev.url)
                elif recipe is None and dev.recipe is None:
                    found = [
                        Diagnostic(
                            inv.path,
                            *dev.at.get("device", dev.where),
                            "no recipe: give the device one (recipe: in its entry, one of its groups "
                            "or defaults) or name one on the command line" + _group_hint(inv, dev),
                        )
                    ]
                else:
                    r = cache.for_device(dev.profile, dev.overrides, None if recipe is not None else dev.recipe)
                    if r.snapshot is not None:
                        found = [
                            Diagnostic(
                                inv.path,
                                *dev.at.get("recipe", dev.where),
                                f"{r.path} is one device's snapshot: it restores only the device it was "
                                "taken from (a fleet run: deployer rollback --from-report REPORT.json)",
                            )
                        ]
                    else:
                        url = parse_url(
                            dev.url,
                            timeout=timeout or dev.timeout,
                            retries=retries if retries is not None else dev.retries,
                        )
                        jobs.append(
                            Job(
                                dev.name,
                                r,
                                url,
                                unit if unit is not None else dev.unit,
                                dev.groups[0] if dev.groups else None,
                                commit_owed=dev.name in owed,
                            )
                        )
            except InputError as e:
                found = [_at_inventory(inv, dev, d) for d in e.diagnostics]
            except UsageError as e:  # BadURL too
                found = [Diagnostic(inv.path, *dev.where, str(e))]
        for d in found:
            concerns.setdefault(d, []).append(dev.name)
    # one device named twice (--unit may make it so), said with the rest
    for d in _same_devices(
        inv.path, [(dev, unit if unit is not None else dev.unit) for dev in inv.select(limit)], check_urls=False
    ):
        concerns.setdefault(d, [])
    if concerns:
        # the RECIPE argument replaces the recipes the inventory gives: say so where that is likely the mistake
        own = {d.name for d in inv.devices if recipe is not None and d.recipe is not None and d.recipe != recipe.path}

        def said(d: Diagnostic, names: list[str]) -> str:
            if not names:  # concerns the inventory itself (a device named twice)
                return d.message
            return (
                f"{d.message} ({_devices(names)}"
                + (
                    "; the inventory gives them recipes of their own: leave out RECIPE to use those"
                    if set(names) <= own
                    else ""
                )
                + ")"
            )

        raise InputError(Diagnostic(d.path, d.line, d.col, said(d, names)) for d, names in concerns.items())
    return jobs


def _group_hint(inv: Inventory, dev: FleetDevice) -> str:
    """A group the device lists that has no settings, but nearly the name of one that has (a typo)."""
    import difflib

    for g in dev.groups:
        if g not in inv.groups:
            near = difflib.get_close_matches(g, inv.groups, n=1)
            if near:
                return f"; its group '{g}' has no entry under groups: (did you mean '{near[0]}'?)"
    return ""


def _at_inventory(inv: Inventory, dev: FleetDevice, d: Diagnostic) -> Diagnostic:
    """A recipe file the inventory names that cannot be read at all: said where the inventory names it."""
    if d.line == 0 and dev.recipe is not None and d.path == dev.recipe:
        return Diagnostic(inv.path, *dev.at.get("recipe", dev.where), f"recipe {dev.recipe}: {d.message}")
    return d


def _devices(names: Sequence[str], show: int = 8) -> str:
    """``device a`` / ``devices a, b, c`` / ``devices a, ..., h and 12 more``."""
    if len(names) == 1:
        return f"device {names[0]}"
    listed = ", ".join(names[:show])
    return f"devices {listed}" + (f" and {len(names) - show} more" if len(names) > show else "")
