"""The public Python API: load, plan, apply, diff, pull, for one device or a fleet; sync and async.

The command line and the Ansible modules are both written on top of this module::

    import deployer
    recipe = deployer.load_recipe("line3.yaml")
    plan = deployer.plan(recipe, "tcp://10.0.0.11:502")          # reads the device, writes nothing
    report = deployer.apply(recipe, "tcp://10.0.0.11:502", unit=1)
    report.exit_code, report.to_json()
    drift = deployer.diff(recipe, "tcp://10.0.0.11:502")         # [] when the device matches
    report = deployer.apply_fleet(recipe, "inventory.yaml", limit="line3", batch="1,10%,100%")

    inventory = deployer.inventory_from([{"name": "d1", "url": "tcp://10.0.0.11:502"}])
    jobs = deployer.fleet_jobs(recipe, inventory)                # one checked Job per device
    plans = deployer.plan_fleet(jobs)                            # check mode: name -> Plan or error

Every ``x`` has an ``x_async`` twin for callers with their own event loop. Every error is a
``DeployerError`` (``deployer.errors`` documents the tree and each one's exit code): invalid
input raises ``InputError`` (with file positions) or ``UsageError`` before anything is sent; an
unreachable device raises ``TransportError`` from ``plan``/``diff``/``pull``, and is a device
status (``unreachable``) in an apply report.

``__all__`` below is the public surface (``deployer`` serves the same list, loading this module on
first use); ``tests/test_exported_members.py`` pins it. Anything else here, or in deployer's
subpackages, may change without notice.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import Callable, Coroutine, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

from .agent.client import Agent
from .errors import (
    AgentError,
    BadURL,
    CodecError,
    Declined,
    DeployerError,
    IdentityMismatch,
    InputError,
    Locked,
    RunInterrupted,
    StalePlan,
    TransportError,
    UsageError,
)
from .fleet.inventory import FleetDevice, Inventory, load_inventory
from .fleet.inventory import fleet_jobs as _fleet_jobs
from .fleet.inventory import inventory_from as _inventory_from
from .limits import BATCH_BY, LIMITS, Bound
from .load.yamlsrc import Source
from .planning.model import Plan, Target
from .planning.planfile import load_plan, plan_to_json
from .planning.planner import make_plan
from .portable import file_name, user_name
from .profile import Profile, is_profile_path, load_profile, resolve_profile
from .profile.model import address_text
from .recipe.loader import Entry, Recipe, with_overrides
from .recipe.loader import load_recipe as _load_recipe
from .recipe.text import recipe_text
from .report import DeviceResult, ParameterResult, Report, report_from_json, report_text, run_info
from .run.request import PreparedRun, RunRequest
from .transport.urls import DeviceURL, describe, parse_url

if TYPE_CHECKING:  # served by __getattr__ below: their modules import pymodbus, loaded when a run needs them
    from .execute.job import Job
    from .execute.probe import ProbeResult
    from .execute.scan import ScanResult
    from .execute.session import ApplyOptions
    from .fleet.rollout import ReadJob
    from .profile.emit import Draft
    from .profile.importers.sunspec import DeviceModel as SunSpecModel
    from .state.journal import Unfinished
    from .state.learned import Entry as LearnedEntry
    from .transport.ports import SerialPort
    from .window.confirm import Awaiting

# the names above that __all__ lists are this module's public surface, re-exported on purpose
_REEXPORTED = (Agent, AgentError, LIMITS, Bound, BadURL, CodecError, Declined, DeployerError, IdentityMismatch,
               InputError, Locked, RunInterrupted, StalePlan, TransportError, UsageError, FleetDevice, Inventory,
               load_inventory, Plan, load_plan, plan_to_json, Profile, load_profile, Recipe, DeviceResult,
               ParameterResult, Report, report_from_json, report_text, run_info, user_name, file_name,
               DeviceURL, PreparedRun, RunRequest, address_text)

# public names whose modules load on first use: offline work (validate, an offline plan, a command's
# --help) does not pay for the transports (pymodbus)
_LAZY = {"ApplyOptions": "deployer.execute.session", "Job": "deployer.execute.job",
         "ReadJob": "deployer.fleet.rollout"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'deployer.api' has no attribute {name!r}")


__all__ = [
    "LIMITS",
    "Agent",
    "AgentError",
    "ApplyOptions",
    "BadURL",
    "Bound",
    "CodecError",
    "Declined",
    "DeployerError",
    "DeviceResult",
    "DeviceURL",
    "Drift",
    "FleetDevice",
    "FromDefault",
    "IdentityMismatch",
    "InputError",
    "Inventory",
    "Job",
    "Locked",
    "ParameterResult",
    "Plan",
    "PreparedRun",
    "Profile",
    "ReadJob",
    "Recipe",
    "Report",
    "RunInterrupted",
    "RunRequest",
    "RunStatus",
    "StalePlan",
    "TransportError",
    "UsageError",
    "address_text",
    "apply",
    "apply_async",
    "apply_fleet",
    "apply_fleet_async",
    "builtin_profiles",
    "check_folder",
    "check_output",
    "confirm",
    "confirm_outcome",
    "defaults_diff",
    "describe_url",
    "device_url",
    "diff",
    "diff_async",
    "diff_values",
    "duration",
    "file_name",
    "fleet_jobs",
    "forget_learned",
    "import_csv",
    "import_sunspec",
    "import_sunspec_chain",
    "import_wb_template",
    "import_xlsx",
    "imported_profile",
    "inventory_from",
    "learned_limits",
    "load_inventory",
    "load_plan",
    "load_profile",
    "load_recipe",
    "non_default",
    "out_of_range",
    "plan",
    "plan_async",
    "plan_cost",
    "plan_fleet",
    "plan_fleet_async",
    "plan_frames",
    "plan_to_json",
    "plan_values",
    "prepare_run",
    "probe",
    "profile_csv",
    "profile_skeleton",
    "profile_table",
    "pull",
    "pull_async",
    "pull_jobs",
    "pull_names",
    "pulled_recipe",
    "read_fleet",
    "read_fleet_async",
    "read_jobs",
    "read_report",
    "recipe_from",
    "register_address",
    "report_from_json",
    "report_text",
    "resolve_run",
    "run_fleet",
    "run_fleet_async",
    "run_info",
    "run_prepared",
    "run_prepared_async",
    "run_status",
    "safe_options",
    "scan",
    "serial_ports",
    "snapshot_text",
    "sunspec_models",
    "sunspec_reported",
    "taught_recipe",
    "url_option",
    "user_name",
    "validate_file",
    "write_output",
    "writing_caches",
]


_T = TypeVar("_T")


def _kind(value: object) -> str:
    text = repr(value)
    return f"{type(value).__name__} {text if len(text) <= 40 else text[:39] + '...'}"


def _need_recipe(recipe: object, call: str) -> None:
    """Refuse, before anything is sent, what a caller passed where a loaded Recipe belongs."""
    if not isinstance(recipe, Recipe):
        hint = " (load it first: deployer.load_recipe(path))" if isinstance(recipe, (str, os.PathLike)) else ""
        raise UsageError(f"{call} takes a Recipe{hint}, got {_kind(recipe)}")


def _need_unit(unit: object) -> None:
    if unit is None:
        return
    if isinstance(unit, bool) or not isinstance(unit, int):
        raise UsageError(f"unit must be an int from 1 to 247 (0 is broadcast), got {_kind(unit)}")
    if not 0 <= unit <= 247:
        raise UsageError(f"unit must be from 1 to 247 (0 is broadcast), got {unit}")


def _need_timing(timeout: object, retries: object) -> None:
    if timeout is not None:
        LIMITS.timeout.check(timeout, "timeout")
    if retries is not None:
        LIMITS.retries.check(retries, "retries")


def _need_path(value: object, call: str, what: str) -> None:
    if not isinstance(value, (str, os.PathLike)):
        raise UsageError(f"{call} takes {what} as a path (str or os.PathLike), got {_kind(value)}")


def _need_inventory(inventory: object, call: str) -> None:
    if not isinstance(inventory, (str, os.PathLike, Inventory)):
        raise UsageError(f"{call} takes an inventory file or an Inventory (deployer.inventory_from(devices)), "
                         f"got {_kind(inventory)}")


def _need_parallel(parallel: object) -> None:
    LIMITS.parallel.check(parallel, "parallel")


def record_meta(inventory: str | None = None, given: Sequence[str] = ()) -> list[tuple[str, str]]:
    """What the commissioning record says at the top of every page: the inventory's ``meta:`` (site, project,
    customer, line ...), then each ``KEY=VALUE`` of ``given`` (the command line's ``--meta``), which wins."""
    out: dict[str, str] = {}
    if inventory is not None:
        out.update(load_inventory(inventory).meta)
    for item in given:
        key, sep, value = str(item).partition("=")
        if not sep or not key.strip():
            raise UsageError(f"--meta {item!r}: expected KEY=VALUE (e.g. site='Plant 3')")
        out[key.strip()] = value.strip()
    return list(out.items())


def _need_batch_by(batch_by: object, call: str) -> str:
    if batch_by not in BATCH_BY:
        raise UsageError(f"{call}: batch_by is 'profile' or 'group', not {batch_by!r}")
    return str(batch_by)


def _need_options(options: object, call: str) -> ApplyOptions:
    """``options`` (None: the defaults) checked against the bounds, before anything is sent."""
    from .execute.session import ApplyOptions

    if options is None:
        return ApplyOptions()
    if not isinstance(options, ApplyOptions):
        raise UsageError(f"{call} takes options=ApplyOptions(...), got {_kind(options)}")
    if options.on_error not in ("continue", "stop"):
        raise UsageError(f"on_error must be 'continue' or 'stop', got {_kind(options.on_error)}")
    _need_path(options.state_dir, call, "options.state_dir")
    for key in ("soak", "confirm_within", "health_interval", "lock_timeout"):
        value = getattr(options, key)
        if value is not None:
            bound: Bound = getattr(LIMITS, key)
            bound.check(value, key)
    return options


def _sync(call: str, coro: Callable[[], Coroutine[Any, Any, _T]]) -> _T:
    """Run a coroutine for a sync API call; inside a running event loop, say to await the async twin."""
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return asyncio.run(coro())
    raise UsageError(f"deployer.{call}() cannot run inside a running event loop; await deployer.{call}_async()")


def load_recipe(path: str | os.PathLike[str], **kw: Any) -> Recipe:
    """A recipe file, validated against its profile.

    Raises:
        InputError: every problem of the recipe (and its profile), with its position.
        UsageError: ``path`` is not a path.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise UsageError(f"load_recipe takes a path (str or os.PathLike), got {_kind(path)}")
    return _load_recipe(path, **kw)


def _taught(recipe: Recipe, state_dir: str | None, url: DeviceURL, unit: int) -> Recipe:
    """``recipe`` with the limits its device taught an earlier apply, as apply will use them."""
    if state_dir is None:
        return recipe
    from .state import learned

    return learned.for_recipe(recipe, state_dir, url, unit)[0]


def describe_url(url: DeviceURL) -> str:
    """A device URL as text, without secrets (no key, certificate or CA paths): for reports and logs."""
    return describe(url)


def recipe_from(profile: str | Profile, parameters: Mapping[str, Any], *, name: str = "inline",
                base: Recipe | None = None) -> Recipe:
    """A recipe from values given in code (``{"F07": "10 s"}``), on its own or over ``base``'s values.

    ``profile``: a Profile, a built-in id or a profile file (ignored when ``base`` is given).

    Raises:
        InputError: a value that is not valid for its parameter (all of them at once).
        UsageError: an unknown built-in profile id; arguments of the wrong type.
    """
    if not isinstance(parameters, Mapping):
        raise UsageError(f"recipe_from takes the parameters as a mapping (name -> value), got {_kind(parameters)}")
    if not isinstance(profile, (str, Profile)):
        raise UsageError(f"recipe_from takes a profile id, a profile file or a Profile, got {_kind(profile)}")
    if base is not None:
        _need_recipe(base, "recipe_from(base=...)")
    for key in parameters:
        if not isinstance(key, str):
            raise UsageError(f"recipe_from takes parameter names as str keys, got {_kind(key)}")
    src = Source(f"<{name}>")
    entries = [Entry(k, v, src, ("parameters", k)) for k, v in parameters.items()]
    if base is None:
        prof = profile if isinstance(profile, Profile) else resolve_profile(profile)
        ref = prof.source or prof.id
        base = Recipe(name, None, prof, (), profile_ref=ref)
    return with_overrides(base, entries)


def device_url(url: str | DeviceURL, *, timeout: float | None = None, retries: int | None = None) -> DeviceURL:
    """Parse a device URL (``tcp://HOST:PORT``, ``rtu:///dev/ttyUSB0?baudrate=19200`` ...); a DeviceURL as is.

    ``timeout`` (seconds per attempt) and ``retries`` apply where the URL does not set its own
    (bounds: ``LIMITS.timeout``, ``LIMITS.retries``).

    Raises:
        BadURL: a malformed URL, an unknown scheme or option (a UsageError).
        UsageError: a ``timeout`` or ``retries`` out of its bounds.
    """
    _need_timing(timeout, retries)
    if isinstance(url, DeviceURL):
        return url
    if not isinstance(url, str):
        raise UsageError(f"device_url takes a URL such as tcp://10.0.0.11:502, got {_kind(url)}")
    return parse_url(url, timeout=timeout, retries=retries)  # BadURL is a UsageError


def _target(recipe: Recipe, device: str | DeviceURL | None, unit: int | None) -> tuple[DeviceURL, int]:
    _need_unit(unit)
    text = device if device is not None else (recipe.device.url if recipe.device else None)
    if text is None:
        raise UsageError("no device: pass a device URL or set device.url in the recipe")
    u = unit if unit is not None else (recipe.device.unit if recipe.device and recipe.device.unit is not None else 1)
    return device_url(text), u


# ---- one device --------------------------------------------------------------------------------


async def plan_async(recipe: Recipe, device: str | DeviceURL | None = None, unit: int | None = None, *,
                     write_all: bool = False, offline: bool = False, state_dir: str | None = ".deployer") -> Plan:
    """The requests apply would send: against what the device holds now, or ``offline`` the full write plan."""
    _need_recipe(recipe, "plan")
    _need_unit(unit)
    if offline:
        u = unit if unit is not None else 1
        return make_plan(recipe, Target(None, u, recipe.profile_ref or recipe.profile.id), None, write_all=write_all)
    url, u = _target(recipe, device, unit)
    recipe = _taught(recipe, state_dir, url, u)
    from .execute.read import read_current

    current = await read_current(recipe.profile, [d.name for d in recipe.desired], url, u)
    return make_plan(recipe, Target(describe(url), u, recipe.profile_ref or recipe.profile.id), current,
                     write_all=write_all)


def plan(recipe: Recipe, device: str | DeviceURL | None = None, unit: int | None = None, *,
         write_all: bool = False, offline: bool = False, state_dir: str | None = ".deployer") -> Plan:
    """The requests ``apply`` would send: against what the device holds now (read, nothing written), or
    ``offline`` the full write plan. ``device``/``unit`` default to the recipe's ``device``.

    The limits a device taught an earlier apply (``deployer learned list``, kept in ``state_dir``) are in
    force, as they are when ``apply`` runs; ``state_dir=None`` plans with the profile's limits alone.

    Raises:
        UsageError: no device (none given and none in the recipe), a bad URL, unit 0 (broadcast).
        TransportError: the device cannot be read (Unreachable also when its identity does not match).
    """
    _need_recipe(recipe, "plan")
    return _sync("plan", lambda: plan_async(recipe, device, unit, write_all=write_all, offline=offline,
                                            state_dir=state_dir))


async def apply_async(recipe: Recipe, device: str | DeviceURL | None = None, unit: int | None = None, *,
                      options: ApplyOptions | None = None, name: str | None = None,
                      soak: float | str | None = None, health_interval: float | str | None = None,
                      confirm_within: float | str | None = None,
                      on_confirm_wait: Callable[[str, float], None] | None = None,
                      report_path: str | None = None) -> Report:
    """Apply to one device; the report says per parameter what it holds now (never raises for a device fault).

    A safe change: ``soak`` ("30s", or seconds) watches the profile's health checks after the write and
    rolls the device back when one fails; ``confirm_within`` holds the profile's commit until ``confirm``
    is called (from another thread, task or process with the same state directory), else rolls back.
    ``on_confirm_wait(run, deadline)`` is told the run id to confirm once it waits. The run is journaled in
    ``options.state_dir`` (``deployer status`` sees it); ``report_path``: the report file, written before
    the first request and at the end. Raises RunInterrupted (with its ``report``) when cancelled mid-run.
    """
    _need_recipe(recipe, "apply")
    url, u = _target(recipe, device, unit)
    if report_path is not None:
        _need_path(report_path, "apply", "report_path")
    opts = safe_options(options, soak=soak, health_interval=health_interval, confirm_within=confirm_within)
    from .execute.job import Job
    from .run.runner import run_async

    return await run_async([Job(name or recipe.name, recipe, url, u)], label=recipe.path or recipe.name,
                           parallel=1, options=opts, report_path=report_path, on_confirm_wait=on_confirm_wait)


def plan_values(recipe: Recipe, current: Mapping[str, tuple[int, ...]] | None, device: DeviceURL | None = None,
                unit: int = 1, *, write_all: bool = False) -> Plan:
    """The plan of ``recipe`` against values already read (``current``: {name: registers}, as ``pull`` and
    ``read_fleet`` give them), or with ``current`` None the full write plan, offline. ``device`` and ``unit``:
    what the plan names as its target (``device`` None: none). Nothing is read or sent; the limits taught
    by devices are the caller's (``taught_recipe``)."""
    target = Target(describe(device) if device is not None else None, unit, recipe.profile_ref or recipe.profile.id)
    return make_plan(recipe, target, current, write_all=write_all)


def plan_cost(plan: Plan, profile: Profile, device: DeviceURL | None = None) -> dict[str, Any]:
    """What a plan's write requests and their answers cost on the device's line (its URL's serial settings,
    else Modbus's default: RTU at 19200 baud 8E1): ``registers`` written (coils included) and ``coils``,
    ``framing`` (``rtu`` or ``ascii``), ``line`` ("19200 baud 8E1"), ``characters`` (bytes on RTU, characters
    on ASCII), ``seconds`` (about, pauses included) and ``pauses`` (seconds of the pauses the device needs
    between requests and after connecting: the URL's options, else the profile's ``limits``)."""
    from .planning.wire import line_cost, wire_stats
    from .transport.urls import pacing

    if device is not None and device.scheme in ("rtu", "ascii"):
        ln = device.line
        framing, baud = device.scheme, ln.baudrate
        bits = 1 + ln.bytesize + (ln.parity != "N") + ln.stopbits
        line = f"{ln.baudrate} baud {ln.bytesize}{ln.parity}{ln.stopbits}"
    else:
        framing, baud, bits, line = "rtu", 19200, 11, "19200 baud"
    chars, seconds = line_cost(plan, framing=framing, baud=baud, char_bits=bits)
    lim = profile.limits
    after, between = pacing(device or DeviceURL("tcp"), lim.pause_after_connect, lim.pause_between_requests)
    # each write follows another request (the snapshot read at least)
    pauses = after + between * len(plan.writes) if plan.writes and (after or between) else 0.0
    return {"registers": int(wire_stats(plan)["registers"]),
            "coils": sum(w.count for w in plan.writes if w.function in (5, 15)), "framing": framing,
            "line": line, "characters": chars, "seconds": seconds + pauses, "pauses": pauses}


def plan_frames(plan: Plan, framing: str) -> list[tuple[bytes, bytes | None]]:
    """Each write request of a plan as the exact bytes on the wire, ``framing`` ``rtu``, ``ascii`` or ``tcp``
    (transaction ids 1, 2, ... on TCP): (the query, the device's normal answer; None for a broadcast).

    Raises:
        UsageError: an unknown framing.
    """
    from typing import cast

    from .planning.frames import Framing, request_frame, response_frame

    if framing not in ("rtu", "ascii", "tcp"):
        raise UsageError(f"plan_frames: framing is rtu, ascii or tcp, not {framing!r}")
    how, unit = cast(Framing, framing), plan.device.unit
    return [(request_frame(w, unit, how, transaction_id=i),
             None if unit == 0 else response_frame(w, unit, how, transaction_id=i))
            for i, w in enumerate(plan.writes, 1)]


def apply(recipe: Recipe, device: str | DeviceURL | None = None, unit: int | None = None, *,
          options: ApplyOptions | None = None, name: str | None = None, **safe: Any) -> Report:
    """Apply the recipe to one device: plan against what it holds, write, read back, verify, report.

    A device fault (unreachable, refused, not verified, locked by another run) is the device's
    status in the report (``report.exit_code`` says it as the command line would), not an exception.

    Raises:
        UsageError: no device, a bad URL, a broadcast without ``options.allow_broadcast``.
        StalePlan: ``options.expected`` (a saved plan) no longer matches the device.
        Declined: ``options.confirm`` answered no.
        RunInterrupted: the run was interrupted (``.report`` says what every device holds).

    ``safe``: ``soak``, ``health_interval``, ``confirm_within``, ``on_confirm_wait``, ``report_path`` (see
    ``apply_async``).
    """
    _need_recipe(recipe, "apply")
    return _sync("apply", lambda: apply_async(recipe, device, unit, options=options, name=name, **safe))


def safe_options(options: ApplyOptions | None, *, soak: float | str | None = None,
                 health_interval: float | str | None = None,
                 confirm_within: float | str | None = None) -> ApplyOptions:
    """``options`` with a soak and a confirmation window (durations as "30s" or seconds).

    A confirmation needs a run id to be named by: one is made when ``options`` has none.

    Raises:
        UsageError: a duration that is not one (e.g. "soon"), or out of its bounds (``LIMITS``).
    """
    from dataclasses import replace

    from .state.journal import new_run_id

    opts = _need_options(options, "safe_options")
    changes: dict[str, Any] = {}
    for key, value in (("soak", soak), ("health_interval", health_interval), ("confirm_within", confirm_within)):
        if value is not None:
            changes[key] = duration(value, key)
    opts = _need_options(replace(opts, **changes), "safe_options")
    if opts.confirm_within is not None and opts.run_id is None:
        opts = replace(opts, run_id=new_run_id())
    return opts


def duration(value: object, what: str) -> float:
    """Seconds in a duration as people write it ("250ms", "30s", "5m", "1h"; a bare number is seconds),
    checked against the bound of the argument ``what`` (a field of ``LIMITS``: "soak", "pause" ...).

    Raises:
        UsageError: not a duration, or out of its bound, naming ``what``.
    """
    from .load.durations import parse_duration

    if isinstance(value, bool) or not isinstance(value, str | int | float):
        raise UsageError(f"{what} takes a duration such as \"30s\" or a number of seconds, got {_kind(value)}")
    try:
        seconds = parse_duration(value)
    except ValueError as e:
        raise UsageError(f"{what}: {e}") from None
    bound: Bound = getattr(LIMITS, what)
    return bound.check(seconds, what)


def confirm(run: str | None = None, *, state_dir: str = ".deployer") -> str:
    """Confirm a run that waits (``confirm_within``): its held-back commit is sent. Returns the run id.

    Raises:
        UsageError: no run (or several, and ``run`` is None) waits in ``state_dir``, or the waiting
            process is gone, or its time ran out; ``run`` or ``state_dir`` of the wrong type.
    """
    if run is not None and not isinstance(run, str):
        raise UsageError(f"confirm takes the run id as a str, got {_kind(run)}")
    _need_path(state_dir, "confirm", "state_dir")
    from .window.confirm import confirm_run

    return confirm_run(os.fspath(state_dir), run).run


def confirm_outcome(run: str | None = None, *, state_dir: str = ".deployer",
                    on_confirmed: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Confirm a run that waits, as ``confirm`` does, and wait for what it did: its outcome record
    (``committed``: the devices its commit reached). ``on_confirmed(run)`` is called once the confirmation is
    given, before the wait (the run reads its parameters again first).

    Raises:
        UsageError: as ``confirm``.
        NotCommitted: the commit did not reach every device (each named, and why), or the run's process ended
            without saying.
    """
    if run is not None and not isinstance(run, str):
        raise UsageError(f"confirm_outcome takes the run id as a str, got {_kind(run)}")
    _need_path(state_dir, "confirm_outcome", "state_dir")
    from .window.confirm import confirm_run, outcome

    target = confirm_run(os.fspath(state_dir), run)
    if on_confirmed is not None:
        on_confirmed(target.run)
    return outcome(os.fspath(state_dir), target)


@dataclass(frozen=True)
class RunStatus:
    """What ``deployer status`` shows of a state folder (``run_status``), read only: the ``runs`` that need a
    look (never finished, interrupted while writing, or waiting for a confirmation; oldest first, each with
    who ran what and its devices), ``unreadable`` lines of the audit log (cut off by a crash), the runs
    ``awaiting`` a confirmation (run id -> when and whether its process still waits) and those that died
    ``soaking`` (run id -> its report file), the device ``locks`` held on this machine now (in ``lock_folder``,
    every run's whatever its state folder; ``held`` says them one line per holder), and the ``journal`` read."""

    journal: str
    runs: list[Unfinished]
    unreadable: int
    awaiting: dict[str, Awaiting]
    soaking: dict[str, str | None]
    lock_folder: str
    locks: list[dict[str, Any]]
    held: list[str]


def run_status(state_dir: str = ".deployer") -> RunStatus:
    """The runs of ``state_dir`` that need a look, and the devices held on this machine now (``RunStatus``).

    Raises:
        UsageError: ``state_dir`` is not a path.
    """
    _need_path(state_dir, "run_status", "state_dir")
    from .state import holder, journal, lock
    from .window.confirm import awaiting, soaking

    folder = os.fspath(state_dir)
    runs, torn = journal.unfinished(folder)
    locks_in = lock.lock_dir()
    locks = holder.held(locks_in)
    return RunStatus(journal.path_of(folder), runs, torn, {a.run: a for a in awaiting(folder)}, soaking(folder),
                     locks_in, locks, holder.summary(locks) if locks else [])


def resolve_run(run: str, *, state_dir: str = ".deployer") -> Unfinished:
    """Acknowledge a run ``run_status`` lists, after a look: recorded in the audit log (by whom, when); it is
    listed no more. Returns the run as it was listed.

    Raises:
        UsageError: no such run needs a look in ``state_dir``.
    """
    _need_path(state_dir, "resolve_run", "state_dir")
    from .load.messages import printable
    from .state import journal

    try:
        return journal.resolve(os.fspath(state_dir), run)
    except KeyError:
        raise UsageError(f"no run {printable(str(run))} needs a look in {journal.path_of(os.fspath(state_dir))} "
                         "(deployer status lists them)") from None


@dataclass(frozen=True)
class Drift:
    """One parameter whose device value is not the recipe's (``device`` None: it cannot be read)."""

    name: str
    desired: str
    desired_raw: tuple[int, ...]
    device: str | None
    device_raw: tuple[int, ...] | None

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "desired": self.desired, "device": self.device,
                "desired_raw": list(self.desired_raw),
                "device_raw": None if self.device_raw is None else list(self.device_raw),
                "status": "drift" if self.device_raw is not None else "not readable"}


def diff_values(recipe: Recipe, current: Mapping[str, tuple[int, ...]]) -> list[Drift]:
    """The recipe's parameters the device does not hold (or that cannot be read), in recipe order."""
    out = []
    for d in recipe.desired:
        cur = current.get(d.name)
        if cur is None or not d.parameter.same_value(cur, d.registers):  # a bit field compares its own bits
            out.append(Drift(d.name, d.text, d.registers,
                             None if cur is None else d.parameter.format_registers(cur), cur))
    return out


async def diff_async(recipe: Recipe, device: str | DeviceURL | None = None, unit: int | None = None) -> list[Drift]:
    """``diff`` for callers with their own event loop."""
    _need_recipe(recipe, "diff")
    url, u = _target(recipe, device, unit)
    from .execute.read import read_current

    return diff_values(recipe, await read_current(recipe.profile, [d.name for d in recipe.desired], url, u))


def diff(recipe: Recipe, device: str | DeviceURL | None = None, unit: int | None = None) -> list[Drift]:
    """The recipe's parameters the device does not hold now (read only); ``[]`` when it matches.

    Raises:
        UsageError: no device, a bad URL, unit 0.
        TransportError: the device cannot be read.
    """
    _need_recipe(recipe, "diff")
    return _sync("diff", lambda: diff_async(recipe, device, unit))


@dataclass(frozen=True)
class FromDefault:
    """One parameter whose device value is not its factory default (the profile's ``default``)."""

    name: str
    default: str
    default_raw: tuple[int, ...]
    device: str
    device_raw: tuple[int, ...]

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "default": self.default, "device": self.device,
                "default_raw": list(self.default_raw), "device_raw": list(self.device_raw)}


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


def pulled_recipe(profile: Profile, values: Mapping[str, tuple[int, ...]], *, name: str, url: str, unit: int,
                  comment: str = "", relative_to: str | None = None) -> str:
    """Recipe text that sets every given parameter to the values read (applies back as a no-op)."""
    from .recipe.model import DeviceSpec

    ref = profile.id
    if profile.source:
        ref = os.path.relpath(profile.source, os.path.dirname(os.path.abspath(relative_to))) if relative_to \
            else profile.source
    return recipe_text(ref, {profile.parameter(n): v for n, v in values.items()}, name=name,
                       device=DeviceSpec(url, unit), comment=comment)


def pull_names(profile: Profile) -> list[str]:
    """What pull reads: every parameter that can be read and written back (a momentary command is no setting)."""
    return [p.name for p in profile.parameters if p.readable and p.writable and not p.action]


async def pull_async(profile: str | Profile, device: str | DeviceURL, unit: int = 1, *,
                     names: Sequence[str] | None = None) -> dict[str, tuple[int, ...]]:
    """``pull`` for callers with their own event loop."""
    _need_unit(unit)
    if not isinstance(profile, (str, Profile)):
        raise UsageError(f"pull takes a profile id, a profile file or a Profile, got {_kind(profile)}")
    prof = profile if isinstance(profile, Profile) else resolve_profile(profile)
    if names is not None:
        unknown = [n for n in names if not isinstance(n, str) or prof.get(n) is None]
        if unknown:
            raise UsageError(f"pull: profile {prof.id} has no parameter {', '.join(map(repr, unknown))}")
    from .execute.read import read_current

    return await read_current(prof, pull_names(prof) if names is None else list(names), device_url(device), unit)


def pull(profile: str | Profile, device: str | DeviceURL, unit: int = 1, *,
         names: Sequence[str] | None = None) -> dict[str, tuple[int, ...]]:
    """Every readable, writable parameter of a device (or only ``names``): name -> registers
    (``pulled_recipe`` makes a recipe).

    Raises:
        UsageError: an unknown built-in profile, a bad URL, unit 0, a name the profile does not have.
        InputError: an invalid profile file.
        TransportError: the device cannot be read.
    """
    return _sync("pull", lambda: pull_async(profile, device, unit, names=names))


# ---- fleets ----------------------------------------------------------------------------------


def fleet_jobs(recipe: Recipe | None, inventory: str | Inventory, *, limit: str | None = None,
               timeout: float | None = None, retries: int | None = None, unit: int | None = None) -> list[Job]:
    """One checked job per selected device: ``recipe`` (None: each device's own from the inventory) with
    the device's profile and overrides.

    ``inventory``: a file or an Inventory (``inventory_from``); ``limit``: names, groups, globs, ``!x``,
    ``@REPORT.json`` (as ``--limit``). ``timeout``, ``retries`` and ``unit`` override every device's.

    Raises:
        InputError: an invalid inventory, or devices that cannot have their job (profile, recipe, overrides,
            URL), naming the devices, all at once.
        UsageError: nothing selected, or a ``limit`` word that matches nothing; arguments of the wrong type
            or out of their bounds (``LIMITS``).
    """
    if recipe is not None:
        _need_recipe(recipe, "fleet_jobs")
    _need_inventory(inventory, "fleet_jobs")
    _need_timing(timeout, retries)
    _need_unit(unit)
    inv = inventory if isinstance(inventory, Inventory) else load_inventory(inventory)
    jobs = _fleet_jobs(inv, recipe, limit, timeout=timeout, retries=retries, unit=unit)
    if not jobs:
        raise UsageError(f"no device selected from {inv.path}")
    return jobs


async def apply_fleet_async(recipe: Recipe | None, inventory: str | Inventory, *, limit: str | None = None,
                            parallel: int = 8, batch: str | None = None, max_failures: str | None = None,
                            options: ApplyOptions | None = None, report_path: str | None = None,
                            on_start: Callable[[Job], None] | None = None,
                            on_done: Callable[[DeviceResult], None] | None = None,
                            batch_by: str = "profile") -> Report:
    """Apply to the devices of an inventory (``limit`` selects): staged, with a failure budget, see ``run_fleet``.

    ``recipe`` None: each device gets the recipe the inventory gives it."""
    return await run_fleet_async(fleet_jobs(recipe, inventory, limit=limit),
                                 recipe_name=None if recipe is None else recipe.path or recipe.name,
                                 parallel=parallel, batch=batch, max_failures=max_failures, options=options,
                                 report_path=report_path, on_start=on_start, on_done=on_done, batch_by=batch_by)


async def run_fleet_async(jobs: Sequence[Job], *, recipe_name: str | None = None, parallel: int = 8,
                          batch: str | None = None, max_failures: str | None = None,
                          options: ApplyOptions | None = None, report_path: str | None = None,
                          on_start: Callable[[Job], None] | None = None,
                          on_done: Callable[[DeviceResult], None] | None = None,
                          via: str = "api", signals: bool = False, batch_by: str = "profile", **safe: Any) -> Report:
    """Apply jobs as one journaled fleet run (``run.runner.run_async``): ``batch`` ("1,10%,100%") stages it,
    ``max_failures`` ("2", "5%") caps it. Each batch takes its count or share of every profile of the line (one
    device of each profile first), or of every group with ``batch_by="group"`` (a device counts in the first
    group it lists); any device of the first batch that does not end ok ends the rollout.

    ``report_path``: written before the first device starts (every device ``skipped``, "not
    finished") and rewritten as devices finish, so after a crash ``limit="@REPORT"`` retries
    exactly what did not end ok, and ``rollback --from-report`` restores what it wrote. ``via``: who runs it
    (for the journal); ``signals``: SIGINT and SIGTERM interrupt it (own process, main thread). ``safe``:
    ``rollback_on_failure``, ``between_batches`` and ``on_confirm_wait`` of ``fleet.rollout.apply_many`` (the
    soak itself is in ``options``).
    """
    _need_parallel(parallel)
    batch_by = _need_batch_by(batch_by, "run_fleet")
    options = _need_options(options, "run_fleet")
    if report_path is not None:
        _need_path(report_path, "run_fleet", "report_path")
    from .run.runner import run_async

    return await run_async(jobs, label=recipe_name, parallel=parallel, batch=batch, max_failures=max_failures,
                           options=options, report_path=report_path, on_start=on_start, on_done=on_done, via=via,
                           signals=signals, batch_by=batch_by, **safe)


def apply_fleet(recipe: Recipe | None, inventory: str | Inventory, **kw: Any) -> Report:
    """Apply to the devices of an inventory; ``kw`` as for ``apply_fleet_async`` (``recipe`` None: each device's
    own from the inventory).

    Raises:
        InputError: an invalid inventory, or a device's profile or overrides (all devices checked first).
        UsageError: nothing selected, a bad ``limit``/``batch``/``max_failures``, a report file that cannot
            be written, too few open files for ``parallel``.
        StalePlan: a saved plan (``options.expected``) no longer matches its device.
    """
    if recipe is not None:
        _need_recipe(recipe, "apply_fleet")
    _need_inventory(inventory, "apply_fleet")
    return _sync("apply_fleet", lambda: apply_fleet_async(recipe, inventory, **kw))


def run_fleet(jobs: Sequence[Job], **kw: Any) -> Report:
    """Apply jobs (from ``fleet``, or made by hand) as one fleet run; ``kw`` as for ``run_fleet_async``.

    Raises:
        UsageError: a bad ``batch``/``max_failures``, a report file that cannot be written, too few open files.
        StalePlan: a saved plan (``options.expected``) no longer matches its device.
    """
    return _sync("run_fleet", lambda: run_fleet_async(jobs, **kw))


async def read_fleet_async(jobs: Sequence[ReadJob], *, parallel: int = 8,
                           on_done: Callable[[str, str | None], None] | None = None,
                           ) -> dict[str, dict[str, tuple[int, ...]] | TransportError | UsageError]:
    """Current values of many devices: name -> registers by parameter, or the error that stopped the read."""
    from .fleet.rollout import read_many
    from .run.runner import ensure_files

    _need_parallel(parallel)
    ensure_files(parallel, len(jobs))
    return await read_many(jobs, parallel=parallel, on_done=on_done)


def read_fleet(jobs: Sequence[ReadJob], *, parallel: int = 8) -> dict[str, dict[str, tuple[int, ...]] | TransportError
                                                                    | UsageError]:
    """Current values of many devices, ``parallel`` at a time (one per bus): name -> registers by
    parameter, or the error that stopped that device's read (never raised for one device).

    Raises:
        UsageError: too few open files for ``parallel``.
    """
    return _sync("read_fleet", lambda: read_fleet_async(jobs, parallel=parallel))


def read_jobs(jobs: Sequence[Job]) -> list[ReadJob]:
    """Plan and diff read what each device's recipe names."""
    from .fleet.rollout import ReadJob

    return [ReadJob(j.name, j.recipe.profile, tuple(d.name for d in j.recipe.desired), j.url, j.unit) for j in jobs]


def pull_jobs(inventory: str | Inventory, *, limit: str | None = None, profile: str | Profile | None = None,
              timeout: float | None = None, retries: int | None = None, unit: int | None = None) -> list[ReadJob]:
    """What ``pull --inventory`` reads: one ``ReadJob`` per selected device, of every parameter ``pull_names``
    gives for the device's profile: its own (or its groups'), else its recipe's, as plan, apply and diff use it,
    else ``profile``. ``timeout``, ``retries`` and ``unit`` stand for the inventory's where given. Read them
    with ``read_fleet``; nothing is sent here.

    Raises:
        InputError: every device without a profile, with an unknown one or a bad URL (its position in the
            inventory), and every problem of the files it names.
    """
    from .errors import Diagnostic
    from .fleet.inventory import RecipeCache
    from .fleet.rollout import ReadJob

    inv = inventory if isinstance(inventory, Inventory) else load_inventory(inventory)
    cache = RecipeCache(None, inv.path)  # profile paths are relative to the inventory, as for plan and apply
    jobs: list[ReadJob] = []
    errors: list[Diagnostic] = []
    for dev in inv.select(limit):
        try:
            if dev.profile is not None:
                prof = cache.profile(dev.profile)
            elif dev.recipe is not None:
                prof = cache.base(dev.recipe, None).profile
            elif profile is not None:
                prof = profile if isinstance(profile, Profile) else resolve_profile(profile)
            else:
                raise UsageError("no profile: set profile (or a recipe) in the inventory, or pass --profile")
            url = device_url(dev.url, timeout=timeout or dev.timeout,
                             retries=retries if retries is not None else dev.retries)
        except UsageError as e:
            errors.append(Diagnostic(inv.path, *dev.where, f"{dev.name}: {e}"))
            continue
        except InputError as e:
            errors.extend(e.diagnostics)
            continue
        jobs.append(ReadJob(dev.name, prof, tuple(pull_names(prof)), url, unit if unit is not None else dev.unit))
    if errors:
        raise InputError(errors)
    return jobs


def out_of_range(profile: Profile, values: Mapping[str, Sequence[int]]) -> list[str]:
    """The names among ``values`` whose registers lie outside the profile's range: ``pulled_recipe`` keeps
    those as comments, since a recipe could not set them."""
    from .recipe.text import value_text

    return [n for n, regs in values.items() if value_text(profile.parameter(n), regs) is None]


async def plan_fleet_async(jobs: Sequence[Job], *, parallel: int = 8, write_all: bool = False,
                           on_done: Callable[[str, str | None], None] | None = None,
                           state_dir: str | None = ".deployer") -> dict[str, Plan | TransportError | UsageError]:
    """``plan_fleet`` for callers with their own event loop; ``on_done(name, error or None)`` per device read."""
    from dataclasses import replace

    _need_parallel(parallel)
    jobs = [replace(j, recipe=_taught(j.recipe, state_dir, j.url, j.unit)) for j in jobs]
    values = await read_fleet_async(read_jobs(jobs), parallel=parallel, on_done=on_done)
    out: dict[str, Plan | TransportError | UsageError] = {}
    for j in jobs:
        cur = values[j.name]
        out[j.name] = cur if isinstance(cur, Exception) else make_plan(
            j.recipe, Target(describe(j.url), j.unit, j.recipe.profile_ref or j.recipe.profile.id), cur,
            write_all=write_all)
    return out


def plan_fleet(jobs: Sequence[Job], *, parallel: int = 8, write_all: bool = False,
               state_dir: str | None = ".deployer") -> dict[str, Plan | TransportError | UsageError]:
    """Check mode for many devices: read each, plan against what it holds, write nothing; with the limits
    each device taught an earlier apply in force (kept in ``state_dir``; None: the profiles' alone).

    Returns name -> its Plan (``plan.writes`` empty: nothing to change), or the error that stopped
    its read (never raised for one device), in the order of ``jobs``.

    Raises:
        UsageError: too few open files for ``parallel``.
    """
    return _sync("plan_fleet", lambda: plan_fleet_async(jobs, parallel=parallel, write_all=write_all,
                                                        state_dir=state_dir))


def inventory_from(devices: Iterable[Mapping[str, Any]], *, name: str = "<devices>") -> Inventory:
    """An inventory from a list of devices given in code (Ansible host vars, a database), checked as a file is.

    Each device: ``name`` and ``url`` (required), ``unit`` (1), ``profile`` (a built-in id or a path),
    ``groups``, ``timeout``, ``retries`` and ``parameters`` (values over the recipe's), as in an
    inventory file. ``name`` is what messages call the list.

    Raises:
        InputError: a device that is not valid (all of them at once, positions in the list).
    """
    return _inventory_from(devices, name)



# ---- a run as a client describes it (the command line, Ansible, the site agent) -------------------------


def prepare_run(request: RunRequest) -> PreparedRun:
    """Check an apply or rollback request and build its jobs, nothing sent: the command line's ``apply`` and
    ``rollback`` are this, a confirmation, and ``run_prepared``.

    Raises:
        UsageError: a bad combination of options (``--limit`` without an inventory ...), a number out of its
            bounds (``LIMITS``), no device, a snapshot given as a recipe, a soak without health checks.
        InputError: an invalid recipe, plan, inventory or snapshot.
    """
    from .run.request import prepare

    if not isinstance(request, RunRequest):
        raise UsageError(f"prepare_run takes a RunRequest, got {_kind(request)}")
    return prepare(request)


async def run_prepared_async(prepared: PreparedRun, **kw: Any) -> Report:
    """``run_prepared`` for callers with their own event loop."""
    from .run.request import execute

    if not isinstance(prepared, PreparedRun):
        raise UsageError(f"run_prepared takes a PreparedRun (deployer.prepare_run(request)), got {_kind(prepared)}")
    return await execute(prepared, **kw)


def run_prepared(prepared: PreparedRun, **kw: Any) -> Report:
    """Run a prepared request as one journaled run and return its report.

    ``kw``: ``confirm(plan, device)`` (an async question before each device's write), ``command_line`` and
    ``argv`` (what started it), ``via``, ``signals`` (SIGINT/SIGTERM interrupt it), ``on_start``, ``on_done``,
    and the rollout's ``between_batches``, ``on_confirm_wait``, ``on_soak``, ``on_changed``.

    Raises:
        UsageError: options the run itself refuses (too few open files, a report file that cannot be written).
        StalePlan: a saved plan no longer matches its device. Declined: ``confirm`` answered no.
        RunInterrupted: the run was interrupted (``.report`` says what every device holds).
    """
    return _sync("run_prepared", lambda: run_prepared_async(prepared, **kw))


def writing_caches() -> contextlib.AbstractContextManager[None]:
    """A block within which deployer keeps its disk caches (pint's parsed units in ``~/.cache``) up to date,
    as the command line does for each command; outside one, deployer only reads them and leaves no files."""
    from .state.caches import writing

    return writing()


def read_report(path: str | os.PathLike[str], profiles: Sequence[str | Profile] = ()) -> Report:
    """An earlier run's report file (``--report``, a fleet's live report, one a crash left unfinished) as a
    Report. A report is data: no file it names is opened. Values read in engineering units as the report
    describes its profiles, or with ``profiles`` given here (ids, files or Profiles), else as register words.

    Raises:
        InputError: not a deployer report, or not a valid one (with its position).
        UsageError: the file cannot be read; an unknown profile.
    """
    from .report import read_report as _read_report
    from .report import report_from_json

    _need_path(path, "read_report", "the report file")
    try:
        doc = _read_report(os.fspath(path))
    except OSError as e:
        raise UsageError(f"cannot read {os.fspath(path)}: {e.strerror or e}") from None
    return report_from_json(doc, [p if isinstance(p, Profile) else load_profile(p) for p in profiles])


def probe(profile: str | Profile, device: str | DeviceURL, unit: int = 1, *,
          expect: Mapping[str, str] | None = None) -> ProbeResult:
    """Check a profile against a live device, read-only (``deployer probe``): its identity, every readable
    parameter, and for ``expect`` (name -> a value known to be held, in the parameter's unit) the byte/word
    layout or scale that gives it. Returns a result with ``identity``, ``values``, ``findings`` and
    ``changes`` (suggested profile changes; empty when the profile fits).

    Raises:
        UsageError: a bad URL, unit or profile, an ``expect`` name the profile does not have.
        TransportError: the device cannot be read.
    """
    from .execute.probe import probe as _probe

    _need_unit(unit)
    prof = profile if isinstance(profile, Profile) else load_profile(profile)
    wanted = dict(expect or {})
    for name in wanted:
        if prof.get(name) is None:
            raise UsageError(f"probe: profile {prof.id} has no parameter {name!r}")
    url = device_url(device)
    return _sync("probe", lambda: _probe(prof, url, unit, wanted))


def scan(device: str | DeviceURL, units: Iterable[int], *, register: int = 0) -> ScanResult:
    """Ask each unit id of ``units`` on a bus (the URL's timeout per unit, no retries), read-only
    (``deployer scan``): a result with ``units`` (each ``unit``, ``answer``, ``identity``), ``asked``,
    ``seconds`` and ``url``; ``.inventory_text(url, when)`` is an inventory fragment of the units found.

    Raises:
        UsageError: a bad URL. TransportError: the bus cannot be opened.
    """
    from .execute.scan import scan as _scan

    url = device_url(device)
    ids = list(units)
    return _sync("scan", lambda: _scan(url, ids, register=register))


# ---- what devices taught (STATE/learned.json) ------------------------------------------------------


def serial_ports() -> list[SerialPort]:
    """This system's serial ports as pyserial finds them, sorted by name (COM2 before COM10): each with its
    ``device`` (COM3, /dev/ttyUSB0), the ``url`` that names it (``rtu://COM3``), the adapter's ``description``
    and ``hwid`` (USB VID:PID and serial number), and ``to_json()``. Nothing is opened."""
    from .transport.ports import serial_ports as _serial_ports

    return _serial_ports()


def learned_limits(state_dir: str = ".deployer") -> tuple[str, list[LearnedEntry]]:
    """What devices taught by their refusals (``deployer learned list``): the file's path, and its entries
    (each ``profile``, ``device``, ``limits``, ``seen``, ``when``, ``describe_limits()``, ``to_json()``).

    Raises:
        InputError: a learned file deployer did not write (with its position and how to clear it).
    """
    from .state import learned

    _need_path(state_dir, "learned_limits", "state_dir")
    return learned.path_of(os.fspath(state_dir)), learned.load(os.fspath(state_dir))


def forget_learned(state_dir: str = ".deployer", *, profile: str | None = None, device: str | DeviceURL | None = None,
                   unit: int = 1) -> list[LearnedEntry]:
    """Forget what devices taught (``deployer learned forget``): of ``profile`` (a built-in id or a file), of
    ``device`` (a URL, with ``unit``), or everything when neither is given. Returns the entries forgotten.

    Raises:
        UsageError: a bad URL or unit.
    """
    from .state import learned

    _need_path(state_dir, "forget_learned", "state_dir")
    _need_unit(unit)
    ref = None
    if profile is not None:
        ref = os.path.abspath(profile) if is_profile_path(profile) else profile  # as profile_ref names it
    key = None if device is None else learned.device_id(device_url(device), unit)
    return learned.forget(os.fspath(state_dir), profile=ref, device=key)


def taught_recipe(recipe: Recipe, device: str | DeviceURL, unit: int = 1, *, state_dir: str = ".deployer"
                  ) -> tuple[Recipe, str | None]:
    """``recipe`` with the limits ``device`` taught an earlier apply in force, as ``plan`` and ``apply`` use
    them, and the note that says so (None: nothing taught, the recipe unchanged).

    Raises:
        UsageError: a bad URL or unit. InputError: a learned file deployer did not write.
    """
    from .state import learned

    _need_recipe(recipe, "taught_recipe")
    _need_unit(unit)
    out, entry = learned.for_recipe(recipe, os.fspath(state_dir), device_url(device), unit)
    return out, None if entry is None else learned.note(entry)


# ---- the files deployer writes ---------------------------------------------------------------------


def _file_kind(data: object) -> str | None:
    if not isinstance(data, dict):
        return None
    if data.get("schema") == "deployer.plan/1":
        return "plan"
    if "recipe" in data:
        return "recipe"
    if "devices" in data:
        return "inventory"
    if "users" in data:
        return "users"  # the agent's users file (deployer agent --users)
    params = data.get("parameters")
    declares = isinstance(params, dict) and any(isinstance(v, dict) and "register" in v for v in params.values())
    if "profile" in data and (declares or data.keys() & {"tables", "addressing", "limits", "identity", "commit"}):
        return "profile"
    if "profile" in data or "extends" in data:
        return "recipe"  # a recipe without its 'recipe' key: let the schema say so
    return None


def _count(count: int, noun: str) -> str:
    return f"{count} {noun}{'' if count == 1 else 's'}"


def validate_file(path: str | os.PathLike[str]) -> str:
    """Check one file of any kind (a profile, recipe, inventory or saved plan, told by its keys) as
    ``deployer validate`` does, nothing sent; returns a one-line summary ("recipe line3: 4 parameters for
    profile example-inverter"). An inventory is checked as ``plan`` and ``apply`` would check it: each
    device's profile, URL, and its recipe with its overrides.

    Raises:
        InputError: the file is not valid, or not a deployer file (with positions).
        UsageError: ``path`` is not a path.
    """
    from .load import yamlsrc
    from .planning.planfile import plan_from_json
    from .profile import load_profile_file

    _need_path(path, "validate_file", "the file")
    where = os.fspath(path)
    data, src = yamlsrc.load(where, hand_over=True)  # the loader below takes it over: parsed once
    try:
        kind = _file_kind(data)
        if kind == "profile":
            prof = load_profile_file(where)
            return f"profile {prof.id}: {_count(len(prof.parameters), 'parameter')}"
        if kind == "recipe":
            rec = _load_recipe(where)
            return f"recipe {rec.name}: {_count(len(rec.desired), 'parameter')} for profile {rec.profile.id}"
        if kind == "inventory":
            inv = load_inventory(where)
            # what plan and apply would check before sending anything: each device's profile, URL, and its
            # recipe (from the inventory) with its overrides; devices without one get theirs on the command line
            jobs = _fleet_jobs(inv, None, None, require_recipe=False)
            recipes = {j.recipe.path for j in jobs}
            return (f"inventory: {_count(len(inv.devices), 'device')}"
                    + (f", {_count(len(recipes), 'recipe')}" if recipes else ""))
        if kind == "users":
            from .agent.users import parse as parse_users

            people = parse_users(data, src)
            return f"users: {_count(len(people), 'user')}, {sum(not u.disabled for u in people.values())} enabled"
        if kind == "plan":
            saved = plan_from_json(data, where, src=src)
            return f"plan: {_count(len(saved.writes), 'write request')} for profile {saved.device.profile}"
        what = ("cannot tell what this file is" if isinstance(data, dict) else
                f"expected a mapping, got {'a list' if isinstance(data, list) else 'a single value'}")
        raise InputError([src.error((), f"{what}: a profile has 'profile' and 'parameters', a recipe has "
                                         "'recipe', an inventory has 'devices', the agent's users file has 'users'")])
    finally:
        yamlsrc.forget(where)


def snapshot_text(profile: str | Profile, values: Mapping[str, tuple[int, ...]], *, name: str, url: str,
                  unit: int = 1, applied: str, path: str, taken: float | None = None) -> str:
    """A snapshot's text as ``apply`` writes it before its first write (a recipe that ``rollback`` restores
    bit for bit): what device ``name`` at ``url`` unit ``unit`` held (``values``: {parameter: registers}) at
    ``taken`` (seconds since the epoch; None: now) before ``applied`` (a recipe's path or name), saved as
    ``path`` (its comment says how to restore it).

    Raises:
        UsageError: an unknown profile or parameter.
    """
    import time

    from .state.snapshot import snapshot_text as _snapshot_text

    prof = profile if isinstance(profile, Profile) else load_profile(profile)
    unknown = [n for n in values if prof.get(n) is None]
    if unknown:
        raise UsageError(f"snapshot_text: profile {prof.id} has no parameter {', '.join(map(repr, unknown))}")
    when = time.gmtime(time.time() if taken is None else taken)
    return _snapshot_text(prof, values, name=name, url=url, unit=unit, taken=when, applied=applied, label=applied,
                          path=path)


def url_option(name: str) -> tuple[list[str], str | None, str | None]:
    """A device URL option (``baudrate``, ``timeout``): the schemes that take it (none: no such option), its
    default and what it allows, as ``deployer explain`` shows them (docs/urls.md says what each means)."""
    from .transport.urls import option_facts

    return option_facts(name)


def builtin_profiles() -> list[Profile]:
    """Every built-in profile (``deployer profiles list``), by id."""
    from .profile import builtin_profile, builtin_profile_ids

    return [builtin_profile(pid) for pid in builtin_profile_ids()]


def profile_csv(profile: str | Profile) -> tuple[str, list[str]]:
    """A profile as a CSV register list (``profiles export csv``; ``profiles import csv`` reads it back: wire
    addresses, tables as rows), and what a register list cannot say about it (each lost on a round trip).

    Raises:
        UsageError: an unknown profile.
        InputError: a profile file that is not valid.
    """
    from .profile.importers.spreadsheet import not_exported, profile_to_csv

    prof = profile if isinstance(profile, Profile) else load_profile(profile)
    return profile_to_csv(prof), not_exported(prof)


def profile_skeleton(profile_id: str, path: str = "FILE") -> str:
    """A commented profile skeleton for ``profile_id`` (``profiles new``), to fill in from the device's manual;
    ``path``: where it will be, for the command its comments suggest. Checking the id is the caller's (the
    profile schema's ``profile`` pattern)."""
    from .profile.skeleton import profile_skeleton as _skeleton

    return _skeleton(profile_id, path)


def import_csv(path: str, *, profile_id: str, columns: Mapping[str, str] | None = None, addressing: str = "address",
               delimiter: str | None = None, byte_order: str | None = None, decimal: str | None = None
               ) -> tuple[Draft, list[str]]:
    """A vendor's CSV register list (``profiles import csv``) as a draft profile, and warnings; make the profile
    with ``imported_profile``. ``columns``: our column -> its header; ``addressing``: ``address``,
    ``register-number`` or ``modicon``; ``decimal``: ``comma`` or ``point`` (None: told cell by cell).

    Raises:
        InputError: every bad cell at once, at its position.
        UsageError: the file cannot be read.
    """
    from .profile.importers.spreadsheet import read_csv

    return read_csv(path, profile_id=profile_id, columns=columns, addressing=addressing, delimiter=delimiter,
                    byte_order=byte_order, decimal=decimal)


def import_xlsx(path: str, *, profile_id: str, sheet: str | None = None, columns: Mapping[str, str] | None = None,
                addressing: str = "address", byte_order: str | None = None, decimal: str | None = None
                ) -> tuple[Draft, list[str]]:
    """A register list in an Excel workbook (``profiles import xlsx``; needs openpyxl), as ``import_csv`` reads
    a CSV file; ``sheet``: the worksheet (None: the first).

    Raises:
        InputError: every bad cell at once, at FILE[SHEET]:ROW:COLUMN.
        UsageError: the file cannot be read, or openpyxl is not installed.
    """
    from .profile.importers.spreadsheet import read_xlsx

    return read_xlsx(path, profile_id=profile_id, sheet=sheet, columns=columns, addressing=addressing,
                     byte_order=byte_order, decimal=decimal)


def import_wb_template(path: str, *, profile_id: str | None = None, channels: bool = True
                       ) -> tuple[Draft, list[str]]:
    """A wb-mqtt-serial device template (``profiles import wb-template``) as a draft profile, and warnings (the
    last one counting the entries left out, when some were): its parameters become settings, its channels
    read-only values (``channels`` False: left out). ``profile_id`` None: the template's device_type.

    Raises:
        InputError: not such a template, or invalid (at its position).
    """
    from .profile.importers.wbtemplate import read_wb_template

    imported = read_wb_template(path, profile_id=profile_id, channels=channels)
    warnings = imported.warnings
    if imported.left_out:
        n = imported.left_out
        warnings = [*warnings, f"{path}: {n} {'entry' if n == 1 else 'entries'} of the template left out "
                               "(see the warnings above)"]
    return imported.draft, warnings


def imported_profile(draft: Draft, path: str, comment: str = "") -> tuple[str, Profile]:
    """The profile an importer's draft makes: its text (``comment`` on top) and the Profile it loads as, checked
    to read back as imported; ``path``: where it will be written (the positions of its problems).

    Raises:
        InputError: the draft's problems, pointing at the source's rows.
    """
    from .profile.emit import check

    return check(draft, path, comment)


def profile_table(profile: str | Profile) -> tuple[str, list[list[str]]]:
    """A profile as ``profiles show`` lists it: the name of its byte order (ABCD, CDAB ...) and one row of text
    per parameter: name, address (as plans write it), type ('uint32 CDAB', 'bool bit 3', 'uint16 bits 3..5',
    'string[8] ascii'), unit, resolution, range (or its labels), access, default and description.

    Raises:
        UsageError: an unknown profile.
        InputError: a profile file that is not valid.
    """
    from .profile.codec import format_decimal, layout_name, mask_shift

    prof = profile if isinstance(profile, Profile) else load_profile(profile)

    def type_text(p: Any) -> str:  # the layout only when not the default
        if p.is_string:
            return f"string[{p.count}] {p.encoding}" + (" BA" if p.byte_swap else "")
        if p.mask:
            shift, width = mask_shift(p.mask)
            return f"{p.type} bit {shift}" if width == 1 else f"{p.type} bits {shift}..{shift + width - 1}"
        return str(p.type) if p.layout in ("AB", "ABCD", "ABCDEFGH") else f"{p.type} {p.layout}"

    rows: list[list[str]] = []
    for p in prof.parameters:
        rng = "" if p.min is None and p.max is None else (
            f"{'' if p.min is None else format_decimal(p.min)}..{'' if p.max is None else format_decimal(p.max)}")
        if p.values:
            rng = ", ".join(f"{label}={raw}" for label, raw in p.values)
        default = "" if p.default is None else p.default if isinstance(p.default, str) else (
            str(bool(p.default)).lower() if p.type == "bool" else format_decimal(p.default))
        rows.append([p.name, address_text(p.register_type, p.address), type_text(p), p.unit or "",
                     "" if p.is_string or p.type == "bool" else format_decimal(p.scale), rng, p.access, default,
                     p.description])
    return layout_name(prof.word_order, prof.byte_swap), rows


def register_address(text: str) -> int:
    """A register address as profiles write it: 4354, 0x1102 or 1102h (a protocol address); ValueError if it is
    not one."""
    from .profile import parse_register

    return parse_register(text)


def import_sunspec(model: str, *, at: int = 40002, scale_factors: Mapping[str, int] | None = None,
                   counts: Mapping[str, int] | None = None, profile_id: str | None = None,
                   point_values: Mapping[str, int] | None = None, length: int | None = None
                   ) -> tuple[Draft, list[str]]:
    """A SunSpec model (its number, name or a model JSON file; pysunspec2's definitions) as a draft profile with
    its ID register at protocol address ``at``, and warnings (``profiles import sunspec``). ``scale_factors``
    and ``counts``: what the device reports (by point and group name); ``point_values`` and ``length``: its
    count points and L as ``sunspec_reported`` and ``sunspec_models`` read them.

    Raises:
        UsageError: an unknown model, or pysunspec2 is not installed.
        InputError: a model file that is not valid.
    """
    from .profile.importers.sunspec import read_model

    return read_model(model, at=at, scale_factors=scale_factors, counts=counts, profile_id=profile_id,
                      point_values=point_values, length=length)


def sunspec_models(device: str | DeviceURL, unit: int = 1, *, at: int = 40002, model: str | None = None,
                   search: bool = False) -> list[SunSpecModel]:
    """Read a SunSpec device's models, read-only: ``model`` at ``at`` (its ID checked), or with ``model`` None
    the whole chain from the 'SunS' marker two registers before ``at`` to the end marker (``search``: also
    where devices put it, 0 and 50000). Each with its ID, address, length L and registers.

    Raises:
        TransportError: the device cannot be read, or has no such registers (the message says where to look).
        UsageError: a bad URL, or what was read is not SunSpec.
    """
    from .errors import ExceptionResponse
    from .profile.importers import sunspec
    from .transport.clients import open_transport

    _need_unit(unit)
    url = device_url(device)

    async def run() -> list[SunSpecModel]:
        transport = open_transport(url)
        await transport.connect()

        async def read(address: int, count: int) -> list[int]:
            out: list[int] = []
            for a in range(address, address + count, 125):
                n = min(125, address + count - a)
                try:
                    out += await transport.read_holding_registers(a, n, unit)
                except ExceptionResponse as e:
                    said = f"{describe(url)} unit {unit}: reading {n} registers at {a} answered {e}"
                    if e.code == 2:
                        raise sunspec.NotThere(f"{said}: check --at (SunSpec devices put 'SunS' at 40000, 0 or "
                                               "50000, the first model's ID 2 registers after it)") from None
                    raise TransportError(said) from None
            return out

        try:
            if model is None:
                return await sunspec.device_chain(read, at, search=search)
            return [await sunspec.device_model(read, model, at)]
        finally:
            await transport.close()

    try:
        return asyncio.run(run())
    except sunspec.NotThere as e:  # no such registers: the device is there, the model is not where asked
        raise TransportError(str(e)) from None


def sunspec_reported(model: str, found: SunSpecModel) -> tuple[dict[str, int], dict[str, int], list[str]]:
    """The scale factors and count points a device reports in its model ``found`` (``sunspec_models``), by point
    name, and warnings (a scale factor not implemented or out of range: the points it scales import raw)."""
    from .profile.importers.sunspec import reported

    return reported(model, found)


def import_sunspec_chain(models: list[SunSpecModel], *, scale_factors: Mapping[str, int] | None = None,
                         counts: Mapping[str, int] | None = None, profile_id: str | None = None,
                         source: str = "the device") -> tuple[Draft, list[str]]:
    """One draft profile of a device's whole model chain (``sunspec_models`` without a model): each model's
    points named MODEL.POINT (common.Mn, inverter.W), its scale factors and counts as the device reports them
    (``scale_factors`` and ``counts`` given here win), the markers and model IDs as its identity.

    Raises:
        UsageError: a model pysunspec2 does not know, or pysunspec2 is not installed.
    """
    from .profile.importers.sunspec import chain_draft

    return chain_draft(models, scale_factors=scale_factors, counts=counts, profile_id=profile_id, source=source)


def check_folder(folder: str | os.PathLike[str], *, what: str) -> None:
    """Create ``folder`` if need be and make sure a file can be written there (``what``: what goes there, for
    the message), before any device is read.

    Raises:
        UsageError: it cannot be created or written, and why.
    """
    from .run.runner import check_writable

    check_writable(os.fspath(folder), what)


def check_output(path: str | os.PathLike[str], *, replace: bool = True, what: str = "") -> None:
    """Whether deployer may write an output file at ``path``, said before any work: only new paths and
    regular files (a link, FIFO, device node, socket or folder is refused, never opened); an existing file
    only with ``replace``. ``what`` names the file in the message ("the report").

    Raises:
        UsageError: the path is refused (``OutputRefused``).
    """
    from .state.durable import check_output as _check

    _check(os.fspath(path), replace=replace, what=what)


def write_output(path: str | os.PathLike[str], text: str | bytes, *, replace: bool = True, what: str = "") -> None:
    """Write an output file (a report, plan, page, recipe or profile) as deployer writes its own: whole or
    not at all, and durable (``check_output``'s rule, a temporary file, fsync, rename, the folder fsync'ed).

    Raises:
        UsageError: the path is refused, or the disk refuses (full, read-only).
    """
    from .state.durable import write_atomic

    write_atomic(os.fspath(path), text, replace=replace, what=what)
