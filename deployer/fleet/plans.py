"""A fleet's plan: each device's plan (or why it has none), with how each device is reached, for ``apply``."""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from ..errors import DeployerError, UsageError
from ..planning.model import Plan
from ..transport.urls import describe

if TYPE_CHECKING:  # its module imports the transports (pymodbus): an offline plan does not need them
    from ..execute.job import Job
    from ..profile import Profile


class FleetPlan:
    """Every selected device's plan, in the inventory's order, or the error that stopped its plan (a device
    that could not be read: ``TransportError``; a device no plan can be made for: ``UsageError``).

    ``fleet[name]`` is the device's Plan (or raises its error), ``fleet.plans`` the plans made, ``fleet.errors``
    the others, ``fleet.changes`` whether executing it writes anything. ``apply(fleet)`` executes exactly these
    plans (each device refused before its first write when it no longer holds what its plan was made against),
    with each device's URL, unit and group as the inventory gave them (``batch_by="group"``); a device without a
    plan refuses the whole apply: plan again, or apply ``fleet.without_errors()``.
    """

    def __init__(
        self, jobs: Sequence[Job], results: Mapping[str, Plan | DeployerError], *, recipe: str | None, inventory: str
    ) -> None:
        self._jobs = {j.name: j for j in jobs}
        self._results = {j.name: results[j.name] for j in jobs}
        self.recipe = recipe  # what was planned (a recipe's path or name; None: each device's own from the inventory)
        self.inventory = inventory  # the inventory's path (or the name of a list of devices)

    def __repr__(self) -> str:
        return f"FleetPlan(devices={len(self._results)}, planned={len(self.plans)}, errors={len(self.errors)})"

    def __len__(self) -> int:
        return len(self._results)

    def __iter__(self) -> Iterator[str]:
        """The devices' names, in the inventory's order."""
        return iter(self._results)

    def __contains__(self, name: object) -> bool:
        return name in self._results

    def __getitem__(self, name: str) -> Plan:
        """The device's plan; its error when it has none (KeyError: no such device in the plan)."""
        got = self._results[name]
        if isinstance(got, DeployerError):
            raise got
        return got

    @property
    def plans(self) -> dict[str, Plan]:
        """The devices that have a plan: name -> Plan."""
        return {n: p for n, p in self._results.items() if isinstance(p, Plan)}

    @property
    def errors(self) -> dict[str, DeployerError]:
        """The devices that have none: name -> why (``TransportError``: it could not be read)."""
        return {n: e for n, e in self._results.items() if isinstance(e, DeployerError)}

    @property
    def changes(self) -> bool:
        """Whether executing the plans writes anything on any device."""
        return any(p.changes for p in self.plans.values())

    def profile(self, name: str) -> Profile:
        """The profile device ``name`` is planned with (its own from the inventory, else the recipe's)."""
        return self._jobs[name].recipe.profile

    def device(self, name: str) -> tuple[str, int]:
        """Device ``name``'s URL (without secrets) and unit."""
        job = self._jobs[name]
        return describe(job.url), job.unit

    def without_errors(self) -> FleetPlan:
        """This plan without the devices that have none."""
        return FleetPlan(
            [j for n, j in self._jobs.items() if n in self.plans],
            self._results,
            recipe=self.recipe,
            inventory=self.inventory,
        )

    def to_json(self) -> dict[str, Any]:
        """As ``deployer plan --inventory --json`` prints it: the recipe, and per device its plan (a saved plan's
        JSON) or its error."""
        return {
            "recipe": self.recipe,
            "devices": [
                {"name": n, "plan": r.to_json()} if isinstance(r, Plan) else {"name": n, "error": str(r)}
                for n, r in self._results.items()
            ],
        }


def executable_jobs(fleet: FleetPlan) -> list[Job]:
    """What ``apply(fleet)`` runs: each device's job, its plan to be executed unchanged. UsageError when a device
    has no plan."""
    missing = fleet.errors
    if missing:
        shown = "; ".join(f"{n}: {e}" for n, e in list(missing.items())[:5])
        more = f" (and {len(missing) - 5} more)" if len(missing) > 5 else ""
        raise UsageError(
            f"the fleet plan has no plan for {len(missing)} device{'s' if len(missing) != 1 else ''} "
            f"({shown}{more}): plan again, or apply the plan's without_errors()"
        )
    plans = fleet.plans
    return [replace(j, plan=plans[n]) for n, j in fleet._jobs.items()]
