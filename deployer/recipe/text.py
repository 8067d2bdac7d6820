"""Recipe text written from register values (snapshots, pull) that loads back to the same registers."""

from __future__ import annotations

import functools
import json
import math
import re
from collections.abc import Mapping, Sequence
from decimal import Decimal, InvalidOperation
from typing import TYPE_CHECKING

import yaml

from ..errors import CodecError
from ..load import yamlsrc
from ..profile import Parameter, codec

if TYPE_CHECKING:
    from .model import DeviceSpec, SnapshotInfo

_PLAIN_KEY = re.compile(r"^[A-Za-z_][\w.\[\]-]*$")


def _range_text(param: Parameter) -> str:
    lo = "-" if param.min is None else codec.format_decimal(param.min)
    hi = "-" if param.max is None else codec.format_decimal(param.max)
    unit = f" {param.unit}" if param.unit else ""
    return f"{lo}..{hi}{unit}"


def value_text(param: Parameter, registers: Sequence[int]) -> str | None:
    """A register value as recipe text that loads back to exactly these registers.

    None when the value lies outside the profile's range (a recipe could not set it).
    """
    if param.is_string:
        try:
            text = param.text_of(tuple(registers))
            return text if param.encode_text(text) == tuple(registers) else None
        except CodecError:
            return None
    raw = param.decode(tuple(registers))
    label = param.label_for(raw)
    if label is not None:
        return label
    if isinstance(raw, float) and not math.isfinite(raw):
        return None  # no recipe text loads back to a NaN or an infinity
    bounds = param.raw_bounds()
    if bounds is not None and not bounds[0] <= raw <= bounds[1]:
        return None
    if param.type == codec.BOOL:
        return "true" if raw else "false"
    if param.is_float and param.scale == 1 and param.offset == 0:
        text = _positional(codec.shortest_float_repr(float(raw), param.type))
    else:
        text = codec.format_decimal(param.to_engineering(tuple(registers)))
    return f"{text} {param.unit}" if param.unit else text


def _positional(text: str) -> str:
    """A number's shortest text written out as a person would ('4.5e+03' -> '4500', a float32's 4500 rpm), as
    Python's ``repr`` does: with an exponent only below 0.0001 or from 1e16 on (a 3.4e+38 stays so)."""
    d = Decimal(text)
    return format(d, "f") if d.is_finite() and -4 <= d.adjusted() < 16 else text


# Text YAML certainly reads back as the same plain string when the implicit resolvers call it a
# string: word characters, spaces, '.', '-', '/', '%' and '°' only (no ':', '#', quotes or
# indicators), neither starting nor ending with a space or an indicator.
_PLAIN_SAFE = re.compile(r"^\w(?:[\w .\-/%°]*[\w.%°])?$")
_RESOLVER = yaml.resolver.Resolver()


def _reads_back(text: str) -> bool:
    """True when ``k: TEXT`` loads back as exactly ``TEXT`` (a number or the same string)."""
    try:
        Decimal(text)
        return True
    except InvalidOperation:
        pass
    if _PLAIN_SAFE.match(text):  # the common case, without running a parser per value
        tag = _RESOLVER.resolve(yaml.ScalarNode, text, (True, False))  # type: ignore[no-untyped-call]
        return bool(tag == "tag:yaml.org,2002:str")
    try:  # both parsers must agree (libyaml reads some text with tabs differently)
        return all(
            yaml.load(f"k: {text}", Loader=loader) == {"k": text} for loader in (yamlsrc.FastLoader, yaml.SafeLoader)
        )
    except yaml.YAMLError:
        return False


def snapshot_value(param: Parameter, registers: Sequence[int]) -> str | None:
    """Recipe text for exactly these registers, even outside the profile's range (``{raw: N}``).

    None only for values no text can say (a NaN or infinite float): snapshots restore those from
    their recorded registers.
    """
    if param.is_string:  # text that does not read back exactly is restored from its registers
        return value_text(param, registers)
    raw = param.decode(tuple(registers))
    if isinstance(raw, float) and not math.isfinite(raw):
        return None
    text = value_text(param, registers)
    if text is not None:
        return text
    if isinstance(raw, float):
        r = repr(raw)
        return f"{{raw: {r if '.' in r or 'e' not in r else r.replace('e', '.0e', 1)}}}"
    return f"{{raw: {raw}}}"


def recipe_text(
    profile_ref: str,
    values: Mapping[Parameter, Sequence[int]],
    *,
    name: str,
    device: DeviceSpec | None = None,
    comment: str = "",
    snapshot: SnapshotInfo | None = None,
) -> str:
    """A recipe that sets every given parameter to the given registers (YAML text).

    Values outside the profile's range are kept as comments (a recipe cannot set them), except in
    a snapshot (``snapshot`` given), which records them as ``{raw: N}`` plus every raw register.
    """
    return recipe_head(profile_ref, name=name, device=device, comment=comment, snapshot=snapshot) + values_text(
        list(values.items()), snapshot is not None
    )


def recipe_head(
    profile_ref: str,
    *,
    name: str,
    device: DeviceSpec | None = None,
    comment: str = "",
    snapshot: SnapshotInfo | None = None,
) -> str:
    """``recipe_text`` up to its values: the comment, the recipe's name, profile and device, the snapshot's facts."""
    lines = [f"# {c}" for c in comment.splitlines()] if comment else []
    lines.append(f"recipe: {json.dumps(name)}")
    lines.append(f"profile: {json.dumps(profile_ref)}")
    if device is not None and (device.url or device.unit is not None):
        dev = {k: v for k, v in (("url", device.url), ("unit", device.unit)) if v is not None}
        lines.append(f"device: {json.dumps(dev)}")
    if snapshot is not None:
        lines.append("snapshot:  # what rollback restores: these raw registers, as the device held them")
        for k, v in (
            ("profile_sha256", snapshot.profile_sha256),
            ("taken", snapshot.taken),
            ("applied", snapshot.applied),
        ):
            if v is not None:
                lines.append(f"  {k}: {json.dumps(v)}")
        if snapshot.identity is not None:  # Function 43 objects: a later run tells a replaced device
            lines.append(f"  identity: {json.dumps(dict(snapshot.identity))}")
    return "\n".join(lines) + "\n"


def values_text(values: Sequence[tuple[Parameter, Sequence[int]]], snapshot: bool) -> str:
    """``recipe_text`` from its values on (a snapshot's from ``registers:``): the values in register order
    (holding registers, then coils; ``values`` in their order where parameters share a register)."""
    return _values_text(sorted(values, key=lambda kv: kv[0].key), snapshot)


# the values part of written recipes, by (parameter, registers) of each value: the devices of a fleet
# mostly hold the same values, and rendering 100 parameters' lines was most of a snapshot's CPU. The entry
# keeps its parameters, so the ids in its key stay theirs.
_VALUES: dict[tuple[bool, tuple[tuple[int, tuple[int, ...]], ...]], tuple[tuple[Parameter, ...], str]] = {}
_VALUES_KEPT = 64


def _values_text(ordered: Sequence[tuple[Parameter, Sequence[int]]], snapshot: bool) -> str:
    """From ``registers:`` (a snapshot) or ``parameters:`` on: the lines that say the values."""
    key = (snapshot, tuple([(id(param), tuple(regs)) for param, regs in ordered]))
    hit = _VALUES.get(key)
    if hit is not None:
        return hit[1]
    lines = []
    if snapshot:
        lines.append("  registers:" if ordered else "  registers: {}")
        lines.extend(f"    {_key(param.name)}: [{', '.join(str(w) for w in regs)}]" for param, regs in ordered)
        # where they were: rollback --force (the profile changed) restores a parameter only where it was
        lines.append("  addresses:" if ordered else "  addresses: {}")
        lines.extend(f"    {_key(param.name)}: [{param.address}, {param.count}]" for param, _ in ordered)
    body = [_body_line(param, tuple(regs), snapshot) for param, regs in ordered]
    lines.append("parameters:" if any(not b.lstrip().startswith("#") for b in body) else "parameters: {}")
    text = "\n".join(lines + body) + "\n"
    while len(_VALUES) >= _VALUES_KEPT:
        del _VALUES[next(iter(_VALUES))]  # the oldest
    _VALUES[key] = (tuple(param for param, _ in ordered), text)
    return text


@functools.lru_cache(maxsize=1 << 16)
def _body_line(param: Parameter, regs: tuple[int, ...], snapshot: bool) -> str:
    """One parameter's line of a written recipe (a comment when no value can say it).

    Cached: the devices of a fleet mostly hold the same values, and rendering a value (decode,
    range, engineering text, does YAML read it back) was most of a snapshot's CPU.
    """
    key = _key(param.name)
    v = snapshot_value(param, regs) if snapshot else value_text(param, regs)
    words = " ".join(f"{w:04X}" for w in regs)
    if v is None:
        if param.is_string:
            return f"  # {key}: registers {words}h are not {param.encoding} text padded with {param.padding}"
        raw = param.decode(regs)
        why = "restored from snapshot.registers" if snapshot else f"is outside the profile's range {_range_text(param)}"
        return f"  # {key}: raw {raw} ({words}h) {why}"
    if v.startswith("{raw:"):
        return f"  {key}: {v}  # {words}h, outside the profile's range {_range_text(param)}"
    # numbers stay numbers (in the profile's unit); text stays plain where YAML reads it back as the same text
    rendered = v if param.type == codec.BOOL or (not param.is_string and _reads_back(v)) else json.dumps(v)
    return f"  {key}: {rendered}"


def _key(name: str) -> str:
    return name if _PLAIN_KEY.match(name) else json.dumps(name)
