"""deployer: deploy parameter sets (recipes) to Modbus devices; plan, apply, verify, report.

The public API is ``deployer.api``, importable from here: ``deployer.load_recipe``, ``deployer.plan``,
``deployer.apply``, ``deployer.diff``, ``deployer.pull``, ``deployer.rollback``, ``deployer.confirm``,
``deployer.status``, the types they take and return, and the errors (the whole tree in ``deployer.errors``);
``deployer.aio`` has the operations as coroutines. ``deployer.__all__`` is ``deployer.api.__all__``: one list.
The API loads on first use, so ``import deployer`` stays cheap (the command line's start-up time depends on it).
"""

from __future__ import annotations

import logging as _logging
import os as _os
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .api import *  # noqa: F403  (what __getattr__ serves, for type checkers)

    __version__: str

_HERE = _os.path.dirname(__file__)

# pymodbus logs every timeout and unknown unit through the root logger's last-resort handler;
# deployer reports those itself, so the library stays quiet unless the user configures logging.
_log = _logging.getLogger("pymodbus")
_log.addHandler(_logging.NullHandler())
_log.propagate = False


def __getattr__(name: str) -> Any:
    if name == "__version__":  # pyproject.toml's, the one place (importlib.metadata costs start-up time)
        from importlib.metadata import version

        return version("modbus-deployer")
    if name == "aio":  # the public coroutines: ``import deployer`` then ``await deployer.aio.plan(...)``
        import importlib

        return importlib.import_module("deployer.aio")
    # not for dunders or a submodule not imported yet (``from deployer import errors`` asks here first); by the
    # folder's own spelling: Windows' and macOS' file names ignore case, and LIMITS is not limits.py there either
    if (name.startswith("__") and name != "__all__") or name in _modules() or f"{name}.py" in _modules():
        raise AttributeError(f"module 'deployer' has no attribute {name!r}")
    from . import api

    if name == "__all__" or name in api.__all__:
        return getattr(api, name)
    from .api.deprecated import REMOVED, removed

    if name in REMOVED:  # a name earlier releases exported: one more release, with a warning
        return removed(name)
    raise AttributeError(f"module 'deployer' has no attribute {name!r}")


_MODULES: frozenset[str] = frozenset()


def _modules() -> frozenset[str]:
    global _MODULES
    if not _MODULES:
        _MODULES = frozenset(_os.listdir(_HERE))
    return _MODULES


def __dir__() -> list[str]:
    from . import api

    return sorted([*globals(), *api.__all__])
