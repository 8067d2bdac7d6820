"""Fleets: an inventory of devices, applied in parallel except where devices share a bus."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from . import yamlsrc
from .diagnostics import Diagnostic, InputError, UsageError
from .recipe import Entry, Recipe, expand, load_recipe

if TYPE_CHECKING:
    from .executor import Job


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
        """All devices, or those named ``limit`` or in group ``limit`` (comma-separated list)."""
        if not limit:
            return self.devices
        wanted = {w.strip() for w in limit.split(",") if w.strip()}
        return tuple(d for d in self.devices if d.name in wanted or wanted & set(d.groups))


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
        if prof is not None and (prof.endswith((".yaml", ".yml")) or "/" in prof):
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


def fleet_jobs(inv: Inventory, recipe: Recipe, limit: str | None, *, timeout: float | None = None,
               retries: int | None = None, unit: int | None = None) -> list[Job]:
    """One job per selected device: the recipe with the device's profile and overrides, its URL parsed.

    Everything is checked before any device is touched; all problems at once as an InputError.
    """
    from .executor import Job
    from .profile import resolve_profile
    from .transport import BadURL, parse_url

    jobs: list[Job] = []
    errors: list[Diagnostic] = []
    for dev in inv.select(limit):
        try:
            r = recipe
            if dev.overrides or (dev.profile and dev.profile != recipe.profile_ref):
                assert recipe.path is not None
                prof = resolve_profile(dev.profile) if dev.profile else None
                r = load_recipe(recipe.path, extra=dev.overrides, profile=prof)
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
