"""Disk caches (answers kept between runs to save start-up time): who may write them.

Every process reads them; only the command line writes them (it calls ``allow_writes`` first), so
the library's and the Ansible modules' callers leave no files behind in the user's home. Today
the one cache is pint's answers (``deployer.profile.units``) and pint's own parsed definitions.
"""

from __future__ import annotations

_ALLOWED: list[bool] = []


def allow_writes() -> None:
    """This process (the command line) may write the disk caches."""
    _ALLOWED[:] = [True]


def writes_allowed() -> bool:
    return bool(_ALLOWED)
