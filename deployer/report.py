"""Results of an apply, per device and per parameter, as the report JSON (docs/reference/report.md)."""

from __future__ import annotations

import copy
import functools
import json
import operator
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

from .errors import EXIT_FAILED, EXIT_INVALID, EXIT_OK, EXIT_UNREACHABLE, Diagnostic, InputError
from .load.messages import clipped_repr
from .state.durable import write_atomic

if TYPE_CHECKING:
    from .profile import Parameter, Profile

REPORT_SCHEMA = "deployer.report/3"
# the first line of a fleet's report file while the run goes on (``fleet.livereport``): then one device per line
STREAM_SCHEMA = "deployer.report-stream/3"
# rolled-back: written and verified, then restored from the snapshot (a failed health check, no confirmation)
ParamStatus = Literal["ok", "unchanged", "failed", "mismatch", "unverified", "skipped", "rolled-back"]
# sent: a broadcast that went out; skipped: a fleet never started it (nothing sent); rolled-back: restored after
# the write; interrupted: the run stopped (Ctrl-C, SIGTERM, a crash) while the device was in flight: with a
# snapshot, writes may have gone out
DeviceStatus = Literal["ok", "sent", "partial", "failed", "unreachable", "skipped", "rolled-back", "interrupted"]
DEVICE_STATUSES: tuple[DeviceStatus, ...] = (
    "ok",
    "sent",
    "partial",
    "failed",
    "unreachable",
    "skipped",
    "rolled-back",
    "interrupted",
)
# the profile's commit steps: sent, held back (a soak or a confirmation waits), never sent, failed
CommitState = Literal["sent", "held", "not sent", "failed"]


@dataclass
class RequestRecord:
    function: int
    address: int
    count: int
    result: str = "ok"  # ok | exception | no response | connection lost | broadcast | interrupted
    exception_code: int | None = None
    attempts: int = 1
    step: int | None = None  # the plan step (1-based) it executes, or that the deviation stands in for
    deviation: str | None = None  # what only the device decided: "split", "function-06", "recovery-read" ...
    window: bool = False  # sent at a safe change's end (its commit's own plan, or the rollback), after the apply's

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "function": self.function,
            "address": self.address,
            "count": self.count,
            "result": self.result,
            "exception_code": self.exception_code,
            "attempts": self.attempts,
        }
        if self.step is not None:
            out["step"] = self.step
        if self.deviation is not None:
            out["deviation"] = self.deviation
        if self.window:
            out["window"] = True
        return out


def show_registers(p: Parameter, regs: Sequence[int] | None) -> str | None:
    """Engineering text for registers ('10 s', 'coast'), or the raw words where the codec cannot show them."""
    return None if regs is None else p.show_registers(tuple(regs))


@dataclass(slots=True)  # slots: a fleet makes 100 per device
class ParameterResult:
    name: str
    address: int
    count: int
    desired: str
    desired_raw: tuple[int, ...]
    before_raw: tuple[int, ...] | None = None
    after_raw: tuple[int, ...] | None = None
    status: ParamStatus = "skipped"
    error: str | None = None
    register_type: str = "holding"
    # the profile's parameter, for engineering texts in the human table (not in the JSON contract); the
    # texts are made only when shown: a fleet's report is mostly JSON, and formatting every value cost more
    parameter: Parameter | None = field(default=None, repr=False, compare=False)

    @property
    def before(self) -> str | None:
        return None if self.parameter is None else show_registers(self.parameter, self.before_raw)

    @property
    def after(self) -> str | None:
        return None if self.parameter is None else show_registers(self.parameter, self.after_raw)

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "address": self.address,
            "count": self.count,
            "desired": self.desired,
            "desired_raw": list(self.desired_raw),
            "before_raw": None if self.before_raw is None else list(self.before_raw),
            "after_raw": None if self.after_raw is None else list(self.after_raw),
            "status": self.status,
            "error": self.error,
            **({"register_type": self.register_type} if self.register_type != "holding" else {}),
        }


@dataclass(frozen=True, slots=True)
class Tally:
    """What a finished device's report said, in numbers: kept instead of its requests and parameters once
    its JSON is in the report file (a fleet of 10,000 devices held 34 KB of result objects per device)."""

    write_requests: int
    read_requests: int
    requests: int
    changed: int  # parameters written whose value changed
    failed: int  # parameters failed, mismatched or unverified
    written: tuple[str, ...]  # the journal's "written": parameters sent (ok, failed, mismatch, unverified)


_WRITTEN: dict[tuple[str, ...], tuple[str, ...]] = {}  # devices that wrote the same parameters share one tuple
_SENT = ("ok", "failed", "mismatch", "unverified")  # a parameter's statuses once it was sent (``written``)
_FAILED = ("failed", "mismatch", "unverified")


@dataclass
class DeviceResult:
    name: str
    url: str
    unit: int
    profile: str
    status: DeviceStatus = "ok"
    snapshot: str | None = None
    requests: list[RequestRecord] = field(default_factory=list)
    parameters: list[ParameterResult] = field(default_factory=list)
    error: str | None = None  # why the device failed, was unreachable or was skipped
    seconds: float | None = None  # how long the device's session took (fleets: for the summary table)
    profile_ref: str | None = None  # the profile used: its file's absolute path, or the built-in id
    notices: list[str] = field(default_factory=list)  # things the user should know that are not failures
    restored: str | None = None  # a rollback: the snapshot (absolute path) this device was restored from
    snapshot_sha256: str | None = None  # the SHA-256 of the snapshot file as written (rollback checks it)
    identity: dict[str, str] | None = None  # Function 43 objects (vendor, product_code, revision ...), if it answers
    learned: dict[str, int] = field(default_factory=dict)  # profile limits this run's refusals taught
    recipe: str | None = None  # the recipe (or snapshot, plan) file this device was given
    batch: int | None = None  # fleets: the batch the device ran in (or would have: skipped)
    commit: CommitState | None = None  # None: the profile has no commit steps, or nothing was written
    profile_sha256: str | None = None  # the SHA-256 of the profile file's text (None: a built-in profile)
    unrecorded: list[str] = field(default_factory=list)  # what the journal or report could not record (disk full)
    tally: Tally | None = None  # set once the requests and parameters were dropped (``small``)
    seen: str | None = None  # when (UTC) the values in the parameters' after_raw were read from the device
    # the profile's health checks (indices) failing before a safe change that was written anyway
    # (ApplyOptions.allow_unhealthy): its window does not hold them against the change; the notices say it
    unhealthy_before: tuple[int, ...] = field(default=(), repr=False, compare=False)
    # its report line as ``device_json`` made it where the device ran (a fleet's worker process): not remade here
    report_line: bytes | None = field(default=None, repr=False, compare=False)

    # the counts are of what the device received: every attempt of a request is a request
    @property
    def write_requests(self) -> int:
        if self.tally is not None:
            return self.tally.write_requests
        return sum(r.attempts for r in self.requests if r.function in (5, 6, 15, 16))

    @property
    def read_requests(self) -> int:
        if self.tally is not None:
            return self.tally.read_requests
        return sum(r.attempts for r in self.requests if r.function in (1, 2, 3, 4))

    @property
    def request_count(self) -> int:
        """Every request the device received: reads, writes, Function 43, each attempt."""
        return self.tally.requests if self.tally is not None else sum(r.attempts for r in self.requests)

    @property
    def repeated(self) -> int:
        """Requests sent again (after no answer, or a busy one): counted in the totals above."""
        return sum(r.attempts - 1 for r in self.requests)

    @property
    def changed_count(self) -> int:
        """Parameters written whose value changed."""
        if self.tally is not None:
            return self.tally.changed
        return sum(1 for p in self.parameters if p.status == "ok" and p.before_raw != p.after_raw)

    @property
    def failed_count(self) -> int:
        if self.tally is not None:
            return self.tally.failed
        return sum(1 for p in self.parameters if p.status in _FAILED)

    @property
    def written(self) -> tuple[str, ...]:
        """The parameters sent to the device (ok, failed, mismatch, unverified): the journal's ``written``."""
        if self.tally is not None:
            return self.tally.written
        return tuple([p.name for p in self.parameters if p.status in _SENT])

    def head(self) -> DeviceResult:
        """A copy without its requests, parameters and notices (what the report stream says of a device while it
        writes); ``copy.copy``: ``replace`` ran the __init__ of its 24 fields, for every device of a fleet."""
        out = copy.copy(self)
        out.requests, out.parameters, out.notices = [], [], []
        return out

    def small(self) -> DeviceResult:
        """This result without its requests and parameters, their numbers kept (``tally``): what a fleet
        keeps of a device once its JSON is in the report file. Its ``to_json`` is no longer the report's."""
        out = copy.copy(self)  # ``replace`` without its __init__ of 24 fields: the same fields, the same values
        out.requests, out.parameters = [], []
        if self.tally is not None:
            return out
        # ``written``, ``changed_count`` and ``failed_count`` at once (a fleet does this for every device)
        params = self.parameters
        written = tuple([p.name for p in params if p.status in _SENT])
        ok = [p for p in params if p.status == "ok"]
        changed = sum([p.before_raw != p.after_raw for p in ok])
        failed = len(written) - len(ok)  # sent, not ok: failed, mismatch or unverified
        if len(_WRITTEN) > 1024:  # a long-lived caller's many recipes: keep the table small
            _WRITTEN.clear()
        tally = Tally(
            self.write_requests,
            self.read_requests,
            self.request_count,
            changed,
            failed,
            _WRITTEN.setdefault(written, written),
        )
        out.tally = tally
        return out

    def settle(self) -> None:
        """Device status from its parameters (unless already decided: sent, failed, unreachable, skipped ...)."""
        if self.status in ("unreachable", "failed", "skipped", "sent", "rolled-back", "interrupted"):
            return
        bad = [p for p in self.parameters if p.status not in ("ok", "unchanged")]
        if not bad:
            self.status = "ok"
        elif len(bad) == len(self.parameters) and not any(p.status == "unverified" for p in bad):
            self.status = "failed"
        else:
            self.status = "partial"

    def to_json(self) -> dict[str, Any]:
        return self._json([r.to_json() for r in self.requests], [p.to_json() for p in self.parameters])

    def _json(self, requests: list[Any], parameters: list[Any]) -> dict[str, Any]:
        """``to_json`` with these requests and parameters (``device_json`` puts its own texts in their place)."""
        out: dict[str, Any] = {
            "name": self.name,
            "url": self.url,
            "unit": self.unit,
            "profile": self.profile,
            "status": self.status,
            "snapshot": self.snapshot,
            "requests": requests,
            "parameters": parameters,
        }
        if self.error is not None:
            out["error"] = self.error
        if self.seconds is not None:
            out["seconds"] = round(self.seconds, 3)
        if self.profile_ref is not None:
            out["profile_ref"] = self.profile_ref
        if self.notices:
            out["notices"] = list(self.notices)
        if self.restored is not None:
            out["restored"] = self.restored
        if self.snapshot_sha256 is not None:
            out["snapshot_sha256"] = self.snapshot_sha256
        if self.identity is not None:
            out["identity"] = dict(self.identity)
        if self.seen is not None:
            out["seen"] = self.seen
        if self.learned:
            out["learned"] = dict(self.learned)
        if self.recipe is not None:
            out["recipe"] = self.recipe
        if self.batch is not None:
            out["batch"] = self.batch
        if self.commit is not None:
            out["commit"] = self.commit
        if self.profile_sha256 is not None:
            out["profile_sha256"] = self.profile_sha256
        if self.unrecorded:
            out["unrecorded"] = list(self.unrecorded)
        return out


@dataclass
class Report:
    recipe: str | None
    devices: list[DeviceResult]
    seconds: float = 0.0
    run: dict[str, Any] | None = None  # who ran what, where and when (``run_info``, with the run's "id" and
    # "state_dir" in the journal, and "interrupted" when it stopped early); None: not known
    run_id: str | None = None  # the run's id in the journal (None: a run without one)
    state_dir: str | None = None  # absolute path of the folder with the journal and the snapshots
    interrupted: str | None = None  # why the run stopped early ("SIGINT", "SIGTERM", "cancelled"), else None
    unrecorded: list[str] = field(default_factory=list)  # what the run could not record (the report file, the
    # journal's run-finished line: a full disk); the devices' outcome stands, the run exits 4
    refused: str | None = None  # why the run was refused before its first write (a stale saved plan, a "no"): exit 1

    def __repr__(self) -> str:
        # short on purpose: asyncio.run's SIGINT bookkeeping (signal.getsignal on a partial holding the
        # main task) makes CPython 3.11 repr the task's result in full, which for 200 devices x 100
        # parameters took 0.2 s of every fleet command
        return f"Report(recipe={self.recipe!r}, devices={len(self.devices)}, seconds={self.seconds:.3f})"

    def summary(self) -> dict[str, Any]:
        counts: dict[str, int] = {s: sum(1 for d in self.devices if d.status == s) for s in DEVICE_STATUSES}
        return {
            "devices": len(self.devices),
            **counts,
            "write_requests": sum(d.write_requests for d in self.devices),
            "read_requests": sum(d.read_requests for d in self.devices),
            "requests": sum(d.request_count for d in self.devices),
            "seconds": round(self.seconds, 3),
        }

    def to_json(self) -> dict[str, Any]:
        """The report document (schema ``deployer.report/3``) as plain values."""
        return _document(
            self.recipe,
            [d.to_json() for d in self.devices],
            self.summary(),
            self.run_doc(),
            profiles_json(self.devices),
        )

    def run_doc(self) -> dict[str, Any] | None:
        """The report's ``run``: ``run_info`` with the journal's run id and state folder, and the interruption."""
        doc = dict(self.run or {})
        for key, value in (("id", self.run_id), ("state_dir", self.state_dir), ("interrupted", self.interrupted)):
            if value is not None:
                doc[key] = value
        if self.unrecorded:
            doc["unrecorded"] = list(self.unrecorded)
        return doc or None

    @property
    def exit_code(self) -> int:
        """The run's exit code (docs/design.md): 3 only when every device was unreachable (nothing written anywhere).

        A broadcast that went out (``sent``) counts as success: the user asked for an unverifiable write.
        """
        if self.refused is not None:
            return EXIT_INVALID  # as the command line exits: nothing was written, the plan or the answer said no
        if not self.devices:
            return EXIT_OK
        if all(d.status == "unreachable" for d in self.devices) and not self.unrecorded:
            return EXIT_UNREACHABLE
        if self.unrecorded:
            return EXIT_FAILED  # something reached a device that the report or the journal could not record
        if any(d.status not in ("ok", "sent") or d.unrecorded for d in self.devices):
            return EXIT_FAILED  # a device that did not end ok, or an outcome the journal could not record
        return EXIT_OK


def _document(
    recipe: str | None,
    devices: list[Any],
    summary: dict[str, Any],
    run: dict[str, Any] | None = None,
    profiles: dict[str, Any] | None = None,
) -> dict[str, Any]:
    doc = {"schema": REPORT_SCHEMA, "recipe": recipe, "devices": devices, "summary": summary}
    if run is not None:
        doc["run"] = run
    if profiles:
        doc["profiles"] = profiles
    return doc


# ---- what a report says of its profiles ---------------------------------------------------------
# A report is data: its readers never open a file it names (a report naming /etc/shadow as its
# profile put that file's lines on the screen). What ``deployer report`` and the pages need of a
# profile to show values in engineering units is stored in the report itself, once per distinct
# profile: for each parameter the run wrote, how its registers read.

_VIEW_DEFAULTS: dict[str, Any] = {
    "word_order": "big",
    "scale": "1",
    "offset": "0",
    "unit": None,
    "values": {},
    "byte_swap": False,
    "mask": 0,
    "size": 0,
    "encoding": "ascii",
    "padding": "nul",
    "register_type": "holding",
    "manual_number": "",
    "manual_text": "",
}


def parameter_view(p: Parameter) -> dict[str, Any]:
    """How a parameter's registers read (``Parameter.show_registers``), as JSON: what differs from the defaults."""
    full = {
        "address": p.address,
        "type": p.type,
        "word_order": p.word_order,
        "scale": str(p.scale),
        "offset": str(p.offset),
        "unit": p.unit,
        "values": dict(p.values),
        "byte_swap": p.byte_swap,
        "mask": p.mask,
        "size": p.size,
        "encoding": p.encoding,
        "padding": p.padding,
        "register_type": p.register_type,
        "manual_number": p.manual_number,
        "manual_text": p.manual_text,
    }
    return {k: v for k, v in full.items() if k not in _VIEW_DEFAULTS or v != _VIEW_DEFAULTS[k]}


def profiles_json(devices: Iterable[DeviceResult]) -> dict[str, Any]:
    """The report's ``profiles``: profile (as devices name it in ``profile_ref``) -> its id, SHA-256 and a
    view of each parameter the devices hold results of; each parameter made once per profile."""
    out: dict[str, Any] = {}
    seen: set[int] = set()
    for d in devices:
        if d.profile_ref is None or not d.parameters or id(d.parameters) in seen:
            continue
        seen.add(id(d.parameters))
        entry = out.setdefault(d.profile_ref, {"id": d.profile, "sha256": d.profile_sha256, "parameters": {}})
        views = entry["parameters"]
        for r in d.parameters:
            if r.parameter is not None and r.name not in views:
                views[r.name] = parameter_view(r.parameter)
    return out


def parameter_from_view(name: str, view: Any) -> Parameter | None:
    """The parameter a report's view describes (``parameter_view``), checked; None when it is not one."""
    from decimal import Decimal, InvalidOperation

    from .profile import Parameter, codec

    if not isinstance(view, dict):
        return None
    v = {**_VIEW_DEFAULTS, **view}
    try:
        p = Parameter(
            name,
            int(v["address"]),
            str(v["type"]),
            word_order=str(v["word_order"]),
            scale=Decimal(str(v["scale"])),
            offset=Decimal(str(v["offset"])),
            unit=None if v["unit"] is None else str(v["unit"]),
            values=tuple((str(k), int(x)) for k, x in dict(v["values"]).items()),
            byte_swap=v["byte_swap"] is True,
            mask=int(v["mask"]),
            size=int(v["size"]),
            encoding=str(v["encoding"]),
            padding=str(v["padding"]),
            register_type=v["register_type"],
            manual_number=str(v["manual_number"]),
            manual_text=str(v["manual_text"]),
        )
    except (KeyError, TypeError, ValueError, InvalidOperation):
        return None
    if (
        p.type not in (*codec.TYPE_NAMES, codec.STRING, codec.BOOL)
        or p.word_order not in ("big", "little")
        or p.register_type not in ("holding", "input", "coil", "discrete")
        or not 0 <= p.mask <= 0xFFFF
        or not 0 <= p.size <= 123
        or not p.scale.is_finite()
        or not p.offset.is_finite()
    ):
        return None
    return p


def run_info(command: str | None, started: float, user: str | None = None) -> dict[str, Any]:
    """Who ran what, where and when, for the report (``started``: the run's start, seconds since the epoch;
    ``user``: the person, where the process's own user is not who asked: the agent's authenticated user)."""
    import datetime
    import socket

    from . import __version__
    from .portable import user_name

    user = user or user_name()  # a uid without a name (a container): the number says who
    when = datetime.datetime.fromtimestamp(started, datetime.UTC).isoformat(timespec="seconds")
    return {"command": command, "user": user, "host": socket.gethostname(), "started": when, "version": __version__}


def device_json(d: DeviceResult) -> bytes:
    """``json.dumps(d.to_json())`` as ASCII bytes, its requests and parameters from texts made once each.

    A fleet writes 100 parameters per device, and each of their entries (name, address, desired value,
    the registers before and after, status) mostly repeats from device to device: encoding them anew took
    most of the report's CPU. An entry's text is kept by everything it says (``_ROWS``), so a changed field
    is a new entry, never a stale one."""
    if d.report_line is not None:
        return d.report_line
    if not d.parameters and not d.requests:
        return json.dumps(d.to_json()).encode()
    requests = "[" + ", ".join([_request_json(r) for r in d.requests]) + "]"
    params = "[" + ", ".join(_parameters_json(d.parameters)) + "]"
    # no string value can hold these texts unescaped, so the first match of each is the key itself
    return (
        json.dumps(d._json([], []))
        .replace('"requests": []', f'"requests": {requests}', 1)
        .replace('"parameters": []', f'"parameters": {params}', 1)
        .encode()
    )


_ROWS: dict[tuple[Any, ...], str] = {}
_ROWS_KEPT = 1 << 16  # entries remembered (devices holding values of their own would grow it without end)


def _parameters_json(params: Sequence[ParameterResult]) -> list[str]:
    """``json.dumps(p.to_json())`` of each parameter, from ``_ROWS`` where the same entry was made before."""
    # the key: all an entry says (comprehensions and map: a fleet does this for every parameter of every device)
    keys = [
        (
            p.name,
            p.address,
            p.count,
            p.desired,
            p.desired_raw,
            p.before_raw,
            p.after_raw,
            p.status,
            p.error,
            p.register_type,
        )
        for p in params
    ]
    try:
        texts = list(map(_ROWS.get, keys))
    except TypeError:  # registers given as lists (made in code): nothing kept
        return [_parameter_json(p) for p in params]
    if None in texts:
        if len(_ROWS) + len(keys) > _ROWS_KEPT:
            _ROWS.clear()
        for i, text in enumerate(texts):
            if text is None:
                texts[i] = _ROWS[keys[i]] = _parameter_json(params[i])
    return texts  # type: ignore[return-value]  # no None left


def _parameter_json(p: ParameterResult) -> str:
    """``json.dumps(p.to_json())``."""
    error = "null" if p.error is None else _text(p.error)
    kind = "" if p.register_type == "holding" else f', "register_type": {_text(p.register_type)}'
    return (
        f'{{"name": {_text(p.name)}, "address": {p.address}, "count": {p.count}, "desired": {_text(p.desired)}, '
        f'"desired_raw": {_words(p.desired_raw)}, "before_raw": {_words(p.before_raw)}, '
        f'"after_raw": {_words(p.after_raw)}, "status": {_text(p.status)}, "error": {error}{kind}}}'
    )


_REQUEST = operator.attrgetter(
    "function", "address", "count", "result", "exception_code", "attempts", "step", "deviation", "window"
)
_REQUESTS: dict[tuple[Any, ...], str] = {}


def _request_json(r: RequestRecord) -> str:
    """``json.dumps(r.to_json())``, kept by all it says (a fleet's devices send the same requests)."""
    key = _REQUEST(r)
    text = _REQUESTS.get(key)
    if text is None:
        if len(_REQUESTS) >= _ROWS_KEPT:
            _REQUESTS.clear()
        text = _REQUESTS[key] = json.dumps(r.to_json())
    return text


def _words(regs: Sequence[int] | None) -> str:
    """A register list as JSON (``null`` for None)."""
    return "null" if regs is None else json.dumps(list(regs))


@functools.lru_cache(maxsize=1 << 12)
def _text(s: str) -> str:
    return json.dumps(s)


def report_parts(
    recipe: str | None,
    devices: Sequence[bytes],
    summary: dict[str, Any],
    run: dict[str, Any] | None = None,
    profiles: dict[str, Any] | None = None,
) -> list[bytes]:
    """The report document as pieces of JSON text, one device per line (each from ``device_json``).

    The pieces are written with one gathering write (``write_atomic``), never joined into one big
    string: a fleet's report file is rewritten as devices finish.
    """
    head, tail = json.dumps(_document(recipe, [], summary, run, profiles)).split('"devices": []', 1)
    out = [f'{head}"devices": [\n'.encode()]
    for i, d in enumerate(devices):
        if i:
            out.append(b",\n")
        out.append(d)
    out.append(f"\n]{tail}\n".encode())
    return out


def report_text(report: Report) -> str:
    """A report as JSON text, one device per line (``--json`` and the ``--report`` file of a fleet)."""
    return b"".join(
        report_parts(
            report.recipe,
            [device_json(d) for d in report.devices],
            report.summary(),
            report.run_doc(),
            profiles_json(report.devices),
        )
    ).decode()


def write_json(data: dict[str, Any], path: str, *, what: str = "") -> None:
    """Write atomically and durably: a report or plan is evidence, keep it whole (``write_atomic``'s rule)."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    write_atomic(path, json.dumps(data, indent=2) + "\n", what=what)


def read_report(path: str) -> dict[str, Any]:
    """An earlier run's report file, checked to be a deployer report (InputError); OSError is the caller's.

    The file of a fleet run that is still going, or was killed, is a stream (``fleet.livereport``): it is
    read as the document it stands for (``stream_document``)."""
    with open(path, encoding="utf-8") as f:
        try:
            first = f.readline()
            if first.startswith('{"schema": "deployer.report-stream/'):
                data = stream_document(path, first, f)
            else:
                f.seek(0)
                data = json.load(f, parse_constant=_no_constant, parse_float=_finite)
        except json.JSONDecodeError as e:
            raise InputError([Diagnostic(path, e.lineno, e.colno, f"not a report (invalid JSON: {e.msg})")]) from None
        except UnicodeDecodeError:
            raise InputError([Diagnostic(path, 1, 1, "not a report (not UTF-8 text)")]) from None
        except (ValueError, RecursionError):  # NaN, Infinity, 1e400, nesting too deep: check_report says where
            data = None
    check_report(path, data, stream=first.startswith('{"schema": "deployer.report-stream/'))
    assert isinstance(data, dict)  # check_report refused anything else
    return data


def stream_document(path: str, first: str, lines: Iterable[str]) -> dict[str, Any]:
    """The report document a stream stands for (its first line read: ``first``): each device's last line,
    in the order the devices first appear; the summary counted from them (``seconds``: 0, not known).
    A last line cut short (the run was killed while appending it) is left out: the device's line before
    it stands. Raises json.JSONDecodeError for anything else that is not JSON."""
    head = json.loads(first)
    if not isinstance(head, dict) or head.get("schema") != STREAM_SCHEMA:
        raise InputError(
            [
                Diagnostic(
                    path,
                    1,
                    1,
                    f"not a deployer report (a stream of another version: "
                    f"{str(head.get('schema') if isinstance(head, dict) else head)!r})",
                )
            ]
        )
    devices: dict[str, Any] = {}
    for number, line in enumerate(lines, 2):
        if not line.endswith("\n"):  # cut short by a crash: only the last line can be
            break
        try:
            dev = json.loads(line)
        except json.JSONDecodeError as e:
            raise InputError([Diagnostic(path, number, e.colno, f"not a report (invalid JSON: {e.msg})")]) from None
        if isinstance(dev, dict) and isinstance(dev.get("name"), str):
            devices[dev["name"]] = dev  # a later line replaces an earlier one; the first fixed the order
    listed = list(devices.values())
    counts: dict[str, int] = {s: sum(1 for d in listed if d.get("status") == s) for s in DEVICE_STATUSES}
    functions = [r.get("function") for d in listed for r in d.get("requests") or [] if isinstance(r, dict)]
    summary: dict[str, Any] = {
        "devices": len(listed),
        **counts,
        "write_requests": sum(1 for f in functions if f in (5, 6, 15, 16)),
        "read_requests": sum(1 for f in functions if f in (1, 2, 3, 4)),
        "seconds": 0.0,
    }
    return _document(
        head.get("recipe"),
        listed,
        summary,
        head.get("run") if isinstance(head.get("run"), dict) else None,
        head.get("profiles") if isinstance(head.get("profiles"), dict) else None,
    )


def report_from_json(doc: dict[str, Any], profiles: Sequence[Profile] = ()) -> Report:
    """An earlier run's report document (``read_report``) as a Report, for ``deployer report``.

    Values are shown in engineering units from what the report says of its profiles (``profiles``,
    written by the run), or from ``profiles`` the user names (matched by id); a built-in profile by
    its id. A file the report names is never opened: a report is data. Else values are shown as
    register words, with a notice. Reports of older versions have fewer fields: what is missing stays empty.
    """
    from .profile import builtin_profile, builtin_profile_ids

    found = doc.get("profiles")
    stored: dict[str, Any] = found if isinstance(found, dict) else {}
    given = {p.id: p for p in profiles}
    views: dict[tuple[str, str, str | None], tuple[dict[str, Parameter] | None, str | None]] = {}

    def profile_of(ref: str, name: str, digest: str | None) -> tuple[dict[str, Parameter] | None, str | None]:
        """The parameters to show a device's values with, and a notice about them."""
        key = (ref, name, digest)
        if key not in views:
            entry = stored.get(ref)
            if name in given:  # named on the command line: the user's word over the report's
                prof = given[name]
                views[key] = (
                    {p.name: p for p in prof.parameters},
                    None
                    if digest is None or prof.digest in (None, digest)
                    else f"values shown with profile {prof.source or prof.id} as given; the run used another "
                    f"version of it (SHA-256 {digest[:12]})",
                )
            elif isinstance(entry, dict) and isinstance(entry.get("parameters"), dict):
                views[key] = (
                    {
                        n: q
                        for n, v in entry["parameters"].items()
                        if isinstance(n, str) and (q := parameter_from_view(n, v)) is not None
                    },
                    None,
                )
            elif ref in builtin_profile_ids() and digest is None:  # part of deployer, not a file the report names
                views[key] = ({p.name: p for p in builtin_profile(ref).parameters}, None)
            else:
                views[key] = (
                    None,
                    f"values shown as registers: the report does not describe profile {name or ref} "
                    "(a report of an older version); name it with: deployer report --profile FILE",
                )
        return views[key]

    devices = []
    for d in doc.get("devices") or []:
        if not isinstance(d, dict):
            continue
        ref = str(d.get("profile_ref") or d.get("profile") or "")
        prof, notice = profile_of(ref, str(d.get("profile", "")), d.get("profile_sha256")) if ref else (None, None)
        notices = [str(n) for n in d.get("notices") or []]
        if notice is not None:
            notices.append(notice)
        res = DeviceResult(
            str(d.get("name", "?")),
            str(d.get("url", "")),
            int(d.get("unit") or 0),
            str(d.get("profile", "")),
            status=d.get("status", "ok"),
            snapshot=d.get("snapshot"),
            error=d.get("error"),
            seconds=d.get("seconds"),
            profile_ref=d.get("profile_ref"),
            notices=notices,
            recipe=d.get("recipe"),
            batch=d.get("batch"),
            commit=d.get("commit"),
            profile_sha256=d.get("profile_sha256"),
            identity={str(k): str(v) for k, v in d["identity"].items()}
            if isinstance(d.get("identity"), dict)
            else None,
            learned={str(k): int(v) for k, v in (d.get("learned") or {}).items()},
            seen=None if d.get("seen") is None else str(d["seen"]),
        )
        res.requests = [
            RequestRecord(
                int(r.get("function", 0)),
                int(r.get("address", 0)),
                int(r.get("count", 0)),
                r.get("result", "ok"),
                r.get("exception_code"),
                int(r.get("attempts", 1)),
            )
            for r in d.get("requests") or []
            if isinstance(r, dict)
        ]
        for p in d.get("parameters") or []:
            if not isinstance(p, dict):
                continue
            param = prof.get(str(p.get("name"))) if prof is not None else None

            def raw(key: str, p: dict[str, Any] = p) -> tuple[int, ...] | None:
                v = p.get(key)
                return None if v is None else tuple(int(w) for w in v)

            res.parameters.append(
                ParameterResult(
                    str(p.get("name", "?")),
                    int(p.get("address", 0)),
                    int(p.get("count", 0)),
                    str(p.get("desired", "")),
                    raw("desired_raw") or (),
                    raw("before_raw"),
                    raw("after_raw"),
                    p.get("status", "skipped"),
                    p.get("error"),
                    str(p.get("register_type", "holding")),
                    parameter=param,
                )
            )
        devices.append(res)
    summary = doc.get("summary")
    seconds = float(summary.get("seconds") or 0.0) if isinstance(summary, dict) else 0.0
    run = doc.get("run")
    return Report(doc.get("recipe"), devices, seconds, run if isinstance(run, dict) else None)


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number a report holds")


def _finite(text: str) -> float:
    value = float(text)
    if value in (float("inf"), float("-inf")):
        raise ValueError(f"{text} is out of range")
    return value


def check_report(path: str, data: Any, *, stream: bool = False) -> None:
    """Raise InputError unless ``data`` (the file ``path``, read) is a report of a version this deployer
    reads that is valid against the report schema: a hand-edited report is refused at the position of
    what is wrong, never shown half or with a traceback.

    Every version so far only added fields, so the current schema (its ``schema`` key aside) checks the
    older ones too; what a report of an older version lacks stays empty. A report a crash left
    unfinished (a fleet's stream, the devices not finished yet) is a valid report of its version.
    ``data`` None: the JSON reader refused a number (NaN, Infinity, 1e400); the positioned reader finds it.
    """
    from .load import schema

    if data is not None:
        if (
            not isinstance(data, dict)
            or not isinstance(data.get("schema"), str)
            or not data["schema"].startswith("deployer.report/")
        ):
            raise InputError([Diagnostic(path, 1, 1, f'not a deployer report (no "schema": "{REPORT_SCHEMA}")')])
        version = data["schema"].removeprefix("deployer.report/")
        current = int(REPORT_SCHEMA.rsplit("/", 1)[1])
        if not version.isdigit() or not 1 <= int(version) <= current:
            raise InputError(
                [
                    Diagnostic(
                        path,
                        1,
                        1,
                        f"a report of version {clipped_repr(data['schema'])}: this "
                        f"deployer reads versions 1 to {current} (deployer.report/"
                        f"{current}); a newer deployer wrote it, or not deployer",
                    )
                ]
            )
        if schema.is_valid({**data, "schema": REPORT_SCHEMA}, "report") is True:
            return
    raise InputError(_report_problems(path, data, stream=stream))


def _report_problems(path: str, data: Any, *, stream: bool) -> list[Diagnostic]:
    """What is wrong with a report, each at its position where the file can be read again with positions
    (the slow reader runs only for a report that is wrong)."""
    from decimal import Decimal

    from .load import schema, yamlsrc

    value, src = data, yamlsrc.Source(path)  # a stream's lines are no one document: positions 1:1
    if not stream:
        try:
            value, src = yamlsrc.load(path)
        except InputError as e:  # too large for the positioned reader, or its own complaint
            if data is None:
                return list(e.diagnostics)
    if not isinstance(value, dict):
        return [Diagnostic(path, 1, 1, f'not a deployer report (no "schema": "{REPORT_SCHEMA}")')]
    found = schema.validate({**value, "schema": REPORT_SCHEMA}, "report", src)

    def numbers(v: Any, at: tuple[str | int, ...]) -> None:  # what JSON cannot hold as a float: 1e400
        if isinstance(v, Decimal) and not abs(v) < Decimal("1e300"):
            found.append(src.error(at, f"{v} is out of range"))
        elif isinstance(v, dict):
            for k, x in v.items():
                numbers(x, (*at, k))
        elif isinstance(v, list):
            for i, x in enumerate(v):
                numbers(x, (*at, i))

    numbers(value, ())
    return found or [Diagnostic(path, 1, 1, "not a report deployer wrote (NaN, Infinity or a number out of range)")]
