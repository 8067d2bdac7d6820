"""Profiles for real devices end to end: layouts, strings, bit fields, guarded and sequenced writes."""

from __future__ import annotations

import asyncio
import json
import shutil
import subprocess
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from deployer.cli import main
from deployer.errors import InputError
from deployer.execute.device import apply_device
from deployer.execute.session import ApplyOptions
from deployer.load import schema
from deployer.planning.model import Target
from deployer.planning.planner import plan_writes
from deployer.planning.steps import make_plan
from deployer.profile import Limits, Parameter, Profile
from deployer.recipe.loader import Desired, load_recipe
from deployer.report import DeviceResult, Report
from deployer.testing.simulator import Simulator, SimulatorThread
from deployer.transport.clients import parse_url
from tests.helpers import count, profile_from, run_with

pytestmark = pytest.mark.timeout(60)

FIELDS = """\
profile: fields
parameters:
  running: {register: 0x10, type: bool, bits: 3, access: read-only, description: drive running}
  fault: {register: 0x10, type: bool, bits: 0, access: read-only}
  enable: {register: 0x30, type: bool, bits: 0}
  direction: {register: 0x30, type: bool, bits: 1, values: {forward: 0, reverse: 1}}
  mode: {register: 0x30, type: uint16, bits: 3..5, values: {speed: 0, torque: 1, position: 2}}
  jog_step: {register: 0x30, type: uint16, mask: 0xF000, scale: 0.5, unit: mm}
  name: {register: 0x31, type: string, count: 4, padding: space}
  gain: {register: 0x35, type: float32, byte_order: CDAB, default: 1.5}
  limit: {register: 0x37, type: int32, swap: word_byte}
  accel: {register: 0x40, type: uint16, scale: 0.1, unit: s, stage: 1, restart: true}
"""

GUARDS = """\
preconditions:
  - {register: 0x10, bits: 3, equals: 0, description: drive stopped}
unlock:
  - {register: 0x20, raw: 0x5AA5, description: parameter password, wait: 120}
lock:
  - {register: 0x20, raw: 0, description: lock parameters}
commit:
  - {register: 0x21, raw: 1, description: store to EEPROM, wait: 150}
stages:
  - {stage: 0, wait: 100}
"""


@pytest.fixture
def fields(tmp_path: Path) -> Profile:
    return profile_from(tmp_path, FIELDS)


@pytest.fixture
def drive(tmp_path: Path) -> Profile:
    return profile_from(tmp_path, FIELDS.replace("profile: fields", "profile: drive") + GUARDS, "drive.yaml")


def recipe(tmp: Path, body: str, profile: str = "dev.yaml") -> str:
    p = tmp / "r.yaml"
    p.write_text(f"recipe: r\nprofile: {profile}\nparameters:\n{body}")
    return str(p)


def apply(sim: Simulator, path: str, tmp: Path, *, between: object = None) -> DeviceResult:
    """Apply; ``between(sim)`` runs after the snapshot read and before the first write."""
    rec = load_recipe(path)

    async def body(s: Simulator) -> DeviceResult:
        async def confirm(plan: object, res: object) -> bool:
            if callable(between):
                between(s)
            return True

        return await apply_device(
            rec,
            parse_url(s.url + "?timeout=0.5"),
            1,
            options=ApplyOptions(state_dir=str(tmp / ".d"), backoff=0.01, confirm=confirm),
        )

    return run_with(sim, body)


# ---- the profile ------------------------------------------------------------------------------


def test_layouts_fields_and_strings_load(fields: Profile) -> None:
    assert fields.parameter("gain").layout == "CDAB"
    assert fields.parameter("limit").layout == "DCBA"
    assert fields.parameter("mode").mask == 0x0038 and fields.parameter("jog_step").mask == 0xF000
    assert fields.parameter("name").count == 4
    assert fields.parameter("gain").encode(1.5) == (0x0000, 0x3FC0)  # 3FC00000h, words swapped
    assert fields.parameter("limit").encode(-2) == (0xFEFF, 0xFFFF)  # FFFFFFFEh reversed bytewise


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ("  whole: {register: 0x30, type: uint16}\n", "whole (registers 0x0030-0x0030) overlaps the bit field"),
        (
            "  clash: {register: 0x30, type: uint16, bits: 5..6}\n",
            "clash (bits 5..6 of register 0x0030) overlaps mode (bits 3..5, line 7)",
        ),
        ("  late: {register: 0x30, type: bool, bits: 7, stage: 2}\n", "a register is written as one unit"),
        ("  wide: {register: 0x50, type: bool, bits: 1..2}\n", "a bool field is one bit"),
        ("  odd: {register: 0x50, type: uint16, mask: 0x0101}\n", "not one contiguous group of bits"),
        ("  big: {register: 0x50, type: uint32, bits: 1}\n", "a bit field is uint16, int16 or bool"),
        ("  s: {register: 0x50, type: string}\n", "a string needs 'count'"),
        ("  s: {register: 0x50, type: string, count: 2, unit: s}\n", "'unit' does not apply to a string"),
        ("  n: {register: 0x50, type: uint16, count: 2}\n", "'count' applies to strings only"),
        ("  both: {register: 0x50, type: uint32, swap: word, byte_order: ABCD}\n", "both set the layout"),
        ("  e: {register: 0x50, type: uint16, bits: 0..1, values: {a: 4}}\n", "value 4 of 'a' does not fit in 2 bits"),
    ],
)
def test_profile_errors_with_positions(tmp_path: Path, extra: str, message: str) -> None:
    with pytest.raises(InputError) as e:
        profile_from(tmp_path, FIELDS + extra)
    text = "\n".join(str(d) for d in e.value.diagnostics)
    assert message in text
    assert all(d.line > 0 for d in e.value.diagnostics)


def test_recipe_values_for_strings_and_fields(tmp_path: Path, fields: Profile) -> None:
    path = recipe(tmp_path, "  name: PUMP\n  enable: true\n  direction: reverse\n  jog_step: 3.5 mm\n")
    rec = load_recipe(path)
    got = {d.name: d.registers for d in rec.desired}
    assert got["name"] == (0x5055, 0x4D50, 0x2020, 0x2020)
    assert got["enable"] == (0x0001,) and got["direction"] == (0x0002,) and got["jog_step"] == (0x7000,)
    bad = recipe(tmp_path, '  name: "A NAME TOO LONG"\n  mode: 9\n  enable: maybe\n')
    with pytest.raises(InputError) as e:
        load_recipe(bad)
    text = "\n".join(str(d) for d in e.value.diagnostics)
    assert "r.yaml:4:9: error: name: 'A NAME TOO LONG' is 15 characters; 4 registers hold at most 8" in text
    assert "r.yaml:5:9: error: mode: raw value 9 does not fit in the field's 3 bits (0..7)" in text
    assert "r.yaml:6:11: error: enable:" in text


def test_two_fields_of_one_register_plan_as_one_word(tmp_path: Path, fields: Profile) -> None:
    rec = load_recipe(recipe(tmp_path, "  direction: reverse\n  mode: torque\n  name: AB\n"))
    target = Target(None, 1, "dev.yaml")
    plan = make_plan(rec, target, {"direction": (0xF001,), "mode": (0xF001,), "name": (0, 0, 0, 0)})
    assert [(w.address, w.registers, w.parameters) for w in plan.writes] == [  # 0x30 and 0x31.. in one request
        (0x30, (0xF00B, 0x4142, 0x2020, 0x2020, 0x2020), ("direction", "mode", "name"))
    ]  # F001h's other bits kept
    # one field already right: the register still goes as one unit, that field as a bridge
    plan = make_plan(rec, target, {"direction": (0x0002,), "mode": (0x0002,)})
    assert {p.name: p.action for p in plan.parameters} == {"direction": "bridge", "mode": "write", "name": "write"}
    assert plan.writes[0].registers[0] == 0x000A
    assert (
        make_plan(rec, target, {"direction": (0x000A,), "mode": (0x000A,), "name": rec.desired[-1].registers}).writes
        == ()
    )


# ---- bit fields against the simulator -------------------------------------------------------


def test_other_bits_changed_between_snapshot_and_write_are_kept(tmp_path: Path, fields: Profile) -> None:
    sim = Simulator(fields, init={0x30: 0x0000})
    path = recipe(tmp_path, "  direction: reverse\n  mode: torque\n")

    def operator_changes_other_fields(s: Simulator) -> None:
        s.write("enable", (0x7001,))  # jog_step 7 and enable set on the panel after our snapshot

    res = apply(sim, path, tmp_path, between=operator_changes_other_fields)
    assert res.status == "ok", res.to_json()
    assert sim.read("mode") == (0x700B,)  # 7xxxh and bit 0 kept, direction and mode written
    writes = [e for e in sim.log if e.function == 16]
    assert [(w.address, w.values) for w in writes] == [(0x30, [0x700B])]  # two fields, one write
    before_write = sim.log[sim.log.index(writes[0]) - 1]
    assert (before_write.function, before_write.address) == (3, 0x30)  # read right before the write
    assert {p.name: p.status for p in res.parameters} == {"direction": "ok", "mode": "ok"}
    # the snapshot holds each field's value and loads back as a recipe
    snap = load_recipe(res.snapshot or "")
    assert {d.name: d.text for d in snap.desired} == {"direction": "forward", "mode": "speed"}


def test_pull_fields_strings_and_layouts(tmp_path: Path, fields: Profile, capsys: pytest.CaptureFixture[str]) -> None:
    init = {0x30: 0x3013, 0x31: 0x4142, 0x32: 0x4320, 0x33: 0x2020, 0x34: 0x2020, 0x37: 0xFEFF, 0x38: 0xFFFF}
    with SimulatorThread(fields, init=init) as sim:
        out = tmp_path / "pulled.yaml"
        with pytest.raises(SystemExit) as exc:
            main(["pull", "--profile", str(tmp_path / "dev.yaml"), "--device", sim.url, "-o", str(out)])
        assert exc.value.code == 0, capsys.readouterr()
    text = out.read_text()
    for line in (
        "enable: true",
        "direction: reverse",
        "mode: position",
        "jog_step: 1.5 mm",
        'name: "ABC"',
        "limit: -2",
        "gain: 1.5",
    ):
        assert f"  {line}\n" in text, text
    pulled = load_recipe(str(out))
    assert {d.name: d.registers for d in pulled.desired}["name"] == (0x4142, 0x4320, 0x2020, 0x2020)


# ---- guarded and sequenced writes -------------------------------------------------------------


def test_guarded_profile_refuses_while_running(
    tmp_path: Path, drive: Profile, capsys: pytest.CaptureFixture[str]
) -> None:
    path = recipe(tmp_path, "  mode: torque\n  accel: 2 s\n", "drive.yaml")
    report = tmp_path / "report.json"
    with SimulatorThread(drive) as sim:
        sim.write("running", (0x0008,))  # the drive runs
        with pytest.raises(SystemExit) as exc:
            main(
                [
                    "apply",
                    path,
                    "--device",
                    sim.url,
                    "--yes",
                    "--report",
                    str(report),
                    "--state-dir",
                    str(tmp_path / ".d"),
                ]
            )
        log = list(sim.log)
    assert exc.value.code == 4
    assert count(log, 16) == 0 and count(log, 6) == 0  # nothing written, not even the unlock
    dev = json.loads(report.read_text())["devices"][0]
    assert dev["status"] == "failed"
    assert dev["error"] == (
        "precondition failed: register 0x0010 bit 3 (drive stopped) is 1, expected 0; nothing was written"
    )
    assert "drive stopped" in capsys.readouterr().out


def test_unlock_writes_commit_lock_in_order_with_waits(tmp_path: Path, drive: Profile) -> None:
    path = recipe(tmp_path, "  mode: torque\n  gain: 2.5\n  accel: 2 s\n", "drive.yaml")
    sim = Simulator(drive)
    res = apply(sim, path, tmp_path)
    assert res.status == "ok", res.to_json()
    assert res.notices == ["accel takes effect after a power cycle"]
    assert Report("r", [res]).exit_code == 0
    writes = [e for e in sim.log if e.function in (6, 16)]
    assert [(w.address, w.values) for w in writes] == [
        (0x20, [0x5AA5]),  # unlock
        (0x30, [0x0008]),
        (0x35, [0x0000, 0x4020]),  # stage 0: mode, gain (2.5 = 40200000h, CDAB)
        (0x40, [20]),  # stage 1: accel
        (0x21, [1]),  # commit: store to EEPROM
        (0x20, [0]),
    ]  # lock
    # never busy: every wait was kept (the device has no Function 43: that answers 01)
    assert not any(e.result.startswith("exception") for e in sim.log if e.function != 43)
    # the request log's timestamps (taken as each request arrives) show every wait
    first_after_unlock = sim.log[sim.log.index(writes[0]) + 1]
    assert first_after_unlock.time - writes[0].time >= 0.12  # unlock wait: 120 ms
    assert writes[3].time - writes[2].time >= 0.10  # after stage 0: 100 ms
    assert writes[5].time - writes[4].time >= 0.15  # after commit: 150 ms
    assert writes[2].time - writes[1].time < 0.10  # no wait inside a stage
    assert sim.read("mode") == (0x0008,) and sim.registers()[0x20] == 0  # locked again


def test_simulator_models_the_lock_and_the_busy_wait(tmp_path: Path, drive: Profile) -> None:
    from pymodbus.client import ModbusTcpClient

    with SimulatorThread(drive) as sim:
        client = ModbusTcpClient("127.0.0.1", port=int(sim.url.rsplit(":", 1)[1]), retries=0)
        assert client.connect()  # type: ignore[no-untyped-call]
        try:
            assert client.write_register(0x40, 5, device_id=1).exception_code == 4  # locked
            assert not client.write_register(0x20, 0x5AA5, device_id=1).isError()
            assert client.write_register(0x40, 5, device_id=1).exception_code == 6  # busy for 120 ms
            import time

            time.sleep(0.15)
            assert not client.write_register(0x40, 5, device_id=1).isError()
            sim.write("running", (0x0008,))
            assert client.write_register(0x40, 6, device_id=1).exception_code == 4  # refused while running
        finally:
            client.close()  # type: ignore[no-untyped-call]


def test_lock_is_sent_after_a_failed_write(tmp_path: Path, drive: Profile) -> None:
    path = recipe(tmp_path, "  mode: torque\n  accel: 2 s\n", "drive.yaml")
    sim = Simulator(drive)
    sim.faults.fail_registers = frozenset({0x40})
    res = apply(sim, path, tmp_path)
    assert res.status == "partial"
    writes = [(e.address, e.values) for e in sim.log if e.function == 16]
    assert writes[0] == (0x20, [0x5AA5]) and writes[-1] == (0x20, [0])  # unlocked, then locked again
    assert (0x21, [1]) not in writes  # no commit after a failure
    assert res.notices == []  # accel failed: nothing to restart for


def test_restart_notice_in_report_json(tmp_path: Path, drive: Profile) -> None:
    res = apply(Simulator(drive), recipe(tmp_path, "  accel: 3 s\n", "drive.yaml"), tmp_path)
    data = Report("r", [res]).to_json()
    import jsonschema

    jsonschema.validate(data, schema.schema("report"))
    assert data["devices"][0]["notices"] == ["accel takes effect after a power cycle"]
    assert data["devices"][0]["status"] == "ok"


# ---- an independent client: mbpoll (libmodbus) ----------------------------------------------

MBPOLL = shutil.which("mbpoll")


@pytest.mark.skipif(MBPOLL is None, reason="mbpoll (libmodbus) is not installed")
def test_mbpoll_reads_our_layouts(tmp_path: Path, fields: Profile) -> None:
    path = recipe(tmp_path, "  gain: 123.456\n  limit: 305419896\n  name: ABC\n")
    sim = SimulatorThread(fields)
    with sim as s:
        rec = load_recipe(path)
        import asyncio

        res = asyncio.run(apply_device(rec, parse_url(s.url), 1, options=ApplyOptions(state_dir=str(tmp_path / ".d"))))
        assert res.status == "ok"
        port = s.url.rsplit(":", 1)[1]

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

        # mbpoll's 32-bit types take the low word first (CDAB) unless -B: our CDAB float reads as is
        assert "[53]: \t123.456" in poll("-r", "53", "-t", "4:float")
        # DCBA 12345678h = registers 7856h 3412h: mbpoll shows the words as they are
        assert "[55]: \t0x7856" in poll("-r", "55", "-c", "2", "-t", "4:hex")
        assert "[56]: \t0x3412" in poll("-r", "55", "-c", "2", "-t", "4:hex")
        assert "[49]: \t0x4142" in poll("-r", "49", "-c", "2", "-t", "4:hex")


def test_nothing_to_write_needs_no_guard(tmp_path: Path, drive: Profile) -> None:
    sim = Simulator(drive, init={0x30: 0x0008})  # mode already torque
    path = recipe(tmp_path, "  mode: torque\n", "drive.yaml")
    rec = load_recipe(path)

    async def body(s: Simulator) -> DeviceResult:
        s.write("running", (0x0008,))
        return await apply_device(rec, parse_url(s.url), 1, options=ApplyOptions(state_dir=str(tmp_path / ".d")))

    res = run_with(sim, body)
    assert res.status == "ok" and res.parameters[0].status == "unchanged"
    assert res.parameters[0].desired_raw == (0x0008,)  # the register's word, like before_raw and after_raw
    assert count(sim.log, 16) == 0


def test_simulator_init_from_a_recipe_with_fields(tmp_path: Path, fields: Profile) -> None:
    from deployer.testing.simulator import init_from_recipe

    rec = load_recipe(recipe(tmp_path, "  enable: true\n  mode: position\n  jog_step: 2 mm\n"))
    assert init_from_recipe(rec) == {0x30: 0x4011}


def test_rollback_restores_a_fields_bits_and_keeps_the_rest(tmp_path: Path, fields: Profile) -> None:
    sim = Simulator(fields, init={0x30: 0x0000})
    res = apply(sim, recipe(tmp_path, "  direction: reverse\n  mode: torque\n"), tmp_path)
    assert res.status == "ok" and sim.read("mode") == (0x000A,)
    snapshot = load_recipe(res.snapshot or "")

    async def rollback(s: Simulator) -> DeviceResult:
        s.write("enable", (s.read("enable")[0] | 0x5001,))  # meanwhile: enable and jog_step changed on the panel
        return await apply_device(snapshot, parse_url(s.url), 1, options=ApplyOptions(state_dir=str(tmp_path / ".d")))

    back = run_with(sim, rollback)
    assert back.status == "ok", back.to_json()
    assert sim.read("mode") == (0x5001,)  # direction and mode as before the apply, the panel's bits kept


def test_diff_compares_a_fields_own_bits(tmp_path: Path, fields: Profile, capsys: pytest.CaptureFixture[str]) -> None:
    from deployer.api.values import diff_values

    rec = load_recipe(recipe(tmp_path, "  direction: reverse\n  mode: torque\n"))
    assert diff_values(rec, {"direction": (0xF00B,), "mode": (0xF00B,)}) == []  # other bits differ: no drift
    drift = diff_values(rec, {"direction": (0xF001,), "mode": (0xF00B,)})
    assert [(d.name, d.device) for d in drift] == [("direction", "forward")]
    with pytest.raises(SystemExit):
        main(["profiles", "show", str(tmp_path / "dev.yaml")])
    out = capsys.readouterr().out
    assert "mode" in out and "uint16 bits 3..5" in out and "float32 CDAB" in out and "string[4] ascii" in out
    with pytest.raises(SystemExit):
        main(["plan", str(tmp_path / "r.yaml")])
    assert "keeps its other bits as the device holds them" in capsys.readouterr().out


# ---- a device we did not write: umodbus -------------------------------------------------------


class _Recording(dict[int, int]):
    """umodbus's register store, remembering every write in order (umodbus has no request log)."""

    def __init__(self, values: dict[int, int]) -> None:
        super().__init__(values)
        self.writes: list[tuple[int, int, float]] = []

    def __setitem__(self, address: int, value: int) -> None:
        import time

        self.writes.append((address, value, time.monotonic()))
        super().__setitem__(address, value)


def test_guarded_sequence_against_umodbus(tmp_path: Path, drive: Profile) -> None:
    from tests.helpers import umodbus_server

    store = _Recording({a: 0 for a in (0x10, 0x20, 0x21, 0x30, 0x31, 0x32, 0x33, 0x34, 0x35, 0x36, 0x37, 0x38, 0x40)})
    store[0x10] = 0x0009  # running (bit 3) and a fault bit
    store[0x30] = 0x4001  # jog_step 4, enabled
    store.writes.clear()
    rec = load_recipe(recipe(tmp_path, "  mode: position\n  accel: 1.5 s\n", "drive.yaml"))
    with umodbus_server(store) as port:

        def run() -> DeviceResult:
            return asyncio.run(
                apply_device(
                    rec,
                    parse_url(f"tcp://127.0.0.1:{port}?timeout=1"),
                    1,
                    options=ApplyOptions(state_dir=str(tmp_path / ".d")),
                )
            )

        refused = run()
        assert refused.status == "failed" and "drive stopped" in (refused.error or "")
        assert store.writes == []  # nothing written
        store[0x10] = 0x0001  # stopped (the fault bit stays)
        store.writes.clear()
        res = run()
    assert res.status == "ok", res.to_json()
    assert [(a, v) for a, v, _ in store.writes] == [(0x20, 0x5AA5), (0x30, 0x4011), (0x40, 15), (0x21, 1), (0x20, 0)]
    t = [w[2] for w in store.writes]
    assert t[1] - t[0] >= 0.12 and t[2] - t[1] >= 0.10 and t[4] - t[3] >= 0.15  # unlock, stage 0, commit waits


def test_rejected_field_register_and_a_saved_plan(
    tmp_path: Path, fields: Profile, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(InputError, match="a bit field must be readable"):
        profile_from(tmp_path, FIELDS + "  cmd: {register: 0x50, type: bool, bits: 0, access: write-only}\n", "wo.yaml")
    # the device refuses the control word: both fields of it fail, the string after it still goes
    sim = Simulator(fields)
    sim.faults.fail_registers = frozenset({0x30})
    res = apply(sim, recipe(tmp_path, "  direction: reverse\n  mode: torque\n  name: AB\n"), tmp_path)
    st = {p.name: p.status for p in res.parameters}
    assert st == {"direction": "failed", "mode": "failed", "name": "ok"}, res.to_json()
    # plan --out against the device, then apply PLAN.json: the field register is merged again at write time
    with SimulatorThread(fields, init={0x30: 0x0001}) as s:
        plan = tmp_path / "plan.json"
        path = recipe(tmp_path, "  mode: torque\n  name: AB\n")
        with pytest.raises(SystemExit):
            main(["plan", path, "--device", s.url, "--out", str(plan), "--state-dir", str(tmp_path / "s")])
        assert [s["values"] for s in json.loads(plan.read_text())["steps"] if s["kind"] == "write"] == [
            [0x0009, 0x4142, 0x2020, 0x2020, 0x2020]
        ]
        s.write("enable", (0x3001,))  # jog_step changes after the plan was made
        with pytest.raises(SystemExit) as exc:
            main(["apply", str(plan), "--yes", "--state-dir", str(tmp_path / ".d")])
        assert exc.value.code == 0, capsys.readouterr()
        assert s.read("mode") == (0x3009,) and s.read("name") == (0x4142, 0x2020, 0x2020, 0x2020)


# ---- planner property: a register of fields plans like one whole register ----------------------


@st.composite
def _field_case(draw: st.DrawFn) -> tuple[list[Desired], dict[str, tuple[int, ...]], list[Desired], int]:
    """Registers 0..n-1 (some gaps), each a whole uint16 or 1-3 fields; the same recipe with whole registers."""
    n = draw(st.integers(1, 12))
    desired: list[Desired] = []
    whole: list[Desired] = []
    current: dict[str, tuple[int, ...]] = {}
    for a in range(n):
        if draw(st.booleans()) and a:
            continue  # a gap the recipe does not name
        word = draw(st.integers(0, 0xFFFF))
        if draw(st.booleans()):
            p = Parameter(f"r{a}", a, "uint16")
            value = draw(st.integers(0, 0xFFFF))
            desired.append(Desired(p, str(value), (value,)))
            whole.append(Desired(p, str(value), (value,)))
            current[p.name] = (word,)
            continue
        merged = word
        for k, (lo, width) in enumerate([(0, 2), (4, 3), (12, 4)][: draw(st.integers(1, 3))]):
            mask = ((1 << width) - 1) << lo
            p = Parameter(f"r{a}f{k}", a, "uint16", mask=mask)
            raw = draw(st.integers(0, (1 << width) - 1))
            desired.append(Desired(p, str(raw), p.encode(raw)))
            current[p.name] = (word,)
            merged = (merged & ~mask) | (raw << lo)
        q = Parameter(f"r{a}", a, "uint16")
        whole.append(Desired(q, str(merged), (merged,)))
        current[q.name] = (word,)
    return desired, current, whole, draw(st.integers(1, 5))


@settings(max_examples=200, deadline=None)
@given(_field_case())
def test_fields_plan_like_whole_registers(
    case: tuple[list[Desired], dict[str, tuple[int, ...]], list[Desired], int],
) -> None:
    desired, current, whole, limit = case
    limits = Limits(max_write_registers=limit)
    _, writes = plan_writes(desired, limits, current)
    _, expected = plan_writes(whole, limits, current)
    # the same requests, registers and words as if each field register were one merged uint16
    assert [(w.address, w.registers) for w in writes] == [(w.address, w.registers) for w in expected]
    named = {d.parameter.address for d in desired}
    for w in writes:
        assert set(range(w.address, w.address + w.count)) <= named  # never a register the recipe does not name
        for i, word in enumerate(w.registers):
            for d in desired:
                if d.parameter.address == w.address + i and d.parameter.mask:
                    assert d.parameter.same_value((word,), d.registers)  # the field's new bits
                    others = ~sum(e.parameter.mask for e in desired if e.parameter.address == d.parameter.address)
                    assert word & others & 0xFFFF == current[d.name][0] & others & 0xFFFF  # the rest as held


def test_builtin_example_drive_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from deployer.profile import builtin_profile

    example = Path(__file__).parent.parent / "recipes" / "examples" / "example-drive-axis1.yaml"
    prof = builtin_profile("example-drive")
    report = tmp_path / "report.json"
    with SimulatorThread(prof) as sim:
        sim.write("ready", (0x0008 | 0x0001,))  # running
        with pytest.raises(SystemExit) as exc:
            main(
                [
                    "apply",
                    str(example),
                    "--device",
                    sim.url,
                    "--yes",
                    "--report",
                    str(report),
                    "--state-dir",
                    str(tmp_path / ".d"),
                ]
            )
        assert exc.value.code == 4 and count(sim.log, 16) == 0
        sim.write("ready", (0x0001,))  # stopped
        with pytest.raises(SystemExit) as exc:
            main(
                [
                    "apply",
                    str(example),
                    "--device",
                    sim.url,
                    "--yes",
                    "--report",
                    str(report),
                    "--state-dir",
                    str(tmp_path / ".d"),
                ]
            )
        assert exc.value.code == 0, capsys.readouterr()
        writes = [(e.address, e.values) for e in sim.log if e.function == 16]
        assert sim.read("axis_name")[:3] == (0x582D, 0x4158, 0x4953)  # "X-AXIS"
    dev = json.loads(report.read_text())["devices"][0]
    assert dev["status"] == "ok"
    assert dev["notices"] == ["motor_poles takes effect after a power cycle"]
    assert writes[0] == (0x1F, [0x5AA5]) and writes[-2:] == [(0x20, [1]), (0x1F, [0])]  # unlock ... commit, lock
    assert "note: motor_poles takes effect after a power cycle" in capsys.readouterr().out


def test_field_register_unreadable_before_its_write_is_not_written(tmp_path: Path, fields: Profile) -> None:
    sim = Simulator(fields)
    rec = load_recipe(recipe(tmp_path, "  direction: reverse\n"))

    async def body(s: Simulator) -> DeviceResult:
        async def confirm(plan: object, res: object) -> bool:
            # the next request (the read right before the write) gets no answer
            s.faults.drop_every = len(s.log) + 1
            return True

        return await apply_device(
            rec,
            parse_url(s.url + "?timeout=0.2&retries=0"),
            1,
            options=ApplyOptions(state_dir=str(tmp_path / ".d"), confirm=confirm),
        )

    res = run_with(sim, body)
    assert res.parameters[0].status == "failed"
    assert (res.parameters[0].error or "").startswith("reading the register to keep its other bits")
    assert count(sim.log, 16) == 0 and sim.read("direction") == (0,)


def test_simulate_set_makes_the_drive_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import signal

    from tests.conftest import simulate_process

    example = Path(__file__).parent.parent / "recipes" / "examples" / "example-drive-axis1.yaml"
    proc, _, port = simulate_process("example-drive", "--set", "0x10=9")
    try:
        with pytest.raises(SystemExit) as exc:
            main(
                [
                    "apply",
                    str(example),
                    "--device",
                    f"tcp://127.0.0.1:{port}",
                    "--yes",
                    "--state-dir",
                    str(tmp_path / ".d"),
                ]
            )
        assert exc.value.code == 4
        assert "precondition failed: register 0x0010 bit 3 (drive stopped) is 1" in capsys.readouterr().out
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
    for bad, message in (
        ("0x10", "expected ADDR=RAW"),
        ("0x999=1", "not declared in profile example-drive"),
        ("0x10=70000", "a register holds 0..65535"),
    ):
        with pytest.raises(SystemExit) as exc:
            main(["simulate", "example-drive", "--set", bad])
        assert exc.value.code == 1 and message in capsys.readouterr().err


@pytest.mark.skipif(MBPOLL is None, reason="mbpoll (libmodbus) is not installed")
def test_mbpoll_sees_the_guarded_drive(tmp_path: Path, drive: Profile) -> None:
    """An independent client (libmodbus) checks the simulated drive: locked, refusing, then what apply wrote."""
    assert MBPOLL is not None
    with SimulatorThread(drive) as sim:
        port = sim.url.rsplit(":", 1)[1]

        def poll(*args: str, write: str | None = None) -> subprocess.CompletedProcess[str]:
            assert MBPOLL is not None
            return subprocess.run(
                [
                    MBPOLL,
                    "-m",
                    "tcp",
                    "-p",
                    port,
                    "-a",
                    "1",
                    "-0",
                    "-1",
                    *args,
                    "127.0.0.1",
                    *([write] if write else []),
                ],
                capture_output=True,
                text=True,
                timeout=20,
            )

        refused = poll("-r", "64", "-t", "4", write="15")  # accel while the parameters are locked
        assert refused.returncode != 0 and "Slave device or server failure" in refused.stdout + refused.stderr
        rec = load_recipe(recipe(tmp_path, "  mode: torque\n  direction: reverse\n  accel: 2 s\n", "drive.yaml"))
        options = ApplyOptions(state_dir=str(tmp_path / ".d"))
        res = asyncio.run(apply_device(rec, parse_url(sim.url), 1, options=options))
        assert res.status == "ok"
        out = poll("-r", "48", "-t", "4:hex")
        assert out.returncode == 0 and "[48]: \t0x000A" in out.stdout  # direction and mode bits
        out = poll("-r", "32", "-c", "2", "-t", "4")
        assert "[32]: \t0" in out.stdout and "[33]: \t1" in out.stdout  # locked again, stored to EEPROM
        again = poll("-r", "64", "-t", "4", write="15")
        assert "Slave device or server failure" in again.stdout + again.stderr  # and refusing again
