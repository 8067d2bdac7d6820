"""Which answers a session believes: a late serial answer never becomes a value.

RTU, ASCII and rtu+tcp answers carry no transaction id. An answer that comes after its request timed
out looks like the answer to the next request of its shape (same unit, function and byte count), and
the transport's settling catches it only while the line is silent (deployer.transport.clients). So a
session's ``Trust`` starts ``trusted`` and turns ``doubting`` for the rest of the session once its line
went out of step on one of its requests: a request unanswered, an answer wrong or late, bytes nobody
asked for, a lost connection. While doubting, every value read is read again, after the line has been
silent long enough that no earlier answer is still on its way (twice the timeout, or 1.5 times the
longest the device was seen to stay silent), and taken only when that read's answer was the first
thing to come after it and equals the read before it. Else up to ``CONFIRMATIONS`` reads are made,
then ``Untrusted`` is raised: the caller stops as for a silent device, and nothing is taken.

Modbus/TCP (transaction ids) is never in doubt.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

from ..errors import BadAnswer, ConnectionLost, NoResponse, TransportError, Untrusted
from ..transport import clients as tp

CONFIRMATIONS = 3  # reads after the first before a value is given up as untrusted
State = Literal["trusted", "doubting"]


class Trust:
    """What one session (one unit over one transport) believes of its answers."""

    def __init__(self, transport: tp.Transport) -> None:
        self.transport = transport
        self.state: State = "trusted"
        self.rereads = 0  # confirming reads sent
        self.unanswered = 0  # attempts that timed out
        self.wrong: list[str] = []  # answers that were not to the request (BadAnswer)
        self.lost = 0  # connections lost
        self._desyncs = transport.desyncs if transport.shifts else 0

    @property
    def doubting(self) -> bool:
        return self.state == "doubting"

    def after(self, error: TransportError | None = None) -> None:
        """Called after each attempt of a request: in doubt from now on when the line went out of step."""
        t = self.transport
        if not t.shifts:
            return
        if isinstance(error, BadAnswer):
            self.wrong.append(str(error))
        elif isinstance(error, NoResponse):
            self.unanswered += 1
        elif isinstance(error, ConnectionLost):
            self.lost += 1
        moved, self._desyncs = t.desyncs != self._desyncs, t.desyncs
        if moved or isinstance(error, (NoResponse, ConnectionLost)):
            self.state = "doubting"

    def _what(self) -> str:
        """What put the line out of step, for the report."""
        t, said = self.transport, []
        if self.unanswered:
            said.append(
                f"{self.unanswered} request{'s' if self.unanswered != 1 else ''} went unanswered within the "
                f"timeout ({t.url.timeout:g} s)"
            )
        if t.late_answers:
            n = len(t.late_answers)
            said.append(
                f"the device answered {n} request{'s' if n != 1 else ''} after the timeout (up to "
                f"{max(t.late_answers):.2f} s)"
            )
        if self.wrong:
            said.append(f"{len(self.wrong)} wrong answer{'s' if len(self.wrong) != 1 else ''} ({self.wrong[0]})")
        if self.lost:
            said.append("the connection was lost")
        return "; ".join(said) or "bytes nobody asked for came on the line"

    def overlook(self) -> None:
        """The last request's silence puts nothing in doubt (an identification request: no answer to it
        could pass for a read's)."""
        self._desyncs = self.transport.desyncs

    def refusal(self, function: int, address: int, count: int, seen: Sequence[Sequence[int]]) -> Untrusted:
        """The error for a read whose value no confirming read agreed with."""
        what = ("bit" if function in (1, 2) else "register") + ("s" if count != 1 else "")
        got = " then ".join("[" + ", ".join(map(str, v)) + "]" for v in seen)
        silence, _ = self.transport.silence()
        return Untrusted(
            f"the serial line went out of step ({self._what()}), so an answer could be another request's: the read "
            f"of {count} {what} at 0x{address:04X} (function {function}) gave {got}, and no read after {silence:.2f} s "
            f"of silence agreed with the one before it; nothing of it is taken{self._advice()}"
        )

    def notice(self) -> str | None:
        """What the device's report says when the session was in doubt (None: it never was)."""
        if not self.doubting:
            return None
        silence, _ = self.transport.silence()
        n = self.rereads
        return (
            f"the serial line went out of step ({self._what()}): every value read after it was read again after "
            f"{silence:.2f} s of silence and taken only when both reads agreed ({n} confirming "
            f"read{'s' if n != 1 else ''}){self._advice()}"
        )

    def _advice(self) -> str:
        """The timeout that would have served: 1.5 times the longest the device stayed silent, when that
        is more than the timeout."""
        t = self.transport
        _, slowest = t.silence()
        if slowest <= t.url.timeout:
            return ""
        served = math.ceil(slowest * 1.5 * 10) / 10
        return (
            f"; the device stayed silent up to {slowest:.2f} s after a request: timeout={served:g} would have "
            f"served (set it on the URL)"
        )
