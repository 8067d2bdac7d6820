"""The public Python API: load, plan, apply, diff, pull, for one device or a fleet; sync and async.

The command line and the Ansible modules are both written on top of this module::

    import deployer
    recipe = deployer.load_recipe("line3.yaml")
    plan = deployer.plan(recipe, "tcp://10.0.0.11:502")          # reads the device, writes nothing
    report = deployer.apply(recipe, "tcp://10.0.0.11:502", unit=1)
    report.exit_code, report.to_json()
    drift = deployer.diff(recipe, "tcp://10.0.0.11:502")         # [] when the device matches
    report = deployer.apply_fleet(recipe, "inventory.yaml", limit="line3", batch="1,10%,100%")

Every ``x`` has an ``x_async`` twin for callers with their own event loop. Errors in input
raise ``InputError`` (with file positions) or ``UsageError`` before anything is sent; an
unreachable device raises ``TransportError`` from ``plan``/``diff``/``pull``, and is a device
status (``unreachable``) in an apply report.
"""

from __future__ import annotations

import asyncio
import os
import resource
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from .execute.read import read_current
from .execute.session import ApplyOptions
from .fleet.inventory import Inventory, fleet_jobs, load_inventory
from .fleet.livereport import LiveReport, not_finished
from .fleet.rollout import Job, ReadJob, apply_many, batch_sizes, failure_budget, read_many
from .load.diagnostics import InputError, UsageError
from .load.yamlsrc import Source
from .planning.model import Plan, Target
from .planning.planner import make_plan
from .profile import Profile, resolve_profile
from .recipe.loader import Entry, Recipe, load_recipe, with_overrides
from .recipe.text import recipe_text
from .report import DeviceResult, Report
from .transport.clients import DeviceURL, TransportError, describe, parse_url

__all__ = [
    "ApplyOptions",
    "DeviceResult",
    "Drift",
    "InputError",
    "Inventory",
    "Plan",
    "Profile",
    "Recipe",
    "Report",
    "TransportError",
    "UsageError",
    "apply",
    "apply_async",
    "apply_fleet",
    "apply_fleet_async",
    "device_url",
    "diff",
    "diff_async",
    "diff_values",
    "load_inventory",
    "load_profile",
    "load_recipe",
    "plan",
    "plan_async",
    "pull",
    "pull_async",
    "pulled_recipe",
    "read_fleet",
    "read_fleet_async",
    "recipe_from",
]


def load_profile(ref: str) -> Profile:
    """A built-in profile id or a profile file."""
    return resolve_profile(ref)


def recipe_from(profile: str | Profile, parameters: Mapping[str, Any], *, name: str = "inline",
                base: Recipe | None = None) -> Recipe:
    """A recipe from values given in code (``{"F07": "10 s"}``), on its own or over ``base``'s values."""
    src = Source(f"<{name}>")
    entries = [Entry(k, v, src, ("parameters", k)) for k, v in parameters.items()]
    if base is None:
        prof = profile if isinstance(profile, Profile) else resolve_profile(profile)
        ref = prof.source or prof.id
        base = Recipe(name, None, prof, (), profile_ref=ref)
    return with_overrides(base, entries)


def device_url(url: str | DeviceURL, *, timeout: float | None = None, retries: int | None = None) -> DeviceURL:
    """Parse a device URL (``tcp://HOST:PORT``, ``rtu:///dev/ttyUSB0?baudrate=19200`` ...); UsageError if bad."""
    if isinstance(url, DeviceURL):
        return url
    return parse_url(url, timeout=timeout, retries=retries)  # BadURL is a UsageError


def _target(recipe: Recipe, device: str | DeviceURL | None, unit: int | None) -> tuple[DeviceURL, int]:
    text = device if device is not None else (recipe.device.url if recipe.device else None)
    if text is None:
        raise UsageError("no device: pass a device URL or set device.url in the recipe")
    u = unit if unit is not None else (recipe.device.unit if recipe.device and recipe.device.unit is not None else 1)
    return device_url(text), u


# ---- one device --------------------------------------------------------------------------------


async def plan_async(recipe: Recipe, device: str | DeviceURL | None = None, unit: int | None = None, *,
                     write_all: bool = False, offline: bool = False) -> Plan:
    """The requests apply would send: against what the device holds now, or ``offline`` the full write plan."""
    if offline:
        u = unit if unit is not None else 1
        return make_plan(recipe, Target(None, u, recipe.profile_ref or recipe.profile.id), None, write_all=write_all)
    url, u = _target(recipe, device, unit)
    current = await read_current(recipe.profile, [d.name for d in recipe.desired], url, u)
    return make_plan(recipe, Target(describe(url), u, recipe.profile_ref or recipe.profile.id), current,
                     write_all=write_all)


def plan(recipe: Recipe, device: str | DeviceURL | None = None, unit: int | None = None, *,
         write_all: bool = False, offline: bool = False) -> Plan:
    return asyncio.run(plan_async(recipe, device, unit, write_all=write_all, offline=offline))


async def apply_async(recipe: Recipe, device: str | DeviceURL | None = None, unit: int | None = None, *,
                      options: ApplyOptions | None = None, name: str | None = None) -> Report:
    """Apply to one device; the report says per parameter what it holds now (never raises for a device fault)."""
    url, u = _target(recipe, device, unit)
    return await apply_many([Job(name or recipe.name, recipe, url, u)], parallel=1, options=options,
                            recipe_name=recipe.path or recipe.name)


def apply(recipe: Recipe, device: str | DeviceURL | None = None, unit: int | None = None, *,
          options: ApplyOptions | None = None, name: str | None = None) -> Report:
    return asyncio.run(apply_async(recipe, device, unit, options=options, name=name))


@dataclass(frozen=True)
class Drift:
    """One parameter whose device value is not the recipe's (``device`` None: it cannot be read)."""

    name: str
    desired: str
    desired_raw: tuple[int, ...]
    device: str | None
    device_raw: tuple[int, ...] | None

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "desired": self.desired, "device": self.device,
                "desired_raw": list(self.desired_raw),
                "device_raw": None if self.device_raw is None else list(self.device_raw),
                "status": "drift" if self.device_raw is not None else "not readable"}


def diff_values(recipe: Recipe, current: Mapping[str, tuple[int, ...]]) -> list[Drift]:
    """The recipe's parameters the device does not hold (or that cannot be read), in recipe order."""
    out = []
    for d in recipe.desired:
        cur = current.get(d.name)
        if cur is None or not d.parameter.same_value(cur, d.registers):  # a bit field compares its own bits
            out.append(Drift(d.name, d.text, d.registers,
                             None if cur is None else d.parameter.format_registers(cur), cur))
    return out


async def diff_async(recipe: Recipe, device: str | DeviceURL | None = None, unit: int | None = None) -> list[Drift]:
    url, u = _target(recipe, device, unit)
    return diff_values(recipe, await read_current(recipe.profile, [d.name for d in recipe.desired], url, u))


def diff(recipe: Recipe, device: str | DeviceURL | None = None, unit: int | None = None) -> list[Drift]:
    return asyncio.run(diff_async(recipe, device, unit))


def pulled_recipe(profile: Profile, values: Mapping[str, tuple[int, ...]], *, name: str, url: str, unit: int,
                  comment: str = "", relative_to: str | None = None) -> str:
    """Recipe text that sets every given parameter to the values read (applies back as a no-op)."""
    from .recipe.loader import DeviceSpec

    ref = profile.id
    if profile.source:
        ref = os.path.relpath(profile.source, os.path.dirname(os.path.abspath(relative_to))) if relative_to \
            else profile.source
    return recipe_text(ref, {profile.parameter(n): v for n, v in values.items()}, name=name,
                       device=DeviceSpec(url, unit), comment=comment)


def pull_names(profile: Profile) -> list[str]:
    """What pull reads: every parameter that can be read and written back."""
    return [p.name for p in profile.parameters if p.readable and p.writable]


async def pull_async(profile: str | Profile, device: str | DeviceURL, unit: int = 1) -> dict[str, tuple[int, ...]]:
    """Every readable, writable parameter of a device: name -> registers."""
    prof = profile if isinstance(profile, Profile) else resolve_profile(profile)
    return await read_current(prof, pull_names(prof), device_url(device), unit)


def pull(profile: str | Profile, device: str | DeviceURL, unit: int = 1) -> dict[str, tuple[int, ...]]:
    return asyncio.run(pull_async(profile, device, unit))


# ---- fleets ----------------------------------------------------------------------------------


def ensure_files(parallel: int, devices: int) -> None:
    """One socket per device in flight: raise the soft open-file limit towards the hard one, or say why not."""
    need = min(parallel, devices) + 64  # sockets, plus the report, snapshots, logs and the interpreter's own
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft >= need:
        return
    if hard != resource.RLIM_INFINITY and hard < need:
        raise UsageError(f"--parallel {parallel} needs about {need} open files, but this system allows {hard} "
                         f"(ulimit -Hn); use --parallel {max(1, hard - 64)} or raise the limit")
    resource.setrlimit(resource.RLIMIT_NOFILE, (need if hard == resource.RLIM_INFINITY else hard, hard))


def fleet_options(devices: int, *, parallel: int, batch: str | None, max_failures: str | None,
                  report_path: str | None = None) -> tuple[list[int], int | None]:
    """Check a fleet run's options before anything happens: batch sizes, failure budget, open files,
    and that the report file can be written (it is written before the first device starts)."""
    sizes = batch_sizes(batch, devices)
    budget = failure_budget(max_failures, devices)
    ensure_files(parallel, devices)
    if report_path:
        check_writable(os.path.dirname(os.path.abspath(report_path)), f"the report {report_path}")
    return sizes, budget


def check_writable(folder: str, what: str) -> None:
    """Create ``folder`` if needed and make sure a file can be written there, or say why not (UsageError)."""
    probe = os.path.join(folder, f".deployer-probe-{os.getpid()}")
    try:
        os.makedirs(folder, exist_ok=True)
        with open(probe, "w", encoding="utf-8"):
            pass
        os.remove(probe)
    except OSError as e:
        raise UsageError(f"cannot write {what}: {e.strerror}") from None


def fleet(recipe: Recipe, inventory: str | Inventory, *, limit: str | None = None, timeout: float | None = None,
          retries: int | None = None, unit: int | None = None) -> list[Job]:
    """One checked job per selected device (the recipe with the device's profile and overrides)."""
    inv = inventory if isinstance(inventory, Inventory) else load_inventory(inventory)
    jobs = fleet_jobs(inv, recipe, limit, timeout=timeout, retries=retries, unit=unit)
    if not jobs:
        raise UsageError(f"no device selected from {inv.path}")
    return jobs


async def apply_fleet_async(recipe: Recipe, inventory: str | Inventory, *, limit: str | None = None,
                            parallel: int = 8, batch: str | None = None, max_failures: str | None = None,
                            options: ApplyOptions | None = None, report_path: str | None = None,
                            on_start: Callable[[Job], None] | None = None,
                            on_done: Callable[[DeviceResult], None] | None = None) -> Report:
    """Apply to the devices of an inventory (``limit`` selects): staged, with a failure budget, see ``run_fleet``."""
    return await run_fleet_async(fleet(recipe, inventory, limit=limit), recipe_name=recipe.path or recipe.name,
                                 parallel=parallel, batch=batch, max_failures=max_failures, options=options,
                                 report_path=report_path, on_start=on_start, on_done=on_done)


async def run_fleet_async(jobs: Sequence[Job], *, recipe_name: str | None = None, parallel: int = 8,
                          batch: str | None = None, max_failures: str | None = None,
                          options: ApplyOptions | None = None, report_path: str | None = None,
                          on_start: Callable[[Job], None] | None = None,
                          on_done: Callable[[DeviceResult], None] | None = None) -> Report:
    """Apply jobs as one fleet run: ``batch`` ("1,10%,100%") stages it, ``max_failures`` ("2", "5%") caps it.

    ``report_path``: written before the first device starts (every device ``skipped``, "not
    finished") and rewritten as devices finish, so after a crash ``limit="@REPORT"`` retries
    exactly what did not end ok.
    """
    sizes, budget = fleet_options(len(jobs), parallel=parallel, batch=batch, max_failures=max_failures,
                                  report_path=report_path)
    live = None
    if report_path:
        live = LiveReport(report_path, recipe_name, not_finished(jobs))

    def done(r: DeviceResult) -> None:
        if live is not None:
            live.finished(r)
        if on_done is not None:
            on_done(r)

    try:
        report = await apply_many(jobs, parallel=parallel, options=options, recipe_name=recipe_name,
                                  on_start=on_start, on_done=done, batches=sizes, max_failures=budget)
    finally:
        if live is not None:
            live.stop()
    if live is not None:
        live.close(report)
    return report


def apply_fleet(recipe: Recipe, inventory: str | Inventory, **kw: Any) -> Report:
    return asyncio.run(apply_fleet_async(recipe, inventory, **kw))


def run_fleet(jobs: Sequence[Job], **kw: Any) -> Report:
    return asyncio.run(run_fleet_async(jobs, **kw))


async def read_fleet_async(jobs: Sequence[ReadJob], *, parallel: int = 8,
                           on_done: Callable[[str, str | None], None] | None = None,
                           ) -> dict[str, dict[str, tuple[int, ...]] | TransportError | UsageError]:
    """Current values of many devices: name -> registers by parameter, or the error that stopped the read."""
    ensure_files(parallel, len(jobs))
    return await read_many(jobs, parallel=parallel, on_done=on_done)


def read_fleet(jobs: Sequence[ReadJob], *, parallel: int = 8) -> dict[str, dict[str, tuple[int, ...]] | TransportError
                                                                    | UsageError]:
    return asyncio.run(read_fleet_async(jobs, parallel=parallel))


def read_jobs(jobs: Sequence[Job]) -> list[ReadJob]:
    """Plan and diff read what each device's recipe names."""
    return [ReadJob(j.name, j.recipe.profile, tuple(d.name for d in j.recipe.desired), j.url, j.unit) for j in jobs]

