"""Engineering units with pint, on Decimal magnitudes so conversions stay exact.

Each unit check and each (unit, parameter unit) pair is resolved by pint once: a
multiplicative conversion becomes one Decimal factor (``ms`` -> ``s``: 0.001, applied as
``x * factor`` exactly as pint applies it); conversions with an offset (``degF`` -> ``degC``)
keep going through pint. Those answers are also kept on disk (``~/.cache/deployer``, one file
per installed pint): importing pint and building its registry costs about 0.1 s, a third of
a small command, so a command whose units were all seen before does not import pint at all.

Every process reads that cache; only the command line writes it (and lets pint keep its own
parsed definitions in ``~/.cache/deployer/pint-60``): see ``deployer.state.caches``.

Units mean what they mean in the field, not always what pint says (``FIELD_DEFINITIONS``, docs/recipes.md):
a revolution is one cycle (60 rpm = 1 Hz = 1 rps; pint makes it 2 pi radians), an angle is a dimension of
its own, so a cycle frequency never silently becomes an angular velocity (rad/s) or back; a parameter that
wants that conversion says so (``cycles_as_angles``: one cycle = one turn = 2 pi rad = 360 deg).
"""

from __future__ import annotations

import atexit
import contextlib
import importlib.util
import json
import os
import re
import zlib
from decimal import Context, Decimal, localcontext
from functools import cache, lru_cache
from typing import Any

from ..state.caches import writes_allowed

# whole unit texts as the field writes them -> as pint reads them
_ALIASES = {
    "%": "percent",
    "‰": "permille",
    "%RH": "percent",
    "% RH": "percent",
    "%rH": "percent",
    "r/min": "rpm",
    "r/s": "rps",
    "rev/min": "rpm",
    "rev/s": "rps",
    "kg/cm2": "kgf/cm**2",
    "kg/cm²": "kgf/cm**2",
}  # a gauge's kg/cm2 is a pressure (pint: mass per area)
# m2, m3, mm2, ft3 as written on nameplates and in manuals: a power (pint reads 'm3' as an unknown unit);
# 'Nm3' (normal cubic metres, which depend on reference conditions) stays unknown
_POWERS = re.compile(r"(?<![\w])(km|dm|cm|mm|m|ft|in|yd)([23])(?![\w])")

# Loaded after pint's own definitions, replacing them where the field means something else
# (docs/recipes.md, "Units as the field means them", lists each with pint's meaning).
FIELD_DEFINITIONS = (
    # an angle has a dimension of its own (pint: dimensionless), so rad/s is not 1/s and deg is not a number
    "radian = [angle] = rad",
    # a revolution is one cycle: 60 rpm = 1 Hz = 1 rps (pint: 2 pi radians, so 3000 rpm was 314.16 Hz)
    "turn = 1 = _ = revolution = cycle = circle = rev",
    "newton_meter = newton * meter = Nm",  # pint: a textile yarn count (km/kg)
    "cubic_foot_per_minute = foot ** 3 / minute = cfm",  # pint: centifermi
    "@alias metric_horsepower = PS = CV",  # pint: PS is petasiemens
    "@alias refrigeration_ton = TR",  # pint: teramolar gas constant
    "liter_per_minute = liter / minute = lpm",
    "gallon_per_minute = gallon / minute = gpm",  # US gallons, as pint's gallon
)
_ANGLE_OF_A_TURN = "2 * pi * radian"
# digits pint computes factors with: a factor like 1/60 is then exact to far beyond the 28 digits of a
# result, so 3000 rpm becomes 50 Hz, not 50.00000000000000000000000001 (which no register resolution fits)
_GUARD = Context(prec=60)


def precise() -> Any:
    """The Decimal context every use of ``registry()`` runs in. pint computes a definition's numbers (degF's
    5/9, a degree's pi/180) as it reads them and each unit's factor on first use, and keeps both: read or used
    at 28 digits, 68 degF would stay 19.99999999999999999999999998 degC for every later conversion."""
    return localcontext(_GUARD)


def _cache_base() -> str:
    """Where deployer keeps its caches: ~/.cache/deployer (XDG_CACHE_HOME; %LOCALAPPDATA% on Windows)."""
    base = (
        os.environ.get("XDG_CACHE_HOME")
        or (os.name == "nt" and os.environ.get("LOCALAPPDATA"))
        or os.path.join(os.path.expanduser("~"), ".cache")
    )
    return os.path.join(base, "deployer")


@cache
def registry() -> Any:
    """pint's registry with the field's definitions over its own; use it inside ``precise()``."""
    import pathlib

    import pint

    kwargs: dict[str, Any] = {
        "non_int_type": Decimal,
        "autoconvert_offset_to_baseunit": True,
        "on_redefinition": "ignore",
        "filename": None,
    }
    with precise():  # the definitions' numbers too: computed as they are read
        ureg: Any = None
        if writes_allowed():
            # pint keeps its parsed definitions on disk: 0.02 s instead of 0.12 s a command. A folder of our own,
            # not pint's ~/.cache/pint, where other programs keep definitions read at 28 digits; without a
            # writable cache directory it builds them from the definitions
            with contextlib.suppress(Exception):
                ureg = pint.UnitRegistry(cache_folder=os.path.join(_cache_base(), f"pint-{_GUARD.prec}"), **kwargs)
        if ureg is None:
            ureg = pint.UnitRegistry(**kwargs)
        # pint's definitions, then the field's over them; no unit is resolved before both are in (pint resolves
        # each on first use), so nothing keeps pint's meaning
        ureg.load_definitions(pathlib.Path(pint.__file__).parent / "default_en.txt")
        ureg.load_definitions(list(FIELD_DEFINITIONS))
    return ureg


_SYMBOLS = {"percent": "%", "permille": "‰"}  # shown as engineers write them: 12 %, not 12 percent


def normalize(text: str) -> str:
    """The unit for display: as the user wrote it, but percent and permille as their symbols
    (pint reads either spelling: ``_pint_text``)."""
    t = text.strip()
    return _SYMBOLS.get(t, t)


def _pint_text(text: str) -> str:
    t = text.strip()
    return _POWERS.sub(r"\1**\2", _ALIASES.get(t, t))


_MAX_KEPT = 2000  # entries of each kind on disk
# in the cache file's key: a new one leaves answers kept before behind (3: the factors, and the definitions
# pint reads, with guard digits only)
_CACHE_FORMAT = "3"


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
            base = _cache_base()
            # the field's definitions in the key too: answers given under other definitions are not these
            ours = zlib.crc32(
                "\n".join(
                    (
                        *FIELD_DEFINITIONS,
                        _ANGLE_OF_A_TURN,
                        str(_GUARD.prec),
                        _CACHE_FORMAT,
                        json.dumps(_ALIASES),
                        _POWERS.pattern,
                    )
                ).encode()
            )
            key = f"{zlib.crc32(origin.encode()):08x}-{st.st_mtime_ns}-{ours:08x}"
            self.path = os.path.join(base, f"units-{key}.json")
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
        with precise():
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
def _conversion(from_unit: str, to_unit: str, turns: bool = False) -> Decimal | str | None:
    """The factor from ``from_unit`` to ``to_unit``; None when an offset is involved; a message when impossible.

    ``turns``: a cycle quantity (rev, rpm, Hz) and an angle quantity (deg, rad/s) convert, one cycle being
    2 pi rad."""
    disk = _disk()
    key = f"{from_unit}\x00{to_unit}" + ("\x00turns" if turns else "")
    if key in disk.factors:
        known = disk.factors[key]
        if known is None or known.startswith("="):
            return None if known is None else Decimal(known[1:])
        return known
    with precise():
        answer = _pint_conversion(from_unit, to_unit, turns)
    if len(key) <= 86 and len(disk.factors) < _MAX_KEPT:
        disk.factors[key] = None if answer is None else (f"={answer}" if isinstance(answer, Decimal) else answer)
        disk.dirty = True
        disk.writable = disk.writable or writes_allowed()
    return answer


def _pint_conversion(from_unit: str, to_unit: str, turns: bool) -> Decimal | str | None:
    import pint

    ureg = registry()
    try:
        src = ureg.Quantity(Decimal(1), _pint_text(from_unit))
    except Exception:
        return f"unknown unit '{_clip(from_unit)}'"
    try:
        one = src.to(_pint_text(to_unit)).magnitude
    except pint.DimensionalityError:
        turned = _turned(src, to_unit)
        if turns and turned is not None:
            return Decimal(turned)
        return _not_convertible(from_unit, to_unit, turned is not None)
    except Exception:
        return f"unknown unit '{_clip(to_unit)}'"
    zero = ureg.Quantity(Decimal(0), _pint_text(from_unit)).to(_pint_text(to_unit)).magnitude
    if Decimal(zero) != 0:
        return None
    return Decimal(one)


def _turned(src: Any, to_unit: str) -> Any:
    """``src`` (one of its unit) in ``to_unit`` counting a cycle as a turn of 2 pi rad; None if that does not help."""
    turn = registry().Quantity(_ANGLE_OF_A_TURN)
    for way in ("cycles to an angle", "an angle to cycles"):
        try:
            candidate = src * turn if way == "cycles to an angle" else src / turn
            return candidate.to(_pint_text(to_unit)).magnitude
        except Exception:  # a dimension mismatch still, or an offset unit (degC), which has no turns
            continue
    return None


# units people write for one thing that pint reads as another: the hint when the conversion fails
_MISREAD = {
    "C": "the coulomb (a temperature is degC or °C)",
    "F": "the farad (a temperature is degF or °F)",
    "deg": "an angle (a temperature is degC or degF)",
    "°": "an angle (a temperature is °C or °F)",
    "degree": "an angle (a temperature is degC or degF)",
    "a": "a year (the ampere is A)",
    "ton": "a mass of 2000 lb (a ton of refrigeration is TR)",
    "pu": "a mass (per-unit values have no unit)",
}


def _not_convertible(from_unit: str, to_unit: str, as_turns: bool) -> str:
    dims = (_dim(from_unit), _dim(to_unit))
    why = f"'{_clip(from_unit)}' is not convertible to '{_clip(to_unit)}' ({dims[0]} vs. {dims[1]})"
    misread = [f"'{u.strip()}' is {_MISREAD[u.strip()]}" for u in (from_unit, to_unit) if u.strip() in _MISREAD]
    if as_turns:
        why += (
            "; a cycle (rev, rpm, Hz) is not an angle (rad, deg, rad/s) unless the profile says "
            "'cycles_as_angles: true' for the parameter (one cycle = 2 pi rad = 360 deg)"
        )
    elif misread:
        why += "; " + ", ".join(misread)
    elif dims[0] == dims[1] == "[temperature]":
        why += "; a temperature difference (delta_degC, delta_degF, K) is not a temperature (degC, degF)"
    return why


def convert(magnitude: Decimal, from_unit: str, to_unit: str, *, cycles_as_angles: bool = False) -> Decimal:
    """Convert exactly; raises ValueError with a user message on a dimension mismatch.

    ``cycles_as_angles``: the parameter's profile lets cycles (rev, rpm, Hz) and angles (deg, rad/s) convert."""
    how = _conversion(from_unit, to_unit, cycles_as_angles)
    if isinstance(how, str):
        raise ValueError(how)
    try:
        if how is not None:
            return _tidy(magnitude * how)
        return _tidy(+_offset_convert(magnitude, from_unit, to_unit))
    except ArithmeticError:  # 1e999999999 ms: beyond Decimal's exponent range
        raise ValueError(f"{magnitude:g} {_clip(from_unit)} is too large to convert to '{_clip(to_unit)}'") from None


@lru_cache(maxsize=256)
def turns_apply(unit: str) -> bool:
    """Whether ``unit`` is an angle or a cycle quantity (what ``cycles_as_angles`` is about)."""
    dims = _dim(unit)
    return "[angle]" in dims or dims in ("dimensionless", "1 / [time]")


def _tidy(d: Decimal) -> Decimal:
    """Without trailing zeros (50, not 50.00000000000000000000000000), never in exponent form (1000, not 1E+3)."""
    n = d.normalize()
    if n.as_tuple().exponent <= 0 or n.adjusted() >= 28:  # type: ignore[operator]
        return n
    return n.quantize(Decimal(1))


@lru_cache(maxsize=4096)
def _offset_convert(magnitude: Decimal, from_unit: str, to_unit: str) -> Decimal:
    """A conversion with an offset (degF -> degC), by pint's own arithmetic, once per distinct value.

    Computed with guard digits, so an exact answer (68 degF = 20 degC) comes out exact."""
    with precise():
        q = registry().Quantity(magnitude, _pint_text(from_unit))
        return Decimal(q.to(_pint_text(to_unit)).magnitude)


def _dim(unit: str) -> str:
    try:
        with precise():
            d = registry().parse_units(_pint_text(unit)).dimensionality
        return str(d) if str(d) != "dimensionless" else "dimensionless"
    except Exception:
        return "?"
