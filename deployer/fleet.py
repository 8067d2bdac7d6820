"""Fleets: an inventory of devices, applied in parallel except where devices share a bus."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

from . import yamlsrc
from .diagnostics import Diagnostic, InputError
from .recipe import Entry, expand


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
        ))
    return Inventory(p, tuple(devices))
