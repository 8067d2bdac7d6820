"""The Ansible collection checked by Ansible's own tools, and its modules' option checks.

`ansible-test sanity --test validate-modules` runs for real (its own virtual environment, set up
from the package index); `ansible-doc` output is read as a user reads it; each module is run the
way Ansible runs it (`python MODULE.py ARGS.json`) against simulators on loopback, so a refused
option is seen to send nothing.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from deployer.profile import builtin_profile
from deployer.testing.simulator import Faults, Simulator
from tests.helpers import Simulators, without_coverage

ROOT = Path(__file__).parent.parent
COLLECTION = ROOT / "ansible_collections" / "deployer" / "modbus"
BIN = Path(sys.executable).parent
PROFILE = builtin_profile("example-inverter")

pytestmark = [
    pytest.mark.timeout(600),
    pytest.mark.skipif(
        not (BIN / "ansible-doc").exists(), reason="ansible-core is a test extra (pip install -e '.[test]')"
    ),
]

# ansible-test fetches a pip bootstrap script from its own CI host, which only the package index can
# stand in for here: where the download fails it names the file to save by hand, and this script, saved
# there, installs the pip version it asks for from the index instead.
_GET_PIP = """import ensurepip, os, subprocess, sys
ensurepip.bootstrap(upgrade=True)
os.environ.pop("PIP_CONFIG_FILE", None)  # ensurepip points it at /dev/null; pip's own settings count
args = [a for a in sys.argv[1:] if a not in ("--no-setuptools", "--no-wheel")]
sys.exit(subprocess.call([sys.executable, "-m", "pip", "install", *args]))
"""
_SAVE_BY_HAND = re.compile(r"bootstrap script can be manually downloaded and saved to: (\S+)")


def test_validate_modules_is_clean(tmp_path: Path) -> None:
    home = tmp_path / "home"
    home.mkdir()
    # ansible-test copies the collection's git-tracked files; a copy outside git takes them all
    tree = tmp_path / "ansible_collections" / "deployer" / "modbus"
    shutil.copytree(COLLECTION, tree, ignore=shutil.ignore_patterns("__pycache__", "output"))
    env = {"HOME": str(home), "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"}
    for _ in range(2):  # a second run once the bootstrap script is where ansible-test looks for it
        proc = subprocess.run(
            [
                str(BIN / "ansible-test"),
                "sanity",
                "--test",
                "validate-modules",
                "--python",
                f"{sys.version_info.major}.{sys.version_info.minor}",
                "--color",
                "no",
            ],
            cwd=tree,
            env=env,
            capture_output=True,
            text=True,
            timeout=540,
        )
        out = proc.stdout + proc.stderr
        wanted = _SAVE_BY_HAND.search(out)
        if proc.returncode == 0 or not wanted or Path(wanted[1]).exists():
            break
        Path(wanted[1]).parent.mkdir(parents=True, exist_ok=True)
        Path(wanted[1]).write_text(_GET_PIP)
    if proc.returncode and any(
        w in out
        for w in ("No matching distribution", "Could not fetch URL", "Download failed", "does not have pip available")
    ):
        pytest.skip(
            "ansible-test could not set up its environment from the package index: " + out.strip().splitlines()[-1]
        )
    assert proc.returncode == 0, out
    assert 'Running sanity test "validate-modules"' in out and "ERROR" not in out


def _doc(name: str, *args: str) -> str:
    env = {
        **without_coverage(),  # ansible-doc only reads the collection: nothing of deployer's to measure
        "ANSIBLE_COLLECTIONS_PATH": str(ROOT),
        "ANSIBLE_NOCOLOR": "1",
        "ANSIBLE_HOME": "/nonexistent",
    }
    proc = subprocess.run([str(BIN / "ansible-doc"), *args, name], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def test_ansible_doc_shows_every_option_whole() -> None:
    out = " ".join(_doc("deployer.modbus.apply").split())
    # a comma in a description no longer cuts it (flow style did: "limit  Inventory selection (names")
    assert "names, groups, globs, `!NAME' to exclude, or `@REPORT.json'" in out
    for sub in ("name", "url", "unit", "profile", "parameters"):  # devices' (agent's come first: a before d)
        assert f" {sub} " in out.split("suboptions:")[2]
    for sub in ("url", "token", "token_file", "ca", "timeout"):
        assert f" {sub} " in out.split("suboptions:")[1]
    assert "check_mode" in out and "diff_mode" in out and "AUTHOR" in out

    docs = {
        m: json.loads(_doc(f"deployer.modbus.{m}", "--json"))[f"deployer.modbus.{m}"]["doc"]
        for m in ("apply", "info", "pull")
    }
    for m, d in docs.items():
        assert d["author"] and d["attributes"]["check_mode"]["support"] == "full", m
        assert set(d["options"]) >= {"device", "devices", "inventory", "limit", "unit", "timeout", "retries"}, m
        assert d["options"]["devices"]["suboptions"]["url"]["required"] is True
    assert docs["apply"]["options"]["agent"]["suboptions"]["url"]["required"] is True
    assert docs["info"]["attributes"]["facts"]["support"] == "full"
    assert "dest" not in docs["info"]["options"] and docs["pull"]["options"]["dest"]["required"] is True
    # the old facts name now means the read-only module
    assert json.loads(_doc("deployer.modbus.facts", "--json")).popitem()[1]["doc"]["module"] == "info"


def run_module(tmp: Path, module: str, args: dict[str, Any], *, check: bool = False) -> tuple[int, dict[str, Any]]:
    """Run a module as Ansible does: ``python MODULE.py ARGS.json``; (exit code, its JSON result)."""
    argfile = tmp / f"args-{module}.json"
    argfile.write_text(
        json.dumps({"ANSIBLE_MODULE_ARGS": {**args, "_ansible_check_mode": check, "_ansible_tmpdir": str(tmp)}})
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run(
        [sys.executable, str(COLLECTION / "plugins" / "modules" / f"{module}.py"), str(argfile)],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp,
        timeout=120,
    )
    out = proc.stdout
    return proc.returncode, json.loads(out[out.index("{") :])


@pytest.mark.parametrize(
    ("args", "words"),
    [
        ({"unit": 0}, "unit is 0, which is broadcast"),
        ({"unit": 300}, "unit must be from 1 to 247"),
        ({"unit": -5}, "unit must be from 1 to 247"),
        ({"timeout": 0}, "timeout must be more than 0"),
        ({"timeout": -1}, "timeout must be more than 0"),
        ({"retries": 1_000_000_000}, "retries must be from 0 to 20"),
        ({"parallel": 0}, "parallel must be from 1 to 1024"),
        ({"limit": "a"}, "device names one device already"),
    ],
)
def test_out_of_range_options_are_refused_before_anything_is_sent(
    tmp_path: Path, args: dict[str, Any], words: str
) -> None:
    with Simulators([Simulator(PROFILE, faults=Faults())]) as (sim,):
        code, res = run_module(
            tmp_path,
            "apply",
            {
                "profile": "example-inverter",
                "parameters": {"F07": "10 s"},
                "device": sim.url,
                "state_dir": str(tmp_path / "st"),
                **args,
            },
        )
        assert code == 1 and res["failed"] and words in res["msg"] and "nothing was sent" in res["msg"], res
        assert sim.log == []


def test_devices_unit_zero_is_not_unit_one(tmp_path: Path) -> None:
    with Simulators([Simulator(PROFILE, faults=Faults())]) as (sim,):
        code, res = run_module(
            tmp_path,
            "apply",
            {
                "profile": "example-inverter",
                "parameters": {"F07": "10 s"},
                "state_dir": str(tmp_path / "st"),
                "devices": [{"name": "a", "url": sim.url, "unit": 0}],
            },
        )
        assert code == 1 and "devices[0].unit is 0, which is broadcast" in res["msg"]
        assert sim.log == []


def test_limit_selects_from_devices(tmp_path: Path) -> None:
    with Simulators([Simulator(PROFILE, faults=Faults()) for _ in range(2)]) as (a, b):
        code, res = run_module(
            tmp_path,
            "apply",
            {
                "profile": "example-inverter",
                "parameters": {"F07": "10 s"},
                "state_dir": str(tmp_path / "st"),
                "devices": [{"name": "a", "url": a.url}, {"name": "b", "url": b.url}],
                "limit": "a",
            },
        )
        assert code == 0, res
        assert [d["name"] for d in res["devices"]] == ["a"]
        assert a.read("F07") == (0, 1000) and b.read("F07") == (0, 500) and b.log == []
        code, res = run_module(
            tmp_path,
            "apply",
            {
                "profile": "example-inverter",
                "parameters": {"F07": "10 s"},
                "state_dir": str(tmp_path / "st"),
                "devices": [{"name": "a", "url": a.url}],
                "limit": "nobody",
            },
        )
        assert code == 1 and "matches no device" in res["msg"] and "nothing was sent" in res["msg"]


def test_one_device_listed_twice_is_refused(tmp_path: Path) -> None:
    with Simulators([Simulator(PROFILE, faults=Faults())]) as (sim,):
        base = {"profile": "example-inverter", "parameters": {"F07": "10 s"}, "state_dir": str(tmp_path / "st")}
        code, res = run_module(
            tmp_path, "apply", {**base, "devices": [{"name": "a", "url": sim.url}, {"name": "a", "url": sim.url}]}
        )
        assert code == 1 and "devices lists 'a' more than once" in res["msg"]
        code, res = run_module(
            tmp_path, "apply", {**base, "devices": [{"name": "a", "url": sim.url}, {"name": "b", "url": sim.url}]}
        )
        assert code == 1 and "'a' and 'b' are one device" in res["msg"]
        code, res = run_module(
            tmp_path,
            "info",
            {"profile": "example-inverter", "devices": [{"name": "a", "url": sim.url}, {"name": "b", "url": sim.url}]},
        )
        assert code == 1 and "are one device" in res["msg"]
        assert sim.log == []


def test_info_reads_and_writes_nothing_and_pull_writes_recipes(tmp_path: Path) -> None:
    with Simulators([Simulator(PROFILE, faults=Faults())]) as (sim,):
        code, res = run_module(
            tmp_path,
            "info",
            {"profile": "example-inverter", "device": sim.url, "name": "d", "parameters": ["F07", "stop_mode"]},
        )
        assert code == 0 and res["changed"] is False, res
        assert res["ansible_facts"]["modbus_parameters"] == {"d": {"F07": "5 s", "stop_mode": "ramp"}}
        assert sorted(p.name for p in tmp_path.iterdir()) == ["args-info.json"]

        dest = tmp_path / "as-found"
        code, res = run_module(
            tmp_path,
            "pull",
            {"profile": "example-inverter", "device": sim.url, "name": "d", "dest": str(dest)},
            check=True,
        )
        assert code == 0 and res["changed"] is True and not dest.exists()
        code, res = run_module(
            tmp_path, "pull", {"profile": "example-inverter", "device": sim.url, "name": "d", "dest": str(dest)}
        )
        assert code == 0 and res["changed"] is True and res["files"] == [str(dest / "d.yaml")]
        assert "F07: 5 s" in (dest / "d.yaml").read_text()
        code, res = run_module(
            tmp_path, "pull", {"profile": "example-inverter", "device": sim.url, "name": "d", "dest": str(dest)}
        )
        assert code == 0 and res["changed"] is False
        assert not any(e.function in (5, 6, 15, 16) for e in sim.log)


def test_unusable_report_and_state_dir_are_clean_errors(tmp_path: Path) -> None:
    with Simulators([Simulator(PROFILE, faults=Faults())]) as (sim,):
        base = {"profile": "example-inverter", "parameters": {"F07": "10 s"}, "device": sim.url}
        folder = tmp_path / "a-folder"
        folder.mkdir()
        code, res = run_module(tmp_path, "apply", {**base, "state_dir": str(tmp_path / "st"), "report": str(folder)})
        assert code == 1 and str(folder) in res["msg"] and "Traceback" not in res.get("module_stderr", ""), res
        blocker = tmp_path / "a-file"
        blocker.write_text("")
        code, res = run_module(tmp_path, "apply", {**base, "state_dir": str(blocker / "state")})
        assert code == 1 and "state" in res["msg"] and "Traceback" not in res.get("module_stderr", ""), res
        assert not any(e.function in (6, 16) for e in sim.log)
        assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".") or "tmp" in p.name) == []


def test_the_collection_uses_only_the_public_api() -> None:
    """The modules use deployer's public names only (pinned by test_exported_members), nothing internal: the
    check is tests/test_import_graph.py's, which sees every import and every ``deployer.NAME``."""
    from tests.test_import_graph import private_uses

    files = sorted((COLLECTION / "plugins").rglob("*.py"))
    assert len(files) >= 6 and [u for p in files for u in private_uses(p)] == []


def test_a_device_already_in_alarm_is_not_written_by_a_soak_unless_allowed(tmp_path: Path) -> None:
    fault = PROFILE.health[0].address
    base = {
        "profile": "example-inverter",
        "parameters": {"F07": "10 s"},
        "state_dir": str(tmp_path / "st"),
        "soak": "200ms",
        "health_interval": "100ms",
    }
    with Simulators([Simulator(PROFILE, init={fault: 7})]) as (sim,):
        code, res = run_module(tmp_path, "apply", {**base, "device": sim.url})
        assert code == 1 and res["devices"][0]["status"] == "failed"
        assert "health check already failing before the change" in res["devices"][0]["error"]
        assert not [e for e in sim.log if e.function in (6, 16)]
        code, res = run_module(tmp_path, "apply", {**base, "device": sim.url, "allow_unhealthy": True})
        assert code == 0, res
        assert sim.read("F07") == (0, 1000)
        sim.log.clear()
        code, res = run_module(
            tmp_path,
            "apply",
            {**{k: v for k, v in base.items() if k != "soak"}, "device": sim.url, "allow_unhealthy": True},
        )
        assert code == 1 and "allow_unhealthy goes with soak" in res["msg"] and sim.log == []
