"""The command line as users and scripts see it: output, files, exit codes (docs/design.md)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jsonschema
import pytest

from deployer.load import schema
from deployer.profile import builtin_profile
from deployer.testing.simulator import SimulatorThread
from tests import contract
from tests.conftest import dead_port
from tests.helpers import cli

pytestmark = pytest.mark.timeout(60)
EXAMPLES = Path(__file__).parent.parent / "recipes" / "examples"


@pytest.fixture
def inverter() -> SimulatorThread:
    return SimulatorThread(builtin_profile("example-inverter"))


def recipe(tmp: Path, body: str = "  F07: 10 s\n  stop_mode: coast\n", name: str = "r.yaml") -> str:
    p = tmp / name
    p.write_text(f"recipe: line\nprofile: example-inverter\nparameters:\n{body}")
    return str(p)


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["aply"], "No such command 'aply'. Did you mean 'apply'?"),  # the group imports its commands lazily
        (["audit", "verfy"], "No such command 'verfy'. Did you mean 'verify'?"),  # a subgroup, as click says it
        (["zzz"], "No such command 'zzz'.\n"),
    ],
)
def test_a_misspelt_command_names_the_nearest(capsys: pytest.CaptureFixture[str], args: list[str], said: str) -> None:
    code, _, err = cli(capsys, *args)
    assert code != 0 and said in err and err.count("Did you mean") <= 1, err


def test_validate_examples(capsys: pytest.CaptureFixture[str]) -> None:
    files = sorted(str(p) for p in EXAMPLES.glob("*.yaml"))
    code, out, _ = cli(capsys, "validate", *files)
    assert code == 0 and out.count(": ok (") == len(files)


def test_profiles_list_and_show(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = cli(capsys, "profiles", "list")
    assert code == 0 and "omron-m1" in out and "oriental-az" in out
    code, out, _ = cli(capsys, "profiles", "show", "omron-m1")
    assert code == 0 and "0x1102 (4354)" in out and "uint32" in out
    code, _, err = cli(capsys, "profiles", "show", "nope")
    assert code == 1 and "unknown built-in profile 'nope'" in err


def test_plan_offline_table_json_out_and_frames(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code, out, _ = cli(capsys, "plan", str(EXAMPLES / "omron-m1-accel.yaml"), "--show-frames")
    assert code == 0
    assert "0x1102 (4354)" in out and "0000 03E8" in out and "10 s" in out
    assert "1 write request" in out and "4 requests in all (3 reads, 1 write)" in out
    assert "01 10 11 02 00 02 04 00 00 03 E8 B2 98" in out and "01 10 11 02 00 02 E5 34" in out
    assert ":01101102000204000003E8EB" in out
    plan_file = tmp_path / "plan.json"
    code, out, _ = cli(
        capsys,
        "plan",
        str(EXAMPLES / "omron-m1-accel.yaml"),
        "--json",
        "--out",
        str(plan_file),
        "--state-dir",
        str(tmp_path / "s"),
    )
    data = json.loads(out)
    jsonschema.validate(data, schema.schema("plan"))
    assert data == json.loads(plan_file.read_text())
    assert [s for s in data["steps"] if s["kind"] == "write"] == [
        {
            "kind": "write",
            "function": 16,
            "address": 4354,
            "count": 2,
            "values": [0, 1000],
            "parameters": ["F07"],
            "stage": 0,
        }
    ]
    assert [s["kind"] for s in data["steps"]] == ["snapshot", "device-id", "write", "verify"]
    assert data["parameters"][0]["current_raw"] is None and data["parameters"][0]["action"] == "write"


def test_plan_against_the_device_and_detailed_exitcode(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, inverter: SimulatorThread
) -> None:
    path = recipe(tmp_path)
    with inverter as sim:
        code, out, _ = cli(capsys, "plan", path, "--device", sim.url, "--detailed-exitcode")
        assert code == 2
        assert "5 s -> 10 s" in out and "ramp -> coast" in out
        assert len(sim.log) > 0 and all(e.function in (3, 43) for e in sim.log)  # plan only reads
        code, _, _ = cli(capsys, "apply", path, "--device", sim.url, "--yes", "--state-dir", str(tmp_path / "s"))
        assert code == 0
        code, out, _ = cli(capsys, "plan", path, "--device", sim.url, "--detailed-exitcode")
        assert code == 0 and "No changes" in out


def test_apply_saved_plan_and_stale_plan(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, inverter: SimulatorThread
) -> None:
    path = recipe(tmp_path)
    plan_file = str(tmp_path / "plan.json")
    with inverter as sim:
        assert (
            cli(capsys, "plan", path, "--device", sim.url, "--out", plan_file, "--state-dir", str(tmp_path / "s"))[0]
            == 0
        )
        n = len(sim.log)
        code, out, _ = cli(capsys, "apply", plan_file, "--yes", "--json", "--state-dir", str(tmp_path / "s"))
        assert code == 0, out
        report = json.loads(out)
        jsonschema.validate(report, schema.schema("report"))
        plan = json.loads(Path(plan_file).read_text())
        contract.check(plan, report["devices"][0], sim.log[n:])  # the device received exactly the saved plan
        # run a second time: refused (the values it was made against are gone), and said why, nothing written
        n = len(sim.log)
        code, _, err = cli(capsys, "apply", plan_file, "--yes", "--state-dir", str(tmp_path / "s"))
        assert code == 1 and "it now holds every value the plan writes (did the plan run already?)" in err, err
        assert not any(e.function == 16 for e in sim.log[n:])
        # the device changed since: the same plan is refused, nothing written
        sim.write("F07", (0, 123))
        n = len(sim.log)
        code, _, err = cli(capsys, "apply", plan_file, "--yes", "--state-dir", str(tmp_path / "s"))
        assert code == 1 and "changed since the plan was made" in err and "F07: now 1.23 s" in err
        assert not any(e.function == 16 for e in sim.log[n:])
        # refused, a script still gets the report: the device skipped, holding what it was found holding
        saved = tmp_path / "refused.json"
        code, out, err = cli(
            capsys, "apply", plan_file, "--yes", "--json", "--report", str(saved), "--state-dir", str(tmp_path / "s")
        )
        assert code == 1 and "F07: now 1.23 s" in err
        for doc in (json.loads(out), json.loads(saved.read_text())):
            jsonschema.validate(doc, schema.schema("report"))
            (device,) = doc["devices"]
            assert device["status"] == "skipped" and "F07: now 1.23 s" in device["error"], device
            assert device["error"].startswith("not written: the device changed since the plan was made")
            f07 = next(p for p in device["parameters"] if p["name"] == "F07")
            assert f07["status"] == "skipped" and f07["before_raw"] == [0, 123], f07
            assert doc["summary"]["skipped"] == 1 and doc["summary"]["write_requests"] == 0
        assert not any(e.function == 16 for e in sim.log[n:])


def test_diff_exit_codes(capsys: pytest.CaptureFixture[str], tmp_path: Path, inverter: SimulatorThread) -> None:
    path = recipe(tmp_path)
    with inverter as sim:
        code, out, _ = cli(capsys, "diff", path, "--device", sim.url)
        assert code == 2 and "F07" in out and "5 s" in out
        cli(capsys, "apply", path, "--device", sim.url, "--yes", "--state-dir", str(tmp_path / "s"))
        code, out, _ = cli(capsys, "diff", path, "--device", sim.url, "--json")
        assert code == 0 and json.loads(out)["drift"] == []


def test_pull_writes_a_valid_recipe_that_applies_as_a_no_op(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, inverter: SimulatorThread
) -> None:
    out_file = tmp_path / "pulled.yaml"
    with inverter as sim:
        sim.write("F07", (0, 4321))
        code, _, err = cli(capsys, "pull", "--profile", "example-inverter", "--device", sim.url, "-o", str(out_file))
        assert code == 0 and "parameters written" in err
        assert "F07: 43.21 s" in out_file.read_text()
        assert cli(capsys, "validate", str(out_file))[0] == 0
        n = len(sim.log)
        code, _, _ = cli(capsys, "apply", str(out_file), "--yes", "--state-dir", str(tmp_path / "s"))
        assert code == 0 and not any(e.function == 16 for e in sim.log[n:])


def test_apply_refuses_without_confirmation_when_not_a_terminal(tmp_path: Path) -> None:
    path = recipe(tmp_path)
    proc = subprocess.run(
        [sys.executable, "-m", "deployer", "apply", path, "--device", "tcp://127.0.0.1:1"],
        capture_output=True,
        text=True,
        stdin=subprocess.DEVNULL,
        timeout=30,
    )
    assert proc.returncode == 1 and "pass --yes" in proc.stderr and "Traceback" not in proc.stderr


def test_broadcast_refused(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code, _, err = cli(capsys, "apply", recipe(tmp_path), "--device", "tcp://127.0.0.1:1", "--unit", "0", "--yes")
    assert code == 1 and "--allow-broadcast" in err


def test_unreachable_exit_3(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    port = dead_port()
    code, out, err = cli(
        capsys,
        "apply",
        recipe(tmp_path),
        "--device",
        f"tcp://127.0.0.1:{port}?timeout=0.3",
        "--yes",
        "--state-dir",
        str(tmp_path / "s"),
    )
    assert code == 3 and "unreachable" in out and "connection refused" in out
    assert not (tmp_path / "s" / "snapshots").exists()
    code, _, err = cli(capsys, "diff", recipe(tmp_path), "--device", f"tcp://127.0.0.1:{port}")
    assert code == 3 and "connection refused" in err


def test_bad_url_exit_1(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code, _, err = cli(capsys, "apply", recipe(tmp_path), "--device", "tcp://h?baud=1", "--yes")
    assert code == 1 and "unknown option 'baud'" in err


def test_fleet_in_parallel_with_per_device_overrides(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    prof = builtin_profile("example-inverter")
    with SimulatorThread(prof) as a, SimulatorThread(prof) as b, SimulatorThread(prof) as c:
        inv = tmp_path / "inventory.yaml"
        inv.write_text(
            "defaults: {timeout: 1.0, retries: 2}\ndevices:\n"
            f"  press-1: {{url: '{a.url}', unit: 1, groups: [line3]}}\n"
            f"  press-2: {{url: '{b.url}', unit: 1, groups: [line3], parameters: {{F07: 12 s}}}}\n"
            f"  press-3: {{url: '{c.url}', unit: 1, groups: [line4]}}\n"
        )
        assert cli(capsys, "validate", str(inv))[0] == 0
        code, out, _ = cli(
            capsys,
            "apply",
            recipe(tmp_path),
            "--inventory",
            str(inv),
            "--limit",
            "line3",
            "--yes",
            "--json",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 0
        report = json.loads(out)
        assert [d["name"] for d in report["devices"]] == ["press-1", "press-2"]
        assert report["summary"]["ok"] == 2
        assert a.read("F07") == (0, 1000) and b.read("F07") == (0, 1200) and c.read("F07") == (0, 500)
        snaps = os.listdir(tmp_path / "s" / "snapshots")
        assert sorted(s.split("-2026")[0] for s in snaps) == ["press-1", "press-2"]


def test_fleet_on_one_serial_line_goes_one_device_at_a_time(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, socat_pair: tuple[str, str]
) -> None:
    a, b = socat_pair
    with SimulatorThread(builtin_profile("example-inverter"), listen=f"rtu://{a}", units=(1, 2)) as sim:
        inv = tmp_path / "inventory.yaml"
        inv.write_text(
            "devices:\n"
            f"  d1: {{url: 'rtu://{b}?baudrate=19200&timeout=1', unit: 1}}\n"
            f"  d2: {{url: 'rtu://{b}?baudrate=19200&timeout=1', unit: 2, parameters: {{F07: 7 s}}}}\n"
        )
        code, out, _ = cli(
            capsys,
            "apply",
            recipe(tmp_path),
            "--inventory",
            str(inv),
            "--yes",
            "--json",
            "--parallel",
            "8",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 0, out
        assert sim.read("F07", 1) == (0, 1000) and sim.read("F07", 2) == (0, 700)
        units = [e.unit for e in sim.log]
        # all of d1's requests, then all of d2's: never interleaved on the line
        assert units == sorted(units)


def test_rollback_command(capsys: pytest.CaptureFixture[str], tmp_path: Path, inverter: SimulatorThread) -> None:
    path = recipe(tmp_path)
    with inverter as sim:
        before = sim.registers()
        code, out, _ = cli(
            capsys, "apply", path, "--device", sim.url, "--yes", "--json", "--state-dir", str(tmp_path / "s")
        )
        snapshot = json.loads(out)["devices"][0]["snapshot"]
        code, _, _ = cli(capsys, "rollback", snapshot, "--yes", "--state-dir", str(tmp_path / "s"))
        assert code == 0
        store = builtin_profile("example-inverter").parameter("eeprom_store").address
        assert {k: v for k, v in sim.registers().items() if k != store} == {
            k: v for k, v in before.items() if k != store
        }


def test_demo_runs(capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The demo leaves nothing in the temporary folder (its files, state and device locks go in a folder
    of its own, removed at the end) unless --keep names a folder for them."""
    monkeypatch.chdir(tmp_path)
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setenv("TMPDIR", str(tmp))
    monkeypatch.delenv("DEPLOYER_LOCK_DIR", raising=False)
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", None)  # TMPDIR is read again
    code, out, _ = cli(capsys, "demo", "--fast")
    assert code == 0, out
    assert "demo finished" in out and "exception 04" in out and "no drift" in out
    assert list(tmp.iterdir()) == [] and "DEPLOYER_LOCK_DIR" not in os.environ
    code, out, _ = cli(capsys, "demo", "--fast", "--keep", str(tmp_path / "kept"))
    assert code == 0, out
    assert (tmp_path / "kept" / ".deployer" / "audit.jsonl").is_file() and list(tmp.iterdir()) == []
    from deployer.cli.demo import LOCK_DIR_ENV
    from deployer.state.lock import ENV

    assert LOCK_DIR_ENV == ENV  # the demo's locks go where the locks look (the command line names it itself)


def _run_on_a_terminal(
    args: list[str], answer: bytes, timeout: float = 30, prompt: bytes = b"Write these values?"
) -> tuple[int, str]:
    """Run deployer with a pseudo-terminal as stdin/stdout/stderr and type ``answer`` at the prompt."""
    import pty
    import select
    import time

    master, slave = pty.openpty()
    proc = subprocess.Popen(
        [sys.executable, "-m", "deployer", *args], stdin=slave, stdout=slave, stderr=slave, close_fds=True
    )
    os.close(slave)
    out = b""
    answered = False
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        ready, _, _ = select.select([master], [], [], 0.1)
        if ready:
            try:
                chunk = os.read(master, 4096)
            except OSError:
                break
            if not chunk:
                break
            out += chunk
            if not answered and prompt in out:
                os.write(master, answer)
                answered = True
        elif proc.poll() is not None:
            break
    code = proc.wait(timeout=10)
    os.close(master)
    return code, out.decode(errors="replace")


@pytest.mark.parametrize(("answer", "expected_code", "written"), [(b"y\n", 0, True), (b"n\n", 1, False)])
def test_apply_asks_on_a_terminal(tmp_path: Path, answer: bytes, expected_code: int, written: bool) -> None:
    with SimulatorThread(builtin_profile("example-inverter")) as sim:
        code, out = _run_on_a_terminal(
            ["apply", recipe(tmp_path), "--device", sim.url, "--state-dir", str(tmp_path / "s")], answer
        )
        assert code == expected_code, out
        assert "5 s -> 10 s" in out  # the changes are shown before the question
        assert (sim.read("F07") == (0, 1000)) is written
        assert any(e.function == 16 for e in sim.log) is written


def test_validate_a_saved_plan_and_write_all(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, inverter: SimulatorThread
) -> None:
    path = recipe(tmp_path)
    plan_file = tmp_path / "plan.json"
    assert cli(capsys, "plan", path, "--out", str(plan_file), "--state-dir", str(tmp_path / "s"))[0] == 0
    code, out, _ = cli(capsys, "validate", str(plan_file))
    assert code == 0 and "plan: 2 write requests for profile example-inverter" in out
    with inverter as sim:
        cli(capsys, "apply", path, "--device", sim.url, "--yes", "--state-dir", str(tmp_path / "s"))
        n = len(sim.log)
        code, out, _ = cli(
            capsys,
            "apply",
            path,
            "--device",
            sim.url,
            "--yes",
            "--write-all",
            "--json",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 0
        assert {p["status"] for p in json.loads(out)["devices"][0]["parameters"]} == {"ok"}
        assert any(e.function == 16 for e in sim.log[n:])


def test_a_plan_or_a_report_where_a_recipe_belongs_is_named_and_validate_knows_a_report(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, inverter: SimulatorThread
) -> None:
    # ten "unknown key" errors told a user who gave diff a saved plan nothing; one line says what the file is
    path = recipe(tmp_path)
    plan_file, report_file = tmp_path / "plan.json", tmp_path / "run.json"
    with inverter as sim:
        assert (
            cli(capsys, "plan", path, "--device", sim.url, "--out", str(plan_file), "--state-dir", str(tmp_path / "s"))[
                0
            ]
            == 0
        )
        code, _, err = cli(
            capsys, "apply", path, "--device", sim.url, "--yes", "--state-dir", str(tmp_path / "s"),
            "--report", str(report_file),
        )  # fmt: skip
        assert code == 0, err
        sim.log.clear()
        for command in ("diff", "plan"):
            code, _, err = cli(capsys, command, str(plan_file), "--device", sim.url)
            assert code == 1 and err.splitlines() == [
                f"{plan_file}:2:3: error: this is a saved plan, not a recipe: 'deployer apply {plan_file}' runs it "
                "unchanged (plan, diff and pull take a recipe)",
                "1 error; nothing was sent to any device",
            ]
        code, _, err = cli(capsys, "diff", str(report_file), "--device", sim.url)
        assert code == 1 and f"this is a run's report, not a recipe: 'deployer report {report_file}' shows it" in err
        assert sim.log == []
    code, out, _ = cli(capsys, "validate", str(report_file), str(plan_file))
    assert code == 0 and f"{report_file}: ok (report: 1 device, 1 ok)" in out
    report_file.write_text(report_file.read_text().replace('"devices"', '"devizes"'))
    code, out, err = cli(capsys, "validate", str(report_file))
    assert code == 1 and "'devices' is a required property" in err


def test_fleet_problems_are_reported_before_anything_is_sent(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    inv = tmp_path / "inventory.yaml"
    inv.write_text(
        "devices:\n  a: {url: 'tcp://127.0.0.1:1?baud=3'}\n  b: {url: 'tcp://127.0.0.1:1', parameters: {F07: 7000 s}}\n"
    )
    code, _, err = cli(capsys, "apply", recipe(tmp_path), "--inventory", str(inv), "--yes")
    assert code == 1
    assert f"{inv}:2:12: error: unknown option 'baud'" in err and "(device a)\n" in err
    assert f"{inv}:3:51: error: F07: 7000 s is out of range 0..6000 s (device b)\n" in err


def test_plan_line_time_follows_the_url_and_broadcast_has_no_answers(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    r = str(EXAMPLES / "omron-m1-accel.yaml")
    code, out, _ = cli(capsys, "plan", r)
    # the snapshot read (8 + 9 bytes), Function 43 (7 + 16: its texts not counted), the write (13 + 8), the read-back
    assert code == 0 and "78 bytes on an RTU line, about 61 ms at 19200 baud 8E1" in out
    # with a serial URL the estimate uses its line settings and framing (ASCII counts characters)
    import deployer
    from deployer.planning.frames import step_frames
    from deployer.planning.wire import plan_cost
    from deployer.transport.urls import parse_url

    rec = deployer.load_recipe(r)
    plan = deployer.plan(rec, offline=True, state_dir=None)
    cost = plan_cost(plan, rec.profile, parse_url("ascii:///dev/ttyS0?baudrate=9600&bytesize=7&parity=E"))
    assert (cost.framing, cost.line) == ("ascii", "9600 baud 7E1")
    frames = [q + (a or b"") for q, a in (step_frames(s, 1, "ascii", i) for i, s in enumerate(plan.steps, 1))]
    write = frames[2]
    assert write == b":01101102000204000003E8EB\r\n:011011020002DA\r\n"  # the manual's frames
    # every frame counted, and the Function 43 answer without its texts: 13 bytes of PDU (2B 0E 01, conformity,
    # more follows, next object, 3 objects; each object's id and length) as ':', hex pairs, LRC, CR LF
    assert cost.bytes == sum(len(f) for f in frames) + 1 + 2 * (1 + 13) + 2 + 2
    assert abs(cost.seconds - cost.bytes * 10 / 9600) < 1e-6  # 7E1: 10 bits a character (rounded to the us)
    assert plan_cost(plan, rec.profile).line == "19200 baud 8E1"
    code, out, _ = cli(capsys, "plan", r, "--unit", "0", "--show-frames")
    assert code == 0 and "response none (broadcast)" in out and "E5 34" not in out
    assert "13 bytes on an RTU line" in out  # the request only: a broadcast is its writes alone


def test_apply_saved_plan_names_its_snapshot_after_the_recipe(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, inverter: SimulatorThread
) -> None:
    with inverter as sim:
        r = recipe(tmp_path)
        code, _, _ = cli(
            capsys,
            "plan",
            r,
            "--device",
            sim.url,
            "--out",
            str(tmp_path / "p.json"),
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 0
        code, out, err = cli(
            capsys,
            "apply",
            str(tmp_path / "p.json"),
            "--device",
            sim.url,
            "--yes",
            "--state-dir",
            str(tmp_path / "s"),
            "--json",
        )
        assert code == 0, err
        snap = json.loads(out)["devices"][0]["snapshot"]
        assert os.path.basename(snap).startswith("line-") and ".json" not in os.path.basename(snap)


def test_no_answer_after_busy_has_no_exception_code(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    from deployer.testing.simulator import Faults

    # requests: identity read, snapshot read, Function 43 (01: none), write (busy: 06), the same write
    # again (no answer: dropped)
    faults = Faults(busy_first=1, drop_every=5)
    with SimulatorThread(builtin_profile("example-inverter"), faults=faults) as sim:
        code, out, _ = cli(
            capsys,
            "apply",
            recipe(tmp_path),
            "--device",
            sim.url + "?timeout=0.2",
            "--yes",
            "--retries",
            "1",
            "--state-dir",
            str(tmp_path / "s"),
            "--json",
        )
    assert code == 4
    requests = json.loads(out)["devices"][0]["requests"]
    assert {
        "function": 16,
        "address": 4354,
        "count": 2,
        "result": "no response",
        "exception_code": None,
        "attempts": 2,
        "step": 4,
    } in requests
    for req in requests:
        assert (req["result"] == "exception") == (req["exception_code"] is not None), req
