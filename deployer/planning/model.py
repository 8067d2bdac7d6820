"""The plan: a plain, serializable value (targets, planned parameters, write and read requests)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

PLAN_SCHEMA = "deployer.plan/1"
Action = Literal["write", "unchanged", "bridge"]
COIL_WRITES = (5, 15)  # Write Single Coil, Write Multiple Coils


@dataclass(frozen=True)
class Target:
    url: str | None
    unit: int
    profile: str  # built-in id, or the profile file's path


@dataclass(frozen=True)
class PlannedParameter:
    name: str
    address: int
    count: int
    desired: str  # engineering text, "10 s"
    desired_raw: tuple[int, ...]
    current_raw: tuple[int, ...] | None  # None when the device was not read
    action: Action
    stage: int = 0
    register_type: str = "holding"  # the Modbus table: holding, coil (values 0/1), discrete, input


@dataclass(frozen=True)
class WriteRequest:
    # 16, or 6 for devices without FC16 (then exactly one register); coils: 15, or 5 for one coil
    function: int
    address: int
    registers: tuple[int, ...]
    parameters: tuple[str, ...]
    stage: int = 0

    @property
    def count(self) -> int:
        return len(self.registers)


@dataclass(frozen=True)
class ReadRequest:
    address: int
    count: int
    function: int = 3  # 3 holding registers, 1 coils, 2 discrete inputs, 4 input registers


@dataclass(frozen=True)
class Plan:
    recipe: str | None
    device: Target
    parameters: tuple[PlannedParameter, ...]
    writes: tuple[WriteRequest, ...]
    reads: tuple[ReadRequest, ...]
    schema: str = PLAN_SCHEMA
    recipe_name: str | None = None  # the recipe's own name: snapshots of 'apply PLAN.json' are named after it
