"""Files deployer reads back that someone else may have edited (issue #28, items 11, 12, 14 and 16):
the learned limits, reports; names too long for a file system; big imports.

Each is refused at its position with exit 1 and never a traceback, before anything is sent.
"""

from __future__ import annotations

import copy
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from deployer.profile import builtin_profile
from deployer.testing.simulator import SimulatorThread
from tests.helpers import cli as run_cli

INVERTER = builtin_profile("example-inverter")
RECIPE = "recipe: line\nprofile: example-inverter\nparameters:\n  F07: 10 s\n  F08: 12 s\n"


def learned_file(state: Path, value: str, url: str) -> None:
    state.mkdir(exist_ok=True)
    port = url.rsplit(":", 1)[1]
    (state / "learned.json").write_text(
        '{"schema": "deployer.learned/1", "devices": [\n'
        f'  {{"profile": "example-inverter", "device": "127.0.0.1:{port}/1", "url": "{url}", "unit": 1,\n'
        f'   "limits": {{"max_write_registers": {value}}}, "seen": "", "when": ""}}]}}\n'
    )


@pytest.mark.parametrize("value", ["1e400", "-Infinity", "NaN", '"x"', "null", "1.5", "true", "0", "999", "[]"])
def test_a_learned_file_deployer_did_not_write_is_refused(
    value: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "r.yaml").write_text(RECIPE)
    state = tmp_path / "st"
    with SimulatorThread(INVERTER) as sim:
        learned_file(state, value, sim.url)
        for args in (
            ["learned", "list"],
            ["plan", str(tmp_path / "r.yaml"), "--device", sim.url],
            ["apply", str(tmp_path / "r.yaml"), "--device", sim.url, "--yes"],
        ):
            code, out, err = run_cli(capsys, *args, "--state-dir", str(state))
            assert code == 1, (args, out, err)
            assert "Traceback" not in err
            first = err.splitlines()[0]
            assert first.startswith(f"{state / 'learned.json'}:3:38: error: limits.max_write_registers"), first
            assert f"deployer learned forget --all --state-dir {state}" in first
        plan_reads = len(sim.log)  # plan read the device; apply sent nothing at all
        assert all(e.function in (3, 43) for e in sim.log)
        assert sim.read("F07") == INVERTER.parameter("F07").default_registers()
        code, out, _ = run_cli(capsys, "learned", "forget", "--all", "--state-dir", str(state))
        assert code == 0 and "not a learned file deployer wrote" in out
        code, _, err = run_cli(
            capsys, "apply", str(tmp_path / "r.yaml"), "--device", sim.url, "--yes", "--state-dir", str(state)
        )
        assert code == 0, err
        assert len(sim.log) > plan_reads


def test_a_learned_file_that_is_not_json_is_refused_where_it_breaks(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    state = tmp_path / "st"
    state.mkdir()
    (state / "learned.json").write_text('{"schema": "deployer.learned/1",\n "devices": [')
    code, _, err = run_cli(capsys, "learned", "list", "--state-dir", str(state))
    assert code == 1 and err.startswith(f"{state / 'learned.json'}:2:14: error: invalid JSON")
    (state / "learned.json").write_bytes(b'{"schema": "deployer.learned/1", "devices": ["\xff"]}')
    code, _, err = run_cli(capsys, "learned", "list", "--state-dir", str(state))
    assert code == 1 and "1:47: error: not UTF-8 text" in err
    (state / "learned.json").write_text(
        json.dumps(
            {
                "schema": "deployer.learned/1",
                "devices": [{"profile": "p", "device": "d", "limits": {"max_read_registers": 2}, "extra": 1}],
            }
        )
    )
    code, _, err = run_cli(capsys, "learned", "list", "--state-dir", str(state))
    assert code == 1 and "unknown key 'extra'" in err and "unknown limit 'max_read_registers'" in err


@pytest.mark.parametrize("name", ["r" * 300, "日本語" * 100, "CON." + "x" * 260])
def test_a_long_recipe_name_gets_a_bounded_snapshot_name(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rec = tmp_path / "r.yaml"
    rec.write_text(RECIPE.replace("recipe: line", f"recipe: {json.dumps(name)}"))
    state = tmp_path / "st"
    with SimulatorThread(INVERTER) as sim:
        before = sim.read("F07")
        code, _, err = run_cli(capsys, "apply", str(rec), "--device", sim.url, "--yes", "--state-dir", str(state))
        assert code == 0, err
        (snap,) = (state / "snapshots").iterdir()
        assert len(snap.name.encode()) <= 130 and snap.name.endswith(".yaml")
        other = tmp_path / "other.yaml"  # another long name with the same start keeps its own snapshot
        other.write_text(rec.read_text().replace(json.dumps(name), json.dumps(name + "2")).replace("10 s", "11 s"))
        code, _, err = run_cli(capsys, "apply", str(other), "--device", sim.url, "--yes", "--state-dir", str(state))
        assert code == 0, err
        assert len(list((state / "snapshots").iterdir())) == 2
        code, _, err = run_cli(capsys, "rollback", str(snap), "--device", sim.url, "--yes", "--state-dir", str(state))
        assert code == 0, err
        assert sim.read("F07") == before


def test_status_of_a_fleet_whose_recipes_come_from_groups(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """What a crashed run of ``apply --inventory`` (no RECIPE: each device's from its groups) leaves in the
    journal: status names the inventory, not an empty recipe, and its check command runs as printed."""
    import shlex

    from deployer.state import journal

    monkeypatch.chdir(tmp_path)
    Path("drive.yaml").write_text(RECIPE)
    with SimulatorThread(INVERTER) as sim:
        Path("site.yaml").write_text(
            f"groups:\n  drives: {{recipe: drive.yaml}}\ndevices:\n  drive-1: {{url: '{sim.url}', groups: [drives]}}\n"
        )
        journal.run_started(
            "st",
            "run-1",
            command="apply",
            argv=["apply", "--inventory", "site.yaml", "--yes"],
            recipe=None,
            via="cli",
            devices=[("drive-1", sim.url, 1)],
        )
        journal.append(
            "st",
            {
                **journal.device_started("run-1", name="drive-1", url=sim.url, unit=1, plan_digest="0" * 64),
                "snapshot": "st/snapshots/s.yaml",
            },
        )
        code, out, err = run_cli(capsys, "status", "--state-dir", "st")
        assert code == 2, out + err  # a run needs a look
        assert "apply --inventory site.yaml by " in out and "apply  by" not in out and "PROFILE" not in out
        check = next(line for line in out.splitlines() if "check with: " in line)
        command = check.split("check with: ")[1].split(";")[0]
        assert command == "deployer diff --inventory site.yaml --limit drive-1"
        code, out, err = run_cli(capsys, *shlex.split(command)[1:])
        assert code == 2 and "drive-1" in out, err  # the device still holds its old values: drift
        assert "undo with: deployer rollback st/snapshots/s.yaml --state-dir st" in check


# ---- deployer report on a hand-edited report (#28 item 12) --------------------------------------


@pytest.fixture(scope="module")
def good_report(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A real report: a recipe applied to a simulator (one value refused, so every field is there)."""
    from deployer.cli import main

    tmp = tmp_path_factory.mktemp("report")
    (tmp / "r.yaml").write_text(RECIPE + "  stop_mode: coast\n")
    with SimulatorThread(INVERTER) as sim, pytest.raises(SystemExit):
        main(
            [
                "apply",
                str(tmp / "r.yaml"),
                "--device",
                sim.url,
                "--yes",
                "--report",
                str(tmp / "run.json"),
                "--state-dir",
                str(tmp / "st"),
            ]
        )
    doc: dict[str, Any] = json.loads((tmp / "run.json").read_text())
    return doc


EDITS: list[tuple[str, Callable[[dict[str, Any]], None], str]] = [
    ("batch an object", lambda d: d["devices"][0].update(batch={"n": 1}), "devices[0].batch: expected an integer"),
    (
        "after_raw text",
        lambda d: d["devices"][0]["parameters"][0].update(after_raw="zz"),
        "devices[0].parameters[0].after_raw: 'zz' is not valid here",
    ),
    ("requests a number", lambda d: d["devices"][0].update(requests=5), "devices[0].requests: expected a list"),
    ("seconds text", lambda d: d["devices"][0].update(seconds="fast"), "devices[0].seconds: expected a number"),
    ("unit text", lambda d: d["devices"][0].update(unit="1"), "devices[0].unit: expected an integer, got '1'"),
    ("summary seconds text", lambda d: d["summary"].update(seconds="x"), "summary.seconds: expected a number"),
    (
        "a register out of range",
        lambda d: d["devices"][0]["parameters"][0].update(before_raw=[70000, 1]),
        "devices[0].parameters[0].before_raw[0]: 70000 is greater than the maximum of 65535",
    ),
    ("a status unknown", lambda d: d["devices"][0].update(status="great"), "devices[0].status: 'great' is not one of"),
    ("devices an object", lambda d: d.update(devices={}), "devices: expected a list"),
    ("a device a list", lambda d: d["devices"].append([]), "devices[1]: expected a mapping"),
    (
        "learned text",
        lambda d: d["devices"][0].update(learned={"max_write_registers": "4"}),
        "devices[0].learned.max_write_registers: expected an integer",
    ),
    (
        "identity a number",
        lambda d: d["devices"][0].update(identity={"vendor": 5}),
        "devices[0].identity.vendor: expected a string",
    ),
    ("a newer version", lambda d: d.update(schema="deployer.report/99"), "this deployer reads versions 1 to"),
    ("not a report", lambda d: d.update(schema="other/1"), "not a deployer report"),
]


@pytest.mark.parametrize(("edit", "message"), [(e[1], e[2]) for e in EDITS], ids=[e[0] for e in EDITS])
def test_deployer_report_on_a_hand_edited_report(
    good_report: dict[str, Any],
    edit: Callable[[dict[str, Any]], None],
    message: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    doc = copy.deepcopy(good_report)
    edit(doc)
    f = tmp_path / "edited.json"
    f.write_text(json.dumps(doc, indent=2))
    for args in (
        ["report", str(f)],
        ["report", str(f), "--html", str(tmp_path / "p.html")],
        ["rollback", "--from-report", str(f), "--yes"],
    ):
        code, _out, err = run_cli(capsys, *args)
        assert code == 1 and "Traceback" not in err, (args, err)
        first = err.splitlines()[0]
        assert first.startswith(f"{f}:") and ": error: " in first and message in first, first
        line, col = first[len(str(f)) + 1 :].split(":")[:2]
        assert int(line) >= 1 and int(col) >= 1
    assert not (tmp_path / "p.html").exists()


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity", "1e400"])
def test_numbers_json_cannot_hold_are_refused_where_they_are(
    good_report: dict[str, Any], token: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = json.dumps(good_report, indent=2).replace('"seconds": ', f'"seconds": {token}, "x": ', 1)
    f = tmp_path / "edited.json"
    f.write_text(text)
    line = next(i for i, t in enumerate(text.splitlines(), 1) if token in t)
    code, _, err = run_cli(capsys, "report", str(f))
    assert code == 1 and err.startswith(f"{f}:{line}:"), err


def test_older_versions_and_unfinished_reports_stay_readable(
    good_report: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for version in (1, 2):
        old = copy.deepcopy(good_report)
        old["schema"] = f"deployer.report/{version}"
        old.pop("run", None)
        for d in old["devices"]:
            for key in ("profile_sha256", "commit", "learned", "identity", "recipe", "seconds", "profile_ref"):
                d.pop(key, None)
        f = tmp_path / f"v{version}.json"
        f.write_text(json.dumps(old))
        code, out, err = run_cli(capsys, "report", str(f))
        assert code == 0 and "F07" in out, err


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_any_edit_of_a_report_is_shown_or_refused_never_a_traceback(
    good_report: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str], data: st.DataObject
) -> None:
    """Edits anywhere in a real report: a value replaced by any JSON value, or a key removed."""
    doc = copy.deepcopy(good_report)
    node: Any = doc
    while True:  # walk down to some mapping or list
        keys = list(node) if isinstance(node, dict) else list(range(len(node)))
        if not keys:
            break
        key = data.draw(st.sampled_from(keys))
        child = node[key]
        if isinstance(child, dict | list) and child and data.draw(st.booleans()):
            node = child
            continue
        json_values = st.recursive(
            st.none()
            | st.booleans()
            | st.integers(-(2**70), 2**70)
            | st.floats(allow_nan=False, allow_infinity=False)
            | st.text(max_size=8),
            lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner, max_size=3),
            max_leaves=6,
        )
        if isinstance(node, dict) and data.draw(st.booleans()):
            del node[key]
        else:
            node[key] = data.draw(json_values)
        break
    f = tmp_path / "fuzzed.json"
    f.write_text(json.dumps(doc))
    code, _, err = run_cli(capsys, "report", str(f), "--html", str(tmp_path / "p.html"))
    assert code in (0, 1) and "Traceback" not in err
    if code == 1:
        assert err.startswith(f"{f}:") and ": error: " in err


# ---- a report is data: nothing it names is opened (#28 item 11) ----------------------------------

OPENED: list[str] = []
_WATCHING: list[bool] = []


def _watch_opens() -> None:
    """Every file this process opens from now on, in OPENED (an audit hook: it cannot be removed, so it
    records only while the list is not cleared away)."""
    import sys

    if not _WATCHING:
        _WATCHING.append(True)
        sys.addaudithook(
            lambda event, args: (
                OPENED.append(str(args[0])) if event == "open" and args and isinstance(args[0], str | bytes) else None
            )
        )


def test_a_report_naming_a_secret_file_never_opens_it(
    good_report: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    secret = tmp_path / "shadow"
    secret.write_text("root:$6$SECRET-SALT$hash:19000:0:99999:7:::\n")
    snapshots = tmp_path / "st" / "snapshots"
    snapshots.mkdir(parents=True)
    disguised = snapshots / "line-20260101T000000Z.yaml"  # named like a snapshot, a link to the secret
    disguised.symlink_to(secret)
    doc = copy.deepcopy(good_report)
    doc.pop("profiles", None)
    doc["devices"][0].update(profile_ref=str(secret), profile="shadow", snapshot=str(secret), status="partial")
    evil = tmp_path / "evil.json"
    evil.write_text(json.dumps(doc))
    doc["devices"][0]["snapshot"] = str(disguised)
    (tmp_path / "evil2.json").write_text(json.dumps(doc))
    journal_dir = tmp_path / "elsewhere"  # a journal named by the report: a link to the secret
    journal_dir.mkdir()
    (journal_dir / "audit.jsonl").symlink_to(secret)
    doc["devices"][0].update(snapshot=None, status="interrupted")
    doc["run"] = {"id": "run-1", "state_dir": str(journal_dir)}
    (tmp_path / "evil3.json").write_text(json.dumps(doc))
    _watch_opens()
    OPENED.clear()
    code, out, err = run_cli(capsys, "report", str(evil), "--html", str(tmp_path / "p.html"))
    assert code == 0 and "values shown as registers" in out and "SECRET" not in out + err
    assert "SECRET" not in (tmp_path / "p.html").read_text()
    for report in (evil, tmp_path / "evil2.json", tmp_path / "evil3.json"):
        code, out, err = run_cli(
            capsys, "rollback", "--from-report", str(report), "--yes", "--state-dir", str(tmp_path / "st")
        )
        assert code == 1 and ("not a snapshot file deployer writes" in err or "not a regular file" in err), err
        assert "SECRET" not in out + err
    assert not [p for p in OPENED if p in (str(secret), str(disguised), str(journal_dir / "audit.jsonl"))], OPENED


def test_a_report_shows_units_without_its_profile_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    profile = tmp_path / "dev.yaml"
    profile.write_text(
        "profile: dev\nparameters:\n  speed: {register: 1, type: uint16, scale: 0.1, unit: Hz}\n"
        "  mode: {register: 2, type: uint16, values: {stop: 0, run: 1}}\n"
    )
    (tmp_path / "r.yaml").write_text("recipe: r\nprofile: dev.yaml\nparameters: {speed: 50 Hz, mode: run}\n")
    from deployer.profile import load_profile

    with SimulatorThread(load_profile(str(profile))) as sim:
        code, _, err = run_cli(
            capsys,
            "apply",
            str(tmp_path / "r.yaml"),
            "--device",
            sim.url,
            "--yes",
            "--report",
            str(tmp_path / "run.json"),
            "--state-dir",
            str(tmp_path / "st"),
        )
    assert code == 0, err
    doc = json.loads((tmp_path / "run.json").read_text())
    assert doc["profiles"][str(profile)]["parameters"]["speed"] == {
        "address": 1,
        "type": "uint16",
        "scale": "0.1",
        "unit": "Hz",
        "size": 1,
    }
    profile.write_text("profile: dev\nparameters: {}\n")  # changed since the run: the report keeps its own
    code, out, _ = run_cli(capsys, "report", str(tmp_path / "run.json"))
    assert code == 0 and " 50 Hz " in out and " run " in out and "values shown as registers" not in out
    del doc["profiles"]  # a report of before: the user names the profile
    (tmp_path / "old.json").write_text(json.dumps(doc))
    code, out, _ = run_cli(capsys, "report", str(tmp_path / "old.json"))
    assert code == 0 and "values shown as registers" in out and " 500 " in out
    profile.write_text("profile: dev\nparameters:\n  speed: {register: 1, type: uint16, scale: 0.1, unit: Hz}\n")
    code, out, _ = run_cli(capsys, "report", str(tmp_path / "old.json"), "--profile", str(profile))
    assert code == 0 and " 50 Hz " in out and "the run used another version" in out


def test_a_fleet_report_describes_each_profile_once(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from deployer.testing.simulator import Simulator
    from tests.helpers import Simulators

    (tmp_path / "r.yaml").write_text(RECIPE)
    with Simulators([Simulator(INVERTER) for _ in range(3)]) as sims:
        (tmp_path / "inv.yaml").write_text(
            "devices:\n" + "".join(f"  d{i}: {{url: '{s.url}'}}\n" for i, s in enumerate(sims))
        )
        code, _, err = run_cli(
            capsys,
            "apply",
            str(tmp_path / "r.yaml"),
            "--inventory",
            str(tmp_path / "inv.yaml"),
            "--yes",
            "--report",
            str(tmp_path / "run.json"),
            "--state-dir",
            str(tmp_path / "st"),
        )
    assert code == 0, err
    text = (tmp_path / "run.json").read_text()
    doc = json.loads(text)
    assert list(doc["profiles"]) == ["example-inverter"] and text.count('"F07": {') == 1
    assert set(doc["profiles"]["example-inverter"]["parameters"]) == {"F07", "F08"}
    del doc["devices"][0]["profile_ref"]  # the built-in by its id, or the report's view: units either way
    (tmp_path / "run.json").write_text(json.dumps(doc))
    from deployer.report import read_report, report_from_json

    shown = report_from_json(read_report(str(tmp_path / "run.json")))
    assert [p.after for d in shown.devices for p in d.parameters] == ["10 s", "12 s"] * 3
    assert not any(d.notices for d in shown.devices)


def test_the_learned_file_is_read_once_for_a_fleet_and_again_when_it_changes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from deployer.state import learned

    state = str(tmp_path)
    assert learned.lookup(state, "p", "a#unit1") is None  # no file: nothing taught
    for i in range(3):
        learned.remember(state, learned.Entry("p", f"d{i}#unit1", {"max_write_registers": 10 + i}, "", "now"))
    reads: list[str] = []
    real = learned.load

    def load(s: str) -> list[learned.Entry]:
        reads.append(s)
        return real(s)

    monkeypatch.setattr(learned, "load", load)
    got = [learned.lookup(state, "p", f"d{i}#unit1") for i in range(3)] * 100  # a fleet asks per device
    assert [e.limits["max_write_registers"] for e in got[:3] if e] == [10, 11, 12] and len(reads) == 1
    learned.remember(state, learned.Entry("p", "d1#unit1", {"write_function": 6}, "", "later"))
    again = learned.lookup(state, "p", "d1#unit1")
    assert again is not None and again.limits == {"max_write_registers": 11, "write_function": 6}


def test_another_processs_learned_limits_are_seen_within_a_second(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The file's status is asked at most every ``RECHECK`` seconds (a fleet asks per device); a change another
    process made (not this one's ``remember``, which is seen at once) is seen after that."""
    import shutil
    import time

    from deployer.state import learned

    state, other = tmp_path / "state", tmp_path / "other"
    learned.remember(str(state), learned.Entry("p", "d#unit1", {"max_write_registers": 10}, "", "now"))
    learned.remember(str(other), learned.Entry("p", "d#unit1", {"max_write_registers": 4}, "", "later"))
    clock = [1000.0]
    monkeypatch.setattr(time, "monotonic", lambda: clock[0])  # the clock ``learned`` reads
    first = learned.lookup(str(state), "p", "d#unit1")
    assert first is not None and first.limits == {"max_write_registers": 10}
    shutil.copy(learned.path_of(str(other)), learned.path_of(str(state)) + ".new")  # as its save does: a new file
    os.replace(learned.path_of(str(state)) + ".new", learned.path_of(str(state)))
    clock[0] += learned.RECHECK / 2
    assert learned.lookup(str(state), "p", "d#unit1") == first  # not asked of the system yet
    clock[0] += learned.RECHECK
    now = learned.lookup(str(state), "p", "d#unit1")
    assert now is not None and now.limits == {"max_write_registers": 4}
