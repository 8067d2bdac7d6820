"""What a recipe names besides its values: its device, and what makes it a snapshot (shared by the loader,
the recipe writer ``text`` and the snapshots, without either importing the other)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass


@dataclass(frozen=True)
class DeviceSpec:
    url: str | None = None
    unit: int | None = None


@dataclass(frozen=True)
class SnapshotInfo:
    """What makes a recipe a snapshot: where it came from and the raw registers it restores."""

    profile_sha256: str | None  # digest of the profile the values were decoded with
    registers: Mapping[str, tuple[int, ...]]  # parameter -> raw words as the device held them
    taken: str | None = None
    applied: str | None = None  # the recipe applied after the snapshot was taken
    profile_changed: bool = False  # loaded with --force although the profile's digest differs
    identity: Mapping[str, str] | None = None  # the device's Function 43 objects when it was read
    addresses: Mapping[str, tuple[int, int]] | None = None  # parameter -> (address, registers) as read
