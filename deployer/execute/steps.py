"""Steps around the writes: identity and precondition checks, unlock/commit/lock actions."""

from __future__ import annotations

import asyncio
from collections.abc import Iterable

from ..errors import IdentityMismatch
from ..planning.model import WriteRequest
from ..profile import Profile, WriteAction, codec, object_name
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


async def check_preconditions(session: Session, profile: Profile) -> str | None:
    """None if every precondition holds (e.g. 'drive stopped'), else which one does not."""
    for c in profile.preconditions:
        (word,) = await session.read(c.address, 1)
        if not c.holds(word):
            return f"precondition failed: {c.what()} is {codec.extract_field(word, c.mask)}, expected {c.equals}"
    return None


async def _send_actions(session: Session, prof: Profile, actions: Iterable[WriteAction]) -> None:
    """The profile's own writes (unlock, commit, lock), each followed by its wait."""
    for action in actions:
        reqs = ([WriteRequest(6, action.address + i, (w,), ()) for i, w in enumerate(action.registers)]
                if prof.limits.write_function == 6 else [WriteRequest(16, action.address, action.registers, ())])
        for r in reqs:
            await session.write(r)
        if action.wait_ms:
            await asyncio.sleep(action.wait_ms / 1000)
