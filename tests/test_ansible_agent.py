"""Many sites through Ansible: the example playbook playbooks/agents.yml drives two real site agents
(deployer agent processes: one with TLS whose user is the playbook's client certificate, one with a token) through
the collection's apply with agent:.
Check mode writes nothing, a real run writes and verifies, a second run is unchanged, and a failed site
stops the rollout before the next site is touched."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from deployer.agent.client import Agent
from deployer.profile import load_profile
from deployer.testing.simulator import Faults, Simulator, SimulatorThread
from tests.agent_helpers import PROFILE, RECIPE, AgentProcess, write_site
from tests.helpers import without_coverage

ROOT = Path(__file__).parent.parent
PLAYBOOK = ROOT / "ansible_collections" / "deployer" / "modbus" / "playbooks" / "agents.yml"
PLAYBOOK_BIN = Path(sys.executable).parent / "ansible-playbook"
TOKENS = {"site-a": "site-a-token-0123456789", "site-b": "site-b-token-0123456789"}

pytestmark = [
    pytest.mark.timeout(300),
    pytest.mark.skipif(
        not PLAYBOOK_BIN.exists() and shutil.which("ansible-playbook") is None,
        reason="ansible-core is a test extra (pip install -e '.[test]')",
    ),
]


def playbook(tmp: Path, inventory: Path, *args: str) -> tuple[int, str]:
    env = {
        **without_coverage(),  # ansible's forks each started coverage (helpers)
        "ANSIBLE_COLLECTIONS_PATH": str(ROOT),
        "ANSIBLE_HOME": str(tmp / "ansible-home"),
        "ANSIBLE_LOCAL_TEMP": str(tmp / "ansible-tmp"),
        "ANSIBLE_REMOTE_TEMP": str(tmp / "ansible-remote"),
        "ANSIBLE_NOCOLOR": "1",
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
    return proc.returncode, proc.stdout + proc.stderr


def recap(out: str, host: str) -> dict[str, int] | None:
    line = next((x for x in out.splitlines() if x.startswith(host) and "ok=" in x), None)
    return None if line is None else {k: int(v) for k, v in (w.split("=") for w in line.split(":", 1)[1].split())}


def writes(sim: Simulator) -> int:
    return sum(1 for e in sim.log if e.function in (6, 16))


def test_a_playbook_rolls_out_through_two_agents(tmp_path: Path) -> None:
    from deployer.agent import users as people
    from tests.certs import issue, make_ca

    ca, ca_key, ca_cert = make_ca(tmp_path, "site-a-ca")
    server_crt, server_key = issue(tmp_path, "gateway-a", ca_key, ca_cert, server=True)
    client_crt, client_key = issue(tmp_path, "ansible.ci", ca_key, ca_cert, server=False)
    users = tmp_path / "users.yaml"  # site-a's: the controller's certificate is a user who runs and takes up edits
    people.edit(
        str(users),
        lambda doc: doc["users"].update(
            {"ansible": {"roles": ["operator", "engineer"], "certificate": {"cn": "ansible.ci"}}}
        ),
        create=True,
    )
    (tmp_path / "drive.yaml").write_text(PROFILE)
    prof = load_profile(str(tmp_path / "drive.yaml"))
    with SimulatorThread(prof, faults=Faults()) as sa, SimulatorThread(prof) as sb:
        sims = {"site-a": sa, "site-b": sb}
        agents: dict[str, AgentProcess] = {}
        try:
            hosts = ["site_agents:", "  hosts:"]
            for site, sim in sims.items():
                folder = tmp_path / site
                folder.mkdir()
                (folder / "drive.yaml").write_text(PROFILE)
                inv = write_site(folder, {f"{site}-d1": sim.url})
                (folder / "token").write_text(TOKENS[site] + "\n")
                how = (
                    ["--tls-cert", server_crt, "--tls-key", server_key, "--tls-client-ca", ca, "--users", str(users)]
                    if site == "site-a"
                    else ["--token-file", str(folder / "token")]
                )
                agents[site] = AgentProcess(inv, folder / "state", *how, check_every="1h")
                url = agents[site].url
                hosts += [
                    f"    {site}:",
                    "      ansible_connection: local",
                    f"      ansible_python_interpreter: {sys.executable}",
                    f"      deployer_agent_url: {json.dumps(url)}",
                ]
                if site == "site-a":
                    hosts += [
                        f"      deployer_agent_ca: {json.dumps(ca)}",
                        f"      deployer_agent_cert: {json.dumps(client_crt)}",
                        f"      deployer_agent_key: {json.dumps(client_key)}",
                    ]
                else:
                    hosts.append(f"      deployer_agent_token: {json.dumps(TOKENS[site])}")
            inventory = tmp_path / "hosts.yml"
            inventory.write_text("\n".join(hosts) + "\n")
            assert agents["site-a"].url.startswith("https://")

            # check mode: both sites would change (the devices are at their factory values), nothing is written
            code, out = playbook(tmp_path, inventory, "--check", "--diff")
            assert code == 0, out
            assert recap(out, "site-a") == recap(out, "site-b") and (recap(out, "site-a") or {})["changed"] == 1
            assert "-accel: 5 s" in out and "+accel: 2 s" in out and "site-b-d1" in out
            assert writes(sa) == writes(sb) == 0

            # a real run: each site's agent writes and verifies its device, one site after the other
            code, out = playbook(tmp_path, inventory)
            assert code == 0, out
            assert (recap(out, "site-a") or {})["changed"] == 1 and (recap(out, "site-b") or {})["changed"] == 1
            assert (recap(out, "site-a") or {})["ok"] == 3 and (recap(out, "site-b") or {})["ok"] == 3
            assert out.count('"speed": "3000 rpm"') == 2 and '"site-b-d1": {' in out  # info's facts, per site
            for sim in sims.values():
                assert sim.read("accel") == (20,) and sim.read("speed") == (3000,) and sim.read("address") == (7,)
            for site, a in agents.items():
                c = (
                    Agent(a.url, ca=ca, cert=client_crt, key=client_key)
                    if site == "site-a"
                    else Agent(a.url, token=TOKENS[site])
                )
                got = c.runs()
                assert len(got) == 1 and got[0]["exit_code"] == 0, got
                # who asked, from the credential (a site token names nobody), not from anything the client says
                assert got[0]["options"]["by"] == (
                    {"user": "ansible", "credential": "certificate"}
                    if site == "site-a"
                    else {"user": None, "credential": "token"}
                ), got[0]["options"]["by"]

            # a second run: nothing to do
            before = {s: writes(sim) for s, sim in sims.items()}
            code, out = playbook(tmp_path, inventory)
            assert code == 0, out
            assert (recap(out, "site-a") or {})["changed"] == 0 and (recap(out, "site-b") or {})["changed"] == 0
            assert {s: writes(sim) for s, sim in sims.items()} == before

            # the files change on both sites; site-a's device rejects the value: site-a fails, site-b is untouched
            for site in sims:
                (tmp_path / site / "r.yaml").write_text(RECIPE.replace("speed: 3000 rpm", "speed: 2500 rpm"))
            sa.faults.fail_registers = frozenset({12})
            before_b = writes(sb)
            code, out = playbook(tmp_path, inventory)
            assert code != 0
            assert (recap(out, "site-a") or {})["failed"] == 1, out
            assert "site-a-d1 partial: speed failed (exception 04" in out or "site-a-d1 failed" in out, out
            assert recap(out, "site-b") is None or (recap(out, "site-b") or {})["ok"] == 0, out
            assert writes(sb) == before_b and sb.read("speed") == (3000,)
            for a in agents.values():
                assert a.terminate() == 0
        finally:
            for a in agents.values():
                a.kill()
