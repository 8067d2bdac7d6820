"""Engineering units with pint, on Decimal magnitudes so conversions stay exact."""

from __future__ import annotations

from decimal import Decimal
from functools import lru_cache
from typing import Any

import pint

_ALIASES = {"%": "percent", "‰": "permille"}


@lru_cache(maxsize=1)
def registry() -> Any:
    return pint.UnitRegistry(non_int_type=Decimal, autoconvert_offset_to_baseunit=True)


def normalize(text: str) -> str:
    """The unit as the user wrote it (kept for display), with '%' spelled out for pint."""
    return text.strip()


def _pint_text(text: str) -> str:
    t = text.strip()
    return _ALIASES.get(t, t)


def check(text: str) -> str | None:
    """None if pint knows the unit, else a message for the user."""
    try:
        registry().parse_units(_pint_text(text))
    except (pint.UndefinedUnitError, pint.errors.DefinitionSyntaxError, AttributeError, ValueError,
            TypeError, AssertionError):
        return f"unknown unit '{text}'"
    except Exception:  # pint raises a zoo of parser errors for garbage input
        return f"unknown unit '{text}'"
    return None


def convert(magnitude: Decimal, from_unit: str, to_unit: str) -> Decimal:
    """Convert exactly; raises ValueError with a user message on a dimension mismatch."""
    ureg = registry()
    try:
        q = ureg.Quantity(magnitude, _pint_text(from_unit))
    except Exception:
        raise ValueError(f"unknown unit '{from_unit}'") from None
    try:
        out = q.to(_pint_text(to_unit)).magnitude
    except pint.DimensionalityError:
        raise ValueError(
            f"'{from_unit}' is not convertible to '{to_unit}' "
            f"({_dim(from_unit)} vs. {_dim(to_unit)})"
        ) from None
    result = Decimal(out)
    # pint's factors are Decimal; strip representation noise like 10.000 -> 10.000 (exact already)
    return result


def _dim(unit: str) -> str:
    try:
        d = registry().parse_units(_pint_text(unit)).dimensionality
        return str(d) if str(d) != "dimensionless" else "dimensionless"
    except Exception:
        return "?"
