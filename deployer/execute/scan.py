"""Which unit ids answer on a bus or behind a gateway, and what they are (commissioning).

Each unit gets one FC03 read of one register with no retry: any answer, data or a Modbus
exception, means a device is there; silence costs one timeout; a gateway's 0Ah/0Bh (path
unavailable, target did not answer) means nobody answers behind it. Units that answered are then
asked for their Device Identification (Function 43 / 14, basic objects); a device without it
answers 01 or nothing and is listed without identity. Read-only: nothing is written.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace

from ..errors import ConnectionLost, ExceptionResponse, NoResponse, Unreachable
from ..profile import object_name
from ..transport import clients as tp
from .connect import opened

GATEWAY_SILENT = (10, 11)  # gateway path unavailable, gateway target device failed to respond


@dataclass
class UnitFound:
    unit: int
    answer: str  # "registers" | "exception NN"
    identity: dict[str, str] | None = None


@dataclass
class ScanResult:
    url: str
    units: list[UnitFound]
    asked: int
    seconds: float

    def inventory_text(self, url_text: str, when: str | None = None) -> str:
        """An inventory fragment listing the units that answered (``when``: the scan's time, UTC, by default now)."""
        return inventory_text(self, url_text, when or time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))


async def scan(
    url: tp.DeviceURL,
    units: Iterable[int],
    *,
    register: int = 0,
    on_unit: Callable[[int, UnitFound | None], None] | None = None,
) -> ScanResult:
    """Ask each unit of ``units`` on ``url`` (its ``timeout`` per unit, no retries). Raises Unreachable."""
    url = replace(url, retries=0)
    transport = opened(url, None)  # one connection for every unit: the bus's pacing (the URL's) for all
    start = time.monotonic()
    found: list[UnitFound] = []
    asked = 0
    await transport.connect()
    try:
        for unit in units:
            asked += 1
            hit = await _probe_unit(transport, unit, register)
            if hit is not None:
                found.append(hit)
            if on_unit is not None:
                on_unit(unit, hit)
    finally:
        await transport.close()
    return ScanResult(tp.describe(url), found, asked, time.monotonic() - start)


async def _probe_unit(transport: tp.Transport, unit: int, register: int) -> UnitFound | None:
    try:
        await transport.read_holding_registers(register, 1, unit)
        answer = "registers"
    except ExceptionResponse as e:
        if e.code in GATEWAY_SILENT:
            return None
        answer = f"exception {e.code:02d}"
    except NoResponse:
        return None
    except ConnectionLost:  # some gateways drop the connection for a unit they cannot reach
        with contextlib.suppress(Unreachable):
            await transport.reconnect()
        return None
    return UnitFound(unit, answer, await identify(transport, unit))


async def identify(transport: tp.Transport, unit: int) -> dict[str, str] | None:
    """Function 43 / 14 basic objects as texts by name, or None for a device without them."""
    try:
        objects = await transport.read_device_identification(unit)
    except (ExceptionResponse, NoResponse):
        return None
    except ConnectionLost:
        with contextlib.suppress(Unreachable):
            await transport.reconnect()
        return None
    return {object_name(i): v.decode("latin-1").strip(" \x00") for i, v in sorted(objects.items())}


def inventory_text(result: ScanResult, url_text: str, when: str) -> str:
    """An inventory fragment listing the units that answered (``deployer validate`` accepts it)."""
    import json

    lines = [
        f"# deployer scan {url_text}: {len(result.units)} of {result.asked} unit ids answered ({when})",
        "# give each device a profile and a recipe (or groups), then: deployer plan --inventory FILE",
        "devices:" if result.units else "devices: {}",
    ]
    for u in result.units:
        what = ", ".join(f"{k} {v}" for k, v in (u.identity or {}).items()) or f"no identification ({u.answer})"
        lines.append(f"  unit-{u.unit}:  # {what}")
        lines.append(f"    url: {json.dumps(url_text)}")
        lines.append(f"    unit: {u.unit}")
    return "\n".join(lines) + "\n"
