"""Values read from devices: compared with a recipe (``Drift``) or with the factory defaults (``FromDefault``),
and kept with their device and profile (``Pulled``), which writes them as recipe text."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from ..profile import Profile
from ..recipe.loader import Recipe


@dataclass(frozen=True)
class Drift:
    """One parameter whose device value is not the recipe's (``device`` None: it cannot be read): its name, the
    recipe's value (``desired``, in engineering units, and ``desired_raw``, register words) and the device's."""

    name: str
    desired: str
    desired_raw: tuple[int, ...]
    device: str | None
    device_raw: tuple[int, ...] | None

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "desired": self.desired,
            "device": self.device,
            "desired_raw": list(self.desired_raw),
            "device_raw": None if self.device_raw is None else list(self.device_raw),
            "status": "drift" if self.device_raw is not None else "not readable",
        }


def diff_values(recipe: Recipe, current: Mapping[str, tuple[int, ...]]) -> list[Drift]:
    """The recipe's parameters the device does not hold (or that cannot be read), in recipe order."""
    out = []
    for d in recipe.desired:
        cur = current.get(d.name)
        if cur is None or not d.parameter.same_value(cur, d.registers):  # a bit field compares its own bits
            out.append(
                Drift(d.name, d.text, d.registers, None if cur is None else d.parameter.format_registers(cur), cur)
            )
    return out


@dataclass(frozen=True)
class FromDefault:
    """One parameter whose device value is not its factory default (the profile's ``default``)."""

    name: str
    default: str
    default_raw: tuple[int, ...]
    device: str
    device_raw: tuple[int, ...]

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "default": self.default,
            "device": self.device,
            "default_raw": list(self.default_raw),
            "device_raw": list(self.device_raw),
        }


def defaults_diff(profile: Profile, current: Mapping[str, tuple[int, ...]]) -> tuple[list[FromDefault], list[str]]:
    """The parameters read (``current``) that differ from their factory default, in profile order; and the
    names read that have no default in the profile (they cannot be compared). A bit field compares its bits."""
    differs, unknown = [], []
    for p in profile.parameters:
        regs = current.get(p.name)
        if regs is None:
            continue
        want = p.default_registers()
        if want is None:
            unknown.append(p.name)
        elif not p.same_value(regs, want):
            differs.append(FromDefault(p.name, p.show_registers(want), want, p.show_registers(regs), tuple(regs)))
    return differs, unknown


def non_default(profile: Profile, values: Mapping[str, tuple[int, ...]]) -> dict[str, tuple[int, ...]]:
    """``values`` without the parameters that hold their factory default (those with no default are kept:
    nobody can say they are factory settings). ``pull --non-default`` writes this."""
    out = {}
    for n, v in values.items():
        p = profile.parameter(n)
        want = p.default_registers()
        if want is None or not p.same_value(v, want):
            out[n] = v
    return out


def pull_names(profile: Profile) -> list[str]:
    """What pull reads: every parameter that can be read and written back (a momentary command is no setting)."""
    return [p.name for p in profile.parameters if p.readable and p.writable and not p.action]


def out_of_range(profile: Profile, values: Mapping[str, Sequence[int]]) -> list[str]:
    """The names among ``values`` whose registers lie outside the profile's range: ``pulled_recipe`` keeps
    those as comments, since a recipe could not set them."""
    from ..recipe.text import value_text

    return [n for n, regs in values.items() if value_text(profile.parameter(n), regs) is None]


def pulled_recipe(
    profile: Profile,
    values: Mapping[str, tuple[int, ...]],
    *,
    name: str,
    url: str,
    unit: int,
    comment: str = "",
    relative_to: str | None = None,
) -> str:
    """Recipe text that sets every given parameter to the values read (applies back as a no-op); values a recipe
    cannot set (``out_of_range``) are kept as comments. ``relative_to``: where the text will be written (a
    profile file is named relative to it)."""
    from ..recipe.model import DeviceSpec
    from ..recipe.text import recipe_text

    ref = profile.id
    if profile.source:
        ref = (
            os.path.relpath(profile.source, os.path.dirname(os.path.abspath(relative_to)))
            if relative_to
            else profile.source
        )
    return recipe_text(
        ref,
        {profile.parameter(n): v for n, v in values.items()},
        name=name,
        device=DeviceSpec(url, unit),
        comment=comment,
    )


class Pulled(dict[str, tuple[int, ...]]):
    """What ``pull`` read from one device: parameter name -> its register words (in the profile's order, or that
    of ``names``); and ``profile``, ``device`` (its URL, without secrets), ``unit`` and ``name`` (the device's in
    an inventory, else the recipe's or the profile's).

    ``texts()`` gives the values in engineering units, ``recipe_text()`` a recipe that sets them (it applies
    back as a no-op), ``out_of_range()`` the values no recipe can set (the recipe keeps them as comments).
    """

    def __init__(
        self, values: Mapping[str, tuple[int, ...]], *, profile: Profile, device: str, unit: int, name: str
    ) -> None:
        super().__init__(values)
        self.profile = profile
        self.device = device
        self.unit = unit
        self.name = name

    def __repr__(self) -> str:
        return f"Pulled({self.name!r}, {len(self)} values of {self.profile.id} at {self.device} unit {self.unit})"

    def texts(self) -> dict[str, str]:
        """Each value in engineering units ("10 s", "coast"), as reports show them."""
        return {n: self.profile.parameter(n).format_registers(v) for n, v in self.items()}

    def out_of_range(self) -> list[str]:
        """The names whose values lie outside the profile's range: no recipe can set them."""
        return out_of_range(self.profile, self)

    def recipe_text(
        self, *, name: str | None = None, comment: str = "", relative_to: str | os.PathLike[str] | None = None
    ) -> str:
        """Recipe text that sets every value read (named ``name``, default ``pulled-DEVICE``; ``comment`` on top);
        ``relative_to``: the file it will be written to (a profile file is named relative to it)."""
        return pulled_recipe(
            self.profile,
            self,
            name=name or f"pulled-{self.name}",
            url=self.device,
            unit=self.unit,
            comment=comment,
            relative_to=None if relative_to is None else os.fspath(relative_to),
        )
