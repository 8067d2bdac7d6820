"""Reading a device's current values (plan, diff, pull, snapshots)."""

from __future__ import annotations

from collections.abc import Sequence

from ..errors import DeviceGone, ExceptionResponse, IdentityMismatch, Unreachable, UsageError
from ..planning.planner import plan_reads
from ..profile import Profile
from ..report import RequestRecord
from ..transport import clients as tp
from .session import Session
from .steps import check_identity
from .verify import values_of

# ---- reading without writing: plan --device, diff, pull ----------------------------------


async def read_current(profile: Profile, names: Sequence[str], url: tp.DeviceURL, unit: int,
                       records: list[RequestRecord] | None = None, *, backoff: float = 0.05,
                       ) -> dict[str, tuple[int, ...]]:
    """Current registers of the named readable parameters. Raises Unreachable / UsageError."""
    if unit == 0:
        raise UsageError("unit 0 is broadcast: nothing can be read from it")
    transport = tp.open_transport(url)
    await transport.connect()
    session = Session(transport, unit, retries=url.retries, backoff=backoff,
                      records=records if records is not None else [])
    try:
        try:
            await check_identity(session, profile)
        except IdentityMismatch as e:  # the device asked for is not there: nothing of it can be read
            raise Unreachable(str(e)) from None
        params = [profile.parameter(n) for n in names]
        reads = plan_reads(profile, [p.name for p in params if p.readable])
        return values_of(params, await session.read_blocks(reads, profile))
    except DeviceGone as e:
        raise Unreachable(f"{tp.describe(url)} unit {unit}: {e}") from None
    except ExceptionResponse as e:
        raise Unreachable(f"{tp.describe(url)} unit {unit}: reading answered {e}") from None
    finally:
        await transport.close()
