"""A syslog receiver as a process of its own, for the forwarding tests where rsyslog is not installed and for
the outage test (killed and started again on the same port).

    python tests/syslog_receiver.py PORT OUT_FILE

Reads RFC 6587 octet-counted frames over TCP, checks each is an RFC 5424 message (``<PRI>1 TIMESTAMP HOST APP
PROCID MSGID [SD] MSG``), and appends it as one line to OUT_FILE (flushed per message). A malformed frame ends
the connection and is written as ``BAD ...``. Prints ``listening`` once it accepts connections.
"""

from __future__ import annotations

import asyncio
import re
import sys

HEADER = re.compile(rb"^<(\d{1,3})>1 (\S+) (\S+) (\S+) (\S+) (\S+) (\[.*?[^\\]\]|-) ")


async def main(port: int, out: str) -> None:
    f = open(out, "ab", buffering=0)  # noqa: SIM115 - open for the process's life

    async def client(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                length = await reader.readuntil(b" ")
                if not length[:-1].isdigit():
                    f.write(b"BAD length " + length[:40] + b"\n")
                    return
                msg = await reader.readexactly(int(length[:-1]))
                if HEADER.match(msg) is None:
                    f.write(b"BAD message " + msg[:80] + b"\n")
                    return
                f.write(msg.replace(b"\n", b"\\n") + b"\n")
        except (asyncio.IncompleteReadError, ConnectionError):
            return
        finally:
            writer.close()

    server = await asyncio.start_server(client, "127.0.0.1", port, reuse_address=True)
    print("listening", flush=True)
    async with server:
        await server.serve_forever()


if __name__ == "__main__":
    asyncio.run(main(int(sys.argv[1]), sys.argv[2]))
