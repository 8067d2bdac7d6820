"""File locks the operating system drops when their holder dies: the backends under ``state.lock``.

Two backends, one chosen at run time (``backend()``), never imported where they do not exist:

``flock`` (POSIX: Linux, macOS, the BSDs)
    ``fcntl.flock`` on the whole file, shared or exclusive.
``range`` (Windows; also Linux when ``fcntl`` cannot be imported)
    a lock on one byte far past the record the file holds (``OFFSET``), shared or exclusive:
    ``LockFileEx`` on Windows, open-file-description locks (``F_OFD_SETLK``, called through ctypes)
    on Linux. Both belong to the open file, not the process, and are dropped when it is closed and
    when the process dies, however it dies; the byte is past the record because Windows' locks are
    mandatory (nobody could read a locked record to say who holds it). ``state.lock`` never removes
    a lock file (Windows refuses to remove an open one anyway): a released one is emptied and stays.

Never a lock file whose mere existence is the lock: a holder killed mid-run would leave it behind.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import os
import sys
import time
from typing import Any

OFFSET = 1 << 30  # the byte the range backend locks: past any record, so records stay readable
_BUSY = (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK)


class Backend:
    name = ""

    def try_lock(self, fd: int, *, shared: bool = False) -> bool:
        """Take the lock without waiting: False when another open file holds it (OSError: cannot lock)."""
        raise NotImplementedError

    def unlock(self, fd: int) -> None:
        raise NotImplementedError

    def lock(self, fd: int, *, poll: float = 0.02) -> None:
        """Exclusive, waiting as long as it takes."""
        while not self.try_lock(fd):
            time.sleep(poll)


class Flock(Backend):
    name = "flock"

    def __init__(self) -> None:
        import fcntl

        self._fcntl: Any = fcntl

    def try_lock(self, fd: int, *, shared: bool = False) -> bool:
        f = self._fcntl
        try:
            f.flock(fd, (f.LOCK_SH if shared else f.LOCK_EX) | f.LOCK_NB)
        except BlockingIOError:
            return False
        return True

    def unlock(self, fd: int) -> None:
        self._fcntl.flock(fd, self._fcntl.LOCK_UN)

    def lock(self, fd: int, *, poll: float = 0.02) -> None:
        self._fcntl.flock(fd, self._fcntl.LOCK_EX)


class Range(Backend):
    """One byte at OFFSET, through ``_primitive`` (LockFileEx or F_OFD_SETLK)."""

    name = "range"

    def __init__(self) -> None:
        self._lock = _windows_range() if sys.platform == "win32" else _ofd_range()

    def try_lock(self, fd: int, *, shared: bool = False) -> bool:
        return bool(self._lock(fd, "shared" if shared else "exclusive"))

    def unlock(self, fd: int) -> None:
        self._lock(fd, "unlock")


def _windows_range() -> Any:
    if sys.platform == "win32":  # the branch mypy checks only for Windows
        import msvcrt
        from ctypes import wintypes

        class Overlapped(ctypes.Structure):
            _fields_ = [
                ("Internal", ctypes.c_void_p),
                ("InternalHigh", ctypes.c_void_p),
                ("Offset", wintypes.DWORD),
                ("OffsetHigh", wintypes.DWORD),
                ("hEvent", wintypes.HANDLE),
            ]

        kernel32 = ctypes.WinDLL("kernel32", use_last_error=True)
        kernel32.LockFileEx.argtypes = [
            wintypes.HANDLE,
            wintypes.DWORD,
            wintypes.DWORD,
            wintypes.DWORD,
            wintypes.DWORD,
            ctypes.POINTER(Overlapped),
        ]
        kernel32.LockFileEx.restype = wintypes.BOOL
        kernel32.UnlockFileEx.argtypes = [
            wintypes.HANDLE,
            wintypes.DWORD,
            wintypes.DWORD,
            wintypes.DWORD,
            ctypes.POINTER(Overlapped),
        ]
        kernel32.UnlockFileEx.restype = wintypes.BOOL
        fail_immediately, exclusive, error_lock_violation, error_not_locked = 0x1, 0x2, 33, 158

        def call(fd: int, what: str) -> bool:
            handle = wintypes.HANDLE(msvcrt.get_osfhandle(fd))
            ov = Overlapped(0, 0, OFFSET & 0xFFFFFFFF, OFFSET >> 32, None)
            if what == "unlock":
                if not kernel32.UnlockFileEx(handle, 0, 1, 0, ctypes.byref(ov)):
                    err = ctypes.get_last_error()
                    if err != error_not_locked:
                        raise ctypes.WinError(err)
                return True
            flags = fail_immediately | (exclusive if what == "exclusive" else 0)
            if kernel32.LockFileEx(handle, flags, 0, 1, 0, ctypes.byref(ov)):
                return True
            err = ctypes.get_last_error()
            if err == error_lock_violation:
                return False
            raise ctypes.WinError(err)

        return call
    raise OSError(errno.ENOSYS, "LockFileEx exists only on Windows")


def _ofd_range() -> Any:
    """F_OFD_SETLK through the C library (Linux 3.15 and later, 64-bit): the lock an open file owns."""
    if not sys.platform.startswith("linux") or ctypes.sizeof(ctypes.c_void_p) != 8:
        raise OSError(errno.ENOSYS, "no file lock on this system: fcntl cannot be imported")

    class Flock64(ctypes.Structure):
        _fields_ = [
            ("l_type", ctypes.c_short),
            ("l_whence", ctypes.c_short),
            ("l_start", ctypes.c_int64),
            ("l_len", ctypes.c_int64),
            ("l_pid", ctypes.c_int32),
        ]

    libc = ctypes.CDLL(None, use_errno=True)
    fcntl_ = libc.fcntl
    fcntl_.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.POINTER(Flock64)]
    fcntl_.restype = ctypes.c_int
    f_ofd_setlk, f_rdlck, f_wrlck, f_unlck = 37, 0, 1, 2
    kinds = {"shared": f_rdlck, "exclusive": f_wrlck, "unlock": f_unlck}

    def call(fd: int, what: str) -> bool:
        lk = Flock64(kinds[what], os.SEEK_SET, OFFSET, 1, 0)
        if fcntl_(fd, f_ofd_setlk, ctypes.byref(lk)) == 0:
            return True
        err = ctypes.get_errno()
        if err in _BUSY and what != "unlock":
            return False
        raise OSError(err, os.strerror(err))

    return call


_chosen: Backend | None = None


def backend() -> Backend:
    """``flock`` where ``fcntl`` can be imported, else ``range`` (OSError when neither exists here)."""
    global _chosen
    if _chosen is None:
        try:
            _chosen = Flock()
        except ImportError:
            _chosen = Range()
    return _chosen


def lock_exclusive(fd: int) -> None:
    """Wait for the exclusive lock of an open file (learned limits: a short critical section)."""
    backend().lock(fd)


def unlock(fd: int) -> None:
    with contextlib.suppress(OSError):
        backend().unlock(fd)
