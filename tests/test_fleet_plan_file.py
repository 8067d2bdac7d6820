"""A saved fleet plan (``plan --inventory --out FLEET.json``): every device's plan in one file that a second person
approves, and ``apply FLEET.json`` executes exactly those plans, with a fleet's batches, canaries and report.

Simulators on 127.0.0.1; what each device received is its request log, compared with its plan step by step.
"""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import pytest

import deployer
from deployer.change import digest
from deployer.load import schema
from deployer.profile import Profile, load_profile
from deployer.testing.simulator import Simulator, SimulatorThread
from tests import contract
from tests.agent_helpers import PROFILE, RECIPE
from tests.conftest import dead_port
from tests.helpers import cli
from tests.test_change_control import accel_changed, allowed, pykeygen, run


def _site(tmp: Path, urls: dict[str, str], policy: str = "") -> Path:
    (tmp / "drive.yaml").write_text(PROFILE)
    (tmp / "r.yaml").write_text(RECIPE)
    groups = ["line3", "line4", "line4"]
    lines = [policy, "devices:"] + [
        f'  {n}: {{url: "{u}", recipe: r.yaml, groups: [{g}]}}' for (n, u), g in zip(urls.items(), groups, strict=False)
    ]
    inv = tmp / "site.yaml"
    inv.write_text("\n".join(lines) + "\n")
    return inv


def _writes(sim: Simulator) -> list[tuple[int, int]]:
    return [(e.function, e.address) for e in sim.log if e.function in (5, 6, 15, 16)]


def test_a_saved_fleet_plan_runs_exactly_its_plans_and_only_once(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # plan --out records in the state folder's audit trail: here
    prof = load_profile_text(tmp_path)
    with SimulatorThread(prof) as a, SimulatorThread(prof) as b, SimulatorThread(prof) as c:
        sims = {"d1": a, "d2": b, "d3": c}
        c.write("speed", (1200,))  # d3 holds other values than d1 and d2: a plan of its own
        inv = _site(tmp_path, {n: s.url for n, s in sims.items()})
        out = str(tmp_path / "fleet.json")
        code, text, err = cli(capsys, "plan", "--inventory", str(inv), "--out", out)
        assert code == 0, err
        said = " ".join(text.split())  # the console wraps long lines
        assert f"fleet plan written to {out} (3 devices); run it unchanged with: deployer apply {out}" in said
        doc = json.loads(Path(out).read_text())
        assert doc["schema"] == "deployer.fleetplan/1" and doc["inventory"] == str(inv)
        assert [(d["name"], d["group"]) for d in doc["devices"]] == [("d1", "line3"), ("d2", "line4"), ("d3", "line4")]
        # d2 holds what d1 holds: d1's plan, for d2 (written once); d3 has its own
        assert [("plan" in d, d.get("plan_of")) for d in doc["devices"]] == [(True, None), (False, "d1"), (True, None)]
        assert doc["devices"][1]["device"] == {
            "url": b.url,
            "unit": 1,
            "profile": doc["devices"][0]["plan"]["device"]["profile"],
        }
        assert doc["change"]["author"] and [i["kind"] for i in doc["change"]["inputs"]] == ["recipe", "profile"]
        jsonschema.validate(doc, schema.schema("fleetplan"))
        assert all(s.log == [] or not _writes(s) for s in sims.values())  # planning reads only
        # in Python: a FleetPlan (deployer.load_plan takes one device's plan, and says what takes this one)
        fleet = deployer.FleetPlan.load(out)
        assert list(fleet) == ["d1", "d2", "d3"] and fleet.device("d2") == (b.url, 1) and fleet.changes
        with pytest.raises(deployer.InputError, match=r"a saved fleet plan, not one device's: .*FleetPlan.load"):
            deployer.load_plan(out)
        with pytest.raises(deployer.UsageError, match="has no argument 'paht'; did you mean 'path'"):
            deployer.FleetPlan.load(paht=out)  # type: ignore[call-arg]
        again = tmp_path / "again.json"  # to_json() and load() go both ways
        again.write_text(json.dumps(fleet.to_json()))
        assert deployer.FleetPlan.load(again).plans == fleet.plans
        assert fleet["d2"].device.url == b.url and fleet["d2"].steps == fleet["d1"].steps
        # --json prints the same document (without the change a saved one records)
        code, text, _ = cli(capsys, "plan", "--inventory", str(inv), "--json")
        shown = json.loads(text)
        assert code == 0 and shown["devices"] == doc["devices"]

        for s in sims.values():
            s.log.clear()
        code, text, err = cli(
            capsys, "apply", out, "--yes", "--json", "--batch", "1,100%", "--batch-by", "group", "--state-dir",
            str(tmp_path / "s"),
        )  # fmt: skip
        assert code == 0, err
        report = json.loads(text)
        jsonschema.validate(report, schema.schema("report"))
        by = {d["name"]: d for d in report["devices"]}
        assert {n: (d["status"], d["batch"]) for n, d in by.items()} == {
            "d1": ("ok", 1),
            "d2": ("ok", 1),
            "d3": ("ok", 2),
        }
        for name, sim in sims.items():  # each device received exactly its saved plan
            contract.check(fleet[name].to_json(), by[name], list(sim.log))
        assert [s.read("accel") for s in sims.values()] == [(20,), (20,), (20,)]

        # run a second time: every device refused before its first write, and said why
        for s in sims.values():
            s.log.clear()
        code, text, err = cli(capsys, "apply", out, "--yes", "--json", "--state-dir", str(tmp_path / "s"))
        again = json.loads(text)
        assert code == 4 and [d["status"] for d in again["devices"]] == ["skipped"] * 3, err
        assert all("did the plan run already?" in d["error"] for d in again["devices"])
        assert all(_writes(s) == [] for s in sims.values())
        # an edited file whose device names a plan it does not hold: refused at its position, nothing sent
        edited = json.loads(Path(out).read_text())
        edited["devices"][1]["plan_of"] = "d9"
        Path(out).write_text(json.dumps(edited, indent=2))
        code, _, err = cli(capsys, "apply", out, "--yes")
        assert code == 1 and "d2: plan_of names no earlier device's plan" in err and f"{out}:" in err, err
        edited["devices"][1]["plan_of"] = "d1"  # and a plan beside it: which one would run is not for a reader to guess
        edited["devices"][1]["plan"] = edited["devices"][2]["plan"]
        Path(out).write_text(json.dumps(edited, indent=2))
        code, _, err = cli(capsys, "apply", out, "--yes")
        assert code == 1 and "d2: a plan and a plan_of: give one of them" in err, err
        del edited["devices"][1]["plan"]  # plan_of not a name, a unit off the bus: said where, never a traceback
        for field, value, said in (
            ("plan_of", ["d1"], "d2: plan_of names no earlier device's plan"),
            ("plan_of", {"a": 1}, "d2: plan_of names no earlier device's plan"),
            ("unit", -1, "d2: unit -1 is outside 0..247"),
            ("unit", True, "d2: its device's url and unit are needed"),
        ):
            entry = json.loads(json.dumps(edited))
            (entry["devices"][1] if field == "plan_of" else entry["devices"][1]["device"])[field] = value
            Path(out).write_text(json.dumps(entry, indent=2))
            for command in ("validate", "apply"):
                code, _, err = cli(capsys, command, out, *(["--yes"] if command == "apply" else []))
                assert code == 1 and said in err and f"{out}:" in err, (field, value, err)
        assert all(_writes(s) == [] for s in sims.values())


def load_profile_text(tmp: Path) -> Profile:
    (tmp / "drive.yaml").write_text(PROFILE)
    return load_profile(str(tmp / "drive.yaml"))


def test_a_fleet_plan_is_written_whole_or_not_at_all(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A device that cannot be planned (unreachable) leaves no file: the saved plan runs every device it names."""
    monkeypatch.chdir(tmp_path)  # plan --out records in the state folder's audit trail: here
    prof = load_profile_text(tmp_path)
    with SimulatorThread(prof) as a:
        inv = _site(tmp_path, {"d1": a.url, "gone": f"tcp://127.0.0.1:{dead_port()}?timeout=0.5&retries=0"})
        out = tmp_path / "fleet.json"
        code, _, err = cli(capsys, "plan", "--inventory", str(inv), "--out", str(out))
        assert code == 1 and "no fleet plan written: 1 device could not be planned (gone:" in err, err
        assert "--limit" in err and not out.exists()
        # left out, the others make a plan; what a saved fleet plan does not take is refused, naming it
        code, _, err = cli(capsys, "plan", "--inventory", str(inv), "--limit", "!gone", "--out", str(out))
        assert code == 0 and out.exists(), err
        code, _, err = cli(capsys, "apply", str(out), "--yes", "--soak", "1s")  # not made for a safe change
        assert (
            code == 1 and "make it with: deployer plan [RECIPE] --inventory FILE --safe-change --out FLEET.json" in err
        ), err
        for extra in (["--limit", "d1"], ["--device", a.url], ["--inventory", str(inv)], ["--write-all"]):
            code, _, err = cli(capsys, "apply", str(out), "--yes", *extra)
            assert code == 1 and "a saved fleet plan runs unchanged, on every device it names" in err, (extra, err)
        assert [e for e in a.log if e.function == 16] == []
        # an edited file: a device without its plan is refused at its position, nothing sent
        doc = json.loads(out.read_text())
        del doc["devices"][0]["plan"]
        out.write_text(json.dumps(doc, indent=2))
        code, _, err = cli(capsys, "apply", str(out), "--yes")
        assert code == 1 and f"{out}:6:5: error: d1 has no plan: plan the fleet again" in err, err
        code, _, err = cli(capsys, "validate", str(out))
        assert code == 1 and "d1 has no plan" in err, err


def test_a_fleet_plan_is_approved_once_for_all_its_devices_and_runs_only_as_approved(tmp_path: Path) -> None:
    """The policy asks line3 for an approval and a reason; the fleet plan's one approval covers its devices, and
    a value changed after it is refused on every device, nothing sent."""
    for n in ("alice", "bob"):
        pykeygen(tmp_path, n)  # no ssh-keygen needed (Windows)
    allowed(tmp_path, "alice", "bob")
    prof = load_profile_text(tmp_path)
    with SimulatorThread(prof) as a, SimulatorThread(prof) as b:
        policy = (
            "change_control:\n  allowed_signers: allowed_signers\n  groups:\n    line3: {approvals: 1, reason: true}"
        )
        inv = str(_site(tmp_path, {"d1": a.url, "d2": b.url}, policy))
        made = run(tmp_path, "plan", "--inventory", inv, "--out", "f.json", "--sign-key", "alice", "--policy", inv)
        assert made.returncode == 0, made.stderr
        refused = run(tmp_path, "apply", "f.json", "--yes", "--policy", inv)
        assert refused.returncode == 1 and "nothing was sent" in refused.stderr, refused.stderr
        assert "a reason (deployer plan" in refused.stderr
        assert "1 approval by distinct users other than the author alice (none so far)" in refused.stderr
        # without --policy too: the inventory the plan was made from governs it (no way around its policy)
        bare = run(tmp_path, "apply", "f.json", "--yes")
        assert bare.returncode == 1 and "1 approval by distinct users" in bare.stderr, bare.stderr
        assert _writes(a) == [] and _writes(b) == []

        again = run(
            tmp_path, "plan", "--inventory", inv, "--out", "f.json", "--sign-key", "alice", "--reason",
            "faster ramps", "--policy", inv,
        )  # fmt: skip
        assert again.returncode == 0, again.stderr
        self_ = run(tmp_path, "approve", "f.json", "--key", "alice", "--policy", inv)
        assert self_.returncode == 1 and "author cannot approve their own change" in self_.stderr
        bob = run(tmp_path, "approve", "f.json", "--key", "bob", "--policy", inv)
        assert bob.returncode == 0 and "has what its policy requires" in bob.stderr, bob.stderr

        good = (tmp_path / "f.json").read_text()
        doc = json.loads(good)  # accel 2.1 s instead of 2 s in d1's plan (d2's too: it shares it), consistently
        assert doc["devices"][1]["plan_of"] == "d1"
        accel_changed(doc["devices"][0]["plan"])
        (tmp_path / "f.json").write_text(json.dumps(doc, indent=2))
        changed = run(tmp_path, "apply", "f.json", "--yes", "--policy", inv)
        assert changed.returncode == 1 and "made over other content" in changed.stderr, changed.stderr
        assert _writes(a) == [] and _writes(b) == []

        (tmp_path / "f.json").write_text(good)
        ran = run(tmp_path, "apply", "f.json", "--yes", "--policy", inv, "--report", "rep.json")
        assert ran.returncode == 0, ran.stderr
        assert a.read("accel") == b.read("accel") == (20,)
        rep = json.loads((tmp_path / "rep.json").read_text())
        assert rep["run"]["change"]["digest"] == digest(json.loads(good))
        assert [(s["signer"], s["meaning"], s["holds"]) for s in rep["run"]["change"]["signatures"]] == [
            ("alice", "authored", True),
            ("bob", "approved", True),
        ]


def test_a_fleet_plan_too_large_to_read_back_is_not_written(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """apply reads a fleet plan within the input limits every file is read in: plan --out refuses one beyond them."""
    from deployer.load import yamlsrc

    prof = load_profile_text(tmp_path)
    with SimulatorThread(prof) as a, SimulatorThread(prof) as b:
        inv = _site(tmp_path, {"d1": a.url, "d2": b.url})
        monkeypatch.setattr(yamlsrc, "MAX_NODES", 100)  # a small file's limit: this fleet's plan is over it
        out = tmp_path / "fleet.json"
        code, _, err = cli(capsys, "plan", "--inventory", str(inv), "--out", str(out))
    assert code == 1 and not out.exists(), err
    assert "no fleet plan written: it would be " in err and "more than a file may hold (32 MiB, 100 values" in err, err
    assert "plan the fleet in parts, a group or a range of names at a time (--limit)" in err


def test_a_saved_plan_talks_to_each_device_as_its_plan_was_made(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A saved plan keeps its device's timeout, retries and pauses (no secret): an inventory's slow gateway is not
    lost to the defaults at apply; a timeout given to the apply goes over them."""
    monkeypatch.chdir(tmp_path)  # plan --out records in the state folder's audit trail: here
    from deployer.run.request import RunRequest, prepare

    prof = load_profile_text(tmp_path)
    with SimulatorThread(prof) as a, SimulatorThread(prof) as b:
        (tmp_path / "r.yaml").write_text(RECIPE)
        inv = tmp_path / "site.yaml"
        inv.write_text(
            f'devices:\n  d1: {{url: "{a.url}", recipe: r.yaml}}\n'
            f'  d2: {{url: "{b.url}?pause_between_requests=20ms", recipe: r.yaml, timeout: 2.5, retries: 0}}\n'
        )
        out = tmp_path / "fleet.json"
        assert cli(capsys, "plan", "--inventory", str(inv), "--out", str(out))[0] == 0
        single = tmp_path / "p.json"
        assert (
            cli(capsys, "plan", str(tmp_path / "r.yaml"), "--device", f"{b.url}?timeout=2.5", "--out", str(single))[0]
            == 0
        )
    doc = json.loads(out.read_text())
    assert doc["devices"][0]["plan"]["device"]["url"] == a.url  # the defaults: nothing to keep
    recorded = doc["devices"][1]["plan"]["device"]["url"]
    assert recorded == f"{b.url}?pause_between_requests=20ms&retries=0&timeout=2.5", recorded
    assert json.loads(single.read_text())["device"]["url"] == f"{b.url}?timeout=2.5"

    def urls(source: Path, **given: object) -> list[tuple[float, int]]:
        jobs = prepare(RunRequest(str(source), **given)).jobs  # type: ignore[arg-type]
        return [(j.url.timeout, j.url.retries) for j in jobs]

    assert urls(out) == [(1.0, 2), (2.5, 0)] and urls(out, timeout=5.0, retries=3) == [(5.0, 3), (5.0, 3)]
    assert urls(single) == [(2.5, 2)] and urls(single, timeout=5.0) == [(5.0, 2)]
