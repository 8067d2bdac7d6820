"""Recipes: parameter values in engineering units for one device type.

Loading resolves the profile, ``extends`` chains, units (pint), enumeration labels, table
entries and ``{raw: N}``, and checks ranges and resolution, all before any device is touched.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from decimal import Decimal
from typing import Any, Literal

from ..errors import CodecError, Diagnostic, InputError, UsageError
from ..load import messages, schema, yamlsrc
from ..profile import Parameter, Profile, codec, is_profile_path, resolve_profile, values
from .model import DeviceSpec, SnapshotInfo
from .text import _range_text, snapshot_value

RECIPE_SCHEMA = "recipe"


@dataclass(frozen=True)
class Desired:
    """One parameter's desired value, validated and encoded."""

    parameter: Parameter
    text: str  # engineering text for reports: "10 s", "coast", "1000"
    registers: tuple[int, ...]  # encoded raw value, parameter.count words

    @property
    def name(self) -> str:
        return self.parameter.name


@dataclass(frozen=True)
class Recipe:
    name: str
    path: str | None  # file the recipe came from
    profile: Profile
    desired: tuple[Desired, ...]  # sorted by (stage, address)
    device: DeviceSpec | None = None
    rounding: str = "exact"
    profile_ref: str | None = None  # built-in id, or the profile file's absolute path
    snapshot: SnapshotInfo | None = None  # set when the file is a snapshot that apply saved


@dataclass(frozen=True)
class Entry:
    """One parameter value as written, with where it was written (for error positions)."""

    name: str
    value: Any
    src: yamlsrc.Source = field(repr=False)
    at: yamlsrc.Path_


# ---- loading ----------------------------------------------------------------------------


def load_recipe(
    path: str | os.PathLike[str], *, extra: Sequence[Entry] = (), profile: Profile | None = None, force: bool = False
) -> Recipe:
    """Load, resolve and check a recipe; all problems at once as an InputError.

    ``extra`` entries (an inventory's per-device overrides) win over the file's values;
    ``profile`` forces the profile (an inventory device's), else the recipe's is resolved.
    A snapshot (a recipe with a ``snapshot`` block) is checked against the profile digest it
    records (``force`` accepts a changed profile and restores the recorded raw registers).
    """
    p = os.fspath(path)
    errors: list[Diagnostic] = []
    layers = _load_chain(p, [], errors)  # base first, this file last
    if errors:
        raise InputError(errors)
    top_data = layers[-1][0]
    prof_ref: str | None = None
    prof_src: yamlsrc.Source | None = None
    device = DeviceSpec()
    rounding = "exact"
    entries: dict[str, Entry] = {}
    for data, src in layers:
        if "profile" in data:
            prof_ref, prof_src = data["profile"], src
        dev = data.get("device") or {}
        device = DeviceSpec(dev.get("url", device.url), dev.get("unit", device.unit))
        if isinstance(dev.get("url"), str):
            from ..errors import BadURL
            from ..transport.urls import parse_url

            try:
                parse_url(dev["url"])
            except BadURL as bad:
                errors.append(src.error(("device", "url"), str(bad)))
        rounding = data.get("rounding", rounding)
        for name, value in (data.get("parameters") or {}).items():
            for e in expand(name, value, src, ("parameters", name)):
                entries.pop(e.name, None)  # re-insert: a later file decides the order too
                entries[e.name] = e
    for e in extra:
        entries.pop(e.name, None)
        entries[e.name] = e

    top_src = layers[-1][1]
    snap_data = top_data.get("snapshot")
    if snap_data is not None and prof_ref is not None and _is_relative_path(prof_ref) and profile is None:
        # a snapshot lives in the snapshots folder: a relative profile path would resolve there by accident
        raise InputError(
            [
                top_src.error(
                    ("profile",),
                    f"a snapshot names its profile by absolute path or built-in id, not the relative path '{prof_ref}'",
                )
            ]
        )
    prof = profile
    if prof is None:
        assert prof_ref is not None and prof_src is not None  # the schema requires one in the chain
        try:
            prof = resolve_profile(prof_ref, relative_to=prof_src.path)
        except UsageError as e:
            raise InputError([prof_src.error(("profile",), str(e))]) from None
        except InputError as e:
            # the profile's own errors, plus where the recipe points at it
            where = prof_src.error(("profile",), f"profile '{prof_ref}' is invalid")
            raise InputError([*e.diagnostics, where]) from None
    # whatever path the profile was named by, the recipe carries one well-defined reference
    resolved_ref = prof.source or prof.id
    snapshot = _snapshot_info(snap_data, prof, top_src, force) if snap_data is not None else None
    desired: list[Desired] = []
    if snapshot is not None and snapshot.profile_changed:
        desired = _from_registers(prof, snapshot, top_src, errors)
        # a parameter the profile moved is restored where the snapshot read it: the recipe's profile says
        # so, and plan, read-back and verification all use that address
        moved = {d.name: d.parameter for d in desired if d.parameter is not prof.get(d.name)}
        if moved:
            prof = replace(prof, parameters=tuple(moved.get(q.name, q) for q in prof.parameters))
    else:
        for entry in entries.values():
            d = _desired(prof, entry, rounding, errors, trusted=snapshot is not None)
            if d is not None:
                desired.append(d)
        if snapshot is not None and not errors:
            desired += _check_snapshot(prof, desired, snapshot, entries, top_src, errors)
    if errors:
        bad_bases = sorted({d.path for d in errors} & {src.path for _, src in layers[:-1]})
        if bad_bases:  # point at this file too: the error is in a recipe it extends
            rel = ", ".join(os.path.relpath(b, os.path.dirname(os.path.abspath(p))) for b in bad_bases)
            errors.append(top_src.error(("extends",), f"the extended recipe {rel} has errors"))
        raise InputError(errors)
    desired.sort(key=lambda d: (d.parameter.stage, d.parameter.address))
    return Recipe(
        name=str(top_data["recipe"]),
        path=p,
        profile=prof,
        desired=tuple(desired),
        device=device if (device.url is not None or device.unit is not None) else None,
        rounding=rounding,
        profile_ref=resolved_ref,
        snapshot=snapshot,
    )


def with_overrides(recipe: Recipe, extra: Sequence[Entry]) -> Recipe:
    """``recipe`` with some values replaced (an inventory device's overrides), its files not read again.

    Same result as ``load_recipe(recipe.path, extra=extra)`` when the profile is the same.
    """
    errors: list[Diagnostic] = []
    new = {}
    for e in extra:
        d = _desired(recipe.profile, e, recipe.rounding, errors)
        if d is not None:
            new[d.name] = d
    if errors:
        raise InputError(errors)
    desired = [d for d in recipe.desired if d.name not in new] + list(new.values())
    desired.sort(key=lambda d: (d.parameter.stage, d.parameter.address))
    return replace(recipe, desired=tuple(desired))


def _is_relative_path(ref: str) -> bool:
    return is_profile_path(ref) and not os.path.isabs(ref)


def _snapshot_info(data: Mapping[str, Any], prof: Profile, src: yamlsrc.Source, force: bool) -> SnapshotInfo:
    """The snapshot block, checked: the profile must be the one the values were decoded with."""
    recorded = data.get("profile_sha256")
    changed = recorded is not None and prof.digest is not None and recorded != prof.digest
    if changed and not force:
        raise InputError(
            [
                src.error(
                    ("snapshot", "profile_sha256"),
                    (
                        f"profile {prof.source or prof.id} changed since this snapshot was taken "
                        f"(sha256 {str(recorded)[:12]}... then, {str(prof.digest)[:12]}... now): its values were "
                        "decoded with the old profile. Check the profile; "
                        "--force restores the recorded raw registers"
                    ),
                )
            ]
        )
    regs = {str(k): tuple(int(w) for w in v) for k, v in (data.get("registers") or {}).items()}
    ident = data.get("identity")
    identity = {str(k): str(v) for k, v in ident.items()} if isinstance(ident, dict) else None
    addresses = (
        {str(k): (int(v[0]), int(v[1])) for k, v in (data.get("addresses") or {}).items()}
        if "addresses" in data
        else None
    )  # snapshots of older versions do not say
    return SnapshotInfo(recorded, regs, data.get("taken"), data.get("applied"), changed, identity, addresses)


def _from_registers(prof: Profile, snap: SnapshotInfo, src: yamlsrc.Source, errors: list[Diagnostic]) -> list[Desired]:
    """--force with a changed profile: the recorded raw words, each where the snapshot read it (a
    parameter the profile moved goes back to its recorded address, unless another parameter of the
    profile now lies there)."""
    out = []
    for name, words in snap.registers.items():
        at: yamlsrc.Path_ = ("snapshot", "registers", name)
        param = prof.get(name)
        if param is None:
            errors.append(src.error(at, f"{name} is no longer in profile {prof.id}: cannot restore it", key=True))
        elif param.count != len(words):
            errors.append(src.error(at, f"{name} now has {param.count} registers, the snapshot recorded {len(words)}"))
        elif not param.writable:
            errors.append(src.error(at, f"{name} is read-only in profile {prof.id} now", key=True))
        elif snap.addresses is not None and name in snap.addresses and snap.addresses[name][0] != param.address:
            old = snap.addresses[name][0]
            there = sorted(
                q.name
                for q in prof.parameters
                if q.name != name
                and q.register_type == param.register_type
                and q.address < old + param.count
                and old < q.address + q.count
            )
            if there:
                errors.append(
                    src.error(
                        ("snapshot", "addresses", name),
                        (
                            f"{name} moved: the snapshot read it at {old} (0x{old:04X}), profile {prof.id} now puts "
                            f"it at {param.address} (0x{param.address:04X}) and {', '.join(there)} at {old}: "
                            "restoring it there "
                            "would write over that; restore it with a recipe"
                        ),
                    )
                )
                continue
            param = replace(param, address=old)  # back where it was read: the device's layout then
            out.append(Desired(param, param.show_registers(tuple(words)), words))
        else:
            out.append(Desired(param, param.show_registers(tuple(words)), words))
    return out


def _check_snapshot(
    prof: Profile,
    desired: Sequence[Desired],
    snap: SnapshotInfo,
    entries: Mapping[str, Entry],
    src: yamlsrc.Source,
    errors: list[Diagnostic],
) -> list[Desired]:
    """The engineering values must say what the recorded registers say: an edited snapshot is refused.

    Returns the recorded values no text can say (NaN, infinity): restored from their registers.
    """
    for d in desired:
        rec = snap.registers.get(d.name)
        e = entries[d.name]
        if rec is None:
            errors.append(e.src.error(e.at, f"{d.name} is not among the snapshot's recorded registers", key=True))
        elif not d.parameter.same_value(rec, d.registers):  # a bit field: its own bits of the word
            errors.append(
                e.src.error(
                    e.at,
                    (
                        f"{d.name}: {d.text} does not match the registers the snapshot recorded "
                        f"({' '.join(f'{w:04X}h' for w in rec)}); a snapshot restores what the device held: "
                        "to write other values, use a recipe"
                    ),
                )
            )
    named = {d.name for d in desired}
    extra = []
    for name, words in snap.registers.items():
        if name in named:
            continue
        param = prof.get(name)
        if param is not None and param.writable and param.count == len(words) and snapshot_value(param, words) is None:
            extra.append(Desired(param, param.show_registers(tuple(words)), words))
            continue
        errors.append(
            src.error(
                ("snapshot", "registers", name),
                f"{name} was recorded but is missing from parameters: a snapshot restores every "
                "value it recorded (edit neither; use a recipe to restore fewer)",
                key=True,
            )
        )
    return extra


MAX_EXTENDS_FILES = 256  # files one recipe may load through 'extends', repeats counted


def _load_chain(
    path: str,
    stack: list[str],
    errors: list[Diagnostic],
    ref: tuple[yamlsrc.Source, yamlsrc.Path_] | None = None,
    loaded: list[int] | None = None,
) -> list[tuple[dict[str, Any], yamlsrc.Source]]:
    """The recipe at ``path`` and its ``extends`` bases, bases first."""
    real = os.path.realpath(path)
    if real in stack:
        assert ref is not None
        chain = " -> ".join(os.path.basename(s) for s in [*stack[stack.index(real) :], real])
        errors.append(ref[0].error(ref[1], f"'extends' makes a cycle: {chain}"))
        return []
    loaded = loaded if loaded is not None else [0]
    loaded[0] += 1
    if loaded[0] > MAX_EXTENDS_FILES:  # hostile input: bases that extend the same bases many times over
        assert ref is not None
        if loaded[0] == MAX_EXTENDS_FILES + 1:
            errors.append(
                ref[0].error(ref[1], f"'extends' loads more than {MAX_EXTENDS_FILES} files (repeats counted)")
            )
        return []
    try:
        data, src = yamlsrc.load(path)
    except InputError as e:
        errors.extend(e.diagnostics)
        if ref is not None and any(d.line == 0 for d in e.diagnostics):
            errors.append(ref[0].error(ref[1], f"cannot load '{os.path.basename(path)}'"))
        return []
    if not isinstance(data, dict):
        errors.append(src.error((), "a recipe must be a mapping (recipe: ..., profile: ..., parameters: ...)"))
        return []
    other = _other_document(schema.document_of(data), path)
    if other is not None:  # said at once: its keys read as a recipe's would be ten errors of no use
        errors.append(src.error(("schema",), f"this is {other}", key=True))
        return []
    schema_errors = schema.validate(data, RECIPE_SCHEMA, src)
    if schema_errors:
        errors.extend(schema_errors)
        return []
    ext = data.get("extends")
    bases: list[tuple[str, yamlsrc.Path_]] = []
    if isinstance(ext, str):
        bases = [(ext, ("extends",))]
    elif isinstance(ext, list):
        bases = [(b, ("extends", i)) for i, b in enumerate(ext)]
    out: list[tuple[dict[str, Any], yamlsrc.Source]] = []
    for base, at in bases:
        base_path = os.path.normpath(os.path.join(os.path.dirname(path), base))
        before = len(errors)
        out.extend(_load_chain(base_path, [*stack, real], errors, (src, at), loaded))
        if len(errors) > before and not any(d.path == src.path for d in errors[before:]):
            errors.append(src.error(at, f"the extended recipe {base} has errors"))
        if loaded[0] > MAX_EXTENDS_FILES:
            break
    out.append((data, src))
    return out


def _other_document(kind: str | None, path: str) -> str | None:
    """What a deployer file given where a recipe belongs is instead (``schema.document_of``), and what takes it."""
    if kind == "plan":
        return (
            f"a saved plan, not a recipe: 'deployer apply {path}' runs it unchanged (plan, diff and pull take a recipe)"
        )
    if kind == "fleetplan":
        return f"a saved fleet plan, not a recipe: 'deployer apply {path}' runs it unchanged"
    if kind == "report":
        return f"a run's report, not a recipe: 'deployer report {path}' shows it"
    return None


_TABLE_ENTRY = re.compile(r"^[A-Za-z_][\w-]*\[\d+\]$")


def expand(name: str, value: Any, src: yamlsrc.Source, at: yamlsrc.Path_) -> Iterable[Entry]:
    """``tbl[3]: {field: v}`` -> ``tbl[3].field: v``; everything else as is."""
    if isinstance(value, dict) and _TABLE_ENTRY.match(name) and not ({"raw", "value"} & value.keys()):
        for field, v in value.items():
            yield Entry(f"{name}.{field}", v, src, (*at, field))
    else:
        yield Entry(name, value, src, at)


_INDEXED = re.compile(r"^([A-Za-z_][\w-]*)\[(\d+)\]\.(.+)$")


def _desired(
    prof: Profile, e: Entry, recipe_rounding: str, errors: list[Diagnostic], *, trusted: bool = False
) -> Desired | None:
    """One entry -> its Desired value (or an error). ``trusted``: a snapshot's ``{raw}`` value held by the
    device itself, which the profile's documented range does not block (the type's range still does)."""
    param = prof.get(e.name)

    def fail(msg: str, *, key: bool = False) -> None:
        errors.append(e.src.error(e.at, f"{e.name}: {msg}" if not key else msg, key=key))

    if param is None:
        m = _INDEXED.match(e.name)
        if m and prof.get(f"{m[1]}[0].{m[3]}") is not None:
            size = sum(1 for n in prof.names() if n.startswith(f"{m[1]}[") and n.endswith(f"].{m[3]}"))
            fail(f"{e.name}: index {m[2]} is out of range; table {m[1]} has entries 0..{size - 1}", key=True)
            return None
        hint = messages.closest(e.name, prof.names())
        fail(
            f"unknown parameter '{e.name}' in profile {prof.id}" + (f"; did you mean '{hint}'?" if hint else ""),
            key=True,
        )
        return None
    if not param.writable:
        fail(f"{e.name} is read-only in profile {prof.id}", key=True)
        return None
    if param.action:
        fail(
            f"{e.name} is an action in profile {prof.id} (a momentary command such as a defrost or reset), not a "
            "setting: a recipe does not set it",
            key=True,
        )
        return None
    value = e.value
    rounding: Literal["exact", "nearest"] = "nearest" if "nearest" in (param.rounding, recipe_rounding) else "exact"
    if param.is_string:
        if isinstance(value, dict) or value is None:
            fail("a string parameter takes text")
            return None
        try:
            regs = param.encode_text(str(value))
        except CodecError as err:
            fail(str(err))
            return None
        return Desired(param, str(value), regs)
    if param.type == codec.BOOL and (isinstance(value, bool) or value in ("true", "false")):
        value = int(value in (True, "true"))
    if isinstance(value, dict) and "raw" in value:
        return _from_raw(param, value["raw"], e, fail, trusted=trusted)
    if isinstance(value, dict):  # {value: ..., rounding: ...}
        if "value" not in value:  # table-entry style keys on a plain parameter
            keys = ", ".join(messages.clip(str(k)) for k in value)
            fail(f"expected a value, {{raw: N}} or {{value: V, rounding: nearest}}, got a mapping with {keys}")
            return None
        rounding = value.get("rounding", rounding)
        value = value["value"]
    try:
        eng = values.engineering(param, value, e.src.word(e.at) if isinstance(value, bool) else None)
    except ValueError as err:
        fail(str(err))
        return None
    if isinstance(eng, tuple):  # an enumeration label: raw value given directly
        return Desired(param, eng[0], param.encode(eng[1]))
    try:
        raw = param.to_raw(eng, rounding)
    except CodecError as err:
        msg = str(err)
        if err.kind == "resolution" and param.unit:  # the resolution and the value said with the unit
            msg = msg.replace(
                f"resolution {codec.format_decimal(param.scale)}",
                f"resolution {codec.format_decimal(param.scale)} {param.unit}",
            )
            msg = msg.replace(codec.format_decimal(eng), f"{codec.format_decimal(eng)} {param.unit}", 1)
        fail(msg)
        return None
    effective = codec.from_raw(raw, param.scale, param.offset)
    lo, hi = param.min, param.max
    if (lo is not None and effective < lo) or (hi is not None and effective > hi):
        fail(f"{_with_unit(eng, param)} is out of range {_range_text(param)}")
        return None
    regs = param.encode(raw)
    return Desired(param, param.format_registers(regs), regs)


def _from_raw(param: Parameter, raw_v: Any, e: Entry, fail: Any, *, trusted: bool = False) -> Desired | None:
    raw: codec.Raw
    if param.is_float:
        raw = float(raw_v)
    elif isinstance(raw_v, int) or (isinstance(raw_v, Decimal) and raw_v == raw_v.to_integral_value()):
        raw = int(raw_v)
    else:
        fail(f"raw value {raw_v} is not an integer")
        return None
    bounds = param.raw_bounds()
    if not trusted and bounds is not None and not bounds[0] <= raw <= bounds[1]:
        fail(f"raw value {raw} is out of range {bounds[0]}..{bounds[1]} ({_range_text(param)})")
        return None
    try:
        regs = param.encode(raw)
    except CodecError as err:
        fail(str(err))
        return None
    return Desired(param, param.format_registers(regs), regs)


def _with_unit(d: Decimal, param: Parameter) -> str:
    text = codec.format_decimal(d)
    return f"{text} {param.unit}" if param.unit else text
