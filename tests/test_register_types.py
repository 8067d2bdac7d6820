"""Coils, discrete inputs and input registers: profiles, plans, frames, apply, snapshots, rollback, pull, diff.

Checked against the Modbus Application Protocol v1.1b3 examples, the simulator, umodbus (a server we
did not write) and mbpoll (libmodbus, a client we did not write).
"""

from __future__ import annotations

import asyncio
import json
import shutil
import subprocess
from pathlib import Path

import pytest

from deployer.errors import ExceptionResponse, InputError
from deployer.execute.device import apply_device
from deployer.execute.session import ApplyOptions
from deployer.planning.frames import request_frame, response_frame
from deployer.planning.model import ReadRequest, Target, WriteRequest
from deployer.planning.planner import plan_reads
from deployer.planning.steps import make_plan
from deployer.profile import Profile, load_profile
from deployer.recipe.loader import load_recipe
from deployer.report import DeviceResult
from deployer.testing.simulator import Simulator, SimulatorThread
from deployer.transport import clients as tp
from tests.helpers import cli, count, profile_from, run_with, umodbus_server

PROFILE = """\
profile: plc
parameters:
  speed: {register: 0x10, type: uint16, default: 5}
  relay1: {register: 19, register_type: coil, default: true}
  relay2: {register: 20, register_type: coil}
  unit_f: {register: 21, register_type: coil, values: {celsius: 0, fahrenheit: 1}, description: temperature unit}
  relay9: {register: 40, register_type: coil}
  alarm: {register: 196, register_type: discrete, default: true}
  door: {register: 197, register_type: discrete}
  temp: {register: 8, register_type: input, type: int16, scale: 0.1, unit: degC, default: 21.5}
  serial: {register: 9, register_type: input, type: uint32, default: 123456}
"""


@pytest.fixture
def plc(tmp_path: Path) -> Profile:
    return profile_from(tmp_path, PROFILE, "plc.yaml")


def recipe(tmp: Path, body: str, name: str = "r.yaml") -> str:
    path = tmp / name
    path.write_text(f"recipe: r\nprofile: plc.yaml\nparameters:\n{body}")
    return str(path)


# ---- golden frames: the specification's examples (PDU = RTU frame without unit id and CRC) ---------------


@pytest.mark.parametrize(
    ("req", "values", "query", "answer"),
    [
        # 6.1 Read Coils 20-38: request 01 0013 0013, response 01 03 CD 6B 05
        (
            ReadRequest(19, 19, 1),
            [1, 0, 1, 1, 0, 0, 1, 1, 1, 1, 0, 1, 0, 1, 1, 0, 1, 0, 1],
            "01 00 13 00 13",
            "01 03 CD 6B 05",
        ),
        # 6.2 Read Discrete Inputs 197-218: request 02 00C4 0016, response 02 03 AC DB 35
        (
            ReadRequest(196, 22, 2),
            [0, 0, 1, 1, 0, 1, 0, 1, 1, 1, 0, 1, 1, 0, 1, 1, 1, 0, 1, 0, 1, 1],
            "02 00 C4 00 16",
            "02 03 AC DB 35",
        ),
        # 6.4 Read Input Register 9: request 04 0008 0001, response 04 02 000A
        (ReadRequest(8, 1, 4), [10], "04 00 08 00 01", "04 02 00 0A"),
    ],
)
def test_read_frames_are_the_specification_examples(
    req: ReadRequest, values: list[int], query: str, answer: str
) -> None:
    assert request_frame(req, 17, "rtu")[1:-2] == bytes.fromhex(query)
    assert response_frame(req, 17, "rtu", values)[1:-2] == bytes.fromhex(answer)


def test_write_frames_are_the_specification_examples() -> None:
    on = WriteRequest(5, 172, (1,), ("c",))  # 6.5 Write Single Coil 173 ON
    assert request_frame(on, 17, "rtu")[1:-2] == bytes.fromhex("05 00 AC FF 00")
    assert response_frame(on, 17, "rtu")[1:-2] == bytes.fromhex("05 00 AC FF 00")
    # 6.11 Write Multiple Coils 20-29: CD 01 = 1011 0011 1 0 from coil 20 up
    many = WriteRequest(15, 19, (1, 0, 1, 1, 0, 0, 1, 1, 1, 0), ("c",))
    assert request_frame(many, 17, "rtu")[1:-2] == bytes.fromhex("0F 00 13 00 0A 02 CD 01")
    assert response_frame(many, 17, "rtu")[1:-2] == bytes.fromhex("0F 00 13 00 0A")
    # the whole frames: the CRC as umodbus computes it, the LRC by hand (0x100 - 0x0D, the low byte of the sum)
    from umodbus.client.serial.redundancy_check import get_crc

    pdu = bytes.fromhex("11 0F 00 13 00 0A 02 CD 01")
    assert request_frame(many, 17, "rtu") == pdu + get_crc(pdu)
    assert request_frame(many, 17, "ascii") == b":110F0013000A02CD01F3\r\n"


def test_frames_refuse_what_no_device_takes() -> None:
    from deployer.errors import UsageError

    with pytest.raises(UsageError, match="1..1968 coils"):
        request_frame(WriteRequest(15, 0, (1,) * 1969, ("c",)), 1, "rtu")
    with pytest.raises(UsageError, match="not 0 or 1"):
        request_frame(WriteRequest(15, 0, (1, 2), ("c",)), 1, "rtu")
    with pytest.raises(UsageError, match="1..2000 coils"):
        request_frame(ReadRequest(0, 2001, 1), 1, "rtu")


# ---- profiles ------------------------------------------------------------------------------------


def test_profile_tables(plc: Profile) -> None:
    relay1, alarm, temp = plc.parameter("relay1"), plc.parameter("alarm"), plc.parameter("temp")
    assert (relay1.register_type, relay1.type, relay1.count, relay1.writable) == ("coil", "bool", 1, True)
    assert (alarm.access, alarm.writable) == ("read-only", False)
    assert (temp.access, temp.writable, temp.count) == ("read-only", False, 1)
    # the same address in two tables is no overlap
    prof = load_profile_text(
        "  a: {register: 5, type: uint16}\n  b: {register: 5, register_type: coil}\n"
        "  c: {register: 5, register_type: discrete}\n  d: {register: 5, register_type: input,"
        " type: uint32}\n"
    )
    assert [p.register_type for p in prof.parameters] == ["holding", "coil", "discrete", "input"]


def load_profile_text(body: str, head: str = "") -> Profile:
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "p.yaml"
        path.write_text(f"profile: p\n{head}parameters:\n{body}")
        return load_profile(str(path))


def errors_of(body: str, head: str = "") -> list[str]:
    with pytest.raises(InputError) as exc:
        load_profile_text(body, head)
    return [f"{d.line}:{d.col}: {d.message}" for d in exc.value.diagnostics]


def test_profile_errors_name_the_key() -> None:
    assert errors_of("  a: {register: 5, register_type: coil, scale: 0.1}\n") == [
        "3:48: 'scale' does not apply to a coil (one bit, 0 or 1)"
    ]
    assert errors_of("  a: {register: 5, register_type: coil, type: uint16}\n") == [
        "3:47: a coil is one bit: type bool (or no type), not uint16"
    ]
    assert errors_of("  a: {register: 5, register_type: input, type: uint16, access: read-write}\n") == [
        "3:64: an input register is read-only (it cannot be written)"
    ]
    assert errors_of("  a: {register: 5, register_type: discrete, access: write-only}\n") == [
        "3:53: a discrete input is read-only (it cannot be written)"
    ]
    assert errors_of("  a: {register: 5, register_type: input}\n") == [
        "3:6: a: 'type' is required for input registers (uint16, int32, float32 ...); only coils and discrete "
        "inputs are bool without it"
    ]
    assert errors_of("  a: {register: 5, register_type: coil}\n  b: {register: 5, register_type: coil}\n") == [
        "4:3: b (coil 0x0005) overlaps a (coil 0x0005, line 3)"
    ]
    assert errors_of(
        "  a: {register: 5, type: uint32, register_type: input}\n"
        "  b: {register: 6, register_type: input, type: uint16}\n"
    ) == ["4:3: b (input registers 0x0006-0x0006) overlaps a (input registers 0x0005-0x0006, line 3)"]


def test_modicon_references_name_the_table() -> None:
    prof = load_profile_text(
        "  c: {register: 20, register_type: coil}\n"
        "  d: {register: 10197, register_type: discrete}\n"
        "  i: {register: 30009, register_type: input, type: uint16}\n"
        "  h: {register: 400017, type: uint16}\n",
        "addressing: modicon\n",
    )
    assert [(p.name, p.address) for p in sorted(prof.parameters, key=lambda p: p.key)] == [
        ("h", 16),
        ("c", 19),
        ("d", 196),
        ("i", 8),
    ]
    assert errors_of("  d: {register: 30009, register_type: discrete}\n", "addressing: modicon\n") == [
        "4:17: 30009 is not a discrete-input reference: addressing: modicon accepts 10001-19999 (5 digits, "
        "addresses 0-9998) or 100001-165536 (6 digits, addresses 0-65535); 3xxxx references are "
        "input registers: set register_type: input"
    ]


# ---- planning ------------------------------------------------------------------------------------


def test_contiguous_coils_merge_into_one_fc15_never_with_registers(tmp_path: Path, plc: Profile) -> None:
    rec = load_recipe(
        recipe(tmp_path, "  speed: 7\n  relay1: false\n  relay2: true\n  unit_f: fahrenheit\n  relay9: true\n")
    )
    plan = make_plan(rec, Target(None, 1, "plc"))
    assert [(w.function, w.address, w.registers, w.parameters) for w in plan.writes] == [
        (16, 0x10, (7,), ("speed",)),
        (15, 19, (0, 1, 1), ("relay1", "relay2", "unit_f")),
        (5, 40, (1,), ("relay9",)),
    ]
    assert [(r.function, r.address, r.count) for r in plan.reads] == [(3, 0x10, 1), (1, 19, 3), (1, 40, 1)]
    # diff-aware: an unchanged coil bridges two changed ones when that saves a request
    current = {"speed": (7,), "relay1": (1,), "relay2": (1,), "unit_f": (0,), "relay9": (1,)}
    plan = make_plan(rec, Target(None, 1, "plc"), current)
    assert [(w.function, w.address, w.registers) for w in plan.writes] == [(15, 19, (0, 1, 1))]
    assert [p.action for p in plan.parameters] == ["unchanged", "write", "bridge", "write", "unchanged"]


def test_coil_limits(tmp_path: Path) -> None:
    body = "".join(f"  c{i}: {{register: {i}, register_type: coil}}\n" for i in range(40))
    for limits, expect in [
        ("", [(15, 0, 40)]),
        ("limits: {max_write_coils: 16, max_read_coils: 24}\n", [(15, 0, 16), (15, 16, 16), (15, 32, 8)]),
        ("limits: {max_write_coils: 1}\n", [(5, i, 1) for i in range(40)]),
        ("limits: {max_frame_bytes: 11}\n", [(15, 0, 16), (15, 16, 16), (15, 32, 8)]),
    ]:
        (tmp_path / "c.yaml").write_text(f"profile: c\n{limits}parameters:\n{body}")
        (tmp_path / "r.yaml").write_text(
            "recipe: r\nprofile: c.yaml\nparameters:\n"
            + "".join(f"  c{i}: {'true' if i % 3 else 'false'}\n" for i in range(40))
        )
        plan = make_plan(load_recipe(str(tmp_path / "r.yaml")), Target(None, 1, "c"))
        assert [(w.function, w.address, w.count) for w in plan.writes] == expect, limits
    prof = load_profile(str(tmp_path / "c.yaml"))
    assert prof.limits.read_coils == 48  # an 11-byte frame: 5 + 6 bytes of bits
    prof = profile_from(tmp_path, f"profile: c\nlimits: {{max_read_coils: 24}}\nparameters:\n{body}")
    assert [(r.function, r.address, r.count) for r in plan_reads(prof, prof.names())] == [(1, 0, 24), (1, 24, 16)]


def test_reads_of_read_only_tables(plc: Profile) -> None:
    assert [(r.function, r.address, r.count) for r in plan_reads(plc, plc.names())] == [
        (3, 0x10, 1),
        (1, 19, 3),
        (1, 40, 1),
        (2, 196, 2),
        (4, 8, 3),
    ]


def test_recipe_cannot_set_read_only_tables(tmp_path: Path, plc: Profile, capsys: pytest.CaptureFixture[str]) -> None:
    path = recipe(tmp_path, "  alarm: false\n  temp: 20 degC\n")
    code, _, err = cli(capsys, "validate", path)
    assert code == 1
    assert f"{path}:4:3: error: alarm is read-only in profile plc" in err
    assert f"{path}:5:3: error: temp is read-only in profile plc" in err


# ---- apply, read-back, snapshot, rollback against the simulator ------------------------------------------


def test_apply_snapshot_and_exact_rollback(tmp_path: Path, plc: Profile, capsys: pytest.CaptureFixture[str]) -> None:
    path = recipe(tmp_path, "  speed: 7\n  relay1: false\n  relay2: true\n  unit_f: fahrenheit\n  relay9: true\n")
    with SimulatorThread(plc) as sim:
        sim.write("relay9", (0,))
        state = str(tmp_path / ".d")
        code, out, err = cli(capsys, "apply", path, "--device", sim.url, "--yes", "--json", "--state-dir", state)
        assert code == 0, err
        report = json.loads(out)["devices"][0]
        assert [(r["function"], r["address"], r["count"]) for r in report["requests"]] == [
            (3, 16, 1),
            (1, 19, 3),
            (1, 40, 1),  # current values
            (43, 0, 1),  # Function 43 identity (the simulator answers 01: none)
            (16, 16, 1),
            (15, 19, 3),
            (5, 40, 1),  # writes
            (3, 16, 1),
            (1, 19, 3),
            (1, 40, 1),
        ]  # read-back
        by_name = {p["name"]: p for p in report["parameters"]}
        assert by_name["relay1"] == {
            "name": "relay1",
            "address": 19,
            "count": 1,
            "desired": "false",
            "desired_raw": [0],
            "before_raw": [1],
            "after_raw": [0],
            "status": "ok",
            "error": None,
            "register_type": "coil",
        }
        assert "register_type" not in by_name["speed"]
        assert [sim.read(n) for n in ("relay1", "relay2", "unit_f", "relay9")] == [(0,), (1,), (1,), (1,)]
        # what the device's log saw on the wire, coil values included
        writes = [(e.function, e.address, e.values) for e in sim.log if e.function in (5, 15, 16)]
        assert writes == [(16, 16, [7]), (15, 19, [0, 1, 1]), (5, 40, [1])]

        snap = Path(report["snapshot"])
        text = snap.read_text()
        assert "    relay1: [1]\n    relay2: [0]\n    unit_f: [0]\n    relay9: [0]\n" in text
        assert "  relay1: true\n  relay2: false\n  unit_f: celsius\n  relay9: false\n" in text
        code, out, err = cli(capsys, "rollback", str(snap), "--yes", "--state-dir", state)
        assert code == 0, err
        assert [sim.read(n) for n in ("speed", "relay1", "relay2", "unit_f", "relay9")] == [
            (5,),
            (1,),
            (0,),
            (0,),
            (0,),
        ]
        # drift on a coil, then pull: read-only tables are not pulled (a recipe cannot set them)
        sim.write("relay2", (1,))
        code, out, _ = cli(capsys, "diff", path, "--device", sim.url, "--json")
        assert code == 2
        assert {d["name"] for d in json.loads(out)["drift"] if d["device_raw"] is not None} == {
            "speed",
            "relay1",
            "unit_f",
            "relay9",
        }
        code, out, _ = cli(capsys, "pull", "--profile", str(tmp_path / "plc.yaml"), "--device", sim.url)
        assert code == 0
        assert out.endswith(
            "parameters:\n  speed: 5\n  relay1: true\n  relay2: true\n  unit_f: celsius\n  relay9: false\n"
        )


def test_saved_plan_with_coils_runs_unchanged(tmp_path: Path, plc: Profile, capsys: pytest.CaptureFixture[str]) -> None:
    path = recipe(tmp_path, "  relay1: false\n  relay2: true\n")
    with SimulatorThread(plc) as sim:
        plan_file = str(tmp_path / "plan.json")
        code, _, err = cli(
            capsys, "plan", path, "--device", sim.url, "--out", plan_file, "--state-dir", str(tmp_path / "s")
        )
        assert code == 0, err
        data = json.loads(Path(plan_file).read_text())
        write = next(s for s in data["steps"] if s["kind"] == "write")
        assert write == {
            "kind": "write",
            "function": 15,
            "address": 19,
            "count": 2,
            "values": [0, 1],
            "parameters": ["relay1", "relay2"],
            "stage": 0,
        }
        assert [(s["function"], s["address"], s["count"]) for s in data["steps"] if s["kind"] == "snapshot"] == [
            (1, 19, 2)
        ]
        assert data["parameters"][0]["register_type"] == "coil"
        code, _, err = cli(
            capsys, "apply", plan_file, "--device", sim.url, "--yes", "--state-dir", str(tmp_path / ".d")
        )
        assert code == 0, err
        assert (sim.read("relay1"), sim.read("relay2")) == ((0,), (1,))
        # a hand-edited plan cannot write a coil with a register function
        write["function"] = 16
        Path(plan_file).write_text(json.dumps(data))
        code, _, err = cli(capsys, "validate", plan_file)
        assert code == 1 and "function 16 writes holdings, but relay1 is a coil" in err


def test_simulator_refuses_like_a_device(plc: Profile, tmp_path: Path) -> None:
    async def body(sim: Simulator) -> list[str]:
        t = tp.open_transport(sim.url + "?timeout=2")
        await t.connect()
        out = []
        for call in (
            lambda: t.read(1, 22, 1, 1),  # no coil 22: 02
            lambda: t.write_coil(196, True, 1),  # a discrete input is no coil: 02
            lambda: t.read(2, 196, 3, 1),  # discrete 198 does not exist: 02
            lambda: t.write_coils(19, [True] * 3, 1),
            lambda: t.read(4, 8, 3, 1),
            lambda: t.read(2, 196, 2, 1),
        ):
            try:
                out.append(str(await call()))
            except ExceptionResponse as e:
                out.append(f"exception {e.code:02d}")
        await t.close()
        return out

    assert run_with(Simulator(plc), body) == [
        "exception 02",
        "exception 02",
        "exception 02",
        "None",
        "[215, 1, 57920]",
        "[1, 0]",
    ]  # 123456 = 0001E240h
    holding_only = profile_from(tmp_path, "profile: h\nparameters:\n  a: {register: 0, type: uint16}\n")

    async def body2(sim: Simulator) -> list[int]:
        t = tp.open_transport(sim.url + "?timeout=2")
        await t.connect()
        codes = []
        for fc in (1, 2, 4):
            with pytest.raises(ExceptionResponse) as exc:
                await t.read(fc, 0, 1, 1)
            codes.append(exc.value.code)
        await t.close()
        return codes

    assert run_with(Simulator(holding_only), body2) == [1, 1, 1]  # a drive without coils: illegal function


def test_simulator_counts_coil_limits(tmp_path: Path) -> None:
    body = "".join(f"  c{i}: {{register: {i}, register_type: coil}}\n" for i in range(20))
    prof = profile_from(
        tmp_path, f"profile: c\nlimits: {{max_write_coils: 8, max_read_coils: 10}}\nparameters:\n{body}"
    )

    async def run(sim: Simulator) -> list[int]:
        t = tp.open_transport(sim.url + "?timeout=2")
        await t.connect()
        codes = []
        for call in (lambda: t.write_coils(0, [True] * 9, 1), lambda: t.read(1, 0, 11, 1)):
            with pytest.raises(ExceptionResponse) as exc:
                await call()
            codes.append(exc.value.code)
        await t.close()
        return codes

    assert run_with(Simulator(prof), run) == [3, 3]
    # and the planner keeps within them: 20 coils in 3 writes of <= 8, read in 2 blocks of <= 10
    (tmp_path / "r.yaml").write_text(
        "recipe: r\nprofile: dev.yaml\nparameters:\n" + "".join(f"  c{i}: true\n" for i in range(20))
    )
    rec = load_recipe(str(tmp_path / "r.yaml"))
    sim = Simulator(prof)
    res = run_with(
        sim, lambda s: apply_device(rec, tp.parse_url(s.url), 1, options=ApplyOptions(state_dir=str(tmp_path / ".d")))
    )
    assert res.status == "ok"
    assert [(e.function, e.address, e.count) for e in sim.log if e.function == 15] == [
        (15, 0, 8),
        (15, 8, 8),
        (15, 16, 4),
    ]
    assert count(sim.log, 1) == 4


def test_a_refused_coil_write_is_reported(tmp_path: Path, plc: Profile) -> None:
    from deployer.profile.model import SPACE
    from deployer.testing.simulator import Faults

    rec = load_recipe(recipe(tmp_path, "  relay1: false\n  relay2: true\n"))
    sim = Simulator(plc, faults=Faults(fail_registers=frozenset({SPACE["coil"] << 16 | 20})))
    res = run_with(
        sim, lambda s: apply_device(rec, tp.parse_url(s.url), 1, options=ApplyOptions(state_dir=str(tmp_path / ".d")))
    )
    assert res.status == "failed"
    assert {p.name: (p.status, p.after_raw) for p in res.parameters} == {
        "relay1": ("failed", (1,)),
        "relay2": ("failed", (0,)),
    }


# ---- implementations we did not write -------------------------------------------------------------------


def test_apply_coils_to_a_umodbus_server(tmp_path: Path) -> None:
    profile_from(
        tmp_path,
        "profile: u\nparameters:\n  speed: {register: 0, type: uint16}\n"
        "  a: {register: 10, register_type: coil}\n  b: {register: 11, register_type: coil}\n"
        "  c: {register: 12, register_type: coil}\n  d: {register: 20, register_type: coil}\n",
        "u.yaml",
    )
    (tmp_path / "r.yaml").write_text(
        "recipe: r\nprofile: u.yaml\nparameters: {speed: 3, a: true, b: false, c: true, d: true}\n"
    )
    rec = load_recipe(str(tmp_path / "r.yaml"))
    store, coils = {0: 0}, {10: 0, 11: 1, 12: 0, 20: 0}
    with umodbus_server(store, coils) as port:
        res = asyncio.run(
            apply_device(
                rec,
                tp.parse_url(f"tcp://127.0.0.1:{port}?timeout=2"),
                1,
                options=ApplyOptions(state_dir=str(tmp_path / ".d")),
            )
        )
    assert res.status == "ok", res
    assert store == {0: 3} and coils == {10: 1, 11: 0, 12: 1, 20: 1}
    assert [(r.function, r.address, r.count) for r in res.requests if r.function in (5, 15, 16)] == [
        (16, 0, 1),
        (15, 10, 3),
        (5, 20, 1),
    ]
    assert {p.name: p.before_raw for p in res.parameters} == {"speed": (0,), "a": (0,), "b": (1,), "c": (0,), "d": (0,)}


MBPOLL = shutil.which("mbpoll")


@pytest.mark.skipif(MBPOLL is None, reason="mbpoll (libmodbus) is not installed")
def test_mbpoll_reads_what_apply_wrote(tmp_path: Path, plc: Profile) -> None:
    rec = load_recipe(recipe(tmp_path, "  relay1: false\n  relay2: true\n  unit_f: fahrenheit\n"))
    with SimulatorThread(plc) as sim:
        res = asyncio.run(
            apply_device(rec, tp.parse_url(sim.url), 1, options=ApplyOptions(state_dir=str(tmp_path / ".d")))
        )
        assert res.status == "ok"
        port = sim.url.rsplit(":", 1)[1]

        def poll(*args: str) -> str:
            assert MBPOLL is not None
            out = subprocess.run(
                [MBPOLL, "-m", "tcp", "-p", port, "-a", "1", "-0", "-1", *args, "127.0.0.1"],
                capture_output=True,
                text=True,
                timeout=20,
            )
            assert out.returncode == 0, out.stderr
            return out.stdout

        assert "[19]: \t0\n[20]: \t1\n[21]: \t1\n" in poll("-t", "0", "-r", "19", "-c", "3")  # coils, FC01
        assert "[196]: \t1\n[197]: \t0\n" in poll("-t", "1", "-r", "196", "-c", "2")  # discrete inputs, FC02
        assert "[8]: \t215\n" in poll("-t", "3", "-r", "8")  # input register, FC04
        # mbpoll writes a coil (FC05); our diff sees it
        assert MBPOLL is not None
        subprocess.run(
            [MBPOLL, "-m", "tcp", "-p", port, "-a", "1", "-0", "-1", "-t", "0", "-r", "40", "127.0.0.1", "1"],
            capture_output=True,
            text=True,
            timeout=20,
            check=True,
        )
        assert sim.read("relay9") == (1,)


def test_identity_in_an_input_register(tmp_path: Path) -> None:
    prof = profile_from(
        tmp_path,
        "profile: d\nidentity:\n  - {register: 0, register_type: input, raw: 0x0310, "
        "description: model code}\nparameters:\n"
        "  model: {register: 0, register_type: input, type: uint16, default: 0x0310}\n"
        "  relay: {register: 0, register_type: coil}\n",
        "d.yaml",
    )
    (tmp_path / "r.yaml").write_text("recipe: r\nprofile: d.yaml\nparameters: {relay: true}\n")
    rec = load_recipe(str(tmp_path / "r.yaml"))
    sim = Simulator(prof)

    async def twice(s: Simulator) -> tuple[DeviceResult, DeviceResult]:
        opts = ApplyOptions(state_dir=str(tmp_path / ".d"))
        first = await apply_device(rec, tp.parse_url(s.url), 1, options=opts)
        s.write("model", (0x0311,))
        s.write("relay", (0,))
        return first, await apply_device(rec, tp.parse_url(s.url), 1, options=opts)

    first, second = run_with(sim, twice)
    assert first.status == "ok" and [(r.function, r.address) for r in first.requests][:1] == [(4, 0)]
    assert second.status == "failed"
    assert second.error == (
        "identity check failed: input register 0x0000 (model code) holds 0x0311, expected 0x0310: "
        "another kind of device answers here; nothing was written"
    )
    assert sim.read("relay") == (0,)


def test_simulate_set_reaches_every_table(tmp_path: Path, plc: Profile, capsys: pytest.CaptureFixture[str]) -> None:
    import signal

    from deployer.cli import main
    from tests.conftest import simulate_process

    profile = str(tmp_path / "plc.yaml")
    proc, _, port = simulate_process(
        profile, "--set", "coil:40=1", "--set", "input:8=300", "--set", "discrete:197=1", "--set", "0x10=9"
    )
    try:

        async def read() -> list[list[int]]:
            t = tp.open_transport(f"tcp://127.0.0.1:{port}?timeout=5")
            await t.connect()
            try:
                return [
                    await t.read(1, 40, 1, 1),
                    await t.read(4, 8, 1, 1),
                    await t.read(2, 196, 2, 1),
                    await t.read(3, 0x10, 1, 1),
                ]
            finally:
                await t.close()

        assert asyncio.run(read()) == [[1], [300], [1, 1], [9]]
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
    for bad, message in (
        ("coil:41=1", "init: coil 41 is not declared in profile plc"),
        ("coil:40=2", "a bit holds 0 or 1"),
        ("relay:1=1", "'relay' is not a table"),
    ):
        with pytest.raises(SystemExit) as exc:
            main(["simulate", profile, "--set", bad])
        assert exc.value.code == 1 and message in capsys.readouterr().err
