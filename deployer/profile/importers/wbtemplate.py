"""Import a wb-mqtt-serial device template (Wiren Board's JSON device descriptions) as a profile.

A template is JSON with ``//`` and ``/* */`` comments: ``device.parameters`` (a list of objects with
``id``, or an object keyed by id) are the device's settings, ``device.channels`` its polled values.
Meanings follow wb-mqtt-serial's template schema and README: ``address`` is the 0-based protocol
address (a number, a decimal or hex string, or ``reg:shift:width`` for some bits of a register);
``scale`` and ``offset`` convert as register = (value - offset) / scale, our engineering = raw x
scale + offset; ``min``/``max``/``default``/``enum`` are engineering values; a parameter with
``readonly: true`` is a setting of the web configurator only, with no register.

Channels are imported as wb-mqtt-serial treats them: writable unless ``readonly``, input registers and
discrete inputs read-only; a ``pushbutton`` channel (a defrost command) becomes an ``action``, which
pull leaves out and a recipe cannot set. ``fw`` becomes the parameter's ``firmware`` range.
What a profile cannot say (``condition``, a separate ``write_address`` ...) is kept in the
description with a warning that names the key and its position; registers two entries share are
imported once (the first entry; the other names are kept in its description), never refused, with
one warning per register where the names may mean different things.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from decimal import Decimal
from typing import Any

from ...errors import Diagnostic, InputError
from ...load import yamlsrc
from .. import codec, firmware, units
from ..emit import Draft, Origin

_FORMATS: dict[str, str] = {
    "u16": "uint16",
    "s16": "int16",
    "u32": "uint32",
    "s32": "int32",
    "u64": "uint64",
    "s64": "int64",
    "float": "float32",
    "double": "float64",
    "u8": "uint16",
    "s8": "int16",
    "string8": "string",
}
_REG_TYPES: dict[str, str] = {
    "holding": "holding",
    "holding_single": "holding",
    "holding_multi": "holding",
    "coil": "coil",
    "discrete": "discrete",
    "input": "input",
    "press_counter": "input",
}
# the control types that imply a unit (wb-mqtt-serial's deprecated types; "value" + units replaces them)
_TYPE_UNITS: dict[str, str] = {
    "temperature": "degC",
    "voltage": "V",
    "current": "A",
    "power": "W",
    "power_consumption": "kWh",
    "rel_humidity": "percent",
}
# units as templates write them -> as pint reads them
_UNITS: dict[str, str] = {
    "deg C": "degC",
    "°C": "degC",
    "%": "percent",
    "%, RH": "percent",
    "lx": "lux",
    "m^3/h": "m**3/h",
    "m^3": "m**3",
    "Ohm": "ohm",
    "mOhm": "milliohm",
    "VA": "V*A",
    "var": "V*A",
    "varh": "V*A*h",
    "VAh": "V*A*h",
    "kvarh": "kV*A*h",
    "kVAh": "kV*A*h",
    "mm/h": "mm/h",
    "deg": "degree",
}
# keys that only arrange the web configurator or the poll loop: nothing a profile or a deployment needs
_UI_KEYS = frozenset(
    {
        "title",
        "id",
        "name",
        "group",
        "order",
        "required",
        "type",
        "sporadic",
        "semi-sporadic",
        "read_period_ms",
        "read_rate_limit_ms",
        "enabled",
        "original_name",
        "vrf",
        "round_to",
        "description",
        "hidden",
        "units",
        "unit",
        "readonly",
        "enum",
        "enum_titles",
        "default",
        "min",
        "max",
        "scale",
        "offset",
        "format",
        "reg_type",
        "address",
        "write_address",
        "word_order",
        "byte_order",
        "string_data_size",
        "error_value",
        "unsupported_value",
        "on_value",
        "off_value",
        "fw",
        "condition",
    }
)
_NAME = re.compile(r"[^A-Za-z0-9_.-]+")
_ADDRESS = re.compile(r"^\s*(0[xX][0-9A-Fa-f]+|\d+)(?::(\d+):(\d+))?\s*$")
MAX_TEMPLATE_ENTRIES = 20000  # parameters + channels: the largest real template has a few thousand channels


def strip_comments(text: str) -> str:
    """JSON with // and /* */ comments -> JSON; comments become spaces, so every position stays the same."""
    out: list[str] = []
    i, n = 0, len(text)
    in_string = False
    while i < n:
        c = text[i]
        if in_string:
            out.append(c)
            if c == "\\" and i + 1 < n:
                out.append(text[i + 1])
                i += 2
                continue
            in_string = c != '"'
            i += 1
        elif c == '"':
            in_string = True
            out.append(c)
            i += 1
        elif text.startswith("//", i):
            j = text.find("\n", i)
            j = n if j < 0 else j
            out.append(" " * (j - i))
            i = j
        elif text.startswith("/*", i):
            j = text.find("*/", i + 2)
            j = n if j < 0 else j + 2
            out.append(re.sub(r"[^\n]", " ", text[i:j]))
            i = j
        else:
            out.append(c)
            i += 1
    return "".join(out)


@dataclass
class _Entry:
    """One parameter or channel on its way into the profile."""

    name: str
    spec: dict[str, Any]
    origin: Origin
    table: str
    address: int
    mask: int
    count: int
    notes: list[str] = field(default_factory=list)  # what goes into the description
    channel: bool = False


@dataclass
class WbImport:
    draft: Draft
    warnings: list[str]
    left_out: int  # entries not imported (each with a warning)


def read_wb_template(path: str, *, profile_id: str | None = None, channels: bool = True) -> WbImport:
    """A profile draft from a wb-mqtt-serial template file, and the warnings about what it could not say."""
    text = strip_comments(yamlsrc.read_text(path))
    _refuse_jinja(path, text)
    try:
        data, src = yamlsrc.load(path, text)
    except InputError as bad:  # the YAML parser reads the JSON: say JSON
        raise InputError(
            [replace(d, message=d.message.replace("invalid YAML", "invalid JSON")) for d in bad.diagnostics]
        ) from None
    if not isinstance(data, dict) or not isinstance(data.get("device"), dict):
        raise InputError(
            [
                src.error(
                    (), "not a wb-mqtt-serial device template: expected an object with 'device' (and 'device_type')"
                )
            ]
        )
    dev: dict[str, Any] = data["device"]
    protocol = dev.get("protocol", "modbus")
    if protocol not in ("modbus", "modbus_io"):
        raise InputError(
            [
                src.error(
                    ("device", "protocol"),
                    f"protocol '{protocol}' is not Modbus: only Modbus templates become profiles",
                )
            ]
        )
    translate = _translations(dev)
    warnings: list[str] = []

    def warn(at: yamlsrc.Path_, message: str) -> None:
        line, col = src.pos(at)
        warnings.append(f"{path}:{line}:{col}: {message}")

    raw_params = dev.get("parameters") or []
    if isinstance(raw_params, Mapping):
        items: list[tuple[yamlsrc.Path_, Any]] = [
            (("device", "parameters", k), {**v, "id": k} if isinstance(v, Mapping) else v)
            for k, v in raw_params.items()
        ]
    elif isinstance(raw_params, list):
        items = [(("device", "parameters", i), v) for i, v in enumerate(raw_params)]
    else:
        raise InputError([src.error(("device", "parameters"), "parameters: expected a list or an object")])
    chans: list[tuple[yamlsrc.Path_, Any]] = (
        [(("device", "channels", i), v) for i, v in enumerate(dev.get("channels") or [])] if channels else []
    )
    if len(items) + len(chans) > MAX_TEMPLATE_ENTRIES:
        raise InputError(
            [
                src.error(
                    ("device",), f"{len(items) + len(chans)} parameters and channels; at most {MAX_TEMPLATE_ENTRIES}"
                )
            ]
        )
    errors = []
    entries: list[_Entry] = []
    left_out = 0
    for channel, group in ((False, items), (True, chans)):
        for at, item in group:
            if not isinstance(item, Mapping):
                errors.append(src.error(at, f"a {'channel' if channel else 'parameter'} must be an object"))
                continue
            entry = _entry(item, at, src, path, warn, translate, channel=channel)
            if entry is None:
                left_out += 1
            else:
                entries.append(entry)
    if errors:
        raise InputError(errors)

    kept, dropped = _resolve_shared(entries, warnings)
    left_out += dropped
    for what in ("setup", "subdevices"):
        if dev.get(what):
            n = len(dev[what]) if isinstance(dev[what], list) else 1
            why = (
                "writes the driver sends at start-up; a recipe sets parameters instead"
                if what == "setup"
                else "nested device templates"
            )
            warn(("device", what), f"{what}: {n} {why}: not imported")
    if not kept:
        raise InputError([src.error(("device",), "the template has no parameter or channel with a Modbus register")])

    device_type = str(data.get("device_type", "wb-device"))
    pid = profile_id or (_NAME.sub("-", device_type).strip("-._") or "wb-device")
    title = translate(str(data.get("title") or dev.get("name") or device_type))
    header: dict[str, Any] = {"profile": pid, "description": f"{title} (wb-mqtt-serial template {device_type})"}
    limits = {}
    for key in ("max_write_registers", "max_read_registers"):
        v = dev.get(key)
        top = 123 if key == "max_write_registers" else 125
        if isinstance(v, int) and v > 0:  # 0 means "as many as the protocol allows" in wb-mqtt-serial
            limits[key] = min(v, top)
    writable = [e for e in kept if e.table == "holding" and "access" not in e.spec]
    if writable and all(e.spec.get("_single") for e in writable):
        limits["write_function"] = 6  # holding_single: "always written one by one, with 06"
    if limits:
        header["limits"] = limits
    params = []
    for k in kept:
        spec = {key: _plain(v) for key, v in k.spec.items() if not key.startswith("_")}
        if k.notes:
            spec["description"] = "; ".join([*([spec["description"]] if spec.get("description") else []), *k.notes])
        params.append((k.name, spec, k.origin))
    return WbImport(Draft(header, params, []), warnings, left_out)


_JINJA = re.compile(r"\{%|\{\{")


def _refuse_jinja(path: str, text: str) -> None:
    """A ``.json.jinja`` template is a program that writes the JSON (wb-mqtt-serial renders it with the
    device's settings first): say how to get the JSON instead of a JSON error at its first ``{%``."""
    m = _JINJA.search(text)
    if m is None and not path.endswith(".jinja"):
        return
    pos = m.start() if m is not None else 0
    line = text.count("\n", 0, pos) + 1
    col = pos - (text.rfind("\n", 0, pos) + 1) + 1
    out = path.removesuffix(".jinja") if path.endswith(".json.jinja") else f"{path}.json"
    raise InputError(
        [
            Diagnostic(
                path,
                line,
                col,
                (
                    "a Jinja template (.json.jinja): wb-mqtt-serial renders it into JSON before use. "
                    "Render it first, with the values your device needs (or its defaults): "
                    "python3 -c 'import jinja2, sys; "
                    "print(jinja2.Template(open(sys.argv[1]).read()).render())' "
                    f"{path} > {out}, then import {out}"
                ),
            )
        ]
    )


def _plain(v: Any) -> Any:
    """Decimals as the emitter writes numbers: int when whole, else float (its shortest text is the decimal's)."""
    if isinstance(v, Decimal):
        return int(v) if v == v.to_integral_value() else float(v)
    return v


def _translations(dev: Mapping[str, Any]) -> Any:
    """English texts for the template's titles when it has them (titles are often keys of 'translations')."""
    tr = dev.get("translations")
    en = tr.get("en") if isinstance(tr, Mapping) else None

    def translate(text: str) -> str:
        if isinstance(en, Mapping) and isinstance(en.get(text), str):
            return str(en[text])
        return text

    return translate


def _number(v: Any) -> Decimal | None:
    if isinstance(v, bool) or v is None:
        return None
    if isinstance(v, int | Decimal | float):
        return Decimal(str(v))
    if isinstance(v, str):
        t = v.strip()
        try:
            return Decimal(int(t, 16)) if t.lower().startswith("0x") else Decimal(t.replace(",", "."))
        except (ValueError, ArithmeticError):
            return None
    return None


@dataclass
class _Item:
    """One template entry while it is read: what every step below needs, and what they found."""

    item: Mapping[str, Any]
    at: yamlsrc.Path_
    label: str  # "parameter 'setpoint'", for warnings
    warn: Any
    translate: Any
    channel: bool
    table: str = "holding"
    reg_type: str = "holding"
    spec: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    address: int = 0
    addr_key: str = "address"
    mask: int = 0
    count: int = 1
    fmt: str = "u16"
    scale: Decimal = Decimal(1)
    offset: Decimal = Decimal(0)
    labels: dict[str, int] = field(default_factory=dict)

    def say(self, key: str | None, message: str) -> None:
        self.warn(self.at if key is None else (*self.at, key), f"{self.label}: {message}")

    @property
    def is_bit(self) -> bool:
        return self.table in ("coil", "discrete") or bool(self.mask and codec.mask_shift(self.mask)[1] == 1)


def _entry(
    item: Mapping[str, Any],
    at: yamlsrc.Path_,
    src: yamlsrc.Source,
    path: str,
    warn: Any,
    translate: Any,
    *,
    channel: bool,
) -> _Entry | None:
    """One parameter or channel as a profile parameter, or None (left out, with a warning)."""
    kind = "channel" if channel else "parameter"
    raw_name = str(item.get("id") if not channel or item.get("id") else item.get("name") or "")
    e = _Item(item, at, f"{kind} '{raw_name}'", warn, translate, channel)
    line, col = src.pos(at)
    if not _kept(e, raw_name, kind):
        return None
    name = _name(e, raw_name, kind)
    e.reg_type = str(item.get("reg_type", "holding"))
    table = _REG_TYPES.get(e.reg_type)
    if table is None:
        e.say("reg_type", f"reg_type '{e.reg_type}' is not a Modbus table: left out")
        return None
    e.table = table
    access = _address_and_access(e)
    if access is None or not _shape(e) or not _scale_offset(e):
        return None
    _unit(e)
    _enum(e)
    _bounds(e)
    _default(e)
    _extras(e)
    if e.channel and item.get("type") == "pushbutton" and access == "read-write":
        e.spec["action"] = True  # a momentary command: wb-mqtt-serial writes it when the button is pressed
        e.notes.append("an action (pushbutton): never pulled, never set by a recipe")
    if access != "read-write":
        e.spec["access"] = access
    if e.table != "holding":
        e.spec["register_type"] = e.table
    spec = {"register": e.address, **e.spec}
    return _Entry(name, spec, Origin(path, line, col), e.table, e.address, e.mask, e.count, e.notes, channel)


def _kept(e: _Item, raw_name: str, kind: str) -> bool:
    """Whether the entry can be imported at all (a name, a register, not a nested device's)."""
    item = e.item
    if not raw_name:
        e.warn(e.at, f"a {kind} without {'name' if e.channel else 'id'}: left out")
        return False
    if e.channel and "device_type" in item:
        e.say(None, f"a channel of a nested device ({item['device_type']}): left out")
        return False
    if not e.channel and item.get("readonly") is True:
        e.say(
            "readonly",
            "readonly: true marks a setting of the web configurator only, with no register in the device: left out",
        )
        return False
    if item.get("address", item.get("write_address")) is None:
        e.say(None, "no address: left out")
        return False
    return True


def _name(e: _Item, raw_name: str, kind: str) -> str:
    """A profile name for the entry; its title (and the template's id where the name differs) as notes."""
    item = e.item
    title = e.translate(str(item.get("title") or item.get("name") or ""))
    if title and title != raw_name:
        e.notes.append(title)
    if item.get("description"):
        e.notes.append(e.translate(str(item["description"])))
    name = _NAME.sub("_", raw_name).strip("_") or kind
    if not re.match(r"^[A-Za-z_]", name):
        name = f"{'c' if e.channel else 'p'}_{name}"
    if name != raw_name and not title:
        e.notes.insert(0, raw_name)
    return name


def _parse_address(e: _Item, key: str) -> tuple[int, int, int] | None:
    m = _ADDRESS.match(str(e.item[key]))
    if not m:
        e.say(key, f"{key} {e.item[key]!r} is not a register address: left out")
        return None
    reg = int(m[1], 16) if m[1].lower().startswith("0x") else int(m[1])
    shift, width = (int(m[2]), int(m[3])) if m[2] is not None else (0, 0)
    if reg > 0xFFFF:
        e.say(key, f"{key} {reg} is beyond 65535: left out")
        return None
    return reg, shift, width


def _address_and_access(e: _Item) -> str | None:
    """The register (and bits), and whether it is read, written or both, as wb-mqtt-serial treats it: a
    channel is writable unless ``readonly``, input registers and discrete inputs never are."""
    item = e.item
    e.addr_key = "address" if "address" in item else "write_address"
    parsed = _parse_address(e, e.addr_key)
    if parsed is None:
        return None
    e.address, shift, width = parsed
    read_only = e.table in ("discrete", "input") or (e.channel and item.get("readonly") is True)
    access = "read-only" if read_only else "read-write"
    if "address" in item and "write_address" in item:
        wparsed = _parse_address(e, "write_address")
        if wparsed is None:
            return None
        if wparsed[0] != e.address and access == "read-write":
            # read at one register, written at another: a profile has one address per parameter
            e.say(
                "write_address",
                f"read at {e.address} but written at write_address {wparsed[0]}: imported "
                "read-only at address (a profile has one register per parameter); the write "
                "address is in its description",
            )
            e.notes.append(f"written at register {wparsed[0]} (write_address)")
            access = "read-only"
    elif e.addr_key == "write_address":
        access = "write-only"
        if width:
            e.say("write_address", "a write-only bit field cannot keep its register's other bits: left out")
            return None
    if width:
        e.mask = -1 if e.table in ("coil", "discrete") else ((1 << width) - 1) << shift
        if shift + width > 16 and e.table not in ("coil", "discrete"):
            e.say(e.addr_key, f"bits {shift}..{shift + width - 1} run past one register: left out")
            return None
    return access


def _shape(e: _Item) -> bool:
    """Type, bits, size and byte layout from ``format``, ``word_order``, ``byte_order``."""
    item, spec = e.item, e.spec
    e.fmt = fmt = str(item.get("format", "u16"))
    if e.table in ("coil", "discrete"):
        if "format" in item and fmt not in ("u16", "u8", "s16"):
            e.say("format", f"format {fmt} on a {e.table} (one bit): ignored")
        if e.mask:
            e.say(e.addr_key, f"a {e.table} has no bits to select: address taken as {e.address}")
            e.mask = 0
        return True
    type_ = _FORMATS.get(fmt)
    if type_ is None:
        e.say("format", f"format {fmt} has no profile type (uint16 ... float64, string8): left out")
        return False
    if e.mask:
        type_ = "bool" if codec.mask_shift(e.mask)[1] == 1 else ("int16" if fmt.startswith("s") else "uint16")
        spec["mask"] = e.mask
    elif fmt in ("u8", "s8"):
        e.mask = spec["mask"] = 0x00FF  # the low byte of the register
    spec["type"] = type_
    if type_ == "string":
        size = item.get("string_data_size")
        if not isinstance(size, int) or not 1 <= size <= 123:
            e.say("format", "string8 needs string_data_size (registers): left out")
            return False
        spec["count"] = e.count = size
    elif not e.mask:
        e.count = codec.register_count(type_)
    _byte_layout(e, type_)
    if e.reg_type == "holding_single" and not e.channel:
        spec["_single"] = True
    return True


def _byte_layout(e: _Item, type_: str) -> None:
    item, spec = e.item, e.spec
    if item.get("word_order") == "little_endian" and e.count > 1 and type_ != "string":
        spec["word_order"] = "little"
    if item.get("byte_order") == "little_endian":
        if e.mask:
            e.say("byte_order", "byte_order little_endian on a bit field: ignored")
        else:
            spec.pop("word_order", None)
            spec["byte_order"] = "DCBA" if item.get("word_order") == "little_endian" and e.count > 1 else "BADC"
    if e.fmt == "string8" and item.get("byte_order") == "little_endian":
        spec.pop("byte_order", None)
        spec["swap"] = "byte"


def _scale_offset(e: _Item) -> bool:
    """register = (value - offset) / scale, as ours: engineering = raw x scale + offset."""
    item, spec = e.item, e.spec
    scale, offset = _number(item.get("scale", 1)), _number(item.get("offset", 0))
    for key, v, neutral in (("scale", scale, 1), ("offset", offset, 0)):
        if key in item and v is None:
            e.say(key, f"{key} {item[key]!r} is not a number: ignored")
        elif v is not None and v != neutral:
            if e.table in ("coil", "discrete") or spec.get("type") in ("bool", "string"):
                e.say(key, f"{key} {v} on a one-bit value or text: ignored")
            elif key == "scale" and v == 0:
                e.say(key, "scale 0: left out")
                return False
            else:
                spec[key] = v
    e.scale = scale if scale and "scale" in spec else Decimal(1)
    e.offset = offset if offset is not None and "offset" in spec else Decimal(0)
    return True


def _unit(e: _Item) -> None:
    item = e.item
    unit_text = item.get("units", item.get("unit"))
    if unit_text is None and isinstance(item.get("type"), str) and item["type"] in _TYPE_UNITS:
        unit_text = _TYPE_UNITS[item["type"]]
    if not unit_text or e.is_bit or e.spec.get("type") == "string":
        return
    u = _UNITS.get(str(unit_text).strip(), str(unit_text).strip())
    if units.check(u):
        key = "units" if "units" in item else ("unit" if "unit" in item else "type")
        e.say(key, f"unit '{unit_text}' is not one pint knows: kept in the description")
        e.notes.append(f"unit: {unit_text}")
    else:
        e.spec["unit"] = u


def _enum(e: _Item) -> None:
    """Enumerations: labels as written (English where the template translates them)."""
    enum, titles = e.item.get("enum"), e.item.get("enum_titles")
    if not isinstance(enum, list) or not enum:
        return
    if not isinstance(titles, list) or len(titles) != len(enum):
        e.notes.append("allowed values: " + ", ".join(str(v) for v in enum))
        if titles is not None:
            e.say(
                "enum_titles",
                f"{len(titles) if isinstance(titles, list) else 0} enum_titles for {len(enum)} "
                "enum values: kept in the description as numbers",
            )
        return
    labels = e.labels
    for v, t in zip(enum, titles, strict=True):
        n = _number(v)
        if n is None:
            e.say("enum", f"enum value {v!r} is not a number: left out of the labels")
            continue
        raw = (n - e.offset) / e.scale
        if raw != raw.to_integral_value():
            e.say("enum", f"enum value {v} is not a whole raw value: left out of the labels")
            continue
        text = e.translate(str(t)).strip() or str(v)
        while text in labels:  # two values with one title: keep both, tell them apart
            text = f"{text} ({v})"
        labels[text] = int(raw)
    if labels:
        e.spec["values"] = labels


def _bounds(e: _Item) -> None:
    for key in ("min", "max"):
        if key not in e.item or e.labels or e.is_bit:
            continue
        v = _number(e.item[key])
        if v is None:
            e.say(key, f"{key} {e.item[key]!r} is not a number: ignored")
        elif not _fits(v, e.spec, e.scale, e.offset):
            e.say(
                key,
                f"{key} {v} does not fit in {e.spec.get('type', 'the register')} ({e.fmt}): kept in the description",
            )
            e.notes.append(f"{key} {v}")
        else:
            e.spec[key] = v


def _default(e: _Item) -> None:
    if "default" not in e.item:
        return
    spec = e.spec
    d = _number(e.item["default"])
    if d is None:
        e.say("default", f"default {e.item['default']!r} is not a number: ignored")
    elif e.labels:
        raw = (d - e.offset) / e.scale
        match = next((t for t, r in e.labels.items() if r == raw), None)
        if match is None:
            e.say("default", f"default {d} is none of the enum values: kept in the description")
            e.notes.append(f"default {d}")
        else:
            spec["default"] = match
    elif e.is_bit:
        spec["default"] = bool(d)
    elif (
        ("min" in spec and d < spec["min"])
        or ("max" in spec and d > spec["max"])
        or not _fits(d, spec, e.scale, e.offset)
    ):
        e.say("default", f"default {d} is outside min..max or the type: kept in the description")
        e.notes.append(f"default {d}")
    else:
        spec["default"] = d


def _extras(e: _Item) -> None:
    """``fw`` (the firmware it needs, carried over), ``condition`` and keys a profile has no word for."""
    item = e.item
    if "fw" in item:
        fw = str(item["fw"]).strip()
        if firmware.check_range(fw) is None:
            e.spec["firmware"] = fw  # wb-mqtt-serial: this revision or later, as a bare revision says
        else:
            e.say("fw", f"fw '{fw}' is not a revision: kept in the description")
        e.notes.append(f"needs firmware {fw} or later")
    if "condition" in item:
        e.notes.append(f"applies when {item['condition']}")
        e.say("condition", f"condition '{item['condition']}' cannot be said in a profile: kept in the description")
    for key in ("error_value", "on_value", "off_value", "unsupported_value"):
        if key in item:
            e.notes.append(f"{key} {item[key]}")
    for key in sorted(k for k in item if k not in _UI_KEYS):
        e.say(key, f"key '{key}' is not understood: kept in the description")
        e.notes.append(f"{key}: {item[key]}")


def _fits(value: Decimal, spec: Mapping[str, Any], scale: Decimal, offset: Decimal) -> bool:
    """Whether an engineering bound is a raw value the parameter's type (or bits) can hold."""
    type_ = spec.get("type")
    if type_ not in codec.TYPE_NAMES or codec.is_float(type_):
        return True
    raw = (value - offset) / scale
    if "mask" in spec:
        lo, hi = codec.field_range(int(spec["mask"]), type_ == "int16")
    else:
        lo, hi = codec.raw_range(type_) or (0, 0)
    return bool(lo - 1 < raw < hi + 1)


def _resolve_shared(entries: list[_Entry], warnings: list[str]) -> tuple[list[_Entry], int]:
    """Registers two entries share: the first keeps them (parameters before channels, in file order).

    An entry at exactly the same place (register, bits, size) is the same value under another name
    (an alias, often under a condition): its name goes into the keeper's description. One that only
    overlaps is left out. Both with a warning naming both positions.
    """
    kept: list[_Entry] = []
    occupied: dict[tuple[str, int], list[_Entry]] = {}  # (table, register) -> the kept entries there
    names: set[str] = set()
    suffix: dict[str, int] = {}  # a taken name -> the next number to try (20,000 channels of one name: linear)
    dropped = 0
    aliases: dict[int, tuple[_Entry, str, list[str]]] = {}  # keeper -> where its first alias is, their names
    for e in entries:
        regs = [(e.table, r) for r in range(e.address, e.address + e.count)]
        clash = next((k for r in regs for k in occupied.get(r, ()) if _overlap(k, e)), None)
        where = f"{e.origin.path}:{e.origin.line}:{e.origin.col}"
        if clash is not None:
            at = f"line {clash.origin.line}"
            if (clash.address, clash.mask, clash.count) == (e.address, e.mask, e.count):
                when = [n for n in e.notes if n.startswith(("applies when", "needs firmware"))]
                if e.name != clash.name:
                    clash.notes.append(
                        f"also named {e.name} in the template" + (f" ({'; '.join(when)})" if when else "")
                    )
                if _ambiguous(clash, e):  # said once per register below, with every other name it has
                    aliases.setdefault(id(clash), (clash, where, []))[2].append(e.name)
            else:
                warnings.append(f"{where}: {e.name} overlaps {clash.name} ({at}) in register {e.address}: left out")
                dropped += 1
            continue
        name = e.name
        k = suffix.get(e.name, 2)
        while name in names:  # a channel named like a parameter (another register)
            name = f"{e.name}_{k}"
            k += 1
        suffix[e.name] = k
        if name != e.name:
            warnings.append(f"{where}: the name {e.name} is taken: imported as {name}")
            e.notes.insert(0, e.name)
            e.name = name
        names.add(name)
        for r in regs:
            occupied.setdefault(r, []).append(e)
        kept.append(e)
    for clash, where, names_ in aliases.values():
        one = len(names_) == 1
        warnings.append(
            f"{where}: {', '.join(names_)} {'shares its' if one else 'share the'} register "
            f"{clash.address} with {clash.name} (line {clash.origin.line}): imported once, as "
            f"{clash.name}; {names_[0] if one else 'they'} {'is' if one else 'are'} named in its "
            "description"
        )
    return kept, dropped


def _ambiguous(keeper: _Entry, alias: _Entry) -> bool:
    """Whether two entries at one place may mean different things: not a channel showing a parameter's value
    (or a channel of the same name), only differently shaped or named settings."""
    if alias.channel and (not keeper.channel or alias.name == keeper.name):
        return any(alias.spec.get(k) != keeper.spec.get(k) for k in _SHAPE)
    return alias.name != keeper.name or alias.spec != keeper.spec


# what makes two entries at one register read one value the same way
_SHAPE = ("type", "mask", "count", "scale", "offset", "word_order", "byte_order", "swap", "register_type")


def _overlap(a: _Entry, b: _Entry) -> bool:
    if a.address + a.count <= b.address or b.address + b.count <= a.address:
        return False
    if a.mask and b.mask and a.address == b.address and a.count == b.count == 1:
        return bool(a.mask & b.mask)
    return True
