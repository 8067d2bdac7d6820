"""The plan is the contract: what a device receives during an apply is the plan's steps plus the deviations the
report names, in order, for every built-in profile, for devices that do not follow the book, and for a device
we did not write (umodbus). ``tests/contract.py`` says what is checked."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from deployer.profile import builtin_profile
from deployer.testing.simulator import Faults, Quirks, SimulatorThread, parse_fault_rule
from tests import contract
from tests.helpers import cli, umodbus_server

EXAMPLES = Path(__file__).resolve().parent.parent / "recipes" / "examples"
RECIPES = {
    "example-drive": "example-drive-axis1.yaml",
    "example-inverter": "conveyor-line3.yaml",
    "omron-m1": "omron-m1-accel.yaml",
    "oriental-az": "oriental-az-op3.yaml",
}
UNITS = {"oriental-az": (4,)}  # the unit its example recipe names


def _refused_register(plan: dict[str, Any]) -> int:
    """A register in the middle of the plan's largest write: refusing it makes the device refuse or cut that write."""
    write = max((s for s in plan["steps"] if s["kind"] == "write"), key=lambda s: s["count"])
    return int(write["address"]) + int(write["count"]) - 1


def _trip(profile: str) -> Faults | None:
    """A fault rule: the inverter trips (0x2000 = 7) once its acceleration time is over 2 s (others: none)."""
    if profile != "example-inverter":
        return None
    return Faults(rules=(parse_fault_rule("F07 > 2 s: 0x2000=7", builtin_profile(profile)),))


# each: (quirks, faults) given the profile and its saved plan; the report must name what they make apply do
QUIRKS: dict[str, Any] = {
    "by the book": lambda prof, plan: (None, None),
    "max-write-registers 2": lambda prof, plan: (Quirks(max_write_registers=2), None),
    "all-or-nothing, a value refused": lambda prof, plan: (
        Quirks(all_or_nothing=True),
        Faults(fail_registers=frozenset({_refused_register(plan)})),
    ),
    "a value refused, the rest written": lambda prof, plan: (
        None,
        Faults(fail_registers=frozenset({_refused_register(plan)})),
    ),
    "fc06-only": lambda prof, plan: (Quirks(fc06_only=True), None),
    "busy-first 2": lambda prof, plan: (None, Faults(busy_first=2)),
    "latency 20 ms": lambda prof, plan: (None, Faults(latency_ms=20)),
    "a fault rule": lambda prof, plan: (None, _trip(prof)),
}  # a device refusing reads across gaps: tests/test_gap_reads.py


@pytest.mark.parametrize("quirk", list(QUIRKS))
@pytest.mark.parametrize("profile", list(RECIPES))
def test_the_device_receives_the_plan_and_the_named_deviations(
    profile: str, quirk: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    prof = builtin_profile(profile)
    recipe = str(EXAMPLES / RECIPES[profile])
    code, out, err = cli(capsys, "plan", recipe, "--json")
    assert code == 0, err
    quirks, faults = QUIRKS[quirk](profile, json.loads(out))
    state = str(tmp_path / "s")
    with SimulatorThread(prof, quirks=quirks, faults=faults, units=UNITS.get(profile, (1,))) as sim:
        plan_file = str(tmp_path / "plan.json")
        code, _, err = cli(capsys, "plan", recipe, "--device", sim.url, "--out", plan_file, "--state-dir", state)
        assert code == 0, err
        plan = json.loads(Path(plan_file).read_text())
        n = len(sim.log)
        code, out, err = cli(capsys, "apply", plan_file, "--device", sim.url, "--yes", "--json", "--state-dir", state)
        device = json.loads(out)["devices"][0]
        contract.check(plan, device, sim.log[n:], complete=device["status"] == "ok")
        if quirk == "by the book" or quirk == "latency 20 ms":
            assert code == 0 and not any(r.get("deviation") for r in device["requests"]), device
        deviations = {r.get("deviation") for r in device["requests"]} - {None}
        retried = any(r["attempts"] > 1 for r in device["requests"])
        longest = max(s["count"] for s in plan["steps"] if s["kind"] == "write")
        expect = {
            "max-write-registers 2": {"split", "recovery-read"} if longest > 2 else set(),
            "fc06-only": {"function-06"},
            "all-or-nothing, a value refused": {"recovery-read"},
            "a value refused, the rest written": {"recovery-read"},
        }.get(quirk, set())
        assert expect <= deviations, (deviations, device["requests"])
        if quirk == "busy-first 2":
            assert retried and not deviations


@pytest.mark.parametrize("profile", list(RECIPES))
def test_apply_of_a_recipe_sends_the_plan_made_against_the_same_values(
    profile: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``apply RECIPE`` plans inside, against what its checks read: the plan ``plan --device`` shows."""
    recipe = str(EXAMPLES / RECIPES[profile])
    state = str(tmp_path / "s")
    with SimulatorThread(builtin_profile(profile), units=UNITS.get(profile, (1,))) as sim:
        code, out, err = cli(capsys, "plan", recipe, "--device", sim.url, "--json", "--state-dir", state)
        assert code == 0, err
        plan = json.loads(out)
        n = len(sim.log)
        code, out, err = cli(capsys, "apply", recipe, "--device", sim.url, "--yes", "--json", "--state-dir", state)
        assert code == 0, err
        contract.check(plan, json.loads(out)["devices"][0], sim.log[n:])


def test_the_example_drive_plan_lists_every_request_and_the_apply_sends_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    recipe = str(EXAMPLES / "example-drive-axis1.yaml")
    with SimulatorThread(builtin_profile("example-drive")) as sim:
        code, out, err = cli(capsys, "plan", recipe, "--device", sim.url, "--show-frames")
        assert code == 0, err
        kinds = [line.split()[1] for line in out.splitlines() if line[:6].strip().isdigit()]
        assert kinds == [
            "identity",
            "snapshot",
            "snapshot",
            "device-id",
            "precondition",
            "unlock",
            "write",
            "read-modify-write",
            "write",
            "verify",
            "verify",
            "commit",
            "lock",
        ]
        assert "step 6 (unlock): FC16 at 0x001F, 1 register: 5AA5 (parameter password)" in out
        assert "step 12 (commit): FC16 at 0x0020, 1 register: 0001 (store parameters to EEPROM)" in out
        assert "rtu   query    01 10 00 20 00 01 02 00 01" in out  # the commit's frame, as sent
        assert "non-volatile memory: 1 write (storing 9 parameters)" in out
        code, out, err = cli(capsys, "plan", recipe, "--device", sim.url, "--json")
        plan = json.loads(out)
        n = len(sim.log)
        code, out, err = cli(
            capsys, "apply", recipe, "--device", sim.url, "--yes", "--json", "--state-dir", str(tmp_path / "s")
        )
        assert code == 0, err
        contract.check(plan, json.loads(out)["devices"][0], sim.log[n:])
        assert [(e.function, e.address) for e in sim.log[n:]] == [
            (3, 0),
            (3, 255),
            (3, 511),
            (43, 0),
            (3, 16),
            (16, 31),
            (16, 255),
            (3, 511),
            (16, 511),
            (3, 255),
            (3, 511),
            (16, 32),
            (16, 31),
        ]


@dataclass
class _Wire:
    function: int
    address: int
    count: int
    values: list[int] | None = None


@pytest.mark.parametrize("quirk", ["by the book", "max-write 2", "fc06-only"])
def test_a_device_we_did_not_write_receives_the_plan(
    quirk: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """umodbus (its own server, its own framing): the requests it saw are the plan's and the named deviations."""
    prof = builtin_profile("example-inverter")
    store = {a: 0 for p in prof.parameters if p.register_type == "holding" for a in range(p.address, p.end)}
    store.update({c.address: c.raw for c in prof.identity})
    wire: list[tuple[int, int, int]] = []
    recipe = str(EXAMPLES / RECIPES["example-inverter"])
    with umodbus_server(
        store, wire=wire, max_write=2 if quirk == "max-write 2" else 0, fc06_only=quirk == "fc06-only"
    ) as port:
        url = f"tcp://127.0.0.1:{port}"
        state = str(tmp_path / "s")
        plan_file = str(tmp_path / "plan.json")
        code, _, err = cli(capsys, "plan", recipe, "--device", url, "--out", plan_file, "--state-dir", state)
        assert code == 0, err
        n = len(wire)
        code, out, err = cli(capsys, "apply", plan_file, "--device", url, "--yes", "--json", "--state-dir", state)
    device = json.loads(out)["devices"][0]
    assert code == 0 and device["status"] == "ok", device
    contract.check(json.loads(Path(plan_file).read_text()), device, [_Wire(*w) for w in wire[n:]])
    deviations = {r.get("deviation") for r in device["requests"]} - {None}
    assert (
        deviations
        == {"by the book": set(), "max-write 2": {"split", "recovery-read"}, "fc06-only": {"function-06"}}[quirk]
    )


def test_the_counts_printed_are_the_devices_request_log(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """ "N requests: ..." counts what the device received: Function 43, and a request sent again (busy) twice."""
    recipe = str(EXAMPLES / "example-drive-axis1.yaml")
    with SimulatorThread(builtin_profile("example-drive"), faults=Faults(busy_first=1)) as sim:
        code, out, err = cli(capsys, "apply", recipe, "--device", sim.url, "--yes", "--state-dir", str(tmp_path / "s"))
        assert code == 0, err
        log = list(sim.log)
    reads = sum(1 for e in log if e.function in (1, 2, 3, 4))
    writes = sum(1 for e in log if e.function in (5, 6, 15, 16))
    assert (
        f"{len(log)} requests: {reads} reads, {writes} writes, 1 device identification (1 of them sent again "
        "after no answer or a busy answer)" in out
    )
    assert (len(log), reads, writes) == (14, 7, 5 + 1)  # the busy write answered 06 once, then took
    assert "deviations" not in out  # a retry is an attempt more of its step, not a deviation


def test_the_apply_says_which_requests_the_device_decided(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    recipe = str(EXAMPLES / "example-drive-axis1.yaml")
    with SimulatorThread(builtin_profile("example-drive"), quirks=Quirks(fc06_only=True)) as sim:
        code, out, err = cli(capsys, "apply", recipe, "--device", sim.url, "--yes", "--state-dir", str(tmp_path / "s"))
    assert code == 0, err
    # the unlock's FC16 answered 01: it and every later write go as Function 06, each word a request
    assert (
        "requests the device decided (deviations from the plan): step 6: 1 function-06; step 7: 2 function-06; "
        "step 9: 1 read-modify-write, 14 function-06; step 12: 1 function-06; step 13: 1 function-06"
    ) in out


# ---- Function 43: asked, not asked, learned -----------------------------------------------------------


def _ids(log: Any) -> int:
    return sum(1 for e in log if e.function == 43)


def test_a_profile_or_url_can_say_the_device_has_no_identification(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = (Path(__file__).resolve().parent.parent / "deployer" / "profiles" / "omron-m1.yaml").read_text()
    (tmp_path / "m1.yaml").write_text(
        text.replace("\nparameters:", "\nlimits: {device_identification: false}\nparameters:", 1)
    )
    (tmp_path / "r.yaml").write_text(
        (EXAMPLES / "omron-m1-accel.yaml").read_text().replace("profile: omron-m1", "profile: m1.yaml")
    )
    recipe = str(tmp_path / "r.yaml")
    with SimulatorThread(builtin_profile("omron-m1")) as sim:
        code, out, err = cli(capsys, "plan", recipe, "--json")
        assert code == 0 and "device-id" not in [s["kind"] for s in json.loads(out)["steps"]]
        code, out, err = cli(capsys, "apply", recipe, "--device", sim.url, "--yes", "--state-dir", str(tmp_path / "s"))
        assert code == 0 and _ids(sim.log) == 0, err
        # the URL overrides the profile, both ways
        code, out, err = cli(capsys, "plan", recipe, "--device", sim.url + "?device_identification=true", "--json")
        assert code == 0 and "device-id" in [s["kind"] for s in json.loads(out)["steps"]]
        n = len(sim.log)
        code, out, err = cli(
            capsys,
            "plan",
            str(EXAMPLES / "omron-m1-accel.yaml"),
            "--device",
            sim.url + "?device_identification=0",
            "--json",
        )
        assert code == 0 and "device-id" not in [s["kind"] for s in json.loads(out)["steps"]] and _ids(sim.log[n:]) == 0
    code, _, err = cli(capsys, "plan", recipe, "--device", "tcp://127.0.0.1:1?device_identification=maybe")
    assert code == 1 and "option device_identification: 'maybe' is none of true, false" in err


def test_a_device_silent_on_function_43_costs_one_timeout_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    recipe = str(EXAMPLES / "omron-m1-accel.yaml")
    state = str(tmp_path / "s")
    with SimulatorThread(builtin_profile("omron-m1"), quirks=Quirks(silent_functions=frozenset({43}))) as sim:
        url = sim.url + "?timeout=1&retries=0"  # no retries: an answer slower than this fails the run (Wine, CI)
        code, out, err = cli(capsys, "apply", recipe, "--device", url, "--yes", "--json", "--state-dir", state)
        assert code == 0, err
        dev = json.loads(out)["devices"][0]
        assert dev["learned"] == {"device_identification": 0} and _ids(sim.log) == 1
        assert any("did not answer Function 43 (device identification) within 1 s" in n for n in dev["notices"])
        code, out, err = cli(capsys, "learned", "list", "--state-dir", state)
        assert code == 0 and "device_identification: 0" in out, out
        # the next plan and apply: no Function 43 step, no request, no timeout
        code, out, err = cli(capsys, "plan", recipe, "--device", url, "--json", "--state-dir", state)
        assert code == 0 and "device-id" not in [s["kind"] for s in json.loads(out)["steps"]]
        n = len(sim.log)
        (tmp_path / "r2.yaml").write_text(Path(recipe).read_text().replace("10 s", "12 s"))
        code, out, err = cli(
            capsys, "apply", str(tmp_path / "r2.yaml"), "--device", url, "--yes", "--json", "--state-dir", state
        )
        assert code == 0 and _ids(sim.log[n:]) == 0, err
        assert any("using what this device taught" in x for x in json.loads(out)["devices"][0]["notices"])


def test_a_safe_changes_plan_reads_the_health_checks_first(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`plan --safe-change` is the plan `apply --soak` executes: the health reads after the preconditions; a saved
    plan without them is refused for a safe change, with the command that makes the right one."""
    recipe = str(EXAMPLES / RECIPES["example-inverter"])  # its profile watches the fault code at 0x2000
    with SimulatorThread(builtin_profile("example-inverter")) as sim:
        plain, safe = str(tmp_path / "plain.json"), str(tmp_path / "safe.json")
        state = str(tmp_path / "s")
        assert cli(capsys, "plan", recipe, "--device", sim.url, "--out", plain, "--state-dir", state)[0] == 0
        assert (
            cli(capsys, "plan", recipe, "--device", sim.url, "--out", safe, "--safe-change", "--state-dir", state)[0]
            == 0
        )
        kinds = [s["kind"] for s in json.loads(Path(safe).read_text())["steps"]]
        assert "health" not in [s["kind"] for s in json.loads(Path(plain).read_text())["steps"]]
        assert kinds.index("health") == kinds.index("write") - 1  # no precondition, no unlock in this profile
        n = len(sim.log)
        code, _, err = cli(capsys, "apply", plain, "--yes", "--soak", "1s", "--state-dir", str(tmp_path / "s"))
        assert code == 1 and "is not the plan of a safe change: it reads no health checks before writing" in err
        assert "--safe-change --out PLAN.json" in err and len(sim.log) == n  # nothing sent
        code, out, err = cli(
            capsys,
            "apply",
            safe,
            "--yes",
            "--json",
            "--soak",
            "0.3s",
            "--health-interval",
            "0.1s",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 0, err
        device = json.loads(out)["devices"][0]
        # the device received the plan; then the soak's reads (not the plan's), then the held commit: a plan of its
        # own at the window's end, its requests marked so
        applied = sum(r["attempts"] for r in device["requests"] if not r.get("window"))
        contract.check(json.loads(Path(safe).read_text()), device, sim.log[n : n + applied])
        assert [(r["function"], r["address"]) for r in device["requests"] if r.get("window")][-1] == (16, 2303)


def _step(plan: dict[str, Any], kind: str) -> dict[str, Any]:
    return next(s for s in plan["steps"] if s["kind"] == kind)


GUARDS: dict[str, Any] = {  # an edit of a saved plan of the example drive, and what refuses it
    "identity check dropped": (
        lambda p: p["steps"].remove(_step(p, "identity")),
        "the plan's identity steps are not profile example-drive's: a plan checks its identity checks",
    ),
    "identity check moved": (
        lambda p: _step(p, "identity").__setitem__("address", 1),
        "the plan's identity steps are not profile example-drive's",
    ),
    "precondition dropped": (
        lambda p: p["steps"].remove(_step(p, "precondition")),
        "the plan's precondition steps are not profile example-drive's",
    ),
    "precondition turned round": (  # "drive stopped" made "drive running"
        lambda p: _step(p, "precondition")["expect"].__setitem__("equals", 1),
        "the plan's precondition steps are not profile example-drive's",
    ),
    "lock written as a coil": (
        lambda p: _step(p, "lock").__setitem__("function", 15),
        "step 13 (lock at 0x001F) is no lock action of profile example-drive",
    ),
}


@pytest.mark.parametrize("edit", list(GUARDS))
def test_a_saved_plan_runs_only_with_the_profiles_checks_and_actions(
    edit: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A saved plan keeps the profile's identity checks and preconditions (the wrong device, a running drive: nothing
    written) and writes its actions where the profile has them: an edited one is refused before the first byte."""
    change, message = GUARDS[edit]
    recipe = str(EXAMPLES / "example-drive-axis1.yaml")
    state = str(tmp_path / "s")
    with SimulatorThread(builtin_profile("example-drive")) as sim:
        plan_file = tmp_path / "p.json"
        assert cli(capsys, "plan", recipe, "--device", sim.url, "--out", str(plan_file), "--state-dir", state)[0] == 0
        plan = json.loads(plan_file.read_text())
        change(plan)
        plan_file.write_text(json.dumps(plan, indent=1))
        sent = len(sim.log)
        code, _, err = cli(capsys, "apply", str(plan_file), "--yes", "--state-dir", state)
        assert code == 1 and message in err and err.startswith(f"{plan_file}:"), err
        assert len(sim.log) == sent  # nothing sent
