"""Recipes: parameter values in engineering units for one device type.

Loading resolves the profile, ``extends`` chains, units (pint), enumeration labels, table
entries and ``{raw: N}``, and checks ranges and resolution, all before any device is touched.
"""

from __future__ import annotations

from dataclasses import dataclass

from .profile import Parameter, Profile


@dataclass(frozen=True)
class DeviceSpec:
    url: str | None = None
    unit: int | None = None


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
