"""deployer: deploy parameter sets (recipes) to Modbus devices; plan, apply, verify, report.

The public API (``deployer.api``) is importable from here: ``deployer.load_recipe``,
``deployer.plan``, ``deployer.apply``, ``deployer.apply_fleet``, ``deployer.diff``,
``deployer.pull`` and their ``*_async`` twins. It loads on first use, so ``import deployer``
stays cheap (the command line's start-up time depends on it).
"""

from __future__ import annotations

import logging as _logging
from typing import Any

__version__ = "0.1.0"

# pymodbus logs every timeout and unknown unit through the root logger's last-resort handler;
# deployer reports those itself, so the library stays quiet unless the user configures logging.
_log = _logging.getLogger("pymodbus")
_log.addHandler(_logging.NullHandler())
_log.propagate = False

_API = frozenset({
    "ApplyOptions", "DeviceResult", "Drift", "InputError", "Inventory", "Plan", "Profile", "Recipe", "Report",
    "TransportError", "UsageError", "apply", "apply_async", "apply_fleet", "apply_fleet_async", "diff",
    "diff_async", "diff_values", "device_url", "load_inventory", "load_profile", "load_recipe", "plan",
    "plan_async", "pull", "pull_async", "pulled_recipe", "recipe_from", "read_fleet", "read_fleet_async",
    "run_fleet", "run_fleet_async", "confirm", "safe_options",
})


def __getattr__(name: str) -> Any:
    if name in _API:
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'deployer' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_API])
