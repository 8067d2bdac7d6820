"""What differs between POSIX (Linux, macOS) and Windows, chosen at run time, never at import.

deployer imports nothing POSIX-only (``fcntl``, ``pwd``, ``resource``, ``termios``) at module level:
each such piece is a function here (or ``state.oslock`` for file locks) that asks what the running
system has. docs/windows.md says what each gives on each system and how it is tested.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import os
import signal
import stat
import sys
import threading
import time
from collections.abc import Callable

WINDOWS = sys.platform == "win32"

# Flags that only some systems have: 0 where absent, so ``os.open(path, A | O_NOFOLLOW)`` runs everywhere.
# O_BINARY: without it Windows' os.write turns "\n" into "\r\n" (a snapshot's digest would not match).
O_BINARY: int = getattr(os, "O_BINARY", 0)
# Windows: descriptors are never inherited by children anyway (PEP 446), so no O_CLOEXEC is lost.
O_CLOEXEC: int = getattr(os, "O_CLOEXEC", 0)
# Windows has no FIFOs at a file path (named pipes live under \\.\pipe\), so no open can block there.
O_NONBLOCK: int = getattr(os, "O_NONBLOCK", 0)
O_NOFOLLOW: int = getattr(os, "O_NOFOLLOW", 0)


def user_name() -> str:
    """The login name (not the uid): who ran it is what an audit trail is for.

    ``getpass.getuser()`` reads LOGNAME, USER, LNAME, USERNAME (Windows sets USERNAME), then the
    password database where there is one; a container's uid without a name gives the number.
    """
    import getpass

    try:
        name = getpass.getuser()
    except (KeyError, OSError, ImportError):  # OSError from 3.13, KeyError/ImportError before
        name = ""
    if name:
        return name
    getuid = getattr(os, "getuid", None)
    return str(getuid()) if getuid is not None else "unknown"


def owner_is_me(st: os.stat_result) -> bool:
    """Whether this process's user owns the file (False where the system has no uids: Windows)."""
    getuid = getattr(os, "getuid", None)
    return getuid is not None and st.st_uid == getuid()


def has_modes() -> bool:
    """Whether files have owners and Unix permission bits here (POSIX; Windows has ACLs instead)."""
    return hasattr(os, "getuid")


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this machine (someone else's counts: it is alive).

    Never ``os.kill(pid, 0)`` on Windows: there it terminates the process instead of probing it.
    """
    if pid <= 0:
        return False
    if WINDOWS:
        return _windows_pid_alive(pid)
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # someone else's process, alive
    except OSError:
        return False
    return True


def _windows_pid_alive(pid: int) -> bool:
    """OpenProcess + GetExitCodeProcess: a process handle for a gone PID either fails or says it exited."""
    if sys.platform == "win32":  # the branch mypy checks only for Windows
        import ctypes
        from ctypes import wintypes

        kernel32 = ctypes.WinDLL("kernel32", use_last_error=True)
        kernel32.OpenProcess.restype = wintypes.HANDLE
        kernel32.OpenProcess.argtypes = [wintypes.DWORD, wintypes.BOOL, wintypes.DWORD]
        kernel32.GetExitCodeProcess.argtypes = [wintypes.HANDLE, ctypes.POINTER(wintypes.DWORD)]
        kernel32.CloseHandle.argtypes = [wintypes.HANDLE]
        process_query_limited_information, still_active, error_access_denied = 0x1000, 259, 5
        handle = kernel32.OpenProcess(process_query_limited_information, False, pid)
        if not handle:
            return ctypes.get_last_error() == error_access_denied  # exists, but not ours to ask
        try:
            code = wintypes.DWORD()
            if not kernel32.GetExitCodeProcess(handle, ctypes.byref(code)):
                return True
            return code.value == still_active
        finally:
            kernel32.CloseHandle(handle)
    return False


def process_start(pid: int) -> float | None:
    """When process ``pid`` started, in a unit of this system's own (Linux: seconds after boot; Windows:
    seconds since the epoch), for telling a process from a later one given its PID; None where the
    system does not say (macOS) or the process is gone."""
    if WINDOWS:
        return _windows_process_start(pid)
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            data = f.read()
    except OSError:
        return None
    sysconf = getattr(os, "sysconf", None)
    try:  # the command name may hold spaces and parentheses: the fields follow the last ')'
        ticks = int(data[data.rindex(b")") + 2 :].split()[19])
        hz = int(sysconf("SC_CLK_TCK")) if sysconf is not None else 100  # USER_HZ: 100 on every Linux ABI
    except (ValueError, IndexError, OSError):
        return None
    return ticks / hz


def _windows_process_start(pid: int) -> float | None:
    """GetProcessTimes' creation time (100 ns ticks since 1601), in seconds since the epoch."""
    if sys.platform == "win32":  # the branch mypy checks only for Windows
        import ctypes
        from ctypes import wintypes

        kernel32 = ctypes.WinDLL("kernel32", use_last_error=True)
        kernel32.OpenProcess.restype = wintypes.HANDLE
        kernel32.OpenProcess.argtypes = [wintypes.DWORD, wintypes.BOOL, wintypes.DWORD]
        kernel32.GetProcessTimes.argtypes = [wintypes.HANDLE] + [ctypes.POINTER(wintypes.FILETIME)] * 4
        kernel32.CloseHandle.argtypes = [wintypes.HANDLE]
        handle = kernel32.OpenProcess(0x1000, False, pid)  # PROCESS_QUERY_LIMITED_INFORMATION
        if not handle:
            return None
        try:
            times = [wintypes.FILETIME() for _ in range(4)]
            if not kernel32.GetProcessTimes(handle, *(ctypes.byref(t) for t in times)):
                return None
            ticks = (times[0].dwHighDateTime << 32) | times[0].dwLowDateTime
            return ticks / 1e7 - 11644473600.0
        finally:
            kernel32.CloseHandle(handle)
    return None


def fchmod(fd: int, mode: int) -> None:
    """``os.fchmod`` where it exists (POSIX; Windows only from Python 3.13, where it sets read-only alone)."""
    f = getattr(os, "fchmod", None)
    if f is not None and not WINDOWS:
        f(fd, mode)


# a secret file's access list on Windows: its owner, SYSTEM and the administrators, not inherited from its folder
PRIVATE_SDDL = "D:P(A;;FA;;;OW)(A;;FA;;;SY)(A;;FA;;;BA)"


# what ``make_private`` does here, for messages
PRIVATE = "only its owner and the administrators may read it" if sys.platform == "win32" else "mode 0600"


def make_private(path: str) -> None:
    """Let nobody but its user (and the system's administrators) read ``path`` (``PRIVATE`` says how).

    POSIX: mode 0600. Windows has no modes: the file gets an access list of its own (``PRIVATE_SDDL``), as
    OpenSSH for Windows wants of a private key, whatever the folder would have handed down (a state folder in
    C:\\site lets every local user read). Raises OSError when the system refuses."""
    if sys.platform == "win32":  # the branch mypy checks only for Windows
        import ctypes

        advapi32 = ctypes.WinDLL("advapi32", use_last_error=True)
        kernel32 = ctypes.WinDLL("kernel32", use_last_error=True)
        sd, dacl = ctypes.c_void_p(), ctypes.c_void_p()
        present, defaulted = ctypes.c_int(), ctypes.c_int()
        if not advapi32.ConvertStringSecurityDescriptorToSecurityDescriptorW(
            ctypes.c_wchar_p(PRIVATE_SDDL), 1, ctypes.byref(sd), None
        ):
            raise ctypes.WinError(ctypes.get_last_error())
        try:
            if not advapi32.GetSecurityDescriptorDacl(
                sd, ctypes.byref(present), ctypes.byref(dacl), ctypes.byref(defaulted)
            ):
                raise ctypes.WinError(ctypes.get_last_error())
            # SE_FILE_OBJECT; DACL_SECURITY_INFORMATION | PROTECTED_DACL_SECURITY_INFORMATION (not inherited)
            err = advapi32.SetNamedSecurityInfoW(
                ctypes.c_wchar_p(path), 1, 0x00000004 | 0x80000000, None, None, dacl, None
            )
            if err:
                raise ctypes.WinError(err)
        finally:
            kernel32.LocalFree(sd)
        return
    os.chmod(path, 0o600)


def open_nofollow(path: str, flags: int, mode: int = 0o666) -> int:
    """``os.open`` that never goes through a symbolic link at ``path`` (OSError ELOOP if one is there).

    POSIX: O_NOFOLLOW, which the kernel checks. Where there is no O_NOFOLLOW (Windows): the path is
    refused when ``lstat`` shows a link or reparse point (a junction), and after opening, the file
    opened must be the one at the path (same device and file id), so a link planted in between is
    found too; an O_EXCL open never follows a link in the first place.
    """
    if O_NOFOLLOW:
        return os.open(path, flags | O_NOFOLLOW, mode)
    with contextlib.suppress(FileNotFoundError):
        if is_link(os.lstat(path)):
            raise OSError(errno.ELOOP, "it is a symbolic link", path)
    fd = os.open(path, flags, mode)
    try:
        st, opened = os.lstat(path), os.fstat(fd)
        if is_link(st) or not same_file(st, opened):
            raise OSError(errno.ELOOP, "it is a symbolic link", path)
    except BaseException:
        os.close(fd)
        raise
    return fd


def same_file(a: os.stat_result, b: os.stat_result) -> bool:
    """Whether two stat results are of one file: same device and file id (where a system leaves either
    at 0, what is known must agree: a file id Windows did not fill in never makes two files of one)."""
    return all(x == y for x, y in ((a.st_dev, b.st_dev), (a.st_ino, b.st_ino)) if x and y)


def still_at(path: str, st: os.stat_result) -> bool:
    """Whether the file ``st`` describes is the one at ``path`` now (a link there is not followed); False when
    nothing is there: a lock taken on a file someone removed or replaced meanwhile holds nothing."""
    try:
        return same_file(os.stat(path, follow_symlinks=False), st)
    except OSError:
        return False


def is_link(st: os.stat_result) -> bool:
    reparse = getattr(stat, "FILE_ATTRIBUTE_REPARSE_POINT", 0)
    return stat.S_ISLNK(st.st_mode) or bool(reparse and getattr(st, "st_file_attributes", 0) & reparse)


def fsync_dir(folder: str) -> bool:
    """Make a folder's entries durable (new and renamed names survive a crash); False where the system
    cannot (Windows opens no folder as a file: NTFS journals its metadata itself, so a rename there is
    as durable as the volume's journal, not promised by an fsync). OSError when the fsync fails."""
    if WINDOWS:
        return False
    fd = os.open(folder, os.O_RDONLY | O_CLOEXEC)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    return True


def replace(src: str, dst: str, *, attempts: int = 20, pause: float = 0.05) -> None:
    """``os.replace``; on Windows, retried for about a second while another process holds ``dst``
    open without sharing deletes (an editor, a virus scanner, the indexer): PermissionError after."""
    for i in range(attempts):
        try:
            os.replace(src, dst)
            return
        except PermissionError:
            if not WINDOWS or i == attempts - 1:
                raise
            time.sleep(pause)


# Windows opens a device, not a file, for these names, whatever the extension ("con.yaml" is the console)
RESERVED_NAMES = frozenset(
    {
        "CON",
        "PRN",
        "AUX",
        "NUL",
        "CONIN$",
        "CONOUT$",
        *(f"{p}{n}" for p in ("COM", "LPT") for n in [*"123456789", "¹", "²", "³"]),
    }
)
NAME_LIMIT = 100  # characters of a file name made from a device or recipe name (Windows paths: 260 in all)


def reserved_name(path: str) -> str | None:
    """The Windows device name a path's last part is (``CON`` for ``out\\con.json``), or None."""
    last = path.rstrip("/\\").replace("\\", "/").rsplit("/", 1)[-1]  # either separator: Windows takes both
    stem = last.split(".")[0].rstrip(" ").upper()
    return stem if stem in RESERVED_NAMES else None


def file_name(name: str, limit: int = NAME_LIMIT) -> str:
    """``name`` as a file name valid on every system, the same everywhere (a snapshot made on Linux
    has the name it would have on Windows): letters, digits, ``-``, ``_`` and ``.`` (others become
    ``_``); no trailing dot or space (Windows drops them); a Windows device name as the part before
    the first dot (``CON``, ``aux.x``, ``COM1``) gets a ``_`` in front; at most ``limit`` characters
    and as many bytes in UTF-8 (a longer name keeps its start and gets a hash of the whole, so two long
    names stay apart)."""
    import hashlib

    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in name).rstrip(". ") or "_"
    if safe.split(".")[0].upper() in RESERVED_NAMES:
        safe = "_" + safe
    if len(safe) > limit or len(safe.encode()) > limit:  # bytes too: Linux allows 255 bytes, a CJK letter is 3
        cut = safe[: limit - 9]
        while len(cut.encode()) > limit - 9:
            cut = cut[:-1]
        safe = cut.rstrip(". ") + "-" + hashlib.sha256(name.encode("utf-8", "surrogatepass")).hexdigest()[:8]
    return safe


def path_error(e: OSError) -> str | None:
    """What a path's OSError means when it is about the path itself (too long), else None."""
    if e.errno == errno.ENAMETOOLONG or getattr(e, "winerror", None) == 206:  # ERROR_FILENAME_EXCED_RANGE
        where = f" ({len(str(e.filename))} characters)" if e.filename else ""
        return f"the path is too long{where}" + (
            "; Windows allows 259 characters unless long paths are "
            "enabled (LongPathsEnabled), or use a shorter --state folder"
            if WINDOWS
            else ""
        )
    return None


def can_fork() -> bool:
    """Whether this system forks processes safely for deployer's workers: Linux (Windows has no fork, and
    macOS's system libraries are not safe to use in a forked child)."""
    return sys.platform.startswith("linux") and hasattr(os, "fork")


def fork() -> int:
    """``os.fork`` where ``can_fork()``; OSError elsewhere."""
    if sys.platform == "win32" or not hasattr(os, "fork"):
        raise OSError(errno.ENOSYS, "this system cannot fork a process")
    return os.fork()


def child_exit_code(pid: int) -> int | None:
    """The exit code of this process's forked child ``pid`` once it ended (it is reaped then), None while it runs
    (-1 once reaped before: nobody else waits for a forked child)."""
    if sys.platform == "win32":
        raise OSError(errno.ENOSYS, "no forked children on Windows")
    try:
        got, status = os.waitpid(pid, os.WNOHANG)
    except ChildProcessError:
        return -1
    return os.waitstatus_to_exitcode(status) if got else None


def kill_child(pid: int) -> None:
    """End this process's forked child ``pid`` at once (SIGKILL; ``child_exit_code`` reaps it)."""
    if sys.platform == "win32":
        raise OSError(errno.ENOSYS, "no forked children on Windows")
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGKILL)


def raise_open_files(need: int) -> int | None:
    """Raise the soft open-file limit towards ``need`` (POSIX ``resource``); the hard limit when it is
    below ``need``, else None.

    Windows has no such limit for sockets (the C runtime's 8192 descriptors are for files), so nothing
    to do there.
    """
    if sys.platform == "win32":
        return None
    try:
        import resource
    except ImportError:
        return None
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft >= need:
        return None
    if hard != resource.RLIM_INFINITY and hard < need:
        return int(hard)
    resource.setrlimit(resource.RLIMIT_NOFILE, (need if hard == resource.RLIM_INFINITY else hard, hard))
    return None


def on_signals(
    loop: object, signals: tuple[signal.Signals, ...], handler: Callable[[signal.Signals], None]
) -> Callable[[], None]:
    """Call ``handler(sig)`` in the event loop's thread when one of ``signals`` arrives; returns the undo.

    ``loop.add_signal_handler`` where the loop has it (POSIX); else (Windows' event loops raise
    NotImplementedError) ``signal.signal`` with a handler that hands over to the loop: on Windows
    Ctrl-C is SIGINT, and the proactor loop wakes for it. Main thread only (as signals are): elsewhere
    nothing is installed. Signals the system lacks are skipped.
    """
    import asyncio

    assert isinstance(loop, asyncio.AbstractEventLoop)
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    undo: list[Callable[[], object]] = []
    quiet = False
    for sig in signals:
        try:
            loop.add_signal_handler(sig, handler, sig)
            undo.append(functools.partial(loop.remove_signal_handler, sig))
            continue
        except (NotImplementedError, AttributeError):
            pass

        def on(signum: int, _frame: object, s: signal.Signals = sig) -> None:
            loop.call_soon_threadsafe(handler, s)

        try:
            old = signal.signal(sig, on)
        except (ValueError, OSError):
            continue
        undo.append(functools.partial(signal.signal, sig, old))
        quiet = True
    if quiet:  # handed over through the loop's wakeup socket (the proactor loop's way)
        _quiet_wakeup()

    def restore() -> None:
        for u in reversed(undo):
            with contextlib.suppress(Exception):
                u()

    return restore


def _quiet_wakeup() -> None:
    """The loop's signal wakeup socket, without the warning for a full one. The proactor loop (Windows) wakes on a
    signal through a byte sent to its socket; a full socket means the loop has bytes to wake on already, yet
    CPython prints "Exception ignored when trying to send to the signal wakeup fd" (BlockingIOError) into the
    console (seen on Ctrl-Break under load). ``warn_on_full_buffer=False`` is the documented way for a socket
    used only to wake up; other errors are still said."""
    fd = signal.set_wakeup_fd(-1)
    if fd != -1:
        signal.set_wakeup_fd(fd, warn_on_full_buffer=False)


def interrupt_signals() -> tuple[signal.Signals, ...]:
    """SIGINT (Ctrl-C), and SIGTERM and SIGBREAK (Windows' Ctrl-Break) where they exist."""
    return tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGBREAK") if hasattr(signal, n))


def write_all(fd: int, data: bytes) -> None:
    """All of ``data`` (short writes resumed)."""
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


def pread(fd: int, size: int, offset: int) -> bytes:
    """Up to ``size`` bytes at ``offset`` in one call where the system has one (Windows has no pread: a seek,
    then a read)."""
    if sys.platform != "win32" and hasattr(os, "pread"):
        return os.pread(fd, size, offset)
    os.lseek(fd, offset, os.SEEK_SET)
    return os.read(fd, size)


def pwrite_all(fd: int, data: bytes, offset: int) -> None:
    """All of ``data`` at ``offset`` (not for a file opened to append), in one call where the system allows."""
    if sys.platform != "win32" and hasattr(os, "pwrite"):
        view = memoryview(data)
        while view:
            n = os.pwrite(fd, view, offset)
            view, offset = view[n:], offset + n
        return
    os.lseek(fd, offset, os.SEEK_SET)
    write_all(fd, data)


def writev_all(fd: int, pieces: list[bytes]) -> None:
    """All of ``pieces``, in order, in as few writev calls as the system allows (short writes resumed);
    one write each where there is no writev (Windows)."""
    if sys.platform == "win32" or not hasattr(os, "writev"):
        for piece in pieces:
            write_all(fd, piece)
        return
    batch = max(1, min(1024, os.sysconf("SC_IOV_MAX")))
    i = 0
    while i < len(pieces):
        chunk = pieces[i : i + batch]
        n = os.writev(fd, chunk)
        total = sum(len(c) for c in chunk)
        if n == total:
            i += batch
            continue
        for k, c in enumerate(chunk):  # a short write: drop what was written, go on from there
            if n < len(c):
                pieces[i + k] = c[n:]
                i += k
                break
            n -= len(c)
