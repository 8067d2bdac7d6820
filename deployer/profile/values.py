"""Values as people write them for one parameter: a number, a number with a unit, or a label.

Recipes and the profile's own health checks (``{parameter: dc_bus_voltage, min: 450 V}``) read values
the same way.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from decimal import Decimal, InvalidOperation
from typing import Any

from ..load import messages
from . import units
from .model import Parameter

THOUSANDS = re.compile(r"^\s*([-+]?\d{1,3}(?:,\d{3})+(?:\.\d+)?)(?![\d,])")  # 3,000 s as manuals print it
NUMBER = re.compile(r"^\s*([-+]?(?:\d[\d_]*(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?)\s*(.*?)\s*$")


def label(labels: Mapping[str, int], text: str) -> tuple[str, int] | None:
    """The label ``text`` names: exactly, else the one label equal to it without regard to case.

    ValueError when several labels differ from ``text`` only in case."""
    if text in labels:
        return text, labels[text]
    folded = [k for k in labels if k.casefold() == text.casefold()]
    if len(folded) == 1:
        return folded[0], labels[folded[0]]
    if folded:
        raise ValueError(
            f"'{text}' matches the labels {messages.label_list(folded)}, which differ only in case: write one exactly"
        )
    return None


def engineering(param: Parameter, value: Any, written: str | None = None) -> Decimal | tuple[str, int]:
    """A written value -> engineering Decimal in the parameter's unit, or (label, raw). ValueError says why not.

    ``written``: a boolean's text as the file has it (``yes``; YAML 1.1 reads it as true), tried as a label.
    """
    labels = dict(param.values)
    if isinstance(value, bool) and written is not None and labels:
        hit = label(labels, written)
        if hit is not None:
            return hit
    if isinstance(value, bool) or value is None:
        raise ValueError(_not_a_value(value, written, labels))
    if isinstance(value, int | Decimal):
        return Decimal(value)
    text = str(value)
    hit = label(labels, text)
    if hit is not None:
        return hit
    thousands = THOUSANDS.match(text)
    if thousands:
        fixed = thousands[1].replace(",", "") + text[thousands.end(1) :]
        raise ValueError(f"'{text}': write numbers without thousands separators: {fixed}")
    m = NUMBER.match(text)
    if not m:
        choices = f" or one of: {messages.label_list(labels)}" if labels else ""
        raise ValueError(f"'{text}' is not a number with a unit{choices}")
    try:
        number = Decimal(m.group(1).replace("_", ""))
    except InvalidOperation:
        raise ValueError(f"'{text}' is not a number") from None
    unit = m.group(2)
    if not unit:
        return number
    target = param.unit or "dimensionless"
    if param.unit is not None and units.normalize(unit) == param.unit:
        return number
    return units.convert(number, unit, target, cycles_as_angles=param.cycles_as_angles)


def _not_a_value(value: object, written: str | None, labels: Mapping[str, int]) -> str:
    got = json.dumps(value)
    hint = ""
    if written is not None:
        got = f"{written} (YAML reads it as {got})"
        hint = f"; the labels are {messages.label_list(labels)}" if labels else "; to mean the text, quote it"
    return f"expected a number, a value with a unit or a label, got {got}{hint}"
