"""The arguments of the public API checked before anything is read or sent: a wrong type or a number out of its
bound (``deployer.LIMITS``) is a UsageError that says what the argument takes."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

from ..errors import UsageError
from ..fleet.inventory import Inventory, inventory_from, load_inventory
from ..limits import BATCH_BY, LIMITS, Bound
from ..profile import Profile
from ..recipe.loader import Recipe
from ..transport.urls import DeviceURL, parse_url


def kind(value: object) -> str:
    """A value as a message shows what was given: its type and (clipped) repr."""
    text = repr(value)
    return f"{type(value).__name__} {text if len(text) <= 40 else text[:39] + '...'}"


def need_recipe(recipe: object, call: str) -> Recipe:
    """Refuse, before anything is sent, what a caller passed where a loaded Recipe belongs."""
    if not isinstance(recipe, Recipe):
        hint = " (load it first: deployer.load_recipe(path))" if isinstance(recipe, (str, os.PathLike)) else ""
        raise UsageError(f"{call} takes a Recipe{hint}, got {kind(recipe)}")
    return recipe


def need_unit(unit: object) -> None:
    if unit is None:
        return
    if isinstance(unit, bool) or not isinstance(unit, int):
        raise UsageError(f"unit must be an int from 1 to 247 (0 is broadcast), got {kind(unit)}")
    if not 0 <= unit <= 247:
        raise UsageError(f"unit must be from 1 to 247 (0 is broadcast), got {unit}")


def need_timing(timeout: object, retries: object) -> None:
    if timeout is not None:
        LIMITS.timeout.check(timeout, "timeout")
    if retries is not None:
        LIMITS.retries.check(retries, "retries")


def need_path(value: object, call: str, what: str) -> str:
    if not isinstance(value, (str, os.PathLike)):
        raise UsageError(f"{call} takes {what} as a path (str or os.PathLike), got {kind(value)}")
    return os.fspath(value)


def need_optional_path(value: object, call: str, what: str) -> str | None:
    return None if value is None else need_path(value, call, what)


def need_parallel(parallel: object) -> int:
    return int(LIMITS.parallel.check(parallel, "parallel"))


def need_flag(value: object, what: str) -> bool:
    if not isinstance(value, bool):
        raise UsageError(f"{what} takes True or False, got {kind(value)}")
    return value


def need_text(value: object, what: str) -> str | None:
    if value is not None and not isinstance(value, str):
        raise UsageError(f"{what} takes a str, got {kind(value)}")
    return value


def need_choice(value: object, what: str, choices: Sequence[str]) -> str:
    if value not in choices:
        raise UsageError(f"{what} must be {' or '.join(repr(c) for c in choices)}, got {kind(value)}")
    return str(value)


def need_batch_by(batch_by: object) -> str:
    return need_choice(batch_by, "batch_by", BATCH_BY)


def need_profile(profile: object, call: str) -> Profile:
    """A Profile, or one named by a built-in id or a profile file."""
    from ..profile import resolve_profile

    if isinstance(profile, Profile):
        return profile
    if not isinstance(profile, (str, os.PathLike)):
        raise UsageError(f"{call} takes a profile id, a profile file or a Profile, got {kind(profile)}")
    return resolve_profile(os.fspath(profile))


def need_names(names: object, prof: Profile, call: str) -> list[str] | None:
    """Parameter names of ``prof`` (None: not given)."""
    if names is None:
        return None
    if isinstance(names, str) or not isinstance(names, Sequence):
        raise UsageError(f"{call} takes names as a list of parameter names, got {kind(names)}")
    unknown = [n for n in names if not isinstance(n, str) or prof.get(n) is None]
    if unknown:
        raise UsageError(f"{call}: profile {prof.id} has no parameter {', '.join(map(repr, unknown))}")
    return list(names)


def need_inventory(inventory: object, call: str) -> Inventory:
    """An Inventory: given, or loaded from a file or a list of device mappings (``load_inventory``)."""
    if isinstance(inventory, Inventory):
        return inventory
    if isinstance(inventory, (str, os.PathLike)):
        return load_inventory(inventory)
    if isinstance(inventory, Sequence) and not isinstance(inventory, bytes):
        return inventory_from(inventory, "<devices>")
    raise UsageError(
        f"{call} takes the inventory as a file, a list of devices or an Inventory "
        f"(deployer.load_inventory(...)), got {kind(inventory)}"
    )


def device_url(url: object, *, timeout: float | None = None, retries: int | None = None) -> DeviceURL:
    """A device URL parsed (a DeviceURL as is); ``timeout`` and ``retries`` where the URL sets none.

    Raises BadURL (a UsageError) for a malformed URL, UsageError for bounds."""
    need_timing(timeout, retries)
    if isinstance(url, DeviceURL):
        return url
    if not isinstance(url, str):
        raise UsageError(f"device_url takes a URL such as tcp://10.0.0.11:502, got {kind(url)}")
    return parse_url(url, timeout=timeout, retries=retries)  # BadURL is a UsageError


def target(
    recipe: Recipe, device: object, unit: int | None, *, timeout: float | None = None, retries: int | None = None
) -> tuple[DeviceURL, int]:
    """The device and unit a call means: given, else the recipe's."""
    need_unit(unit)
    text = device if device is not None else (recipe.device.url if recipe.device else None)
    if text is None:
        raise UsageError("no device: pass a device URL or set device.url in the recipe")
    u = unit if unit is not None else (recipe.device.unit if recipe.device and recipe.device.unit is not None else 1)
    return device_url(text, timeout=timeout, retries=retries), u


def duration(value: object, what: str) -> float:
    """Seconds in a duration as people write it ("250ms", "30s", "5m", "1h"; a bare number is seconds),
    checked against the bound of the argument ``what`` (a field of ``LIMITS``: "soak", "pause" ...).

    Raises:
        UsageError: not a duration, or out of its bound, naming ``what``.
    """
    from ..load.durations import parse_duration

    if isinstance(value, bool) or not isinstance(value, str | int | float):
        raise UsageError(f'{what} takes a duration such as "30s" or a number of seconds, got {kind(value)}')
    try:
        seconds = parse_duration(value)
    except ValueError as e:
        raise UsageError(f"{what}: {e}") from None
    bound: Bound = getattr(LIMITS, what)
    return bound.check(seconds, what)


def optional_duration(value: object, what: str) -> float | None:
    return None if value is None else duration(value, what)


def need_mapping(value: object, what: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise UsageError(f"{what} takes a mapping, got {kind(value)}")
    return value
