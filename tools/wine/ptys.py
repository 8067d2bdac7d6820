"""Null-modem COM port pairs for the suite under Wine: socat's pseudo-terminals, seen by Windows as COMn.

Wine opens ``COMn`` through the link ``$WINEPREFIX/dosdevices/comn``. A Windows process cannot run socat (Wine
starts a Linux program but hands back no handle to end it), so this server, on the Linux side, does it for the
tests (``tests/conftest.py``'s ``socat_pair``): ``make test-windows`` starts it and tells the suite its port in
``DEPLOYER_WINE_PTYS``. One TCP connection per pair, lines of text:

    pair            -> "COMa COMb"   a pair of free numbers from 20 up
    pair 5 6        -> "COM5 COM6"   those two (waits while another test has either)
    wire            -> "A2B B2A"     the bytes that went each way so far, in hex ("-" for none): socat's own
                                     record of the line (-r/-R), not deployer's
    (the connection closed)          socat ended, the links removed

    python3 tools/wine/ptys.py PREFIX     serves on 127.0.0.1, prints its port, ends on SIGTERM or stdin's end
"""

from __future__ import annotations

import signal
import socketserver
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

FIRST_FREE = 20  # pairs asked for without numbers: out of the way of the numbers tests name (COM5, COM10)
_busy: set[int] = set()
_cond = threading.Condition()
_running: set[subprocess.Popen[bytes]] = set()  # ended when the server ends, whatever its connections do


def _take(numbers: tuple[int, int] | None, timeout: float = 120) -> tuple[int, int]:
    deadline = time.monotonic() + timeout
    with _cond:
        while True:
            if numbers is None:
                n = FIRST_FREE
                while n in _busy or n + 1 in _busy:
                    n += 2
                got = (n, n + 1)
            else:
                got = numbers
            if not (set(got) & _busy):
                _busy.update(got)
                return got
            if not _cond.wait(timeout=max(0.0, deadline - time.monotonic())):
                raise TimeoutError(f"COM{got[0]}/COM{got[1]} still in use")


def _give(numbers: tuple[int, int]) -> None:
    with _cond:
        _busy.difference_update(numbers)
        _cond.notify_all()


class Pair(socketserver.StreamRequestHandler):
    prefix: Path

    def handle(self) -> None:
        proc: subprocess.Popen[bytes] | None = None
        numbers: tuple[int, int] | None = None
        work = Path(tempfile.mkdtemp(prefix="ptys-"))
        links: list[Path] = []
        try:
            for raw in self.rfile:
                words = raw.decode().split()
                if words[:1] == ["pair"] and proc is None:
                    numbers = _take((int(words[1]), int(words[2])) if len(words) == 3 else None)
                    links = [self.prefix / "dosdevices" / f"com{n}" for n in numbers]
                    for link in links:
                        link.unlink(missing_ok=True)
                    proc = subprocess.Popen(
                        [
                            "socat",
                            "-r",
                            str(work / "a2b"),
                            "-R",
                            str(work / "b2a"),
                            f"pty,raw,echo=0,link={links[0]}",
                            f"pty,raw,echo=0,link={links[1]}",
                        ],
                        stdout=subprocess.DEVNULL,
                        stderr=subprocess.DEVNULL,
                    )
                    _running.add(proc)
                    deadline = time.monotonic() + 10
                    while not all(link.is_symlink() for link in links) and time.monotonic() < deadline:
                        time.sleep(0.01)
                    ok = all(link.is_symlink() for link in links) and proc.poll() is None
                    self._say(f"COM{numbers[0]} COM{numbers[1]}" if ok else "error: socat did not make the pair")
                elif words[:1] == ["wire"]:
                    self._say(" ".join(_hex(work / f) for f in ("a2b", "b2a")))
                else:
                    self._say(f"error: {raw.decode().strip()!r}?")
        finally:
            if proc is not None:
                proc.terminate()
                proc.wait(timeout=10)
                _running.discard(proc)
            for link in links:
                link.unlink(missing_ok=True)
            for f in work.iterdir():
                f.unlink()
            work.rmdir()
            if numbers is not None:
                _give(numbers)

    def _say(self, line: str) -> None:
        self.wfile.write(line.encode() + b"\n")
        self.wfile.flush()


def _hex(path: Path) -> str:
    data = path.read_bytes() if path.exists() else b""
    return data.hex() or "-"


def _on_eof(server: socketserver.BaseServer) -> None:
    sys.stdin.read()
    server.shutdown()


class Server(socketserver.ThreadingTCPServer):
    daemon_threads = True
    allow_reuse_address = True


def main() -> int:
    prefix = Path(sys.argv[1]).resolve()
    (prefix / "dosdevices").mkdir(parents=True, exist_ok=True)
    handler = type("Handler", (Pair,), {"prefix": prefix})
    with Server(("127.0.0.1", 0), handler) as server:
        print(server.server_address[1], flush=True)
        signal.signal(signal.SIGTERM, lambda *_: threading.Thread(target=server.shutdown).start())
        # ends with the shell that started it too: its stdin is that shell's pipe
        threading.Thread(target=_on_eof, args=(server,), daemon=True).start()
        server.serve_forever()
    for proc in list(_running):
        proc.terminate()
    for link in (prefix / "dosdevices").glob("com*"):
        if link.is_symlink() and str(link.readlink()).startswith("/dev/pts/"):
            link.unlink()
    return 0


if __name__ == "__main__":
    sys.exit(main())
