"""Portability: what runs the same on POSIX, Windows and macOS (docs/windows.md)."""

from __future__ import annotations

import pytest

from deployer.state import lock


def test_the_lock_folder_does_not_follow_tmpdir(monkeypatch: pytest.MonkeyPatch) -> None:
    # a service, a login shell and each macOS user see other TMPDIRs: they must still share locks
    monkeypatch.delenv(lock.ENV, raising=False)
    monkeypatch.setenv("TMPDIR", "/somewhere/else")
    assert lock.lock_dir() == lock.default_lock_dir() == "/tmp/deployer-locks"
    monkeypatch.setenv(lock.ENV, "/srv/locks")
    assert lock.lock_dir() == "/srv/locks"
