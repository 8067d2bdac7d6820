"""Steps around the writes: identity and precondition checks, unlock/commit/lock actions."""

from __future__ import annotations

import asyncio
from collections.abc import Iterable, Sequence

from ..errors import DeviceGone, ExceptionResponse, IdentityMismatch
from ..planning.model import WriteRequest
from ..profile import Profile, WriteAction, codec, object_name
from ..profile.firmware import matches
from ..profile.model import READ_FUNCTION
from .session import Session


async def check_identity(session: Session, profile: Profile) -> None:
    """Raises IdentityMismatch unless every identity register holds its expected value."""
    for chk in profile.identity:
        (value,) = await session.read(chk.address, 1, READ_FUNCTION[chk.register_type])
        if value != chk.raw:
            what = f" ({chk.description})" if chk.description else ""
            table = "input register" if chk.register_type == "input" else "register"
            raise IdentityMismatch(
                f"identity check failed: {table} 0x{chk.address:04X}{what} holds 0x{value:04X}, expected "
                f"0x{chk.raw:04X}: another kind of device answers here",
                address=chk.address, expected=chk.raw, found=value)


def check_identity_objects(profile: Profile, identity: dict[str, str] | None) -> str | None:
    """None if the device's Function 43 objects hold what the profile's identity checks expect, else why not."""
    for chk in profile.identity_objects:
        name = object_name(chk.object_id)
        what = f" ({chk.description})" if chk.description else ""
        if identity is None:
            return (f"identity check failed: the device does not answer Function 43 (device identification); "
                    f"{name}{what} should be {chk.equals!r}")
        if identity.get(name) != chk.equals:
            have = repr(identity[name]) if name in identity else "missing"
            return (f"identity check failed: {name}{what} is {have}, expected {chk.equals!r}: another kind of "
                    f"device answers here")
    return None


async def check_firmware(session: Session, profile: Profile, identity: dict[str, str] | None,
                         names: Sequence[str]) -> str | None:
    """None if the device's firmware revision is one the profile and the parameters ``names`` apply to, else
    why not (the revision found and the one wanted). Read before anything is written."""
    src = profile.firmware
    if src is None:  # no revision to go by (parameters are gated by the profile's firmware source only)
        return None
    gated = [p for p in map(profile.parameter, names) if p.firmware is not None]
    if src.applies is None and not gated:
        return None
    if src.address is None:
        name = object_name(src.object_id or 0)
        revision = None if identity is None else identity.get(name)
        if revision is None:
            why = ("the device does not answer Function 43 (device identification)" if identity is None
                   else f"its Function 43 answer has no {name}")
            return (f"firmware revision unknown: {why}; profile {profile.id} needs it (set firmware.register where "
                    "the device reports it)")
    else:
        revision = src.revision_of(await session.read(src.address, src.count, READ_FUNCTION[src.register_type]))
    if src.applies is not None and not matches(src.applies, revision):
        return (f"firmware {revision!r} ({src.describe()}) is not one profile {profile.id} applies to "
                f"({src.applies})")
    wrong = [p for p in gated if p.firmware is not None and not matches(p.firmware, revision)]
    if wrong:
        said = ", ".join(f"{p.name} needs {p.firmware}" for p in wrong[:5]) + (
            f" and {len(wrong) - 5} more" if len(wrong) > 5 else "")
        return f"firmware {revision!r} ({src.describe()}): {said}"
    return None


async def check_preconditions(session: Session, profile: Profile) -> str | None:
    """None if every precondition holds (e.g. 'drive stopped'), else which one does not."""
    for c in profile.preconditions:
        (word,) = await session.read(c.address, 1)
        if not c.holds(word):
            return f"precondition failed: {c.what()} is {codec.extract_field(word, c.mask)}, expected {c.equals}"
    return None


async def _send_actions(session: Session, prof: Profile, actions: Iterable[WriteAction]) -> None:
    """The profile's own writes (unlock, commit, lock), each followed by its wait.

    In the form the device takes: Function 06 where the profile (or what the device taught) says so, and
    where Function 16 answers 01 (illegal function: nothing was written) one 06 per register; a coil with
    Function 05."""
    for action in actions:
        if action.is_coil:
            await session.write(WriteRequest(5, action.address, action.registers, ()))
        elif prof.limits.write_function == 6:
            await _singles(session, action)
        else:
            try:
                await session.write(WriteRequest(16, action.address, action.registers, ()))
            except ExceptionResponse as e:
                if e.code != 1:
                    raise
                await _singles(session, action)
        if action.wait_ms:
            await asyncio.sleep(action.wait_ms / 1000)


async def _singles(session: Session, action: WriteAction) -> None:
    for i, w in enumerate(action.registers):
        await session.write(WriteRequest(6, action.address + i, (w,), ()))


async def commit_steps(session: Session, prof: Profile, *, around: bool = True) -> tuple[str, bool] | None:
    """Unlock, commit, lock (``around`` False: the commit alone, within an apply's unlock and lock); None when
    all went out, else why not and whether the commit itself is what failed (False: it was sent, but the lock
    step after it failed). A device whose step failed is ``failed``: its parameters stay verified."""
    if prof.unlock and around:
        try:
            await _send_actions(session, prof, prof.unlock)
        except (DeviceGone, ExceptionResponse) as e:
            return f"commit not sent: unlock failed: {e}; the values are verified, in RAM, not stored", True
    failed: tuple[str, bool] | None = None
    for action in prof.commit:
        try:
            await _send_actions(session, prof, [action])
        except (DeviceGone, ExceptionResponse) as e:
            failed = (f"commit '{action.description or hex(action.address)}' failed: {e}; the values are verified, "
                      "in RAM, not stored", True)
            break
    if prof.unlock and prof.lock and around:
        try:
            await _send_actions(session, prof, prof.lock)
        except (DeviceGone, ExceptionResponse) as e:
            lock_failed = f"lock failed: {e}; the device may be left unlocked"
            failed = (f"{failed[0]}; {lock_failed}", True) if failed else (lock_failed, False)
    return failed
