"""A read-only check of a profile against a live device, ending with the profile changes it suggests.

Reads the identity (the profile's identity registers and the device's Function 43 objects), then
every readable parameter in the planner's blocks; a block the device refuses with 02 is read again
parameter by parameter to find which addresses it does not have. Values outside a parameter's
declared range are listed. For parameters whose value the user knows (``expect``), every byte and
word layout is tried on the registers read, and a power-of-ten scale where no layout fits.
Nothing is written.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from decimal import Decimal, InvalidOperation

from ..errors import CodecError, ExceptionResponse, UsageError
from ..planning.planner import plan_reads, read_key
from ..profile import Parameter, Profile, codec, object_name, units
from ..report import RequestRecord
from ..transport import clients as tp
from .connect import connected
from .session import Session
from .verify import values_of

LAYOUTS = (("big", False), ("little", False), ("big", True), ("little", True))  # ABCD, CDAB, BADC, DCBA


@dataclass
class Finding:
    name: str
    what: str  # what was seen
    change: str | None = None  # the suggested profile change, if any


@dataclass
class ProbeResult:
    identity: dict[str, str] | None = None
    values: dict[str, str] = field(default_factory=dict)  # parameter -> value as the profile decodes it
    findings: list[Finding] = field(default_factory=list)
    requests: list[RequestRecord] = field(default_factory=list)

    @property
    def changes(self) -> list[str]:
        return [f.change for f in self.findings if f.change]


def parse_expected(p: Parameter, text: str) -> Decimal:
    """The engineering value of ``--expect NAME=VALUE``: a label, a number in the parameter's unit, or a
    number with a unit convertible to it (``10 s``, ``1500 rpm``). Raises UsageError."""
    for label, raw in p.values:
        if label == text.strip():
            return codec.from_raw(raw, p.scale, p.offset)
    m = re.fullmatch(r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(.*?)\s*", text)
    if m is None:
        raise UsageError(
            f"--expect {p.name}={text}: expected a number (in {p.unit or 'the parameter units'}) or one of its labels"
        )
    try:
        value = Decimal(m.group(1))
    except InvalidOperation:
        raise UsageError(f"--expect {p.name}={text}: not a number") from None
    unit = m.group(2)
    if unit and unit != p.unit:
        if p.unit is None:
            raise UsageError(f"--expect {p.name}={text}: {p.name} has no unit")
        try:
            value = units.convert(value, unit, p.unit, cycles_as_angles=p.cycles_as_angles)
        except Exception as e:  # pint's errors for unknown or incompatible units
            raise UsageError(f"--expect {p.name}={text}: {e}") from None
    return value


async def probe(profile: Profile, url: tp.DeviceURL, unit: int, expect: Mapping[str, str]) -> ProbeResult:
    """Raises Unreachable, DeviceGone (the device stopped answering)."""
    wanted = {name: parse_expected(profile.parameter(name), text) for name, text in expect.items()}
    result = ProbeResult()
    async with connected(url, unit, profile, records=result.requests) as session:
        await _identity(session, profile, result)
        regs = await _read_all(session, profile, result)
    readable = [p for p in profile.parameters if p.readable]
    held = values_of(readable, regs)
    for p in readable:
        words = held.get(p.name)
        if words is None:
            continue
        result.values[p.name] = p.show_registers(words)
        _range(p, words, result)
    for name, value in wanted.items():
        p = profile.parameter(name)
        if name in held:
            _layout(p, held[name], value, result)
    _common_layout(profile, result)
    return result


async def _identity(session: Session, profile: Profile, result: ProbeResult) -> None:
    for chk in profile.identity:
        try:
            (word,) = await session.read(chk.address, 1)
        except ExceptionResponse as e:
            result.findings.append(
                Finding(
                    "identity",
                    f"identity register 0x{chk.address:04X} answers {e}",
                    f"check identity register {chk.address} (0x{chk.address:04X})",
                )
            )
            continue
        if word != chk.raw:
            result.findings.append(
                Finding(
                    "identity",
                    f"identity register 0x{chk.address:04X} holds {word} (0x{word:04X}), the profile expects {chk.raw}",
                    "another kind of device, or the profile's identity raw value "
                    f"for 0x{chk.address:04X} should be {word}",
                )
            )
    result.identity = await session.identify()
    objects = result.identity or {}
    for obj in profile.identity_objects:
        name = object_name(obj.object_id)
        if objects.get(name) != obj.equals:
            result.findings.append(
                Finding(
                    "identity",
                    f"{name} is {objects.get(name)!r}, the profile expects {obj.equals!r}",
                    f"identity object {name} should equal {objects.get(name)!r}"
                    if name in objects
                    else "the device has no Function 43 identity: drop the identity object checks",
                )
            )
    if objects and not profile.identity_objects and "product_code" in objects:
        result.findings.append(
            Finding(
                "identity",
                f"the device identifies itself ({_text(objects)})",
                f"identity: - {{object: product_code, equals: {objects['product_code']!r}}} "
                "(recognises the device before any write)",
            )
        )


async def _read_all(session: Session, profile: Profile, result: ProbeResult) -> dict[int, int]:
    """Every readable parameter; a refused block is read again one parameter at a time."""
    readable = [p for p in profile.parameters if p.readable]
    regs: dict[int, int] = {}
    for r in plan_reads(profile, [p.name for p in readable], gaps=False):
        try:
            regs.update(await session.read_blocks([r]))
            continue
        except ExceptionResponse as e:
            if e.code not in (2, 3):
                raise
        inside = [p for p in readable if p.key >= read_key(r) and p.key + p.count <= read_key(r) + r.count]
        for p in inside:
            try:
                regs.update(await session.read_blocks(plan_reads(profile, [p.name], gaps=False)))
            except ExceptionResponse as e:
                result.findings.append(
                    Finding(
                        p.name,
                        f"{p.name} at 0x{p.address:04X} answers {e} when read",
                        f"{p.name}: access: write-only if it is a command register, else check its address "
                        f"(0x{p.address:04X})",
                    )
                )
    return regs


def _range(p: Parameter, words: tuple[int, ...], result: ProbeResult) -> None:
    bounds = p.raw_bounds()
    if bounds is None or p.is_string or p.mask:
        return
    raw = p.decode(words)
    if isinstance(raw, float) and raw != raw:
        result.findings.append(Finding(p.name, f"{p.name} reads NaN", f"{p.name}: check type and byte_order"))
        return
    if not bounds[0] <= raw <= bounds[1]:
        lo, hi = (p.show_registers(p.encode(b)) for b in bounds)
        result.findings.append(
            Finding(
                p.name,
                f"{p.name} reads {p.show_registers(words)}, outside its declared range {lo}..{hi}",
                f"{p.name}: check its scale, type and byte_order, or widen min/max",
            )
        )


def _close(a: Decimal, b: Decimal) -> bool:
    return a == b or abs(a - b) <= abs(b) * Decimal("1e-6")


def _layout(p: Parameter, words: tuple[int, ...], value: Decimal, result: ProbeResult) -> None:
    """Which layout (and, failing that, which power-of-ten scale) makes ``words`` read as ``value``."""
    if p.is_string or p.mask:
        return
    fits = []
    for order, swap in LAYOUTS:
        if p.count == 1 and order == "little":
            continue
        try:
            raw = codec.decode(words, p.codec_type, order, swap)
        except CodecError:
            continue
        if isinstance(raw, float) and raw != raw:
            continue
        if _close(codec.from_raw(raw, p.scale, p.offset), value):
            fits.append(codec.layout_name(order, swap, p.type))
    mine = p.layout
    if mine in fits:
        result.findings.append(Finding(p.name, f"{p.name} reads {value} as expected ({mine})"))
        return
    if fits:
        layout = fits[0]
        change = f"{p.name}: swap: byte" if p.count == 1 else f"{p.name}: byte_order: {layout}"
        result.findings.append(
            Finding(
                p.name,
                f"{p.name}: {value} is held as {layout} (the profile reads {mine}: {p.show_registers(words)})",
                change,
            )
        )
        return
    raw = p.decode(words)
    if not isinstance(raw, float) and raw and value:
        ratio = (value - p.offset) / Decimal(raw)
        exp = ratio.adjusted()
        if ratio == Decimal(10) ** exp:
            result.findings.append(
                Finding(
                    p.name,
                    f"{p.name} holds raw {raw}; {value} means scale {Decimal(10) ** exp} (the profile says {p.scale})",
                    f"{p.name}: scale: {Decimal(10) ** exp}",
                )
            )
            return
    result.findings.append(
        Finding(
            p.name,
            f"{p.name} reads {p.show_registers(words)} "
            f"({' '.join(f'{w:04X}h' for w in words)}); no byte or word layout "
            f"gives {value}",
            f"{p.name}: check its address and type",
        )
    )


def _common_layout(profile: Profile, result: ProbeResult) -> None:
    """Several parameters wanting the same other layout: say it once, for the whole profile."""
    per = [f.change for f in result.findings if f.change and ": byte_order: " in f.change]
    layouts = {c.rsplit(" ", 1)[1] for c in per if c is not None}
    if len(per) > 1 and len(layouts) == 1:
        result.findings.append(
            Finding(
                "profile",
                f"{len(per)} parameters agree on {layouts.pop()}",
                f"byte_order: {per[0].rsplit(' ', 1)[1]} for the whole profile (top level) instead of per parameter"
                if per[0]
                else None,
            )
        )


def _text(objects: Mapping[str, str]) -> str:
    return ", ".join(f"{k} {v!r}" for k, v in objects.items())
