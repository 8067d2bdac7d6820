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
from tests.helpers import profile_from, quirky_umodbus, run_cli, run_with

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
    return asyncio.run(apply_device(rec, parse_url(url + "?timeout=0.5"), 1, options=ApplyOptions(
        state_dir=str(tmp / ".deployer"), backoff=0.01, **opts)))  # type: ignore[arg-type]


def _apply_sim(sim: Simulator, recipe: str, tmp: Path, url_suffix: str = "?timeout=0.5",
               **opts: object) -> DeviceResult:
    rec = load_recipe(recipe)

    async def body(s: Simulator) -> DeviceResult:
        return await apply_device(rec, parse_url(s.url + url_suffix), 1, options=ApplyOptions(
            state_dir=str(tmp / ".deployer"), backoff=0.01, **opts))  # type: ignore[arg-type]
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
        (16, 100, 14, "exception 03"), (16, 100, 7, "exception 03"), (16, 100, 3, "ok"),
        (16, 103, 4, "exception 03"), (16, 103, 2, "ok"), (16, 105, 2, "exception 03"),
        (16, 105, 1, "exception 03"), (16, 106, 1, "ok"), (16, 107, 7, "ok")]
    extra = len(_writes(sim)) - 1
    assert extra <= 2 * math.ceil(math.log2(N))  # O(log n): a write per half on the way down
    assert not res.learned and not any("limits." in n for n in res.notices)  # a bad value, not a length limit


def test_in_order_device_keeps_todays_handling(tmp_path: Path, device_profile: Profile) -> None:
    sim = Simulator(device_profile)  # writes in address order and stops at the bad value
    res = _apply_sim(sim, _recipe(tmp_path), tmp_path)
    assert _statuses(res) == {f"p{i}": "ok" for i in range(N)} | {f"p{BAD}": "failed"}
    assert _writes(sim) == [(16, 100, 14, "exception 03"), (16, 106, 8, "ok")]


def test_on_error_stop_splits_to_find_the_value_and_sends_nothing_after_it(tmp_path: Path,
                                                                          device_profile: Profile) -> None:
    sim = Simulator(device_profile, quirks=Quirks(all_or_nothing=True))
    res = _apply_sim(sim, _recipe(tmp_path), tmp_path, on_error="stop")
    assert _statuses(res) == ({f"p{i}": "ok" for i in range(BAD)} | {f"p{BAD}": "failed"}
                              | {f"p{i}": "skipped" for i in range(BAD + 1, N)})
    assert [sim.read(f"p{i}")[0] for i in range(N)] == [10 + i if i < BAD else 0 for i in range(N)]
    assert _writes(sim)[-1] == (16, 105, 1, "exception 03")  # the culprit found, nothing sent after it


def test_well_behaved_device_sees_no_extra_request(tmp_path: Path, device_profile: Profile) -> None:
    sim = Simulator(device_profile, quirks=Quirks(all_or_nothing=True))
    res = _apply_sim(sim, _recipe(tmp_path, bad=False), tmp_path)
    assert res.status == "ok"
    assert _writes(sim) == [(16, 100, 14, "ok")]
    assert not res.learned


# ---- learned limits --------------------------------------------------------------------------------


def test_write_limit_is_learned_said_remembered_and_used(tmp_path: Path, device_profile: Profile,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    recipe = _recipe(tmp_path, bad=False)
    state = str(tmp_path / ".deployer")
    with SimulatorThread(device_profile, quirks=Quirks(max_write_registers=4)) as sim:
        res = _apply(sim.url, recipe, tmp_path)
        assert res.status == "ok" and set(_statuses(res).values()) == {"ok"}
        assert [sim.read(f"p{i}")[0] for i in range(N)] == [10 + i for i in range(N)]
        # once the 7-register refusal proved to be about length, the rest goes in pieces of 4
        assert _writes(sim) == [(16, 100, 14, "exception 03"), (16, 100, 7, "exception 03"), (16, 100, 3, "ok"),
                                (16, 103, 4, "ok"), (16, 107, 4, "ok"), (16, 111, 3, "ok")]
        profile_path = str(tmp_path / "dev.yaml")
        assert res.notices == [
            "the device took 4-register writes and refused 7; set limits.max_write_registers: 4 in profile dev"]
        assert res.learned == {"max_write_registers": 4}
        (entry,) = learned.load(state)
        assert (entry.profile, entry.limits) == (profile_path, {"max_write_registers": 4})
        assert entry.device.endswith("#unit1")

        # the next plan uses it, with a note, and the next apply sends no refused request
        recipe2 = _recipe(tmp_path, bad=False, offset=20)
        code, out, err = run_cli(capsys, "plan", recipe2, "--device", sim.url, "--state-dir", state)
        assert code == 0, err
        assert "note: using what this device taught on" in out
        assert "limits.max_write_registers: 4" in out
        assert "4 write requests (14 registers" in out
        sim.log.clear()
        code, out, err = run_cli(capsys, "apply", recipe2, "--device", sim.url, "--yes", "--json",
                                 "--state-dir", state)
        assert code == 0, err
        dev = json.loads(out)["devices"][0]
        assert not any(r["result"] == "exception" for r in dev["requests"] if r["function"] != 43)
        assert _writes(sim) == [(16, 100, 4, "ok"), (16, 104, 4, "ok"), (16, 108, 4, "ok"), (16, 112, 2, "ok")]
        assert any(n.startswith("using what this device taught") for n in dev["notices"])
        assert [sim.read(f"p{i}")[0] for i in range(N)] == [20 + i for i in range(N)]

    code, out, _ = run_cli(capsys, "learned", "list", "--state-dir", state)
    assert code == 0 and "limits.max_write_registers: 4" in out and "dev.yaml" in out
    code, out, _ = run_cli(capsys, "learned", "forget", "--profile", profile_path, "--state-dir", state)
    assert code == 0 and "forgot limits.max_write_registers: 4" in out
    assert learned.load(state) == []


# ---- Function 06 only ------------------------------------------------------------------------------


def test_fc16_refused_with_01_falls_back_to_fc06_and_says_so(tmp_path: Path, device_profile: Profile) -> None:
    sim = Simulator(device_profile, quirks=Quirks(fc06_only=True))
    res = _apply_sim(sim, _recipe(tmp_path, bad=False), tmp_path)
    assert res.status == "ok" and set(_statuses(res).values()) == {"ok"}
    assert _writes(sim) == [(16, 100, 14, "exception 01")] + [(6, 100 + i, 1, "ok") for i in range(N)]
    assert res.notices == ["the device refused Function 16 writes (exception 01) and took Function 06; "
                           "set limits.write_function: 6 in profile dev"]
    assert res.learned == {"write_function": 6}
    assert [sim.read(f"p{i}")[0] for i in range(N)] == [10 + i for i in range(N)]


# ---- the same quirks on a device we did not write (umodbus) ----------------------------------------


def _store() -> dict[int, int]:
    return {100 + i: 0 for i in range(N)}


def test_umodbus_all_or_nothing_device(tmp_path: Path) -> None:
    store = _store()
    wire: list[tuple[int, int, int]] = []  # (function, address, count) of each request
    with quirky_umodbus(store, maximum={100 + BAD: 100}, all_or_nothing=True, wire=wire) as port:
        res = _apply(f"tcp://127.0.0.1:{port}", _recipe(tmp_path), tmp_path)
    assert _statuses(res) == {f"p{i}": "ok" for i in range(N)} | {f"p{BAD}": "failed"}
    assert res.parameters[BAD].error == "exception 03 (illegal data value)"
    assert [store[100 + i] for i in range(N)] == [10 + i if i != BAD else 0 for i in range(N)]
    assert [(a, n) for fc, a, n in wire if fc == 16] == [(100, 14), (100, 7), (100, 3), (103, 4), (103, 2),
                                                          (105, 2), (105, 1), (106, 1), (107, 7)]
    assert res.identity is None  # umodbus answers 01 to Function 43: skipped quietly
    assert [r.exception_code for r in res.requests if r.function == 43] == [1]


def test_umodbus_in_order_device(tmp_path: Path) -> None:
    store = _store()
    wire: list[tuple[int, int, int]] = []  # (function, address, count) of each request
    with quirky_umodbus(store, maximum={100 + BAD: 100}, wire=wire) as port:
        res = _apply(f"tcp://127.0.0.1:{port}", _recipe(tmp_path), tmp_path)
    assert _statuses(res) == {f"p{i}": "ok" for i in range(N)} | {f"p{BAD}": "failed"}
    assert [(a, n) for fc, a, n in wire if fc == 16] == [(100, 14), (106, 8)]


def test_umodbus_write_limit_is_learned(tmp_path: Path) -> None:
    store = _store()
    wire: list[tuple[int, int, int]] = []  # (function, address, count) of each request
    with quirky_umodbus(store, max_write=4, wire=wire) as port:
        res = _apply(f"tcp://127.0.0.1:{port}", _recipe(tmp_path, bad=False), tmp_path)
        assert res.status == "ok"
        assert res.learned == {"max_write_registers": 4}
        assert [store[100 + i] for i in range(N)] == [10 + i for i in range(N)]
        wire.clear()
        res = _apply(f"tcp://127.0.0.1:{port}", _recipe(tmp_path, bad=False, offset=30), tmp_path)
    assert res.status == "ok" and not res.learned
    assert [(a, n) for fc, a, n in wire if fc == 16] == [(100, 4), (104, 4), (108, 4), (112, 2)]
    assert [store[100 + i] for i in range(N)] == [30 + i for i in range(N)]


def test_umodbus_fc06_only_device(tmp_path: Path) -> None:
    store = _store()
    wire: list[tuple[int, int, int]] = []  # (function, address, count) of each request
    with quirky_umodbus(store, fc06_only=True, wire=wire) as port:
        res = _apply(f"tcp://127.0.0.1:{port}", _recipe(tmp_path, bad=False), tmp_path)
    assert res.status == "ok" and res.learned == {"write_function": 6}
    assert [(fc, a) for fc, a, _ in wire if fc in (6, 16)] == [(16, 100)] + [(6, 100 + i) for i in range(N)]
    assert [store[100 + i] for i in range(N)] == [10 + i for i in range(N)]
