"""The agent's desired state: the files (inventory and recipes) and what it adopted from them.

The files are read and checked completely (``load_files``); an invalid edit raises InputError and
changes nothing. What the agent enforces is the adopted state: per device one recipe file in
``STATE/agent/adopted/`` (the values a run through the agent rolled out, or the files' at the first start).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from ..execute.job import Job
from ..fleet.inventory import Inventory, fleet_jobs, load_inventory
from ..profile import Parameter, Profile
from ..recipe.loader import Recipe, load_recipe
from ..recipe.model import DeviceSpec
from ..recipe.text import recipe_text
from ..state.durable import write_atomic
from ..transport.urls import describe


@dataclass(frozen=True)
class Files:
    """The inventory and every device's recipe as the files say now (checked)."""

    inventory: Inventory
    jobs: dict[str, Job]  # by device name, inventory order
    sha256: str  # of the inventory, recipe and profile files' texts: "the files a client looked at"


def _digest(paths: Sequence[str]) -> str:
    h = hashlib.sha256()
    for p in sorted(set(paths)):
        h.update(p.encode() + b"\0")
        try:
            with open(p, "rb") as f:
                h.update(f.read())
        except OSError:
            h.update(b"<unreadable>")
        h.update(b"\0")
    return h.hexdigest()


def load_files(path: str) -> Files:
    """Read and check the inventory and the recipes it names. Raises InputError (every problem at once)."""
    inv = load_inventory(path)
    jobs = fleet_jobs(inv, None, None)
    used = [os.path.abspath(path)]
    for j in jobs:
        if j.recipe.path:
            used.append(os.path.abspath(j.recipe.path))
        if j.recipe.profile.source:
            used.append(os.path.abspath(j.recipe.profile.source))
    return Files(inv, {j.name: j for j in jobs}, _digest(used))


def values_of(recipe: Recipe) -> dict[str, tuple[int, ...]]:
    """The registers a recipe asks for, by parameter name."""
    return {d.name: tuple(d.registers) for d in recipe.desired}


def adopted_dir(state_dir: str) -> str:
    return os.path.join(os.path.abspath(state_dir), "agent", "adopted")


def write_adopted(
    state_dir: str, job: Job, values: Mapping[str, Sequence[int]], *, why: str, path: str | None = None
) -> tuple[str, str]:
    """Write the adopted state of one device as a recipe (values by parameter name); its path and SHA-256.
    ``path``: somewhere else than the adopted folder (a replaced unit's restore)."""
    prof = job.recipe.profile
    path = path or os.path.join(adopted_dir(state_dir), f"{_safe(job.name)}.yaml")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    ref = os.path.abspath(prof.source) if prof.source else prof.id
    params: dict[Parameter, Sequence[int]] = {prof.parameter(n): v for n, v in values.items()}
    text = recipe_text(
        ref,
        params,
        name=job.name,
        device=DeviceSpec(describe(job.url), job.unit),
        comment=f"adopted by the deployer agent: {why}",
    )
    write_atomic(path, text, replace=True, what="the adopted state")
    return path, hashlib.sha256(text.encode()).hexdigest()


def load_adopted(path: str) -> Recipe:
    return load_recipe(path)


def _safe(name: str) -> str:
    """A device name as a file name (names are free text in an inventory)."""
    keep = "".join(c if c.isalnum() or c in "-_." else "_" for c in name).lstrip(".")
    if keep != name:
        keep += "-" + hashlib.sha256(name.encode()).hexdigest()[:8]
    return keep or "device"


def differences(profile: Profile, adopted: Mapping[str, Sequence[int]], files: Recipe) -> list[dict[str, Any]]:
    """The files' values that differ from the adopted ones (pending changes), in the files' order."""
    out = []
    for d in files.desired:
        have = adopted.get(d.name)
        if have is None or not d.parameter.same_value(tuple(have), d.registers):
            out.append(
                {
                    "name": d.name,
                    "adopted": None if have is None else d.parameter.show_registers(tuple(have)),
                    "files": d.text,
                }
            )
    files_names = {d.name for d in files.desired}
    for n, v in adopted.items():
        if n not in files_names:
            out.append({"name": n, "adopted": profile.parameter(n).show_registers(tuple(v)), "files": None})
    return out
