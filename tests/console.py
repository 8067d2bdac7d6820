"""Ctrl-C and Ctrl-Break as a console hands them to a program, for a ``deployer`` child process on any system.

Windows sends no signal from one process to another: a console turns Ctrl-C and Ctrl-Break into SIGINT and SIGBREAK
in the program itself, from a thread of the program's own (the C runtime's console handler raises the signal
there). This module does the same inside the child: ``python -m tests.console deployer ARGS`` runs
``deployer ARGS``; each line ``SIGINT`` or ``SIGBREAK`` on its standard input raises that signal from another
thread, as the console's handler would. ``press(proc, "SIGBREAK")`` types it.
"""

from __future__ import annotations

import os
import runpy
import signal
import subprocess
import sys
import threading

KEYS = {"SIGINT": "Ctrl-C", "SIGBREAK": "Ctrl-Break"}


def start(*args: str, cwd: str | None = None) -> subprocess.Popen[str]:
    """``deployer ARGS`` in a child whose console keys are ``press``'s: stdout and stderr piped, as text."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)}
    return subprocess.Popen(
        [sys.executable, "-m", "tests.console", "deployer", *args],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=cwd,
        env=env,
    )


def press(proc: subprocess.Popen[str], key: str) -> None:
    """Ctrl-C (``SIGINT``) or, where the system has it, Ctrl-Break (``SIGBREAK``) in ``proc``'s console."""
    assert proc.stdin is not None and key in KEYS
    proc.stdin.write(key + "\n")
    proc.stdin.flush()


def keys() -> list[str]:
    """The console keys this system has: Ctrl-C everywhere, Ctrl-Break on Windows."""
    return [k for k in KEYS if hasattr(signal, k)]


def _listen() -> None:
    for line in sys.stdin:
        name = line.strip()
        if name in KEYS and hasattr(signal, name):
            signal.raise_signal(getattr(signal, name))


if __name__ == "__main__":
    assert sys.argv[1] == "deployer"
    threading.Thread(target=_listen, daemon=True).start()
    sys.argv = ["deployer", *sys.argv[2:]]
    runpy.run_module("deployer", run_name="__main__", alter_sys=True)
