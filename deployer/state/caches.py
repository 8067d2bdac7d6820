"""Disk caches (answers kept between runs to save start-up time): who may write them.

Every process reads them; only code inside ``writing()`` writes them (the command line runs each command
in it), so the library's and the Ansible modules' callers leave no files behind in the user's home. Today
the one cache is pint's answers (``deployer.profile.units``) and pint's own parsed definitions.
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Iterator

# a context variable, not a process flag: the permission holds for the code inside writing() (and the
# tasks and threads it starts), not for whatever else the process runs
_WRITES: contextvars.ContextVar[bool] = contextvars.ContextVar("deployer_cache_writes", default=False)


@contextlib.contextmanager
def writing() -> Iterator[None]:
    """Within this block, deployer may write its disk caches (pint's answers in ~/.cache/deployer)."""
    token = _WRITES.set(True)
    try:
        yield
    finally:
        _WRITES.reset(token)


def writes_allowed() -> bool:
    return _WRITES.get()
