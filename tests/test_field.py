"""Devices that do not follow the book: refused blocks split, learned limits, FC06 fallback, pacing, identity.

Each quirk runs against the simulator and against a device from another library (umodbus) with the
same quirk; the tests check the report's statuses, the device's registers and the requests on the wire.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from deployer.execute.device import apply_device
from deployer.execute.session import ApplyOptions
from deployer.profile import Profile
from deployer.recipe.loader import load_recipe
from deployer.report import DeviceResult
from deployer.state import learned
from deployer.testing.simulator import Quirks, Simulator, SimulatorThread
from deployer.transport.clients import parse_url
from tests.helpers import cli, profile_from, run_with, umodbus_server

pytestmark = pytest.mark.timeout(120)

N = 14  # parameters p0..p13 at registers 100..113, one register each
BAD = 5  # p5's value is more than the device takes


def _profile_text(strict: bool) -> str:
    lines = ["profile: dev", "parameters:"]
    for i in range(N):
        top = 100 if strict and i == BAD else 1000
        lines.append(f"  p{i}: {{register: {100 + i}, type: uint16, max: {top}}}")
    return "\n".join(lines) + "\n"


def _recipe(tmp: Path, bad: bool = True, offset: int = 10) -> str:
    (tmp / "dev.yaml").write_text(_profile_text(strict=False))
    body = "".join(f"  p{i}: {500 if bad and i == BAD else offset + i}\n" for i in range(N))
    path = tmp / "r.yaml"
    path.write_text(f"recipe: r\nprofile: dev.yaml\nparameters:\n{body}")
    return str(path)


@pytest.fixture
def device_profile(tmp_path: Path) -> Profile:
    """The device's own rules: p5 takes at most 100 (the recipe's profile does not know)."""
    d = tmp_path / "device"
    d.mkdir()
    return profile_from(d, _profile_text(strict=True))


def _apply(url: str, recipe: str, tmp: Path, **opts: object) -> DeviceResult:
    import asyncio

    rec = load_recipe(recipe)
    return asyncio.run(
        apply_device(
            rec,
            parse_url(url + "?timeout=0.5"),
            1,
            options=ApplyOptions(state_dir=str(tmp / ".deployer"), backoff=0.01, **opts),  # type: ignore[arg-type]
        )
    )


def _apply_sim(
    sim: Simulator, recipe: str, tmp: Path, url_suffix: str = "?timeout=0.5", **opts: object
) -> DeviceResult:
    rec = load_recipe(recipe)

    async def body(s: Simulator) -> DeviceResult:
        return await apply_device(
            rec,
            parse_url(s.url + url_suffix),
            1,
            options=ApplyOptions(state_dir=str(tmp / ".deployer"), backoff=0.01, **opts),  # type: ignore[arg-type]
        )

    return run_with(sim, body)


def _writes(sim: Simulator) -> list[tuple[int, int, int, str]]:
    return [(e.function, e.address, e.count, e.result) for e in sim.log if e.function in (6, 16)]


def _statuses(res: DeviceResult) -> dict[str, str]:
    return {p.name: p.status for p in res.parameters}


# ---- refused blocks are split, not blamed ----------------------------------------------------------


def test_all_or_nothing_device_blames_only_the_refused_value(tmp_path: Path, device_profile: Profile) -> None:
    sim = Simulator(device_profile, quirks=Quirks(all_or_nothing=True))
    res = _apply_sim(sim, _recipe(tmp_path), tmp_path)
    want = {f"p{i}": "ok" for i in range(N)} | {f"p{BAD}": "failed"}
    assert _statuses(res) == want
    assert res.parameters[BAD].error == "exception 03 (illegal data value)"
    assert res.status == "partial"
    assert [sim.read(f"p{i}")[0] for i in range(N)] == [10 + i if i != BAD else 0 for i in range(N)]
    # bisection at parameter boundaries: each refused request of several parameters is sent again in halves
    assert _writes(sim) == [
        (16, 100, 14, "exception 03"),
        (16, 100, 7, "exception 03"),
        (16, 100, 3, "ok"),
        (16, 103, 4, "exception 03"),
        (16, 103, 2, "ok"),
        (16, 105, 2, "exception 03"),
        (16, 105, 1, "exception 03"),
        (16, 106, 1, "ok"),
        (16, 107, 7, "ok"),
    ]
    extra = len(_writes(sim)) - 1
    assert extra <= 2 * math.ceil(math.log2(N))  # O(log n): a write per half on the way down
    assert not res.learned and not any("limits." in n for n in res.notices)  # a bad value, not a length limit


def test_in_order_device_keeps_todays_handling(tmp_path: Path, device_profile: Profile) -> None:
    sim = Simulator(device_profile)  # writes in address order and stops at the bad value
    res = _apply_sim(sim, _recipe(tmp_path), tmp_path)
    assert _statuses(res) == {f"p{i}": "ok" for i in range(N)} | {f"p{BAD}": "failed"}
    assert _writes(sim) == [(16, 100, 14, "exception 03"), (16, 106, 8, "ok")]


def test_on_error_stop_splits_to_find_the_value_and_sends_nothing_after_it(
    tmp_path: Path, device_profile: Profile
) -> None:
    sim = Simulator(device_profile, quirks=Quirks(all_or_nothing=True))
    res = _apply_sim(sim, _recipe(tmp_path), tmp_path, on_error="stop")
    assert _statuses(res) == (
        {f"p{i}": "ok" for i in range(BAD)} | {f"p{BAD}": "failed"} | {f"p{i}": "skipped" for i in range(BAD + 1, N)}
    )
    assert [sim.read(f"p{i}")[0] for i in range(N)] == [10 + i if i < BAD else 0 for i in range(N)]
    assert _writes(sim)[-1] == (16, 105, 1, "exception 03")  # the culprit found, nothing sent after it


def test_well_behaved_device_sees_no_extra_request(tmp_path: Path, device_profile: Profile) -> None:
    sim = Simulator(device_profile, quirks=Quirks(all_or_nothing=True))
    res = _apply_sim(sim, _recipe(tmp_path, bad=False), tmp_path)
    assert res.status == "ok"
    assert _writes(sim) == [(16, 100, 14, "ok")]
    assert not res.learned


# ---- learned limits --------------------------------------------------------------------------------


def test_write_limit_is_learned_said_remembered_and_used(
    tmp_path: Path, device_profile: Profile, capsys: pytest.CaptureFixture[str]
) -> None:
    recipe = _recipe(tmp_path, bad=False)
    state = str(tmp_path / ".deployer")
    with SimulatorThread(device_profile, quirks=Quirks(max_write_registers=4)) as sim:
        res = _apply(sim.url, recipe, tmp_path)
        assert res.status == "ok" and set(_statuses(res).values()) == {"ok"}
        assert [sim.read(f"p{i}")[0] for i in range(N)] == [10 + i for i in range(N)]
        # once the 7-register refusal proved to be about length, the next piece tries the size between 4 and 7
        # (5: refused, split), and then the device's limit is known: the rest goes in pieces of 4
        assert _writes(sim) == [
            (16, 100, 14, "exception 03"),
            (16, 100, 7, "exception 03"),
            (16, 100, 3, "ok"),
            (16, 103, 4, "ok"),
            (16, 107, 5, "exception 03"),
            (16, 107, 2, "ok"),
            (16, 109, 3, "ok"),
            (16, 112, 2, "ok"),
        ]
        profile_path = str(tmp_path / "dev.yaml")
        assert res.notices == [
            "the device took 4-register writes and refused 5; set limits.max_write_registers: 4 in profile dev"
        ]
        assert res.learned == {"max_write_registers": 4}
        (entry,) = learned.load(state)
        assert (entry.profile, entry.limits) == (profile_path, {"max_write_registers": 4})
        assert entry.device.endswith("#unit1")

        # the next plan uses it, with a note, and the next apply sends no refused request
        recipe2 = _recipe(tmp_path, bad=False, offset=20)
        code, out, err = cli(capsys, "plan", recipe2, "--device", sim.url, "--state-dir", state)
        assert code == 0, err
        assert "note: using what this device taught on" in out
        assert "limits.max_write_registers: 4" in out
        assert "4 write requests (14 registers" in out
        sim.log.clear()
        code, out, err = cli(capsys, "apply", recipe2, "--device", sim.url, "--yes", "--json", "--state-dir", state)
        assert code == 0, err
        dev = json.loads(out)["devices"][0]
        assert not any(r["result"] == "exception" for r in dev["requests"] if r["function"] != 43)
        assert _writes(sim) == [(16, 100, 4, "ok"), (16, 104, 4, "ok"), (16, 108, 4, "ok"), (16, 112, 2, "ok")]
        assert any(n.startswith("using what this device taught") for n in dev["notices"])
        assert [sim.read(f"p{i}")[0] for i in range(N)] == [20 + i for i in range(N)]

    code, out, _ = cli(capsys, "learned", "list", "--state-dir", state)
    assert code == 0 and "limits.max_write_registers: 4" in out and "dev.yaml" in out
    code, out, _ = cli(capsys, "learned", "forget", "--profile", profile_path, "--state-dir", state)
    assert code == 0 and "forgot limits.max_write_registers: 4" in out
    assert learned.load(state) == []


def test_a_parameter_longer_than_the_writes_a_device_takes_is_said_so_then_and_later(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A 6-register name on a device taking 2 registers a write: no split can carry it. The apply that finds out
    says its length may be what was refused (not only "illegal data value"); later plans and applies refuse it
    before the first byte, naming the limit as what the device taught, not the profile (which allows it), and how
    to drop it; once forgotten, the profile's limits plan it again."""
    prof = tmp_path / "dev.yaml"
    prof.write_text(
        "profile: dev\nparameters:\n  p0: {register: 100, type: uint16}\n  p1: {register: 101, type: uint16}\n"
        "  p2: {register: 102, type: uint16}\n  name: {register: 110, type: string, count: 6, padding: space}\n"
    )
    recipe = tmp_path / "r.yaml"
    recipe.write_text("recipe: r\nprofile: dev.yaml\nparameters: {p0: 1, p1: 2, p2: 3, name: LONG-AXIS-1}\n")
    state = str(tmp_path / "s")
    with SimulatorThread(load_recipe(str(recipe)).profile, quirks=Quirks(max_write_registers=2)) as sim:
        code, out, err = cli(capsys, "apply", str(recipe), "--device", sim.url, "--yes", "--json", "--state-dir", state)
        dev = json.loads(out)["devices"][0]
        assert code == 4 and dev["status"] == "partial", (out, err)
        (name,) = [p for p in dev["parameters"] if p["name"] == "name"]
        assert name["status"] == "failed"
        assert name["error"] == (
            "exception 03 (illegal data value): the device took writes of up to 2 registers in this run, and "
            "name needs 6 in one request (its length may be what it refused)"
        )
        assert {p["name"]: p["status"] for p in dev["parameters"]} == {
            "p0": "ok",
            "p1": "ok",
            "p2": "ok",
            "name": "failed",
        }
        assert dev["learned"] == {"max_write_registers": 2}

        why = (
            "name needs 6 registers in one request, but the device takes at most 2 per request "
            "(limits.max_write_registers), which this device taught on "
        )
        code, out, err = cli(capsys, "plan", str(recipe), "--device", sim.url, "--state-dir", state)
        assert code == 1 and why in err and "(not its profile: limits.max_write_registers: 2)" in err, (out, err)
        assert "'deployer learned forget' drops what it taught" in err
        sim.log.clear()
        code, out, err = cli(capsys, "apply", str(recipe), "--device", sim.url, "--yes", "--json", "--state-dir", state)
        dev = json.loads(out)["devices"][0]
        assert code == 4 and dev["status"] == "failed" and why in dev["error"], (out, err)
        assert not [e for e in sim.log if e.function in (6, 16)]  # refused before the first byte
        # the recipe naming its device: the plan made without reading it says the same
        (tmp_path / "r2.yaml").write_text(recipe.read_text() + f"device: {{url: '{sim.url}'}}\n")
        code, out, err = cli(capsys, "plan", str(tmp_path / "r2.yaml"), "--state-dir", state)
        assert code == 1 and why in err, (out, err)

        code, out, err = cli(capsys, "learned", "forget", "--all", "--state-dir", state)
        assert code == 0, err
        code, out, err = cli(capsys, "plan", str(recipe), "--device", sim.url, "--state-dir", state)
        assert code == 0 and "taught" not in out + err, (out, err)


def test_api_check_mode_plans_with_what_the_device_taught(tmp_path: Path, device_profile: Profile) -> None:
    """deployer.plan and plan_fleet (Ansible's check mode) plan as apply will send: with the learned limit."""
    import deployer

    state = str(tmp_path / ".deployer")
    with SimulatorThread(device_profile, quirks=Quirks(max_write_registers=4)) as sim:
        assert _apply(sim.url, _recipe(tmp_path, bad=False), tmp_path).learned == {"max_write_registers": 4}
        rec = deployer.load_recipe(_recipe(tmp_path, bad=False, offset=20))
        writes = len(_writes(sim))
        taught = deployer.plan(rec, sim.url, state_dir=state)
        assert [w.count for w in taught.writes] == [4, 4, 4, 2]
        assert [w.count for w in deployer.plan(rec, sim.url, state_dir=None).writes] == [14]
        planned = deployer.plan(rec, inventory=[{"name": "d", "url": sim.url}], state_dir=state)["d"]
        assert isinstance(planned, deployer.Plan) and [w.count for w in planned.writes] == [4, 4, 4, 2]
        assert len(_writes(sim)) == writes  # planning reads only


def test_what_a_device_taught_is_kept_under_its_address_however_spelled() -> None:
    from deployer.transport.urls import parse_url

    keys = {
        learned.device_id(parse_url(f"tcp://{host}:1502"), 3)
        for host in ("127.0.0.1", "localhost", "127.1", "2130706433")
    }
    assert len(keys) == 1 and next(iter(keys)).endswith("#unit3")
    assert learned.device_id(parse_url("tcp://127.0.0.2:1502"), 3) not in keys


# ---- Function 06 only ------------------------------------------------------------------------------


def test_fc16_refused_with_01_falls_back_to_fc06_and_says_so(tmp_path: Path, device_profile: Profile) -> None:
    sim = Simulator(device_profile, quirks=Quirks(fc06_only=True))
    res = _apply_sim(sim, _recipe(tmp_path, bad=False), tmp_path)
    assert res.status == "ok" and set(_statuses(res).values()) == {"ok"}
    assert _writes(sim) == [(16, 100, 14, "exception 01")] + [(6, 100 + i, 1, "ok") for i in range(N)]
    assert res.notices == [
        "the device refused Function 16 writes (exception 01) and took Function 06; "
        "set limits.write_function: 6 in profile dev"
    ]
    assert res.learned == {"write_function": 6}
    assert [sim.read(f"p{i}")[0] for i in range(N)] == [10 + i for i in range(N)]


# ---- the same quirks on a device we did not write (umodbus) ----------------------------------------


def _store() -> dict[int, int]:
    return {100 + i: 0 for i in range(N)}


def test_umodbus_all_or_nothing_device(tmp_path: Path) -> None:
    store = _store()
    wire: list[tuple[int, int, int]] = []  # (function, address, count) of each request
    with umodbus_server(store, maximum={100 + BAD: 100}, all_or_nothing=True, wire=wire) as port:
        res = _apply(f"tcp://127.0.0.1:{port}", _recipe(tmp_path), tmp_path)
    assert _statuses(res) == {f"p{i}": "ok" for i in range(N)} | {f"p{BAD}": "failed"}
    assert res.parameters[BAD].error == "exception 03 (illegal data value)"
    assert [store[100 + i] for i in range(N)] == [10 + i if i != BAD else 0 for i in range(N)]
    assert [(a, n) for fc, a, n in wire if fc == 16] == [
        (100, 14),
        (100, 7),
        (100, 3),
        (103, 4),
        (103, 2),
        (105, 2),
        (105, 1),
        (106, 1),
        (107, 7),
    ]
    assert res.identity is None  # umodbus answers 01 to Function 43: skipped quietly
    assert [r.exception_code for r in res.requests if r.function == 43] == [1]


def test_umodbus_in_order_device(tmp_path: Path) -> None:
    store = _store()
    wire: list[tuple[int, int, int]] = []  # (function, address, count) of each request
    with umodbus_server(store, maximum={100 + BAD: 100}, wire=wire) as port:
        res = _apply(f"tcp://127.0.0.1:{port}", _recipe(tmp_path), tmp_path)
    assert _statuses(res) == {f"p{i}": "ok" for i in range(N)} | {f"p{BAD}": "failed"}
    assert [(a, n) for fc, a, n in wire if fc == 16] == [(100, 14), (106, 8)]


def test_umodbus_write_limit_is_learned(tmp_path: Path) -> None:
    store = _store()
    wire: list[tuple[int, int, int]] = []  # (function, address, count) of each request
    with umodbus_server(store, max_write=5, wire=wire) as port:
        res = _apply(f"tcp://127.0.0.1:{port}", _recipe(tmp_path, bad=False), tmp_path)
        assert res.status == "ok"
        assert [store[100 + i] for i in range(N)] == [10 + i for i in range(N)]
        # 14 and 7 refused, 3 and 4 taken; the next piece tries 5 (between 4 and 7): taken; the last two
        # registers need no longer piece, so 6 is never tried: the limit is known to lie in 5..6
        assert [(a, n) for fc, a, n in wire if fc == 16] == [
            (100, 14),
            (100, 7),
            (100, 3),
            (103, 4),
            (107, 5),
            (112, 2),
        ]
        assert res.learned == {"max_write_registers": 5}
        assert res.notices == [
            "the device took 5-register writes and refused 7; set limits.max_write_registers: 5 in profile dev"
        ]
        wire.clear()
        res = _apply(f"tcp://127.0.0.1:{port}", _recipe(tmp_path, bad=False, offset=30), tmp_path)
    assert res.status == "ok" and not res.learned
    assert [(a, n) for fc, a, n in wire if fc == 16] == [(100, 5), (105, 5), (110, 4)]
    assert [store[100 + i] for i in range(N)] == [30 + i for i in range(N)]


def test_umodbus_fc06_only_device(tmp_path: Path) -> None:
    store = _store()
    wire: list[tuple[int, int, int]] = []  # (function, address, count) of each request
    with umodbus_server(store, fc06_only=True, wire=wire) as port:
        res = _apply(f"tcp://127.0.0.1:{port}", _recipe(tmp_path, bad=False), tmp_path)
    assert res.status == "ok" and res.learned == {"write_function": 6}
    assert [(fc, a) for fc, a, _ in wire if fc in (6, 16)] == [(16, 100)] + [(6, 100 + i) for i in range(N)]
    assert [store[100 + i] for i in range(N)] == [10 + i for i in range(N)]


# ---- pauses the device needs ------------------------------------------------------------------------


def _pacing_profile(tmp: Path, limits: str = "") -> tuple[Profile, str]:
    text = _profile_text(strict=False)
    if limits:
        text = text.replace("parameters:", f"limits: {limits}\nparameters:")
    (tmp / "dev.yaml").write_text(text)
    body = "".join(f"  p{i}: {10 + i}\n" for i in range(3))
    path = tmp / "r.yaml"
    path.write_text(f"recipe: r\nprofile: dev.yaml\nparameters:\n{body}")
    return profile_from(tmp, text, "dev.yaml"), str(path)


def _too_soon(sim: Simulator) -> int:
    return sum(1 for e in sim.log if e.result == "too soon")


def test_device_needing_pauses_drops_requests_that_come_too_soon(tmp_path: Path) -> None:
    prof, recipe = _pacing_profile(tmp_path)
    sim = Simulator(prof, quirks=Quirks(pause_after_connect_ms=200, request_gap_ms=100))
    res = _apply_sim(sim, recipe, tmp_path, url_suffix="?timeout=0.3&retries=3")
    assert _too_soon(sim) > 0  # without pauses: requests lost, each costing a timeout and a retry
    assert any(r.result == "no response" or r.attempts > 1 for r in res.requests)


@pytest.mark.parametrize("where", ["url", "profile"])
def test_pauses_from_the_url_or_the_profile_are_kept(tmp_path: Path, where: str) -> None:
    limits = "{pause_after_connect: 300ms, pause_between_requests: 150}" if where == "profile" else ""
    prof, recipe = _pacing_profile(tmp_path, limits)
    pauses = "&pause_after_connect=0.3&pause_between_requests=150ms" if where == "url" else ""
    suffix = "?timeout=2&retries=0" + pauses
    sim = Simulator(prof, quirks=Quirks(pause_after_connect_ms=200, request_gap_ms=100))
    res = _apply_sim(sim, recipe, tmp_path, url_suffix=suffix)
    assert res.status == "ok", res.to_json()
    assert _too_soon(sim) == 0 and all(r.attempts == 1 and r.result in ("ok", "exception") for r in res.requests)
    assert [sim.read(f"p{i}")[0] for i in range(3)] == [10, 11, 12]


def test_plan_time_estimate_includes_the_pauses(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _, recipe = _pacing_profile(tmp_path, "{pause_after_connect: 1s, pause_between_requests: 250ms}")
    code, out, err = cli(capsys, "plan", recipe)
    assert code == 0, err
    # 1 s after connecting, then 250 ms before each of the other 3 requests (snapshot, Function 43, write,
    # read-back)
    assert "(1750 ms of it waits and pauses the device needs)" in out
    # the device URL's options override the profile's (a recipe's device.url: still an offline plan)
    text = (
        Path(recipe)
        .read_text()
        .replace(
            "parameters:",
            'device: {url: "tcp://127.0.0.1:502?pause_after_connect=0&pause_between_requests=0.1"}\nparameters:',
        )
    )
    Path(recipe).write_text(text)
    code, out, err = cli(capsys, "plan", recipe)
    assert code == 0, err
    assert "116 bytes in Modbus/TCP frames, 300 ms of waits" in out  # 3 pauses of 100 ms between 4 requests


def test_bad_pause_is_an_error_at_its_position(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "dev.yaml").write_text(
        _profile_text(strict=False).replace("parameters:", "limits: {pause_between_requests: soon}\nparameters:")
    )
    code, _, err = cli(capsys, "validate", str(tmp_path / "dev.yaml"))
    assert code == 1
    assert f"{tmp_path / 'dev.yaml'}:2:" in err and "pause_between_requests" in err
    code, _, err = cli(capsys, "plan", _recipe(tmp_path), "--device", "tcp://127.0.0.1:502?pause_after_connect=x")
    assert code == 1 and "pause_after_connect" in err and "is not a duration" in err


# ---- identity (Function 43 / 14) ---------------------------------------------------------------------

ACME = {0: "ACME", 1: "AC-7", 2: "2.1"}


def test_simulator_answers_function_43_as_the_spec_frames_it(device_profile: Profile) -> None:
    """Raw Modbus/TCP bytes, no client library: request 2B 0E 01 00 (read basic identification from
    object 0); the answer lists each object as id, length, text (Modbus Application Protocol 6.21)."""
    import socket

    with SimulatorThread(device_profile, quirks=Quirks(identity=ACME)) as sim:
        host, port = sim.url.removeprefix("tcp://").split(":")
        with socket.create_connection((host, int(port)), timeout=5) as s:
            s.sendall(bytes.fromhex("0001 0000 0005 01 2B0E0100"))
            answer = s.recv(260)
    objects = b"".join(bytes([i, len(t)]) + t.encode() for i, t in ACME.items())
    pdu = bytes.fromhex("2B 0E 01 83 00 00 03") + objects  # conformity 83h, no more follows, 3 objects
    assert answer == bytes.fromhex("0001 0000") + (len(pdu) + 1).to_bytes(2, "big") + b"\x01" + pdu


def test_identity_is_read_reported_snapshotted_and_journaled(
    tmp_path: Path, device_profile: Profile, capsys: pytest.CaptureFixture[str]
) -> None:
    recipe = _recipe(tmp_path, bad=False)
    state = tmp_path / ".deployer"
    with SimulatorThread(device_profile, quirks=Quirks(identity=ACME)) as sim:
        code, out, err = cli(capsys, "apply", recipe, "--device", sim.url, "--yes", "--json", "--state-dir", str(state))
    assert code == 0, err
    dev = json.loads(out)["devices"][0]
    assert dev["identity"] == {"vendor": "ACME", "product_code": "AC-7", "revision": "2.1"}
    assert "identity:" in Path(dev["snapshot"]).read_text()
    snap = load_recipe(dev["snapshot"])
    assert snap.snapshot is not None and snap.snapshot.identity == dev["identity"]
    finished = [
        json.loads(line) for line in (state / "audit.jsonl").read_text().splitlines() if '"device-finished"' in line
    ]
    assert finished[-1]["identity"] == dev["identity"]


def test_a_replaced_device_is_noted(
    tmp_path: Path, device_profile: Profile, capsys: pytest.CaptureFixture[str]
) -> None:
    state = str(tmp_path / ".deployer")
    with SimulatorThread(device_profile, quirks=Quirks(identity=ACME)) as sim:
        code, out, err = cli(
            capsys, "apply", _recipe(tmp_path, bad=False), "--device", sim.url, "--yes", "--state-dir", state
        )
        assert code == 0, err
        assert "identity: vendor 'ACME', product_code 'AC-7', revision '2.1'" in out
        sim.set_identity({0: "ACME", 1: "AC-9", 2: "3.0"})  # swapped for another model
        code, out, err = cli(
            capsys,
            "apply",
            _recipe(tmp_path, bad=False, offset=40),
            "--device",
            sim.url,
            "--yes",
            "--json",
            "--state-dir",
            state,
        )
    assert code == 0, err
    (note,) = [n for n in json.loads(out)["devices"][0]["notices"] if "identity changed" in n]
    assert "product_code 'AC-7'" in note and "product_code 'AC-9'" in note and "replaced" in note


def test_identity_object_check(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = _profile_text(strict=False).replace(
        "parameters:",
        "identity:\n  - {object: vendor, equals: ACME}\n  - {object: product_code, equals: AC-7}\nparameters:",
    )
    (tmp_path / "dev.yaml").write_text(text)
    body = "".join(f"  p{i}: {10 + i}\n" for i in range(N))
    (tmp_path / "r.yaml").write_text(f"recipe: r\nprofile: dev.yaml\nparameters:\n{body}")
    prof = profile_from(tmp_path, text, "dev.yaml")
    with SimulatorThread(prof) as sim:  # serves the profile's identity objects
        code, out, err = cli(
            capsys,
            "apply",
            str(tmp_path / "r.yaml"),
            "--device",
            sim.url,
            "--yes",
            "--json",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 0, err
    with SimulatorThread(prof, quirks=Quirks(identity={0: "ACME", 1: "AC-9"})) as sim:
        code, out, err = cli(
            capsys,
            "apply",
            str(tmp_path / "r.yaml"),
            "--device",
            sim.url,
            "--yes",
            "--json",
            "--state-dir",
            str(tmp_path / "s"),
        )
        dev = json.loads(out)["devices"][0]
        assert code == 4 and dev["status"] == "failed"
        assert dev["error"] == (
            "identity check failed: product_code is 'AC-9', expected 'AC-7': another kind of "
            "device answers here; nothing was written"
        )
        assert not [e for e in sim.log if e.function in (6, 16)]
    store = _store()
    with umodbus_server(store) as port:  # no Function 43 at all
        code, out, err = cli(
            capsys,
            "apply",
            str(tmp_path / "r.yaml"),
            "--device",
            f"tcp://127.0.0.1:{port}",
            "--yes",
            "--json",
            "--state-dir",
            str(tmp_path / "s"),
        )
    dev = json.loads(out)["devices"][0]
    assert code == 4 and dev["error"].startswith("identity check failed: the device does not answer Function 43")
    assert set(store.values()) == {0}


# ---- scan ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("scheme", ["rtu+tcp", "tcp"])
def test_scan_finds_the_units_that_answer_and_writes_an_inventory(
    tmp_path: Path, device_profile: Profile, capsys: pytest.CaptureFixture[str], scheme: str
) -> None:
    out_file = tmp_path / "inventory.yaml"
    with SimulatorThread(
        device_profile, listen=f"{scheme}://127.0.0.1:0", units=(1, 3, 7), quirks=Quirks(identity=ACME)
    ) as sim:
        code, out, err = cli(
            capsys, "scan", sim.url, "--unit", "1-5", "--unit", "7,8", "--timeout", "0.3", "-o", str(out_file), "--json"
        )
        log = list(sim.log)
    assert code == 0, err
    data = json.loads(out)
    assert data["asked"] == 7
    assert [(u["unit"], u["answer"], u["identity"]) for u in data["units"]] == [
        (unit, "exception 02", {"vendor": "ACME", "product_code": "AC-7", "revision": "2.1"}) for unit in (1, 3, 7)
    ]
    # bounded: one request per silent unit (no retry), an FC03 and an FC43 per unit that answers
    assert sorted((e.unit, e.function) for e in log) == sorted(
        [(u, 3) for u in (1, 2, 3, 4, 5, 7, 8)] + [(u, 43) for u in (1, 3, 7)]
    )
    if scheme == "rtu+tcp":  # a serial line: silent units cost their timeout
        assert [e.result for e in log if e.unit not in (1, 3, 7)] == ["no answer"] * 4
    else:  # a TCP gateway answers 0Bh for units it cannot reach: no wait at all
        assert {e.result for e in log if e.unit not in (1, 3, 7)} == {"exception 11"}
    assert "asking 7 unit ids" in err and "at most 2.1 s" in err
    text = out_file.read_text()
    assert "unit-3:  # vendor ACME, product_code AC-7, revision 2.1" in text
    code, _, err = cli(capsys, "validate", str(out_file))
    assert code == 0, err


def test_scan_of_a_silent_bus_exits_3_and_bad_units_are_usage_errors(
    device_profile: Profile, capsys: pytest.CaptureFixture[str]
) -> None:
    with SimulatorThread(device_profile, listen="rtu+tcp://127.0.0.1:0", units=(9,)) as sim:
        code, out, _ = cli(capsys, "scan", sim.url, "--unit", "1-2", "--timeout", "0.1")
    assert code == 3 and "0 of 2 unit ids answered" in out
    code, _, err = cli(capsys, "scan", "tcp://127.0.0.1:1", "--unit", "0-300")
    assert code == 1 and "unit ids are 1..247" in err


# ---- probe ---------------------------------------------------------------------------------------------

DRIVE_TRUTH = """\
profile: drive
byte_order: CDAB
parameters:
  gain: {register: 10, type: float32, default: 2.5}
  count: {register: 12, type: uint32, max: 100000, default: 70000}
  speed: {register: 14, type: uint16, scale: 0.1, unit: Hz, max: 400, default: 50}
  command: {register: 15, type: uint16, access: write-only}
"""
DRIVE_GUESS = """\
profile: drive-guess
parameters:
  gain: {register: 10, type: float32}
  count: {register: 12, type: uint32, max: 100000}
  speed: {register: 14, type: uint16, scale: 0.01, unit: Hz, max: 400}
  command: {register: 15, type: uint16}
"""


def test_probe_finds_word_order_scale_unreadable_register_and_identity(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    truth = profile_from(tmp_path, DRIVE_TRUTH, "truth.yaml")
    guess = tmp_path / "guess.yaml"
    guess.write_text(DRIVE_GUESS)
    with SimulatorThread(truth, quirks=Quirks(identity=ACME)) as sim:
        code, out, err = cli(
            capsys,
            "probe",
            str(guess),
            "--device",
            sim.url,
            "--expect",
            "gain=2.5",
            "--expect",
            "count=70000",
            "--expect",
            "speed=50 Hz",
            "--json",
        )
        writes = [e for e in sim.log if e.function in (5, 6, 15, 16)]
    assert code == 2, err
    data = json.loads(out)
    assert data["identity"] == {"vendor": "ACME", "product_code": "AC-7", "revision": "2.1"}
    assert data["changes"] == [
        "identity: - {object: product_code, equals: 'AC-7'} (recognises the device before any write)",
        "command: access: write-only if it is a command register, else check its address (0x000F)",
        "count: check its scale, type and byte_order, or widen min/max",
        "gain: byte_order: CDAB",
        "count: byte_order: CDAB",
        "speed: scale: 0.1",
        "byte_order: CDAB for the whole profile (top level) instead of per parameter",
    ]
    seen = {f["parameter"]: f["seen"] for f in data["findings"] if f["parameter"] == "gain"}
    assert seen["gain"].startswith("gain: 2.5 is held as CDAB (the profile reads ABCD")
    assert writes == []  # read-only

    # the fixed profile fits: exit 0
    fixed = tmp_path / "fixed.yaml"
    fixed.write_text(
        DRIVE_TRUTH.replace("profile: drive", "profile: drive-fixed").replace(
            "parameters:", "identity:\n  - {object: product_code, equals: AC-7}\nparameters:"
        )
    )
    with SimulatorThread(truth, quirks=Quirks(identity=ACME)) as sim:
        code, out, err = cli(capsys, "probe", str(fixed), "--device", sim.url, "--expect", "gain=2.5")
    assert code == 0, out + err
    assert "gain reads 2.5 as expected (CDAB)" in out and "the profile fits" in out


def test_probe_against_umodbus_finds_the_word_order(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    guess = tmp_path / "guess.yaml"
    guess.write_text("profile: meter\nparameters:\n  energy: {register: 100, type: uint32}\n")
    store = {100: 0x1170, 101: 0x0001}  # 70000 with the low word first
    with umodbus_server(store) as port:
        code, out, err = cli(
            capsys, "probe", str(guess), "--device", f"tcp://127.0.0.1:{port}", "--expect", "energy=70000"
        )
    assert code == 2, err
    assert "energy: 70000 is held as CDAB (the profile reads ABCD: 292552705)" in out
    assert "  - energy: byte_order: CDAB" in out
    assert "identity none (no Function 43)" in out


def test_fleet_run_notes_the_replaced_device(
    tmp_path: Path, device_profile: Profile, capsys: pytest.CaptureFixture[str]
) -> None:
    from tests.helpers import Simulators

    state = str(tmp_path / ".deployer")
    recipe = _recipe(tmp_path, bad=False)
    sims = [Simulator(device_profile, quirks=Quirks(identity=dict(ACME))) for _ in range(3)]
    with Simulators(sims) as (a, b, c):
        inv = tmp_path / "inventory.yaml"
        inv.write_text(
            "devices:\n" + "".join(f"  {n}: {{url: '{s.url}'}}\n" for n, s in zip("abc", (a, b, c), strict=True))
        )
        code, _, err = cli(capsys, "apply", recipe, "--inventory", str(inv), "--yes", "--state-dir", state)
        assert code == 0, err
        b.set_identity({0: "OTHER", 1: "X-1", 2: "9"})  # someone swapped device b
        code, out, err = cli(
            capsys,
            "apply",
            _recipe(tmp_path, bad=False, offset=50),
            "--inventory",
            str(inv),
            "--yes",
            "--json",
            "--state-dir",
            state,
        )
    assert code == 0, err
    notes = {
        d["name"]: [n for n in d.get("notices", []) if "identity changed" in n] for d in json.loads(out)["devices"]
    }
    assert notes["a"] == [] and notes["c"] == []
    (note,) = notes["b"]
    assert "vendor 'ACME'" in note and "vendor 'OTHER'" in note and "it may have been replaced" in note


def test_pauses_are_kept_per_bus_across_the_devices_of_a_gateway(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two units behind one RTU gateway that drops requests coming within 100 ms of its last answer: with
    the pause on both devices' URL, a fleet run of both loses no request (the bus keeps it between them)."""
    from tests.helpers import Simulators

    prof, recipe = _pacing_profile(tmp_path)
    gateway = Simulator(prof, listen="rtu+tcp://127.0.0.1:0", units=(1, 2), quirks=Quirks(request_gap_ms=100))
    with Simulators([gateway]) as (gw,):
        inv = tmp_path / "inventory.yaml"
        url = f"{gw.url}?pause_between_requests=150ms&timeout=2"
        inv.write_text(
            f"defaults: {{retries: 0}}\ndevices:\n  a: {{url: '{url}', unit: 1}}\n  b: {{url: '{url}', unit: 2}}\n"
        )
        code, out, err = cli(
            capsys,
            "apply",
            recipe,
            "--inventory",
            str(inv),
            "--yes",
            "--json",
            "--state-dir",
            str(tmp_path / "s"),
            "--parallel",
            "2",
        )
        log = list(gw.log)
    assert code == 0, err
    assert [d["status"] for d in json.loads(out)["devices"]] == ["ok", "ok"]
    assert {e.unit for e in log} == {1, 2} and _too_soon(gw) == 0


def test_scan_of_a_serial_line(socat_pair: tuple[str, str], device_profile: Profile) -> None:
    """A real serial line (socat pty pair): units 2 and 5 answer, the others stay silent; every unit is
    asked once (unit, 03, register 0, 1 register, as the device decoded it off the line), no retry."""
    import asyncio

    from deployer.execute.scan import scan
    from deployer.transport.urls import parse_url

    a, b = socat_pair

    async def main() -> tuple[list[int], list[bytes]]:
        sim = Simulator(device_profile, listen=f"rtu://{a}", units=(2, 5), quirks=Quirks(identity=ACME))
        async with sim:
            result = await scan(parse_url(f"rtu://{b}?baudrate=19200&timeout=0.2"), range(1, 7))
            return [u.unit for u in result.units], [bytes.fromhex(e.request_hex) for e in sim.log]

    found, requests = asyncio.run(main())
    assert found == [2, 5]
    # the simulator hears every request on the line; units 2 and 5 are also asked for their identity
    assert [r for r in requests if r[1] == 3] == [bytes([u, 3, 0, 0, 0, 1]) for u in range(1, 7)]
    assert [r for r in requests if r[1] == 0x2B] == [bytes([u, 0x2B, 0x0E, 1, 0]) for u in (2, 5)]
