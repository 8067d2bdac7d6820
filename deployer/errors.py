"""Every exception deployer raises, and the exit code each one means.

One tree, one root: a caller catches ``DeployerError`` for anything the library says went wrong,
or a branch of it for one kind. Each class carries the process exit code of the command line
(``exit_code``, a class attribute, as click's ``ClickException.exit_code``); the command line maps an
error to its exit code through that attribute only. Decisions are taken on types and fields, never
on message text; the message (``str(e)``) is written for the user and may change.

::

    DeployerError                  4  base; a run that failed
    ├── InputError                 1  invalid files: diagnostics with FILE:LINE:COL, all at once
    ├── UsageError                 1  a bad option or combination of options
    │   ├── BadURL                 1  a malformed device URL, unknown scheme or option
    │   ├── StalePlan              1  apply PLAN.json: the device no longer holds what it was made against
    │   └── Declined               1  the user answered no at the confirmation prompt
    ├── CodecError                 1  a value its type cannot hold (also a ValueError)
    ├── TransportError             3  the device could not be talked to
    │   ├── Unreachable            3  no connection (refused, no serial device, TLS handshake)
    │   ├── NoResponse             3  no answer within the timeout (one attempt)
    │   │   └── BadAnswer          3  an answer, but not to this request (unit, function, count, echo, CRC)
    │   ├── ConnectionLost         3  the connection dropped
    │   ├── ExceptionResponse      3  a Modbus exception response (``function``, ``code``)
    │   └── DeviceGone             3  no answer and the retry budget spent
    │       └── Untrusted          3  serial answers came late or astray, and a value read after could not be
    │                                 confirmed by a second read after the line fell silent (deployer.execute.trust)
    ├── Locked                     3  another run holds the device (``busy``), or no lock can be taken
    ├── StateError                 1  the state directory cannot be written (disk full, read-only) before a run
    ├── IdentityMismatch           4  the device is not the one the profile describes
    ├── NotCommitted               4  ``deployer confirm``: the confirmed run did not send its commit to every
    │                                 device (a parameter changed in the window, a step failed, time ran out)
    ├── RunInterrupted             4  a run stopped early (Ctrl-C, SIGTERM, cancelled); ``report`` says
    │                                 what every device holds as far as known
    └── AgentError                 4  the site agent refused a request or was not reached; each carries
                                      the exit code the same command has without the agent

Exit codes (a public interface; scripts rely on them): 0 success; 1 invalid input or usage, nothing
sent; 2 ``plan``/``diff`` found changes; 3 unreachable, nothing written; 4 a write failed or did
not verify.

``Diagnostic`` is one problem in one file (``FILE:LINE:COL: error: message``), what an InputError carries.

This module imports nothing of deployer, so every module can import it (and no circle goes through it).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

EXIT_OK = 0
EXIT_INVALID = 1
EXIT_CHANGES = 2
EXIT_UNREACHABLE = 3
EXIT_FAILED = 4

__all__ = [
    "EXIT_CHANGES",
    "EXIT_FAILED",
    "EXIT_INVALID",
    "EXIT_OK",
    "EXIT_UNREACHABLE",
    "AgentError",
    "BadAnswer",
    "BadURL",
    "CodecError",
    "ConnectionLost",
    "Declined",
    "DeployerError",
    "DeviceGone",
    "Diagnostic",
    "ExceptionResponse",
    "IdentityMismatch",
    "InputError",
    "Locked",
    "NoResponse",
    "NotCommitted",
    "RunInterrupted",
    "StalePlan",
    "StateError",
    "TransportError",
    "Unreachable",
    "Untrusted",
    "UsageError",
]


@dataclass(frozen=True, order=True)
class Diagnostic:
    """One problem in one file. ``line`` and ``col`` are 1-based (0 when unknown)."""

    path: str
    line: int
    col: int
    message: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}:{self.col}: error: {self.message}"


class DeployerError(Exception):
    """Base of every error deployer raises; ``exit_code`` is what the command line exits with."""

    exit_code: ClassVar[int] = EXIT_FAILED


class InputError(DeployerError):
    """Invalid input (files, options): nothing may be sent to any device.

    ``diagnostics``: every problem found, sorted by file and position (loaders collect all problems
    of a file before raising, so users fix them in one pass).
    """

    exit_code = EXIT_INVALID

    def __init__(self, diagnostics: Iterable[Diagnostic]) -> None:
        self.diagnostics = sorted(set(diagnostics))
        super().__init__("\n".join(str(d) for d in self.diagnostics))


class UsageError(DeployerError):
    """A bad option or combination of options (not tied to a file position)."""

    exit_code = EXIT_INVALID


class BadURL(UsageError):
    """A malformed device URL, an unknown scheme or option."""


class StalePlan(UsageError):
    """apply PLAN.json: the device no longer holds what the plan was made against.

    ``result``: that device as it was found (its parameters with the values read, nothing written; a
    ``DeviceResult``), and ``report``: the refused run's report holding it (a ``Report``): what ``--json`` and
    ``--report`` give of a refused run. None where no device was read yet."""

    result: Any = None
    report: Any = None


class Declined(UsageError):
    """The user answered no at the confirmation prompt (``result``, ``report``: as ``StalePlan``'s)."""

    result: Any = None
    report: Any = None


class CodecError(DeployerError, ValueError):
    """A value that cannot be represented in its type; the message is meant for the user.

    ``kind``: what is wrong, for callers that decide on it ("resolution": not a multiple of the
    parameter's resolution; "" otherwise).
    """

    exit_code = EXIT_INVALID

    def __init__(self, message: str, *, kind: str = "") -> None:
        self.kind = kind
        super().__init__(message)


class TransportError(DeployerError):
    """Base of everything a transport raises; the message is meant for the user."""

    exit_code = EXIT_UNREACHABLE


class Unreachable(TransportError):
    """Could not connect (refused, no such serial device, TLS handshake failed)."""


class NoResponse(TransportError):
    """The device did not answer within the timeout (one attempt)."""


class BadAnswer(NoResponse):
    """Something answered, but not this request: wrong unit, function, byte count or echo, or garbled.

    A NoResponse for retrying (nothing usable came back), with its own message: it is not silence.
    """


class ConnectionLost(TransportError):
    """The connection dropped; reconnect() may bring it back."""


class ExceptionResponse(TransportError):
    """The device answered request ``function`` with Modbus exception ``code``."""

    NAMES: ClassVar[dict[int, str]] = {
        1: "illegal function",
        2: "illegal data address",
        3: "illegal data value",
        4: "server device failure",
        5: "acknowledge",
        6: "server device busy",
        8: "memory parity error",
        10: "gateway path unavailable",
        11: "gateway target device failed to respond",
    }

    def __init__(self, function: int, code: int) -> None:
        self.function = function
        self.code = code
        super().__init__(f"exception {code:02d} ({self.NAMES.get(code, 'unknown')})")


class DeviceGone(TransportError):
    """The device stopped answering and the retry budget is spent."""


class Untrusted(DeviceGone):
    """On a serial line (RTU, ASCII, rtu+tcp) a request went unanswered, an answer came late or astray, and
    a value read afterwards could not be confirmed: it may be the answer to another request, so nothing is
    taken from it. A DeviceGone, so that every reader stops as for a silent device; the executor refuses to
    write a device whose snapshot it would have held (``failed``, nothing written)."""


class Locked(DeployerError):
    """The device's lock could not be taken.

    ``busy``: another run holds it (waiting may help); False when the lock itself cannot be used
    (the lock directory or file is not usable: waiting does not help).
    """

    exit_code = EXIT_UNREACHABLE

    def __init__(self, message: str, *, busy: bool = True) -> None:
        self.busy = busy
        super().__init__(message)


class StateError(DeployerError):
    """The state directory (journal, snapshots) cannot be written: a full disk, a read-only folder.

    Raised before a run sends anything (exit 1: nothing was sent); once devices are written, the run
    goes on and reports it per device instead (a device whose snapshot cannot be saved is not written).
    """

    exit_code = EXIT_INVALID


class IdentityMismatch(DeployerError):
    """An identity register does not hold the value the profile expects: not the device it describes.

    ``address``: the register; ``expected`` and ``found``: its values.
    """

    def __init__(self, message: str, *, address: int, expected: int, found: int) -> None:
        self.address = address
        self.expected = expected
        self.found = found
        super().__init__(message)


class NotCommitted(DeployerError):
    """A confirmed run did not send its commit to every device: a parameter changed during its window (not
    committed; the rest rolled back), a commit step failed, or its time ran out first. The message names
    each device and why."""


class RunInterrupted(DeployerError):
    """A run stopped early: Ctrl-C or SIGTERM (``reason`` "SIGINT", "SIGTERM"), or its task was cancelled
    ("cancelled"). ``report``: every device as far as known (in flight ``interrupted``, with its snapshot
    when a write may have gone out; never started ``skipped``); the journal has its run-finished line."""

    # typed Any, not deployer.report.Report: this module imports nothing of deployer (no circle through it)
    def __init__(self, report: Any, reason: str = "cancelled") -> None:
        super().__init__(f"the run was interrupted ({reason})")
        self.report = report
        self.reason = reason


class AgentError(DeployerError):
    """The site agent (``deployer agent``) refused a request, or could not be reached.

    ``kind``: the agent's word for it (usage, input, not-found, conflict, locked, refused, internal;
    unreachable when no answer came); ``exit_code``: what the same command exits with without the agent;
    ``diagnostics``: ``FILE:LINE:COL: error: ...`` lines of invalid files.
    """

    def __init__(self, message: str, *, kind: str, exit_code: int, diagnostics: Sequence[str] = ()) -> None:
        super().__init__(message)
        self.kind = kind
        self.diagnostics = list(diagnostics)
        object.__setattr__(self, "exit_code", exit_code)  # the agent says it per answer
