"""Python runs this at start-up in the POSIX-less test's processes (tests/test_posixless.py, PYTHONPATH):
from here on this Linux Python lacks what Windows' Python lacks, and deployer must run without it.

- the POSIX-only modules cannot be imported (``fcntl``, ``pwd``, ``grp``, ``resource``, ``termios``);
- ``os`` has no uids, no ``fchmod``, no O_NOFOLLOW/O_CLOEXEC/O_NONBLOCK, no ``pread``/``writev``/``sysconf``,
  no ``fork`` or ``uname``; ``signal`` has no SIGHUP, SIGUSR1, SIGKILL, SIGALRM and their kind;
- the event loop's ``add_signal_handler`` raises NotImplementedError, as Windows' loops do.

What it cannot make Windows-like: POSIX file semantics (a file in use can be removed), the path syntax,
and the lock primitive under the ``range`` backend (F_OFD_SETLK here, LockFileEx there).
"""

import asyncio.unix_events
import contextlib
import os
import signal
import sys

# Third-party code picks its platform module by sys.platform, which stays "linux" here: platformdirs
# (pint imports it when no units cache is there yet, as on a fresh machine) takes its Unix module and
# uids from os; on Windows it takes its Windows module and never asks. Loaded before the uids go.
with contextlib.suppress(ImportError):
    import platformdirs  # noqa: F401

for _name in ("fcntl", "pwd", "grp", "resource", "termios"):
    sys.modules[_name] = None  # type: ignore[assignment]  # import raises ModuleNotFoundError

for _name in (
    "getuid",
    "geteuid",
    "getgid",
    "getegid",
    "fchmod",
    "O_NOFOLLOW",
    "O_CLOEXEC",
    "O_NONBLOCK",
    "pread",
    "writev",
    "sysconf",
    "fork",
    "uname",
    "getpgid",
    "setsid",
    "killpg",
):
    if hasattr(os, _name):
        delattr(os, _name)

for _name in (
    "SIGHUP",
    "SIGUSR1",
    "SIGUSR2",
    "SIGKILL",
    "SIGALRM",
    "SIGQUIT",
    "alarm",
    "setitimer",
    "pthread_kill",
    "pthread_sigmask",
):  # Windows' signal module has none of these
    if hasattr(signal, _name):
        delattr(signal, _name)


def _no_signal_handlers(*args: object, **kwargs: object) -> None:
    raise NotImplementedError  # what asyncio's Windows event loops raise


asyncio.unix_events._UnixSelectorEventLoop.add_signal_handler = _no_signal_handlers  # type: ignore[method-assign]
asyncio.unix_events._UnixSelectorEventLoop.remove_signal_handler = _no_signal_handlers  # type: ignore[method-assign,assignment]
