"""The token of an agent started without ``--token-file`` or ``--users``, and how its user's clients find it.

No mode of the agent answers a request that carries no credential (a web page in a browser on the gateway
could send one). An agent given none makes a token: ``STATE/agent/token`` (mode 0600; on Windows an access list
for its owner and the administrators alone; made once and kept across restarts; delete it and restart to change
it) and says on stderr where it is, as Jupyter does. For the
clients of the same user on the same machine it leaves a note while it runs, ``RUNTIME/agent-PORT.json``
(the URL, its PID and the token file's path) in a folder of that user's own: ``$DEPLOYER_RUNTIME_DIR``, else
``$XDG_RUNTIME_DIR/deployer``, else ``~/.local/state/deployer/agents`` (``%LOCALAPPDATA%\\deployer\\agents``
on Windows). A client given no token for a loopback URL reads the note of that port (only one written by
itself, of a process still alive) and the token file it names: the command line, ``deployer.Agent`` and the
Ansible modules alike. Anyone else needs the file (``--agent-token-file``): that is the point.

Standard library only: the client side runs in Ansible modules.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import sys
import urllib.parse
from typing import Any

from ..portable import PRIVATE, make_private

ENV = "DEPLOYER_RUNTIME_DIR"
LOOPBACK = ("127.0.0.1", "localhost", "::1")


def runtime_dir() -> str:
    """This user's folder for the notes of their running agents."""
    given = os.environ.get(ENV)
    if given:
        return given
    if os.name == "nt":
        base = os.environ.get("LOCALAPPDATA") or os.path.join(os.path.expanduser("~"), "AppData", "Local")
        return os.path.join(base, "deployer", "agents")
    xdg = os.environ.get("XDG_RUNTIME_DIR")
    if xdg:
        return os.path.join(xdg, "deployer")
    return os.path.join(os.path.expanduser("~"), ".local", "state", "deployer", "agents")


def token_file(agent_folder: str) -> str:
    return os.path.join(agent_folder, "token")


def ensure(agent_folder: str) -> tuple[str, bool]:
    """The generated token's file (made now, mode 0600 or on Windows an access list of its own, when there is
    none) and whether it was made now."""
    path = token_file(agent_folder)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o600)
    except FileExistsError:
        return path, False
    try:
        os.write(fd, (secrets.token_urlsafe(32) + "\n").encode())
        os.fsync(fd)
    finally:
        os.close(fd)
    if sys.platform == "win32":  # no modes there: an access list of its own (its folder's may let every user read)
        try:
            make_private(path)
        except OSError as e:
            os.unlink(path)
            raise OSError(e.errno, f"cannot keep the token file {path} to its owner: {e.strerror or e}") from None
    return path, True


# what keeps the token file to its user, as the agent says it
PROTECTION = PRIVATE


def _note(port: int) -> str:
    return os.path.join(runtime_dir(), f"agent-{port}.json")


def publish(url: str, path: str) -> str | None:
    """Leave the note for this user's clients; its path (None when the folder cannot be written: said)."""
    port = urllib.parse.urlsplit(url).port
    if port is None:
        return None
    note = _note(port)
    try:
        os.makedirs(os.path.dirname(note), mode=0o700, exist_ok=True)
        tmp = f"{note}.{os.getpid()}.tmp"
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_NOFOLLOW", 0), 0o600)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump({"url": url, "pid": os.getpid(), "token_file": os.path.abspath(path)}, f)
        os.replace(tmp, note)
    except OSError as e:
        print(
            f"agent: cannot leave the note for this user's clients in {os.path.dirname(note)}: "
            f"{e.strerror or e} (they need --agent-token-file {path})",
            file=sys.stderr,
            flush=True,
        )
        return None
    return note


def withdraw(note: str | None) -> None:
    """Remove the note (at the agent's stop), when it is still this process's."""
    if note is None:
        return
    with contextlib.suppress(OSError, ValueError):
        with open(note, encoding="utf-8") as f:
            mine = json.load(f).get("pid") == os.getpid()
        if mine:
            os.unlink(note)


def find(url: str) -> str | None:
    """The token of this user's agent at the loopback ``url``, from its note; None when there is none."""
    u = urllib.parse.urlsplit(url)
    try:
        port = u.port
    except ValueError:
        return None
    if (u.hostname or "") not in LOOPBACK or port is None:
        return None
    try:
        with open(_note(port), encoding="utf-8") as f:
            st = os.fstat(f.fileno())
            note: Any = json.load(f)
        if hasattr(os, "getuid") and st.st_uid != os.getuid():
            return None  # only a note this user wrote: another could point the token elsewhere
        if not isinstance(note, dict) or not _alive(int(note.get("pid") or 0)):
            return None
        if urllib.parse.urlsplit(str(note.get("url"))).scheme != u.scheme:
            return None
        with open(str(note["token_file"]), encoding="utf-8") as f:
            token = f.readline().strip()
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return token or None


def _alive(pid: int) -> bool:
    from ..portable import pid_alive

    return pid_alive(pid)
