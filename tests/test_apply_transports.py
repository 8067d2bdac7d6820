"""apply end to end over every transport: the simulator (or umodbus) on TLS, RTU, ASCII and rtu+tcp."""

from __future__ import annotations

import asyncio
import struct
from pathlib import Path

import pytest

from deployer.errors import Unreachable
from deployer.execute.device import apply_device
from deployer.execute.session import ApplyOptions
from deployer.profile import builtin_profile
from deployer.recipe.loader import load_recipe
from deployer.testing.simulator import Simulator, SimulatorThread
from deployer.transport import clients as tp
from tests.helpers import profile_from, umodbus_server

pytestmark = pytest.mark.timeout(60)


def test_tls_apply_with_client_certificate(pki: dict[str, str], tmp_path: Path) -> None:
    listen = f"tls://127.0.0.1:0?cert={pki['server_crt']}&key={pki['server_key']}&ca={pki['ca']}"
    (tmp_path / "r.yaml").write_text("recipe: r\nprofile: omron-m1\nparameters: {F07: 10 s}\n")
    rec = load_recipe(str(tmp_path / "r.yaml"))

    async def main() -> None:
        async with Simulator(builtin_profile("omron-m1"), listen=listen) as sim:
            port = sim.url.rsplit(":", 1)[1]  # the port the system gave
            url = tp.parse_url(
                f"tls://127.0.0.1:{port}?cert={pki['client_crt']}&key={pki['client_key']}&ca={pki['ca']}&timeout=2"
            )
            res = await apply_device(rec, url, 1, options=ApplyOptions(state_dir=str(tmp_path / ".d")))
            assert res.status == "ok", res
            assert sim.read("F07") == (0, 1000)
            wrong = tp.parse_url(
                f"tls://127.0.0.1:{port}?cert={pki['client_crt']}&key={pki['client_key']}"
                f"&ca={pki['other_ca']}&timeout=2"
            )
            with pytest.raises(Unreachable, match="TLS"):
                await tp.open_transport(wrong).connect()

    asyncio.run(main())


SIXTY = "profile: sixty\naddressing: address\nlimits: {max_frame_bytes: 64}\nparameters:\n" + "".join(
    f"  p{i}: {{register: {1000 + i}, type: uint16, max: 1000}}\n" for i in range(60)
)


def test_rtu_sixty_registers_in_three_writes(socat_pair: tuple[str, str], tmp_path: Path) -> None:
    """max_frame_bytes 64 -> at most 27 registers per FC16: 60 parameters go in exactly 3 requests."""
    a, b = socat_pair
    prof = profile_from(tmp_path, SIXTY, "sixty.yaml")
    (tmp_path / "r.yaml").write_text(
        "recipe: r\nprofile: sixty.yaml\nparameters:\n" + "".join(f"  p{i}: {i + 1}\n" for i in range(60))
    )
    rec = load_recipe(str(tmp_path / "r.yaml"))

    async def main() -> None:
        async with Simulator(prof, listen=f"rtu://{a}") as sim:
            res = await apply_device(
                rec,
                tp.parse_url(f"rtu://{b}?baudrate=19200&timeout=1"),
                1,
                options=ApplyOptions(state_dir=str(tmp_path / ".d")),
            )
            assert res.status == "ok", res
            assert [(e.address, e.count) for e in sim.log if e.function == 16] == [(1000, 27), (1027, 27), (1054, 6)]
            assert all(e.count <= 29 for e in sim.log if e.function == 3)  # reads fit in 64-byte frames too
            assert [sim.read(f"p{i}") for i in range(60)] == [(i + 1,) for i in range(60)]

    asyncio.run(main())


def test_ascii_apply_and_the_bytes_on_the_wire(socat_pair: tuple[str, str], tmp_path: Path) -> None:
    a, b = socat_pair
    (tmp_path / "r.yaml").write_text("recipe: r\nprofile: omron-m1\nparameters: {F07: 10 s}\n")
    rec = load_recipe(str(tmp_path / "r.yaml"))

    async def main() -> None:
        async with Simulator(builtin_profile("omron-m1"), listen=f"ascii://{a}") as sim:
            t = tp.open_transport(f"ascii://{b}?timeout=1")
            sent: list[bytes] = []
            t.on_frame = lambda direction, data: sent.append(data) if direction == "send" else None
            await t.connect()
            await t.write_registers(0x1102, [0, 1000], 1)
            await t.close()
            # LRC by hand: 01+10+11+02+00+02+04+00+00+03+E8 = 115h; -15h & FFh = EBh
            assert b"".join(sent) == b":01101102000204000003E8EB\r\n"
            assert sim.read("F07") == (0, 1000)
            sim.write("F07", (0, 0))
            res = await apply_device(
                rec, tp.parse_url(f"ascii://{b}?timeout=1"), 1, options=ApplyOptions(state_dir=str(tmp_path / ".d"))
            )
            assert res.status == "ok" and sim.read("F07") == (0, 1000)

    asyncio.run(main())


def test_rtu_over_tcp_gateway(tmp_path: Path) -> None:
    (tmp_path / "r.yaml").write_text(
        "recipe: r\nprofile: oriental-az\nparameters:\n"
        "  operation_data[3]: {starting_rate: 10000, stopping_rate: 20000, "
        "operating_current: 500}\n"
    )
    rec = load_recipe(str(tmp_path / "r.yaml"))

    async def main() -> None:
        async with Simulator(builtin_profile("oriental-az"), listen="rtu+tcp://127.0.0.1:0", units=(4,)) as sim:
            assert sim.url.startswith("rtu+tcp://")
            frames: list[bytes] = []
            t = tp.open_transport(sim.url + "?timeout=1")
            t.on_frame = lambda d, data: frames.append(data) if d == "send" else None
            await t.connect()
            await t.write_registers(6342, [0, 10000, 0, 20000, 0, 500], 4)
            await t.close()
            assert frames[0] == bytes.fromhex("04 10 18 C6 00 06 0C 00 00 27 10 00 00 4E 20 00 00 01 F4 6C A0")
            sim.write("operation_data[3].starting_rate", (0, 0), unit=4)
            res = await apply_device(rec, tp.parse_url(sim.url), 4, options=ApplyOptions(state_dir=str(tmp_path)))
            assert res.status == "ok" and sim.read("operation_data[3].starting_rate", 4) == (0, 10000)

    asyncio.run(main())


def test_apply_to_a_umodbus_server(tmp_path: Path) -> None:
    store: dict[int, int] = {0x1102: 0, 0x1103: 500}
    (tmp_path / "r.yaml").write_text("recipe: r\nprofile: omron-m1\nparameters: {F07: 10 s}\n")
    rec = load_recipe(str(tmp_path / "r.yaml"))
    with umodbus_server(store) as port:
        res = asyncio.run(
            apply_device(
                rec,
                tp.parse_url(f"tcp://127.0.0.1:{port}?timeout=2"),
                1,
                options=ApplyOptions(state_dir=str(tmp_path / ".d")),
            )
        )
    assert res.status == "ok", res
    assert (store[0x1102], store[0x1103]) == (0, 1000)
    f07 = res.parameters[0]
    assert f07.before_raw == (0, 500) and f07.after_raw == (0, 1000)
    assert struct.pack(">HH", *f07.after_raw) == bytes.fromhex("000003E8")


def test_simulator_thread_serves_plain_clients() -> None:
    with SimulatorThread(builtin_profile("omron-m1")) as sim:

        async def main() -> list[int]:
            t = tp.open_transport(sim.url)
            await t.connect()
            try:
                return await t.read_holding_registers(0x1102, 2, 1)
            finally:
                await t.close()

        assert asyncio.run(main()) == [0, 0]
