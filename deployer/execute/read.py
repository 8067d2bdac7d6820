"""Reading a device without writing: its plan (plan --device), its current values (diff, pull)."""

from __future__ import annotations

from collections.abc import Sequence

from ..errors import DeviceGone, ExceptionResponse, IdentityMismatch, Unreachable, UsageError
from ..planning.model import Plan, Target
from ..planning.planner import plan_reads
from ..profile import Profile, profile_ref
from ..recipe.loader import Recipe
from ..report import RequestRecord
from ..state import learned
from ..transport import clients as tp
from .connect import connected
from .device import Planners, _Device, new_result
from .executor import Execution, check_identity
from .job import Job
from .session import ApplyOptions
from .verify import values_of


async def plan_device(
    recipe: Recipe,
    url: tp.DeviceURL,
    unit: int,
    *,
    write_all: bool = False,
    state_dir: str | None = ".deployer",
    planners: Planners | None = None,
    records: list[RequestRecord] | None = None,
    notices: list[str] | None = None,
    window: bool = False,
) -> Plan:
    """The plan ``apply`` would execute on the device now: the plan's checks run on it (identity, the current
    values, its identification and firmware: reads only), and the plan made against what they read, over the
    limits the device taught an earlier apply (``state_dir``; None: the profile's alone).

    ``notices``: told what the user should know (the limits a device taught are used, answers came late);
    ``window``: the plan of a safe change (``--soak``, ``--confirm-within``: the health checks read first).
    Raises Unreachable (also when the checks refuse the device: another model, another firmware), UsageError."""
    if unit == 0:
        raise UsageError("unit 0 is broadcast: nothing can be read from it")
    if state_dir is not None:  # what devices taught changes the plan: a damaged file is refused before a read
        learned.load(state_dir)
    job = Job(recipe.name, recipe, url, unit)
    opts = ApplyOptions(write_all=write_all, state_dir=state_dir or ".deployer")
    res = new_result(job)
    dev = _Device(job, opts, res, planners or Planners(), window=window)
    if state_dir is not None:
        dev.over_taught()
    async with connected(
        url, unit, recipe.profile, records=records if records is not None else res.requests, notices=res.notices
    ) as session:
        ex = Execution(session, recipe, res, dev.results, opts, dev.shared.values)
        if not await ex.checks(dev.shared.planner.checks):
            why = (res.error or "").removesuffix("; nothing was written")
            raise Unreachable(f"{tp.describe(url)} unit {unit}: {why}")
        dev.keep_taught(ex)
        # the URL as a saved plan runs it again: its timeout, retries and pauses, no secret (as a snapshot keeps it)
        plan, _ = dev.shared.plan(Target(tp.recorded(url), unit, profile_ref(dev.recipe.profile)), ex.before, False)
    if notices is not None:
        notices.extend(res.notices)
    return plan


async def read_current(
    profile: Profile,
    names: Sequence[str],
    url: tp.DeviceURL,
    unit: int,
    records: list[RequestRecord] | None = None,
    *,
    backoff: float = 0.05,
) -> dict[str, tuple[int, ...]]:
    """Current registers of the named readable parameters (diff, pull), after the profile's identity check.
    Raises Unreachable / UsageError."""
    if unit == 0:
        raise UsageError("unit 0 is broadcast: nothing can be read from it")
    async with connected(url, unit, profile, records=records, backoff=backoff) as session:
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
