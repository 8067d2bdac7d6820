"""The plan: a plain, serializable value saying every step apply takes on a device, in order.

A plan is complete: the identity checks, the reads of the current values (the snapshot), the
preconditions, the unlock, each write (with the read before a bit-field write), the read-back, the
commit and the lock, with the waits the profile asks for. ``apply`` executes exactly these steps;
what only the device can decide (a refused request split, a retry) is reported as a named
deviation from the step it replaces (``deployer/execute``), never as a step of its own.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, Literal

from ..profile.model import PROTOCOL_MAX_READ, PROTOCOL_MAX_READ_COILS, PROTOCOL_MAX_WRITE, PROTOCOL_MAX_WRITE_COILS

PLAN_SCHEMA = "deployer.plan/2"
OLD_SCHEMAS = ("deployer.plan/1",)  # refused with the command that makes the plan again
Action = Literal["write", "unchanged", "bridge"]
COIL_WRITES = (5, 15)  # Write Single Coil, Write Multiple Coils
WRITE_FUNCTIONS = (5, 6, 15, 16)
READ_FUNCTIONS = (1, 2, 3, 4)
DEVICE_ID = 43  # Read Device Identification (MEI type 14): basic objects
# the most one request of each function carries (Modbus Application Protocol v1.1b3, 6.1-6.12)
MOST_PER_REQUEST = {
    1: PROTOCOL_MAX_READ_COILS,
    2: PROTOCOL_MAX_READ_COILS,
    3: PROTOCOL_MAX_READ,
    4: PROTOCOL_MAX_READ,
    5: 1,
    6: 1,
    15: PROTOCOL_MAX_WRITE_COILS,
    16: PROTOCOL_MAX_WRITE,
}

# The kinds of step, in the order they can come. The first four check the device and read what it holds,
# before anything is planned against it (``CHECKS``); the rest change it.
StepKind = Literal[
    "identity",
    "snapshot",
    "device-id",
    "firmware",
    "precondition",
    "health",
    "unlock",
    "read-modify-write",
    "write",
    "verify",
    "commit",
    "lock",
]
STEP_KINDS: tuple[StepKind, ...] = (
    "identity",
    "snapshot",
    "device-id",
    "firmware",
    "precondition",
    "health",
    "unlock",
    "read-modify-write",
    "write",
    "verify",
    "commit",
    "lock",
)
CHECKS: frozenset[str] = frozenset(("identity", "snapshot", "device-id", "firmware"))


@dataclass(frozen=True)
class Target:
    url: str | None
    unit: int
    profile: str  # built-in id, or the profile file's path


@dataclass(frozen=True)
class Pacing:
    """Seconds of silence the device needs: after a connection opens, and from an answer to the next request
    (the URL's ``pause_after_connect``/``pause_between_requests``, else the profile's)."""

    after_connect: float = 0.0
    between_requests: float = 0.0


NO_PAUSES = Pacing()


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
class Expect:
    """What a checking read must find: ``(word & mask) >> shift == equals`` (shift: the mask's lowest bit)."""

    equals: int
    mask: int = 0xFFFF

    def holds(self, word: int) -> bool:
        return (word & self.mask) >> _shift(self.mask) == self.equals

    def found(self, word: int) -> int:
        return (word & self.mask) >> _shift(self.mask)


def _shift(mask: int) -> int:
    return (mask & -mask).bit_length() - 1 if mask else 0


@dataclass(frozen=True)
class Step:
    """One request of a plan (and the wait after it).

    ``values``: the words (coils: 0/1) a write sends; None for a secret (an unlock password from the
    environment), which the executor takes from the profile and no output shows. ``parameters``: the recipe
    parameters it writes, reads back or reads before a bit-field write. ``expect``: what an identity or
    precondition read must find. ``wait``: seconds the device needs after it (a stage's settling, a commit's
    store, an unlock's window). ``note``: the profile's description ("drive stopped", "store to EEPROM").
    """

    kind: StepKind
    function: int
    address: int
    count: int
    values: tuple[int, ...] | None = ()
    parameters: tuple[str, ...] = ()
    stage: int = 0
    wait: float = 0.0
    expect: Expect | None = None
    note: str = ""

    @property
    def writes(self) -> bool:
        return self.function in WRITE_FUNCTIONS

    @property
    def secret(self) -> bool:
        return self.values is None

    def read(self) -> ReadRequest:
        return ReadRequest(self.address, self.count, self.function)

    def write(self, values: tuple[int, ...] | None = None) -> WriteRequest:
        """The step as a write request (``values``: a secret's words, from the profile)."""
        words = self.values if values is None else values
        assert words is not None, "a secret step's words come from the profile"
        return WriteRequest(self.function, self.address, words, self.parameters, self.stage)


@dataclass(frozen=True)
class Cost:
    """What executing a plan costs one device, all its steps counted (every step sent once, no retries).

    ``bytes``: requests and answers in the URL's framing (RTU at Modbus's default 19200 8E1 without one);
    ``seconds``: their time on the line at its baud rate (serial framings; 0 for Modbus/TCP, whose time is
    the network's) plus ``waits``, the pauses and waits the steps and the pacing ask for.
    ``non_volatile_writes``: the writes the device stores in memory that wears (a commit's, or every write on
    a profile that states an ``endurance`` and has no commit); ``stores``: the parameters they make lasting.
    """

    requests: int
    reads: int
    writes: int
    bytes: int
    framing: str
    line: str  # "19200 baud 8E1", "Modbus/TCP"
    seconds: float
    waits: float
    non_volatile_writes: int
    stores: tuple[str, ...]


@dataclass(frozen=True)
class Plan:
    """Every step apply takes on one device, in order; and what it does with each recipe parameter."""

    recipe: str | None
    device: Target
    parameters: tuple[PlannedParameter, ...]
    steps: tuple[Step, ...]
    schema: str = PLAN_SCHEMA
    recipe_name: str | None = None  # the recipe's own name: snapshots of 'apply PLAN.json' are named after it
    pacing: Pacing = NO_PAUSES
    profile_sha256: str | None = None  # the profile file's digest (None: built-in); a saved plan runs with it only

    @functools.cached_property
    def writes(self) -> tuple[WriteRequest, ...]:
        """The recipe's write requests (``write`` steps), in order."""
        return tuple(s.write() for s in self.steps if s.kind == "write")

    @functools.cached_property
    def reads(self) -> tuple[ReadRequest, ...]:
        """The blocks read before writing (the snapshot) and after (the read-back): the same ones."""
        return tuple(s.read() for s in self.steps if s.kind == "snapshot")

    @functools.cached_property
    def checks(self) -> int:
        """How many steps lead the plan that only check the device and read what it holds (``CHECKS``)."""
        n = 0
        for s in self.steps:
            if s.kind not in CHECKS:
                break
            n += 1
        return n

    # what the executor asks of every device's plan, made once per plan: the devices of a fleet holding the same
    # values run copies of one plan (``copy.copy`` keeps these) instead of working 100 parameters' worth out again
    @functools.cached_property
    def _desired(self) -> dict[str, tuple[int, ...]]:
        """The raw registers planned for each parameter (the executor's copy of it may change)."""
        return {pp.name: tuple(pp.desired_raw) for pp in self.parameters}

    @functools.cached_property
    def _read_back(self) -> tuple[tuple[int, ...], tuple[ReadRequest, ...]]:
        """The verify steps' numbers (from 1) and their reads."""
        numbers = tuple(n for n, s in enumerate(self.steps, 1) if s.kind == "verify")
        return numbers, tuple(self.steps[n - 1].read() for n in numbers)

    @property
    def changes(self) -> bool:
        """Whether executing the plan writes anything."""
        return any(s.writes for s in self.steps)

    def to_json(self) -> dict[str, Any]:
        """The plan as a saved plan's JSON (docs/reference/plan.md), as ``plan --out`` writes it and ``load_plan``
        reads it back."""
        return plan_to_json(self)


# ---- as JSON (a saved plan: docs/reference/plan.md; planfile reads it back) ---------------------------


def step_to_json(s: Step) -> dict[str, Any]:
    out: dict[str, Any] = {"kind": s.kind, "function": s.function, "address": s.address, "count": s.count}
    if s.writes:
        out["values"] = None if s.values is None else list(s.values)
    if s.parameters:
        out["parameters"] = list(s.parameters)
    if s.kind == "write":
        out["stage"] = s.stage
    if s.wait:
        out["wait"] = s.wait
    if s.expect is not None:
        out["expect"] = {"equals": s.expect.equals, **({"mask": s.expect.mask} if s.expect.mask != 0xFFFF else {})}
    if s.note:
        out["note"] = s.note
    return out


def cost_to_json(c: Cost) -> dict[str, Any]:
    return {
        "requests": c.requests,
        "reads": c.reads,
        "writes": c.writes,
        "bytes": c.bytes,
        "framing": c.framing,
        "line": c.line,
        "seconds": c.seconds,
        "waits": c.waits,
        "non_volatile_writes": c.non_volatile_writes,
        "stores": list(c.stores),
    }


def plan_to_json(plan: Plan, cost: Cost | None = None) -> dict[str, Any]:
    """The plan as saved-plan JSON (docs/reference/plan.md); ``cost``: its informational ``cost`` member."""
    doc: dict[str, Any] = {
        "schema": plan.schema,
        "recipe": plan.recipe,
        **({"recipe_name": plan.recipe_name} if plan.recipe_name is not None else {}),
        "device": {"url": plan.device.url, "unit": plan.device.unit, "profile": plan.device.profile},
        "profile_sha256": plan.profile_sha256,
        "pacing": {"after_connect": plan.pacing.after_connect, "between_requests": plan.pacing.between_requests},
        "parameters": [
            {
                "name": p.name,
                "address": p.address,
                "count": p.count,
                "desired": p.desired,
                "desired_raw": list(p.desired_raw),
                "current_raw": None if p.current_raw is None else list(p.current_raw),
                "action": p.action,
                "stage": p.stage,
                **({"register_type": p.register_type} if p.register_type != "holding" else {}),
            }
            for p in plan.parameters
        ],
        "steps": [step_to_json(s) for s in plan.steps],
    }
    if cost is not None:
        doc["cost"] = cost_to_json(cost)
    return doc
