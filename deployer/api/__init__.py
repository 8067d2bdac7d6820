"""The public Python API: load, plan, apply, diff, pull, roll back; for one device or an inventory.

``__all__`` below is all of it (``deployer`` serves the same names; ``tests/test_exported_members.py`` pins
them); ``deployer.aio`` has the same operations as coroutines, and ``deployer.errors`` the whole error tree::

    import deployer
    recipe = deployer.load_recipe("line3.yaml")
    plan = deployer.plan(recipe, "tcp://10.0.0.11:502")     # a Plan: every step apply takes; nothing written
    report = deployer.apply(plan)                            # executes exactly that plan: a Report
    fleet = deployer.plan(recipe, inventory="fleet.yaml", limit="line3")     # a FleetPlan
    report = deployer.apply(fleet, batch="1,50%", report_path="run.json")
    drift = deployer.diff(recipe, "tcp://10.0.0.11:502")   # [] when the device holds the recipe

As Terraform's: ``plan`` makes a plan, ``apply`` of a plan executes exactly it (each device refused before
its first write when it no longer holds what the plan was made against: ``StalePlan``), ``apply`` of a recipe
plans and executes in one session per device. Every error is a ``DeployerError``, raised before anything is
sent for bad input (``InputError`` with positions, ``UsageError``; a misspelt keyword is one, naming the
nearest right one); a device's fault during ``apply`` is its status in the report, not an exception.

What the command line needs beyond this is ``deployer.api.commands``, which is not public; names earlier
releases exported still work for one release, with a DeprecationWarning naming what stands for them
(``deployer.api.deprecated``). Anything else here, or in deployer's subpackages, may change without notice.
"""

from __future__ import annotations

from typing import Any

from ..agent.client import Agent
from ..calls import blocking, checked
from ..errors import DeployerError, InputError, RunInterrupted, StalePlan, TransportError, UsageError
from ..fleet.inventory import Inventory
from ..fleet.plans import FleetPlan
from ..limits import LIMITS
from ..planning.model import Plan, Step
from ..profile import Profile
from ..profile import load_profile as _load_profile
from ..recipe.loader import Recipe
from ..report import DeviceResult, Report
from . import reading, running
from .loading import load_inventory, load_plan, load_recipe, load_report, recipe_from
from .runs import confirm, status
from .values import Drift

__all__ = [
    "LIMITS",
    "Agent",
    "DeployerError",
    "DeviceResult",
    "Drift",
    "FleetPlan",
    "InputError",
    "Inventory",
    "Plan",
    "Profile",
    "Recipe",
    "Report",
    "RunInterrupted",
    "StalePlan",
    "Step",
    "TransportError",
    "UsageError",
    "apply",
    "confirm",
    "diff",
    "load_inventory",
    "load_plan",
    "load_profile",
    "load_recipe",
    "load_report",
    "plan",
    "pull",
    "recipe_from",
    "rollback",
    "status",
]

load_profile = checked("deployer.load_profile")(_load_profile)

# the blocking twins of deployer.aio's coroutines: each runs in an event loop of its own
plan = blocking("deployer.plan", "deployer.aio.plan")(running.plan)
apply = blocking("deployer.apply", "deployer.aio.apply", hints=running.APPLY_HINTS)(running.apply)
rollback = blocking("deployer.rollback", "deployer.aio.rollback")(running.rollback)
diff = blocking("deployer.diff", "deployer.aio.diff")(reading.diff)
pull = blocking("deployer.pull", "deployer.aio.pull")(reading.pull)

# the names above that __all__ lists, imported to be served from here
_PUBLIC = (
    Agent,
    DeployerError,
    InputError,
    RunInterrupted,
    StalePlan,
    TransportError,
    UsageError,
    Inventory,
    FleetPlan,
    LIMITS,
    Plan,
    Step,
    Profile,
    Recipe,
    DeviceResult,
    Report,
    Drift,
    load_inventory,
    load_plan,
    load_recipe,
    load_report,
    recipe_from,
    confirm,
    status,
)


def __getattr__(name: str) -> Any:
    """A name earlier releases exported: served for one more release, with a DeprecationWarning."""
    from .deprecated import REMOVED, removed  # the submodule itself (``from . import`` would ask here again)

    if name in REMOVED:
        return removed(name)
    raise AttributeError(f"module 'deployer.api' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
