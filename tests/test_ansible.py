"""The Ansible collection (ansible_collections/deployer/modbus) run by ansible-playbook for real.

Two "site gateway" hosts (connection local, the venv's Python) each with two simulated devices
on loopback (one site's devices as host vars, the other's in a deployer inventory on the gateway),
the example playbook playbooks/sites.yml: check mode, a real run, a second run,
and a rejected value that fails its host naming the parameter.
"""

from __future__ import annotations

import json
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
PLAYBOOK = COLLECTION / "playbooks" / "sites.yml"
PLAYBOOK_BIN = Path(sys.executable).parent / "ansible-playbook"
PROFILE = builtin_profile("example-inverter")
WANT = {"F07": (0, 1000), "F08": (0, 1200), "stop_mode": (1,)}

pytestmark = [
    pytest.mark.timeout(300),
    pytest.mark.skipif(
        not PLAYBOOK_BIN.exists() and shutil.which("ansible-playbook") is None,
        reason="ansible-core is a test extra (pip install -e '.[test]')",
    ),
]


def playbook(tmp: Path, inventory: Path, *args: str) -> tuple[int, str, dict[str, list[dict[str, Any]]]]:
    """Run the example playbook; returns exit code, output and each host's task results (tree callback)."""
    tree = tmp / "tree"
    shutil.rmtree(tree, ignore_errors=True)
    env = {
        **without_coverage(),  # ansible's forks each started coverage (helpers)
        "ANSIBLE_COLLECTIONS_PATH": str(ROOT),  # the folder that holds ansible_collections/
        "ANSIBLE_HOME": str(tmp / "ansible-home"),
        "ANSIBLE_LOCAL_TEMP": str(tmp / "ansible-tmp"),
        "ANSIBLE_REMOTE_TEMP": str(tmp / "ansible-remote"),
        "ANSIBLE_NOCOLOR": "1",
        "ANSIBLE_CALLBACKS_ENABLED": "ansible.builtin.tree",
        "ANSIBLE_CALLBACK_TREE_DIR": str(tree),
        "ANSIBLE_HOST_KEY_CHECKING": "0",
        "ANSIBLE_RETRY_FILES_ENABLED": "0",
        "ANSIBLE_STDOUT_CALLBACK": "default",
    }
    exe = str(PLAYBOOK_BIN) if PLAYBOOK_BIN.exists() else "ansible-playbook"
    proc = subprocess.run(
        [exe, "-i", str(inventory), str(PLAYBOOK), *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp,
        timeout=240,
        stdin=subprocess.DEVNULL,
    )
    results: dict[str, list[dict[str, Any]]] = {}
    if tree.exists():
        for f in tree.iterdir():
            results[f.name] = [json.loads(f.read_text())]
    return proc.returncode, proc.stdout + proc.stderr, results


def inventory(tmp: Path, sites: dict[str, list[Simulator]], recipe: Path) -> Path:
    """Ansible's inventory: site-a lists its devices as host vars, site-b points at a deployer inventory."""
    lines = ["site_gateways:", "  hosts:"]
    for site, sims in sites.items():
        lines += [
            f"    {site}:",
            "      ansible_connection: local",
            f"      ansible_python_interpreter: {sys.executable}",
            f"      deployer_recipe: {recipe}",
            f"      deployer_state_dir: {tmp / 'state'}",
            f"      deployer_pulled_dir: {tmp / 'pulled' / site}",
        ]
        if site == "site-b":
            own = tmp / f"{site}-inventory.yaml"
            own.write_text(
                "defaults: {timeout: 1.0, retries: 0}\ndevices:\n"
                + "".join(f"  {site}-d{i}: {{url: '{s.url}'}}\n" for i, s in enumerate(sims))
            )
            lines.append(f"      deployer_inventory: {own}")
            continue
        lines.append("      modbus_devices:")
        lines += [f"        - {{name: {site}-d{i}, url: '{s.url}?timeout=1&retries=0'}}" for i, s in enumerate(sims)]
    p = tmp / "hosts.yml"
    p.write_text("\n".join(lines) + "\n")
    return p


def writes(sims: list[Simulator]) -> int:
    return sum(1 for s in sims for e in s.log if e.function in (6, 16))


def recap(out: str, host: str) -> dict[str, int]:
    line = next(x for x in out.splitlines() if x.startswith(host) and "ok=" in x)
    return {k: int(v) for k, v in (w.split("=") for w in line.split(":", 1)[1].split())}


def test_playbook_check_apply_idempotent_and_a_rejected_value(tmp_path: Path) -> None:
    recipe = tmp_path / "line3.yaml"
    recipe.write_text((COLLECTION / "playbooks" / "line3.yaml").read_text())
    with Simulators([Simulator(PROFILE, faults=Faults()) for _ in range(4)]) as sims:
        sites = {"site-a": sims[:2], "site-b": sims[2:]}
        inv = inventory(tmp_path, sites, recipe)

        # check mode: changed, with a diff per device, and not one write request
        code, out, _ = playbook(tmp_path, inv, "--check", "--diff")
        assert code == 0, out
        assert recap(out, "site-a")["changed"] == 1 and recap(out, "site-b")["changed"] == 1
        assert "-F07: 5 s" in out and "+F07: 10 s" in out and "+stop_mode: coast" in out
        assert "site-b-d1" in out  # the diff names each device
        assert writes(sims) == 0 and all(s.log for s in sims)

        # a real run writes and verifies every device (and the facts task writes the recipe files)
        code, out, results = playbook(tmp_path, inv)
        assert code == 0, out
        assert recap(out, "site-a")["changed"] == 2 and recap(out, "site-b")["changed"] == 2
        assert all(s.read(n) == v for s in sims for n, v in WANT.items())
        values = results["site-b"][0]["values"]  # the last task: pull (its values are the info task's facts)
        assert values["site-b-d0"] == {"F07": "10 s", "F08": "12 s", "stop_mode": "coast"}
        pulled = tmp_path / "pulled" / "site-a" / "site-a-d1.yaml"  # the pull task wrote recipe files
        assert "F07: 10 s" in pulled.read_text() and f'url": "{sims[1].url}' in pulled.read_text()
        # each host's apply is one journaled run (deployer status would list it, had it not finished)
        lines = [json.loads(x) for x in (tmp_path / "state" / "audit.jsonl").read_text().splitlines()]
        started = [x for x in lines if x["event"] == "run-started"]
        assert len(started) == 2 and all(x["via"] == "ansible" and x["command"] == "apply" for x in started)
        assert sorted(d["name"] for x in started for d in x["devices"]) == [
            f"site-{s}-d{i}" for s in "ab" for i in range(2)
        ]
        finished = {x["run"]: x for x in lines if x["event"] == "run-finished"}
        assert all(finished[x["run"]]["exit_code"] == 0 for x in started)
        assert "ok: [site-a]" in out and "modbus_devices" not in out.split("Keep them as recipe files")[1]

        # a second run has nothing to do
        before = writes(sims)
        code, out, _ = playbook(tmp_path, inv)
        assert code == 0, out
        assert recap(out, "site-a")["changed"] == 0 and recap(out, "site-b")["changed"] == 0
        assert writes(sims) == before

        # a device that rejects a value fails its host, naming the parameter; the other site is fine
        recipe.write_text(recipe.read_text().replace("F08: 12 s", "F08: 15 s"))
        sims[3].faults.fail_registers = frozenset({PROFILE.parameter("F08").address})
        code, out, _ = playbook(tmp_path, inv)
        assert code != 0
        assert recap(out, "site-a")["failed"] == 0 and recap(out, "site-b")["failed"] == 1
        assert "site-b-d1 partial: F08 failed (exception 04" in out
        assert sims[2].read("F08") == (0, 1500) and sims[3].read("F08") == (0, 1200)
