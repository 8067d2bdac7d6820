"""COM port pairs for the suite on Windows under Wine (``make test-windows``): socat's pseudo-terminals, made on the
Linux side by ``tools/wine/ptys.py`` and seen here as ``COMn`` (Wine's ``dosdevices/comn`` links)."""

from __future__ import annotations

import os
import socket

BROKER = "DEPLOYER_WINE_PTYS"  # the port tools/wine/ptys.py serves on, set by tools/wine/wine.sh


def available() -> bool:
    return bool(os.environ.get(BROKER))


class ComPair:
    """A null-modem pair of COM ports for as long as the object is open: ``a`` and ``b`` (``COM20``...), or the
    numbers asked for (waits while another test has them)."""

    def __init__(self, numbers: tuple[int, int] | None = None) -> None:
        self._sock = socket.create_connection(("127.0.0.1", int(os.environ[BROKER])), timeout=150)
        self._file = self._sock.makefile("rw", encoding="ascii", newline="\n")
        got = self._ask("pair" + ("" if numbers is None else f" {numbers[0]} {numbers[1]}")).split()
        if len(got) != 2 or not all(g.startswith("COM") for g in got):
            self.close()
            raise AssertionError(f"tools/wine/ptys.py: {' '.join(got)}")
        self.a, self.b = got

    def wire(self) -> tuple[bytes, bytes]:
        """What went a -> b and b -> a on the line so far, as socat recorded it (not as deployer says it sent)."""
        a2b, b2a = self._ask("wire").split()
        return (b"" if a2b == "-" else bytes.fromhex(a2b)), (b"" if b2a == "-" else bytes.fromhex(b2a))

    def _ask(self, line: str) -> str:
        self._file.write(line + "\n")
        self._file.flush()
        return self._file.readline().strip()

    def close(self) -> None:
        self._file.close()
        self._sock.close()

    def __enter__(self) -> ComPair:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()
