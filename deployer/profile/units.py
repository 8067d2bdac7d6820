"""Engineering units with pint, on Decimal magnitudes so conversions stay exact.

Each unit check and each (unit, parameter unit) pair is resolved by pint once: a
multiplicative conversion becomes one Decimal factor (``ms`` -> ``s``: 0.001, applied as
``x * factor`` exactly as pint applies it); conversions with an offset (``degF`` -> ``degC``)
keep going through pint. Those answers are also kept on disk (``~/.cache/deployer``, one file
per installed pint): importing pint and building its registry costs about 0.1 s, a third of
a small command, so a command whose units were all seen before does not import pint at all.

Every process reads that cache; only the command line writes it (and lets pint keep its own
parsed definitions in ``~/.cache/pint``): see ``deployer.state.caches``.
"""

from __future__ import annotations

import atexit
import contextlib
import importlib.util
import json
import os
import zlib
from decimal import Decimal
from functools import cache, lru_cache
from typing import Any

from ..state.caches import writes_allowed

_ALIASES = {"%": "percent", "‰": "permille"}


@cache
def registry() -> Any:
    import pint

    kwargs: dict[str, Any] = {"non_int_type": Decimal, "autoconvert_offset_to_baseunit": True}
    if writes_allowed():
        try:  # pint keeps its parsed definitions on disk (~/.cache/pint): 0.02 s instead of 0.12 s a command
            return pint.UnitRegistry(cache_folder=":auto:", **kwargs)
        except Exception:  # no writable cache directory: build it from the definitions
            pass
    return pint.UnitRegistry(**kwargs)


_SYMBOLS = {"percent": "%", "permille": "‰"}  # shown as engineers write them: 12 %, not 12 percent


def normalize(text: str) -> str:
    """The unit for display: as the user wrote it, but percent and permille as their symbols
    (pint reads either spelling: ``_pint_text``)."""
    t = text.strip()
    return _SYMBOLS.get(t, t)


def _pint_text(text: str) -> str:
    t = text.strip()
    return _ALIASES.get(t, t)


_MAX_KEPT = 2000  # entries of each kind on disk


class _DiskCache:
    """Answers pint gave before, keyed by the installed pint (its path and modification time)."""

    def __init__(self) -> None:
        self.checks: dict[str, str | None] = {}
        self.factors: dict[str, str | None] = {}  # "from\x00to" -> factor text, or a message
        self.dirty = False
        self.writable = False  # answers were added inside caches.writing(): save them at exit
        self.path: str | None = None
        try:
            spec = importlib.util.find_spec("pint")
            origin = spec.origin if spec is not None else None
            if origin is None:
                return
            st = os.stat(origin)
            base = (os.environ.get("XDG_CACHE_HOME") or (os.name == "nt" and os.environ.get("LOCALAPPDATA"))
                    or os.path.join(os.path.expanduser("~"), ".cache"))  # Windows: %LOCALAPPDATA%\deployer
            key = f"{zlib.crc32(origin.encode()):08x}-{st.st_mtime_ns}"
            self.path = os.path.join(base, "deployer", f"units-{key}.json")
            with open(self.path, encoding="utf-8") as f:
                data = json.load(f)
            self.checks, self.factors = dict(data["checks"]), dict(data["factors"])
        except (OSError, ValueError, KeyError, TypeError, ImportError):
            pass  # no cache yet, or unreadable: pint answers, and the cache is written at exit

    def save(self) -> None:
        if not self.dirty or self.path is None or not self.writable:
            return
        from ..errors import DeployerError
        from ..state.durable import write_atomic

        with contextlib.suppress(OSError, DeployerError):  # a cache: no cache is fine
            os.makedirs(os.path.dirname(self.path), exist_ok=True)
            write_atomic(self.path, json.dumps({"checks": self.checks, "factors": self.factors}))


@cache
def _disk() -> _DiskCache:
    d = _DiskCache()
    atexit.register(d.save)
    return d


@lru_cache(maxsize=4096)  # bounded: a long-running process may see garbage from many files
def check(text: str) -> str | None:
    """None if pint knows the unit, else a message for the user."""
    disk = _disk()
    if text in disk.checks:
        return disk.checks[text]
    ureg = registry()  # outside the try: pint that cannot load is no answer about the unit (never kept)
    try:
        ureg.parse_units(_pint_text(text))
        answer = None
    except Exception:  # pint raises a zoo of parser errors for garbage input
        answer = f"unknown unit '{_clip(text)}'"
    if len(text) <= 40 and len(disk.checks) < _MAX_KEPT:  # garbage from hostile files is not worth keeping
        disk.checks[text] = answer
        disk.dirty = True
        disk.writable = disk.writable or writes_allowed()
    return answer


def _clip(text: str) -> str:
    return text if len(text) <= 40 else f"{text[:30]}…"


@lru_cache(maxsize=4096)
def _conversion(from_unit: str, to_unit: str) -> Decimal | str | None:
    """The factor from ``from_unit`` to ``to_unit``; None when an offset is involved; a message when impossible."""
    disk = _disk()
    key = f"{from_unit}\x00{to_unit}"
    if key in disk.factors:
        known = disk.factors[key]
        if known is None or known.startswith("="):
            return None if known is None else Decimal(known[1:])
        return known
    answer = _pint_conversion(from_unit, to_unit)
    if len(key) <= 80 and len(disk.factors) < _MAX_KEPT:
        disk.factors[key] = None if answer is None else (f"={answer}" if isinstance(answer, Decimal) else answer)
        disk.dirty = True
        disk.writable = disk.writable or writes_allowed()
    return answer


def _pint_conversion(from_unit: str, to_unit: str) -> Decimal | str | None:
    import pint

    ureg = registry()
    try:
        src = ureg.Quantity(Decimal(1), _pint_text(from_unit))
    except Exception:
        return f"unknown unit '{_clip(from_unit)}'"
    try:
        one = src.to(_pint_text(to_unit)).magnitude
    except pint.DimensionalityError:
        return (f"'{_clip(from_unit)}' is not convertible to '{_clip(to_unit)}' "
                f"({_dim(from_unit)} vs. {_dim(to_unit)})")
    except Exception:
        return f"unknown unit '{_clip(to_unit)}'"
    zero = ureg.Quantity(Decimal(0), _pint_text(from_unit)).to(_pint_text(to_unit)).magnitude
    if Decimal(zero) != 0:
        return None
    return Decimal(one)


def convert(magnitude: Decimal, from_unit: str, to_unit: str) -> Decimal:
    """Convert exactly; raises ValueError with a user message on a dimension mismatch."""
    how = _conversion(from_unit, to_unit)
    if isinstance(how, str):
        raise ValueError(how)
    try:
        if how is not None:
            return magnitude * how
        return _offset_convert(magnitude, from_unit, to_unit)
    except ArithmeticError:  # 1e999999999 ms: beyond Decimal's exponent range
        raise ValueError(f"{magnitude:g} {_clip(from_unit)} is too large to convert to '{_clip(to_unit)}'") from None


@lru_cache(maxsize=4096)
def _offset_convert(magnitude: Decimal, from_unit: str, to_unit: str) -> Decimal:
    """A conversion with an offset (degF -> degC), by pint's own arithmetic, once per distinct value.

    Not reduced to one factor and one offset: pint rounds its intermediate steps at Decimal's
    precision, and a reordered formula would differ from it in the last digit."""
    q = registry().Quantity(magnitude, _pint_text(from_unit))
    return Decimal(q.to(_pint_text(to_unit)).magnitude)


def _dim(unit: str) -> str:
    try:
        d = registry().parse_units(_pint_text(unit)).dimensionality
        return str(d) if str(d) != "dimensionless" else "dimensionless"
    except Exception:
        return "?"
