"""Users and roles in the agent (issue 48, item 1), against a real agent process and a simulator: every route
refused to every role that lacks it, with the role named, counted and audited; an operator cannot approve, a
viewer cannot apply; who asked is in the run, its events and the journal, from the credential alone; a user
disabled (file or API) is refused at once, without a restart; tokens kept as hashes; client certificates mapped
to users; the users file checked like every input file."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from deployer.agent import roles, server
from deployer.agent import users as people
from deployer.agent.client import Agent
from deployer.errors import AgentError
from deployer.profile import load_profile
from deployer.state import journal
from deployer.testing.simulator import Simulator, SimulatorThread
from tests.agent_helpers import PROFILE, RECIPE, AgentProcess, event, until, write_site, writes_in_log
from tests.test_agent_security import TOKEN, error_of, raw, token_file

pytestmark = pytest.mark.timeout(180)
PEOPLE = {
    "boss": ["admin"],
    "eng": ["engineer"],
    "op": ["operator"],
    "appr": ["approver"],
    "view": ["viewer"],
    "lead": ["engineer", "operator"],
}


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[Simulator]:
    (tmp_path / "drive.yaml").write_text(PROFILE)
    with SimulatorThread(load_profile(str(tmp_path / "drive.yaml"))) as s:
        yield s


def make_users(path: Path, who: dict[str, list[str]] = PEOPLE) -> dict[str, str]:
    """The users file with these users (names -> roles); their tokens."""
    tokens: dict[str, str] = {}

    def change(doc: dict[str, Any]) -> None:
        for name, rs in who.items():
            tokens[name], entry = people.new_token()
            doc["users"][name] = {"roles": rs, "token": entry}

    people.edit(str(path), change, create=True)
    return tokens


def cli(*args: str, **env: str) -> subprocess.CompletedProcess[str]:
    e = {k: v for k, v in os.environ.items() if not k.startswith("DEPLOYER_AGENT")}
    return subprocess.run(
        [sys.executable, "-m", "deployer", *args], capture_output=True, text=True, timeout=90, env={**e, **env}
    )


def metric(c: Agent, name: str, label: str = "") -> float:
    for line in c.metrics().splitlines():
        if line.startswith(name + (f"{{{label}}}" if label else "")) and not line.startswith("#"):
            return float(line.split()[-1])
    return 0.0


def test_every_route_checks_its_role_and_each_refusal_names_it(tmp_path: Path, sim: Simulator) -> None:
    inv = write_site(tmp_path, {"d1": sim.url})
    users = tmp_path / "users.yaml"
    tokens = make_users(users)
    agent = AgentProcess(inv, tmp_path / "state", "--users", str(users))
    try:
        url = agent.url
        c = {n: Agent(url, token=t, timeout=20) for n, t in tokens.items()}
        assert "users-loaded" in [e["kind"] for e in c["view"].events()]
        for name, rs in PEOPLE.items():
            me = c[name].whoami()
            assert me == {"user": name, "credential": "user token", "roles": sorted(rs), "mode": "users"}, me
        refused: dict[str, int] = {}
        for method, path, _ in server.ROUTES:  # every route, every user who lacks its role: a 403 naming the role
            need = roles.ROUTE_ROLES[(method, path)]
            concrete = path.replace("{name}", "d1").replace("{id}", "nope")
            for name, rs in PEOPLE.items():
                if roles.holds(rs, need):
                    continue
                status, _, body = raw(
                    url + concrete,
                    method,
                    b"{}" if method == "POST" else None,
                    {"Authorization": f"Bearer {tokens[name]}", "Content-Type": "application/json"},
                )
                err = error_of(body)
                assert status == 403 and err["kind"] == "forbidden", (method, path, name, body)
                assert f"{name} may not {method} {concrete}: that needs the role {need}" in err["message"]
                refused[need] = refused.get(need, 0) + 1
        # only an admin sees the users (and stops the agent); every role reads
        assert set(refused) == {"engineer", "operator", "approver", "admin"} and refused["admin"] == 4 * 5
        for need, n in refused.items():
            assert metric(c["boss"], "deployer_http_forbidden_requests_total", f'role="{need}"') == n
        # the one route of change control, approvals: not an operator's (the route answers to approvers only)
        with pytest.raises(AgentError) as e:
            c["op"].post("/v1/approvals", {"plan": {}})
        assert e.value.kind == "forbidden" and "needs the role approver" in str(e.value)
        with pytest.raises(AgentError) as e:  # an approver gets past the role to the route itself
            c["appr"].post("/v1/approvals", {"plan": {}})
        assert e.value.kind != "forbidden"
        # a viewer cannot apply; an operator can; nothing was written before
        with pytest.raises(AgentError) as e:
            c["view"].start_run(confirm_within="10m")
        assert e.value.kind == "forbidden" and "needs the role operator" in str(e.value) and e.value.exit_code == 1
        assert c["view"].runs() == [] and writes_in_log(sim.log) == {}
        audit = [x for x in c["boss"].events() if x["kind"] == "access-refused"]
        view_apply = [
            x
            for x in audit
            if x["detail"]["user"] == "view" and x["detail"]["path"] == "/v1/runs" and x["detail"]["method"] == "POST"
        ]
        assert view_apply and view_apply[0]["detail"]["needed"] == "operator"
        assert view_apply[0]["detail"]["roles"] == ["viewer"] and view_apply[0]["detail"]["remote"] == "127.0.0.1"
        assert "refused POST /v1/runs to view (viewer): it needs the role operator" in agent.log()

        run = c["op"].start_run(confirm_within="10m")
        assert run["options"]["by"] == {"user": "op", "credential": "user token"}
        until(lambda: c["op"].windows(), why="the operator's run waits for its confirmation")
        with pytest.raises(AgentError) as e:  # an engineer cannot confirm it
            c["eng"].confirm(run["id"])
        assert e.value.kind == "forbidden" and "needs the role operator" in str(e.value)
        c["lead"].confirm(run["id"])
        end = c["op"].follow(run["id"])
        assert end["exit_code"] == 0 and sim.read("accel") == (20,)
        finished = event(c["view"], "run-finished")
        confirmed = event(c["view"], "window-confirmed")
        assert finished is not None and finished["detail"]["by"]["user"] == "op"
        assert confirmed is not None and confirmed["detail"]["by"]["user"] == "lead"
        assert "confirmed by lead" in confirmed["message"]
        assert end["report"]["run"]["command"] == "agent apply by op"  # the report says who, from the credential
        assert end["report"]["run"]["user"] == "op"  # and the journal: the person, not the agent's own account
        started = [
            json.loads(line)
            for line in Path(journal.path_of(str(tmp_path / "state"))).read_text(encoding="utf-8").splitlines()
            if '"run-started"' in line
        ]
        assert [(x["user"], x["via"]) for x in started if x["run"] == run["id"]] == [("op", "agent")], started
        # a rollback through the agent: by whom, too
        back = c["lead"].rollback(run["id"])
        assert c["lead"].follow(back["id"])["exit_code"] == 0 and back["options"]["by"]["user"] == "lead"
        assert agent.terminate(client=Agent(agent.url, token=tokens["boss"], timeout=20)) == 0
    finally:
        agent.kill()
    assert "Traceback" not in agent.log()


def test_an_operator_rolls_out_the_files_as_an_engineer_took_them_up(tmp_path: Path, sim: Simulator) -> None:
    inv = write_site(tmp_path, {"d1": sim.url})
    users = tmp_path / "users.yaml"
    tokens = make_users(users)
    agent = AgentProcess(inv, tmp_path / "state", "--users", str(users))
    try:
        op, eng = Agent(agent.url, token=tokens["op"]), Agent(agent.url, token=tokens["eng"])
        (tmp_path / "r.yaml").write_text(RECIPE.replace("speed: 3000 rpm", "speed: 2500 rpm"))  # not taken up
        with pytest.raises(AgentError) as e:
            op.reload()
        assert e.value.kind == "forbidden" and "needs the role engineer" in str(e.value)
        # the command line shows the operator what was taken up, and says why
        plan = cli("plan", "--agent", agent.url, DEPLOYER_AGENT_TOKEN=tokens["op"])
        assert plan.returncode == 0 and "taking up an edit needs the role engineer" in plan.stderr, plan.stderr
        assert op.follow(op.start_run()["id"])["exit_code"] == 0
        assert sim.read("speed") == (3000,)  # what was taken up, not the edit on disk
        assert "2500 rpm" in json.dumps(eng.reload())  # the engineer takes it up: pending now
        assert op.follow(op.start_run()["id"])["exit_code"] == 0
        assert sim.read("speed") == (2500,)
        assert agent.terminate(client=Agent(agent.url, token=tokens["boss"], timeout=20)) == 0
    finally:
        agent.kill()


def test_a_disabled_user_is_refused_at_once_without_a_restart(tmp_path: Path, sim: Simulator) -> None:
    inv = write_site(tmp_path, {"d1": sim.url})
    users = tmp_path / "users.yaml"
    made = cli("users", "add", "boss", "--role", "admin", "--name", "Big Boss", "--users", str(users))
    assert made.returncode == 0 and "shown this once" in made.stderr, made.stderr
    boss_token = made.stdout.strip()
    assert people.token_id(boss_token) and boss_token not in users.read_text()  # only its hash is kept
    assert people.check_token(boss_token, people.load(str(users))["boss"].token_hash or "")
    tokens = {"boss": boss_token}
    for name, role in (("op", "operator"), ("view", "viewer")):
        p = cli("users", "add", name, "--role", role, "--users", str(users))
        assert p.returncode == 0, p.stderr
        tokens[name] = p.stdout.strip()
    agent = AgentProcess(inv, tmp_path / "state", "--users", str(users))
    try:
        pid = agent.proc.pid
        op, boss = Agent(agent.url, token=tokens["op"]), Agent(agent.url, token=tokens["boss"])
        assert op.whoami()["user"] == "op"
        me = cli("users", "whoami", "--agent", agent.url, DEPLOYER_AGENT_TOKEN=tokens["boss"])
        assert me.returncode == 0 and me.stdout == "boss: admin (user token; the agent has users)\n", me.stderr
        # disabled by an edit of the file: refused at the very next request
        p = cli("users", "disable", "op", "--users", str(users))
        assert p.returncode == 0, p.stderr
        with pytest.raises(AgentError) as e:
            op.devices()
        assert e.value.kind == "unauthorized" and "op is disabled" in str(e.value)
        added = event(boss, "user-disabled")
        assert added is not None and added["detail"] == {"user": "op", "via": "file"}
        refused = event(boss, "login-refused")
        assert refused is not None and refused["detail"]["why"] == "op is disabled"
        p = cli("users", "enable", "op", "--users", str(users))
        assert p.returncode == 0 and op.whoami()["user"] == "op"
        # through the agent, by an admin: audited with the admin's name
        p = cli("users", "disable", "view", "--agent", agent.url, DEPLOYER_AGENT_TOKEN=tokens["boss"])
        assert p.returncode == 0, p.stderr
        with pytest.raises(AgentError) as e:
            Agent(agent.url, token=tokens["view"]).devices()
        assert "view is disabled" in str(e.value)
        by_api = [x for x in boss.events() if x["kind"] == "user-disabled" and x["detail"]["user"] == "view"]
        assert by_api and by_api[0]["detail"] == {"user": "view", "by": "boss", "via": "api"}
        assert people.load(str(users))["view"].disabled  # in the file, for the next start too
        # an operator cannot manage users; the last admin cannot be disabled
        p = cli("users", "disable", "boss", "--agent", agent.url, DEPLOYER_AGENT_TOKEN=tokens["op"])
        assert p.returncode == 1 and "needs the role admin" in p.stderr
        with pytest.raises(AgentError) as e:
            boss.change_user("boss", disabled=True)
        assert e.value.kind == "refused" and "no enabled admin would be left" in str(e.value)
        # a new token: the old one is refused at once, the new one works
        p = cli("users", "token", "op", "--agent", agent.url, DEPLOYER_AGENT_TOKEN=tokens["boss"])
        assert p.returncode == 0 and p.stdout.strip().startswith("dpl_"), p.stderr
        with pytest.raises(AgentError) as e:
            op.devices()
        assert "a token that is no user's" in str(e.value)  # the new token has an id of its own
        assert Agent(agent.url, token=p.stdout.strip()).whoami()["user"] == "op"
        # a user added through the agent, with their roles changed
        out = boss.add_user("carol", ["approver"], name="Carol Weiss")
        carol = Agent(agent.url, token=out["token"])
        assert carol.whoami() == {
            "user": "carol",
            "name": "Carol Weiss",
            "credential": "user token",
            "roles": ["approver"],
            "mode": "users",
        }
        boss.change_user("carol", roles=["viewer"])
        assert carol.whoami()["roles"] == ["viewer"]
        listed = cli("users", "list", "--agent", agent.url, DEPLOYER_AGENT_TOKEN=tokens["boss"])
        assert "carol (Carol Weiss): viewer; token" in listed.stdout
        assert "view: viewer; token; DISABLED" in listed.stdout
        assert "scrypt" not in listed.stdout and "dpl_" not in listed.stdout
        # a users file edited into something invalid: nobody is let in (the agent cannot tell anyone apart)
        good = users.read_text()
        users.write_text(good.replace("roles: [admin]", "roles: [overlord]"))
        with pytest.raises(AgentError) as e:
            boss.devices()
        assert e.value.kind == "unauthorized" and "users file is invalid" in str(e.value)
        assert "agent: users-invalid:" in agent.log() and "'overlord' is not one of" in agent.log()
        users.write_text(good)
        assert boss.whoami()["user"] == "boss"
        kinds = [x["kind"] for x in boss.events()]
        for kind in (
            "users-loaded",
            "user-disabled",
            "user-enabled",
            "user-token-replaced",
            "user-added",
            "user-roles-changed",
            "users-invalid",
            "login-refused",
            "access-refused",
        ):
            assert kind in kinds, kind
        assert agent.proc.pid == pid and agent.proc.poll() is None  # never restarted
        assert agent.terminate(client=Agent(agent.url, token=tokens["boss"], timeout=20)) == 0
    finally:
        agent.kill()
    assert "Traceback" not in agent.log()


def test_client_certificates_map_to_users(tmp_path: Path, sim: Simulator, pki: dict[str, str]) -> None:
    from tests.certs import issue, make_ca

    inv = write_site(tmp_path, {"d1": sim.url})
    users = tmp_path / "users.yaml"
    tokens = make_users(users, {"boss": ["admin"]})
    ca, key, cert = make_ca(tmp_path, "site-ca")  # the site's CA (pki's "client" certificate is another CA's)
    alice_crt, alice_key = issue(tmp_path, "alice.martin", key, cert, server=False)
    stranger_crt, stranger_key = issue(tmp_path, "stranger", key, cert, server=False)
    server_crt, server_key = issue(tmp_path, "gateway", key, cert, server=True)
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "deployer",
            "users",
            "add",
            "alice",
            "--role",
            "operator",
            "--cert-cn",
            "alice.martin",
            "--no-token",
            "--users",
            str(users),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0 and out.stdout == "", out.stderr  # no token: nothing printed
    agent = AgentProcess(
        inv,
        tmp_path / "state",
        "--users",
        str(users),
        "--tls-cert",
        server_crt,
        "--tls-key",
        server_key,
        "--tls-client-ca",
        ca,
    )
    try:
        url = "https://127.0.0.1:" + agent.url.rsplit(":", 1)[1]
        alice = Agent(url, ca=ca, cert=alice_crt, key=alice_key)
        assert alice.whoami() == {"user": "alice", "credential": "certificate", "roles": ["operator"], "mode": "users"}
        with pytest.raises(AgentError) as e:
            Agent(url, ca=ca, cert=stranger_crt, key=stranger_key).devices()
        assert e.value.kind == "unauthorized" and "(CN=stranger) that is no user's" in str(e.value)
        with pytest.raises(AgentError) as e:  # a certificate another CA signed: the handshake itself fails
            Agent(url, ca=ca, cert=pki["client_crt"], key=pki["client_key"]).devices()
        assert e.value.kind == "unreachable"
        with pytest.raises(AgentError) as e:  # no certificate and no token
            Agent(url, ca=ca).devices()
        assert e.value.kind == "unauthorized"
        assert Agent(url, ca=ca, token=tokens["boss"]).whoami()["user"] == "boss"  # a token without a certificate
        with pytest.raises(AgentError) as e:  # one request, one user
            Agent(url, ca=ca, cert=alice_crt, key=alice_key, token=tokens["boss"]).devices()
        assert "the client certificate is alice's and the token boss's" in str(e.value)
        st = cli("status", "--agent", url, "--agent-ca", ca, "--agent-cert", alice_crt, "--agent-key", alice_key)
        assert st.returncode in (0, 2) and "d1" in st.stdout, st.stderr
        Agent(url, ca=ca, token=tokens["boss"]).change_user("alice", disabled=True)
        with pytest.raises(AgentError) as e:
            alice.devices()
        assert "alice is disabled" in str(e.value)
        assert agent.terminate(client=Agent(agent.url, token=tokens["boss"], ca=ca, timeout=20)) == 0
    finally:
        agent.kill()


def test_the_users_file_is_checked_like_every_input_file(tmp_path: Path, sim: Simulator) -> None:
    bad = tmp_path / "users.yaml"
    _, entry = people.new_token()
    bad.write_text(
        "users:\n"
        "  Alice:\n"
        "    roles: [boss]\n"
        f"  bob:\n    roles: [viewer]\n    token: {{id: '{entry['id']}', scrypt: '{entry['scrypt']}'}}\n"
        f"  carl:\n    roles: [viewer]\n    token: {{id: '{entry['id']}', scrypt: '{entry['scrypt']}'}}\n"
        "  dora:\n    roles: []\n    disabled: maybe\n    password: hunter2\n"
        "  eve:\n    roles: [viewer]\n    token: {id: '0123456789',\n"
        f"             scrypt: '$scrypt$ln=30,r=8,p=1${'A' * 22}${'A' * 43}'}}\n"
    )
    p = cli("validate", str(bad))
    assert p.returncode == 1
    lines = [x for x in p.stderr.splitlines() if ": error: " in x]
    want = [
        (2, 3, "'Alice' does not match"),
        (3, 13, "'boss' is not one of"),
        (11, 12, "should be non-empty"),
        (12, 15, "expected true or false, got 'maybe'"),
        (13, 5, "unknown key 'password'"),
    ]
    for line, col, said in want:
        assert any(x.startswith(f"{bad}:{line}:{col}: error: ") and said in x for x in lines), (line, col, lines)
    # semantic problems once the shapes are right: a token id twice, a hash too costly to check
    bad.write_text(re.sub(r"  (Alice|dora):\n(    .*\n)+", "", bad.read_text()))
    p = cli("validate", str(bad))
    assert p.returncode == 1, p.stdout
    assert re.search(rf"{re.escape(str(bad))}:\d+:\d+: error: token id '{entry['id']}' is bob's already", p.stderr)
    assert "scrypt figures beyond ln=20" in p.stderr
    # the agent refuses to start on it, every problem said, nothing started
    inv = write_site(tmp_path, {"d1": sim.url})
    a = cli("agent", str(inv), "--state-dir", str(tmp_path / "state"), "--users", str(bad), "--listen", "127.0.0.1:0")
    assert a.returncode == 1 and "is bob's already" in a.stderr and "listening" not in a.stderr
    assert "Traceback" not in a.stderr
    good = tmp_path / "good.yaml"
    make_users(good, {"boss": ["admin"]})
    assert cli("validate", str(good)).stdout.endswith("ok (users: 1 user, 1 enabled)\n")
    for args, said in (
        (["--users", str(good), "--token-file", str(token_file(tmp_path))], "one or the other"),
        (["--tls-client-ca", str(good)], "--tls-client-ca maps certificates to users"),
        (["--users", str(tmp_path / "none.yaml")], "none.yaml"),
    ):
        a = cli("agent", str(inv), "--state-dir", str(tmp_path / "state"), "--listen", "127.0.0.1:0", *args)
        assert a.returncode == 1 and said in a.stderr and "Traceback" not in a.stderr, (args, a.stderr)


def test_one_token_for_the_site_holds_every_role_and_names_nobody(tmp_path: Path, sim: Simulator) -> None:
    inv = write_site(tmp_path, {"d1": sim.url})
    agent = AgentProcess(inv, tmp_path / "state", "--token-file", str(token_file(tmp_path)))
    try:
        c = Agent(agent.url, token=TOKEN)
        assert c.whoami() == {"user": None, "credential": "token", "roles": list(sorted(roles.ROLES)), "mode": "token"}
        assert c.info()["auth"] == "token" and c.info()["you"]["user"] is None
        run = c.start_run()
        assert run["options"]["by"] == {"user": None, "credential": "token"}
        assert c.follow(run["id"])["exit_code"] == 0
        with pytest.raises(AgentError) as e:
            c.users()
        assert e.value.kind == "conflict" and "--users FILE" in str(e.value)
        assert c.run(run["id"])["report"]["run"]["command"] == "agent apply by the token"
        assert agent.terminate() == 0
    finally:
        agent.kill()


def test_the_role_table_the_openapi_document_and_the_server_agree() -> None:
    doc = json.loads(Path(server.__file__).with_name("openapi.json").read_text())
    for path, ops in doc["paths"].items():
        for method, op in ops.items():
            assert op["x-role"] == roles.ROUTE_ROLES[(method.upper(), path)], (method, path)
    served = {(m, p) for m, p, _ in server.ROUTES}
    assert served == set(roles.ROUTE_ROLES)
    assert set(roles.ROUTE_ROLES.values()) == set(roles.ROLES)
    assert roles.role_of("POST", "/v1/runs/abc/confirm") == "operator" and roles.role_of("GET", "/v1/nope") is None
    assert roles.holds(["approver"], "viewer") and not roles.holds(["admin"], "operator")
    assert not roles.holds([], "viewer")
    page = (Path(server.__file__).parents[2] / "docs" / "agent.md").read_text()
    for method, path in served:  # the route -> role table of the docs is this one
        assert f"| `{method} {path}` | {roles.ROUTE_ROLES[(method, path)]} |" in page, (method, path)
    for role in roles.ROLES:
        assert f"| {role} | {roles.ABOUT[role]} |" in page, role


def test_a_viewer_reads_the_live_page_with_their_own_token(tmp_path: Path, sim: Simulator) -> None:
    from tests.test_pages import CHROMIUM, Elements, browser

    if CHROMIUM is None:
        pytest.skip("no Chromium (CI installs it: apt-get install chromium)")
    inv = write_site(tmp_path, {"d1": sim.url})
    users = tmp_path / "users.yaml"
    tokens = make_users(users, {"boss": ["admin"], "view": ["viewer"]})
    agent = AgentProcess(inv, tmp_path / "state", "--users", str(users))
    try:
        proc = browser("--dump-dom", f"{agent.url}/#token={tokens['view']}", tmp=tmp_path)
        assert proc.returncode == 0 and 'data-ready="' in proc.stdout, proc.stderr
        doc = Elements(proc.stdout)
        assert [r["data-device"] for r in doc.all("tr", "dev")] == ["d1"]
        where = next(e for e in doc.found if e.get("id") == "where")
        assert "auth users" in str(where["text"]) and "you: view" in str(where["text"])
        assert agent.terminate(client=Agent(agent.url, token=tokens["boss"], timeout=20)) == 0
    finally:
        agent.kill()


def test_a_route_without_a_role_keeps_the_agent_from_starting(monkeypatch: pytest.MonkeyPatch) -> None:
    """A route added without its role in roles.ROUTE_ROLES is a mistake said before anything starts, not a
    route anyone (or no one) may use by default."""
    monkeypatch.setattr(server, "ROUTES", (*server.ROUTES, ("POST", "/v1/erase", server.get_status)))
    with pytest.raises(ValueError, match=r"routes without a role in roles.ROUTE_ROLES: \[\('POST', '/v1/erase'\)\]"):
        server.app(None, token="x" * 20)  # type: ignore[arg-type]
