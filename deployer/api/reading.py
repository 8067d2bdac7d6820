"""Reading devices without writing, as coroutines (``deployer.aio``; ``deployer`` has their blocking twins):
``diff`` (what a device holds against a recipe) and ``pull`` (what it holds), for one device or an inventory."""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, overload

from ..calls import checked
from ..errors import DeployerError, Diagnostic, InputError, UsageError
from ..fleet.inventory import Inventory, fleet_jobs
from ..profile import Profile, resolve_profile
from ..recipe.loader import Recipe
from ..transport.urls import DeviceURL, describe
from .checks import (
    device_url,
    kind,
    need_inventory,
    need_names,
    need_parallel,
    need_profile,
    need_recipe,
    need_text,
    need_timing,
    need_unit,
    target,
)
from .running import InventoryLike
from .values import Drift, Pulled, diff_values, pull_names

if TYPE_CHECKING:
    from ..fleet.rollout import ReadJob


async def _read_many(jobs: Sequence[ReadJob], parallel: int) -> dict[str, dict[str, tuple[int, ...]] | DeployerError]:
    from ..fleet.rollout import read_many
    from ..run.runner import ensure_files

    ensure_files(parallel, len(jobs))
    return dict(await read_many(jobs, parallel=parallel))


def _selected(inventory: InventoryLike, limit: str | None, call: str) -> Inventory:
    need_text(limit, "limit")
    return need_inventory(inventory, call)


@overload
async def diff(
    recipe: Recipe | None,
    device: str | None = None,
    unit: int | None = None,
    *,
    inventory: None = None,
    limit: None = None,
    timeout: float | None = None,
    retries: int | None = None,
    parallel: int = 8,
) -> list[Drift]: ...


@overload
async def diff(
    recipe: Recipe | None,
    device: None = None,
    unit: int | None = None,
    *,
    inventory: InventoryLike,
    limit: str | None = None,
    timeout: float | None = None,
    retries: int | None = None,
    parallel: int = 8,
) -> dict[str, list[Drift] | DeployerError]: ...


@checked("deployer.aio.diff")
async def diff(
    recipe: Recipe | None,
    device: str | None = None,
    unit: int | None = None,
    *,
    inventory: InventoryLike | None = None,
    limit: str | None = None,
    timeout: float | None = None,
    retries: int | None = None,
    parallel: int = 8,
) -> list[Drift] | dict[str, list[Drift] | DeployerError]:
    """The recipe's parameters a device does not hold now (read only): a list of ``Drift``, ``[]`` when it matches.
    ``device`` and ``unit`` default to the recipe's. With ``inventory`` (and ``limit``, ``parallel`` as for
    ``plan``; ``recipe`` None: each device's own): name -> its drift, or the error that stopped its read.

    Raises:
        UsageError: no device, a bad URL, unit 0; arguments of the wrong type or out of their bounds.
        InputError: an invalid inventory, or a device's profile or overrides.
        TransportError: the one device cannot be read (a device of an inventory: its entry, not raised).
    """
    need_unit(unit)
    need_timing(timeout, retries)
    if inventory is None:
        if limit is not None:
            raise UsageError("limit selects devices of an inventory: pass inventory too")
        rec = need_recipe(recipe, "diff")
        url, u = target(rec, device, unit, timeout=timeout, retries=retries)
        from ..execute.read import read_current

        return diff_values(rec, await read_current(rec.profile, [d.name for d in rec.desired], url, u))
    if device is not None:
        raise UsageError("device and inventory exclude each other")
    parallel = need_parallel(parallel)
    chosen = None if recipe is None else need_recipe(recipe, "diff")
    inv = _selected(inventory, limit, "diff")
    jobs = fleet_jobs(inv, chosen, limit, timeout=timeout, retries=retries, unit=unit)
    if not jobs:
        raise UsageError(f"no device selected from {inv.path}")
    from ..fleet.rollout import ReadJob

    read = await _read_many(
        [ReadJob(j.name, j.recipe.profile, tuple(d.name for d in j.recipe.desired), j.url, j.unit) for j in jobs],
        parallel,
    )
    out: dict[str, list[Drift] | DeployerError] = {}
    for j in jobs:
        got = read[j.name]
        out[j.name] = got if isinstance(got, DeployerError) else diff_values(j.recipe, got)
    return out


def pull_reads(
    what: str | Profile | Recipe | None,
    inv: Inventory,
    *,
    limit: str | None,
    names: Sequence[str] | None,
    timeout: float | None,
    retries: int | None,
    unit: int | None,
) -> list[ReadJob]:
    """One read per selected device: of the recipe's parameters (``what`` a Recipe: each device's profile and
    recipe as the inventory gives them, a device named twice refused as for apply), else of every setting of the
    device's profile (its own, else its recipe's from the inventory, else ``what``: a Profile or a profile's id
    or file); only ``names`` when given."""
    from ..fleet.inventory import RecipeCache
    from ..fleet.rollout import ReadJob

    if isinstance(what, Recipe):
        jobs = fleet_jobs(inv, what, limit, timeout=timeout, retries=retries, unit=unit)
        return [ReadJob(j.name, j.recipe.profile, tuple(names or _recipe_names(j.recipe)), j.url, j.unit) for j in jobs]
    cache = RecipeCache(None, inv.path)  # profile paths are relative to the inventory, as for plan and apply
    out: list[ReadJob] = []
    errors: list[Diagnostic] = []
    for dev in inv.select(limit):
        try:
            if dev.profile is not None:
                prof = cache.profile(dev.profile)
            elif dev.recipe is not None:
                prof = cache.base(dev.recipe, None).profile
            elif what is not None:
                prof = what if isinstance(what, Profile) else resolve_profile(what)
            else:
                raise UsageError("no profile: set profile (or a recipe) in the inventory, or pass one")
            url = device_url(
                dev.url, timeout=timeout or dev.timeout, retries=retries if retries is not None else dev.retries
            )
        except UsageError as e:
            errors.append(Diagnostic(inv.path, *dev.where, f"{dev.name}: {e}"))
            continue
        except InputError as e:
            errors.extend(e.diagnostics)
            continue
        out.append(
            ReadJob(dev.name, prof, tuple(names or pull_names(prof)), url, unit if unit is not None else dev.unit)
        )
    if errors:
        raise InputError(errors)
    return out


def _recipe_names(recipe: Recipe) -> list[str]:
    """What pull reads of a recipe: its parameters; of one without any, every setting of its profile."""
    return [d.name for d in recipe.desired] or pull_names(recipe.profile)


@overload
async def pull(
    what: str | os.PathLike[str] | Profile | Recipe,
    device: str | None = None,
    unit: int | None = None,
    *,
    names: Sequence[str] | None = None,
    inventory: None = None,
    limit: None = None,
    timeout: float | None = None,
    retries: int | None = None,
    parallel: int = 8,
) -> Pulled: ...


@overload
async def pull(
    what: str | os.PathLike[str] | Profile | Recipe | None,
    device: None = None,
    unit: int | None = None,
    *,
    names: Sequence[str] | None = None,
    inventory: InventoryLike,
    limit: str | None = None,
    timeout: float | None = None,
    retries: int | None = None,
    parallel: int = 8,
) -> dict[str, Pulled | DeployerError]: ...


@checked("deployer.aio.pull")
async def pull(
    what: str | os.PathLike[str] | Profile | Recipe | None,
    device: str | None = None,
    unit: int | None = None,
    *,
    names: Sequence[str] | None = None,
    inventory: InventoryLike | None = None,
    limit: str | None = None,
    timeout: float | None = None,
    retries: int | None = None,
    parallel: int = 8,
) -> Pulled | dict[str, Pulled | DeployerError]:
    """What a device holds (read only), as ``Pulled``: parameter name -> register words, with its profile and
    device (``texts()`` in engineering units, ``recipe_text()`` a recipe that sets them).

    ``what``: a profile (a Profile, a built-in id or a profile file: every parameter that can be read and
    written back) or a Recipe (its parameters, or with none every setting of its profile; and its device when
    ``device`` is None); ``names``: only these.
    With ``inventory`` (and ``limit``, ``parallel`` as for ``plan``): name -> its Pulled, or the error that
    stopped its read; each device read with its own profile from the inventory, else ``what``'s (None: the
    inventory must give every device one).

    Raises:
        UsageError: an unknown built-in profile, no device, a bad URL, unit 0, a name the profile does not have;
            arguments of the wrong type or out of their bounds.
        InputError: an invalid profile file or inventory.
        TransportError: the one device cannot be read (a device of an inventory: its entry, not raised).
    """
    need_unit(unit)
    need_timing(timeout, retries)
    chosen: Profile | Recipe | None = what if isinstance(what, Recipe) or what is None else need_profile(what, "pull")
    if inventory is None:
        if limit is not None:
            raise UsageError("limit selects devices of an inventory: pass inventory too")
        if chosen is None:
            raise UsageError(f"pull takes a profile id, a profile file, a Profile or a Recipe, got {kind(what)}")
        if isinstance(chosen, Recipe):
            url, u = target(chosen, device, unit, timeout=timeout, retries=retries)
            prof = chosen.profile
            wanted = need_names(names, prof, "pull") or _recipe_names(chosen)
        else:
            if device is None:
                raise UsageError("pull takes a device URL (tcp://HOST:PORT, rtu:///dev/ttyUSB0 ...)")
            url, u, prof = device_url(device, timeout=timeout, retries=retries), 1 if unit is None else unit, chosen
            wanted = need_names(names, prof, "pull") or pull_names(prof)
        return Pulled(
            await _read(prof, wanted, url, u),
            profile=prof,
            device=describe(url),
            unit=u,
            name=chosen.name if isinstance(chosen, Recipe) else prof.id,
        )
    if device is not None:
        raise UsageError("device and inventory exclude each other")
    parallel = need_parallel(parallel)
    inv = _selected(inventory, limit, "pull")
    if names is not None and (isinstance(names, str) or not isinstance(names, Sequence)):
        raise UsageError(f"pull takes names as a list of parameter names, got {kind(names)}")
    jobs = pull_reads(chosen, inv, limit=limit, names=names, timeout=timeout, retries=retries, unit=unit)
    if not jobs:
        raise UsageError(f"no device selected from {inv.path}")
    for j in jobs:
        need_names(list(j.names), j.profile, f"pull ({j.name})")
    read = await _read_many(jobs, parallel)
    out: dict[str, Pulled | DeployerError] = {}
    for j in jobs:
        got = read[j.name]
        out[j.name] = (
            got
            if isinstance(got, DeployerError)
            else Pulled(got, profile=j.profile, device=describe(j.url), unit=j.unit, name=j.name)
        )
    return out


async def _read(profile: Profile, names: Sequence[str], url: DeviceURL, unit: int) -> dict[str, tuple[int, ...]]:
    from ..execute.read import read_current

    return await read_current(profile, list(names), url, unit)
