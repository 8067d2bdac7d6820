"""Who may drive the agent: the token (refused, accepted, on every write), loopback only without one, TLS,
and bad or oversized requests answered as JSON, never a traceback. A real agent process, a simulator."""

from __future__ import annotations

import http.client
import inspect
import json
import os
import socket
import ssl
import subprocess
import sys
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from deployer.agent import server
from deployer.agent.client import Agent
from deployer.errors import AgentError
from deployer.profile import load_profile
from deployer.testing.simulator import Simulator, SimulatorThread
from tests.agent_helpers import PROFILE, AgentProcess, until, write_site

pytestmark = pytest.mark.timeout(90)
TOKEN = "s3cret-token-of-the-site-0123456789"


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[Simulator]:
    (tmp_path / "drive.yaml").write_text(PROFILE)
    with SimulatorThread(load_profile(str(tmp_path / "drive.yaml"))) as s:
        yield s


def raw(
    url: str,
    method: str = "GET",
    body: bytes | None = None,
    headers: dict[str, str] | None = None,
    context: ssl.SSLContext | None = None,
) -> tuple[int, dict[str, str], bytes]:
    req = urllib.request.Request(url, data=body, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=20, context=context) as resp:
            return resp.status, dict(resp.headers), resp.read()
    except urllib.error.HTTPError as e:
        return e.code, dict(e.headers), e.read()


def error_of(body: bytes) -> dict[str, Any]:
    err = json.loads(body)["error"]
    assert isinstance(err, dict) and {"kind", "message", "exit_code"} <= set(err)
    return err


def token_file(tmp: Path, text: str = TOKEN) -> Path:
    p = tmp / "token"
    p.write_text(text + "\n")
    p.chmod(0o600)
    return p


def test_the_token_is_needed_on_every_route_and_accepted(tmp_path: Path, sim: Simulator) -> None:
    inv = write_site(tmp_path, {"d1": sim.url})
    agent = AgentProcess(inv, tmp_path / "state", "--token-file", str(token_file(tmp_path)))
    try:
        url = agent.url
        for headers in (
            {},
            {"Authorization": "Bearer wrong-token-wrong-token"},
            {"Authorization": f"Basic {TOKEN}"},
            {"Authorization": f"Bearer {TOKEN}x"},
            {"Authorization": "Bearer"},
        ):
            status, hdrs, body = raw(url + "/v1/devices", headers=headers)
            assert status == 401 and hdrs["WWW-Authenticate"].startswith("Bearer")
            assert error_of(body)["kind"] == "unauthorized"
        # the watch's first check has said its drift (on a slow start it could come in the middle of the count)
        before = len(
            until(
                lambda: (
                    [e for e in Agent(url, token=TOKEN).events() if e["kind"] == "drift"]
                    and Agent(url, token=TOKEN).events()
                ),
                why="the first check's drift event",
            )
        )
        for method, path, _ in server.ROUTES:  # no route answers without the token, no write happens
            concrete = path.replace("{name}", "d1").replace("{id}", "nope")
            sent = b'{"command": "apply"}' if method == "POST" else None
            status, _, answer = raw(url + concrete, method, sent, {"Content-Type": "application/json"})
            assert status == 401, (method, path, answer)
            assert error_of(answer)["kind"] == "unauthorized"
        status, _, _ = raw(url + "/v1/no-such-route")
        assert status == 401  # not even which paths exist
        c = Agent(url, token=TOKEN)
        assert c.info()["auth"] == "token" and c.runs() == []
        assert len(c.events()) == before and "deployer_device_drifted" in c.metrics()
        refused = [line for line in c.metrics().splitlines() if line.startswith("deployer_http_unauthorized_requests")]
        assert refused and float(refused[0].split()[-1]) >= len(server.ROUTES) + 6
        # audited once a minute per address (the first at once), the rest counted into the next record
        assert agent.log().count("agent: login-refused: refused ") == 1
        first = [e for e in c.events() if e["kind"] == "login-refused"]
        assert len(first) == 1 and first[0]["detail"]["remote"] == "127.0.0.1"
        assert first[0]["detail"]["why"] == "no credential" and first[0]["detail"]["path"] == "/v1/devices"
        with pytest.raises(AgentError) as e:
            Agent(url).devices()
        assert e.value.kind == "unauthorized" and e.value.exit_code == 1
        # the command line: the token from its file or from the environment
        env = {k: v for k, v in os.environ.items() if k != "DEPLOYER_AGENT_TOKEN"}
        cmd = [sys.executable, "-m", "deployer", "status", "--agent", url]
        no = subprocess.run(cmd, capture_output=True, text=True, timeout=60, env=env)
        assert no.returncode == 1 and "needs its token" in no.stderr and "Traceback" not in no.stderr
        by_file = subprocess.run(
            [*cmd, "--agent-token-file", str(tmp_path / "token")], capture_output=True, text=True, timeout=60, env=env
        )
        assert by_file.returncode in (0, 2), by_file.stderr
        by_env = subprocess.run(
            cmd, capture_output=True, text=True, timeout=60, env={**env, "DEPLOYER_AGENT_TOKEN": TOKEN}
        )
        assert by_env.returncode == by_file.returncode and by_env.stdout == by_file.stdout
        assert agent.terminate() == 0
    finally:
        agent.kill()
    assert "Traceback" not in agent.log()
    # at the stop, the refusals counted since the first record are recorded with their number
    import re

    held = re.findall(r"agent: login-refused: .*\((\d+) more like it after the last record\)", agent.log())
    assert held and int(held[0]) >= len(server.ROUTES) + 5, agent.log()


def test_the_token_is_compared_in_constant_time() -> None:
    import re

    from deployer.agent import access, users

    for fn, secrets in ((access.Access.identify, ("given", "self._token")), (users.check_token, ("got", "want"))):
        source = inspect.getsource(fn)
        assert "hmac.compare_digest" in source, fn
        for name in secrets:  # never compared as values: a time that depends on the first byte that differs
            assert not re.search(rf"{re.escape(name)}(\.\w+\(\))?\s*[!=]=|[!=]=\s*{re.escape(name)}\b", source)


def test_beyond_loopback_only_with_a_token_and_tls(tmp_path: Path, sim: Simulator, pki: dict[str, str]) -> None:
    inv = write_site(tmp_path, {"d1": sim.url})
    tok = str(token_file(tmp_path))
    short = tmp_path / "short"
    short.write_text("abc\n")
    tls = ["--tls-cert", pki["server_crt"], "--tls-key", pki["server_key"]]
    refused = {
        "loopback only": ["--listen", "0.0.0.0:0"],
        "needs TLS as well": ["--listen", "0.0.0.0:0", "--token-file", tok],
        "loopback only (127.0.0.1": ["--listen", "0.0.0.0:0", *tls],
        "--tls-cert and --tls-key go together": ["--token-file", tok, "--tls-cert", pki["server_crt"]],
        "at least 16 characters": ["--token-file", str(short)],
        "cannot load them": ["--token-file", tok, "--tls-cert", pki["ca"], "--tls-key", pki["server_key"]],
    }
    for why, args in refused.items():
        p = subprocess.run(
            [sys.executable, "-m", "deployer", "agent", str(inv), "--state-dir", str(tmp_path / "state"), *args],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert p.returncode == 1 and why in p.stderr and "Traceback" not in p.stderr, (why, p.stderr)
    agent = AgentProcess(inv, tmp_path / "state", "--listen", "0.0.0.0:0", "--token-file", tok, *tls)
    try:
        assert agent.url.startswith("https://")
        port = int(agent.url.rsplit(":", 1)[1])
        url = f"https://127.0.0.1:{port}"  # the certificate names 127.0.0.1
        c = Agent(url, token=TOKEN, ca=pki["ca"])
        assert c.info()["auth"] == "token" and [d["name"] for d in c.devices()] == ["d1"]
        with pytest.raises(AgentError) as e:  # a certificate the client's CA did not sign
            Agent(url, token=TOKEN, ca=pki["other_ca"]).devices()
        assert e.value.kind == "unreachable" and "CERTIFICATE_VERIFY_FAILED" in str(e.value)
        with pytest.raises(AgentError) as e:  # TLS without the token
            Agent(url, ca=pki["ca"]).devices()
        assert e.value.kind == "unauthorized"
        cli = [sys.executable, "-m", "deployer", "status", "--agent", url, "--agent-token-file", tok]
        trusted = subprocess.run([*cli, "--agent-ca", pki["ca"]], capture_output=True, text=True, timeout=60)
        assert trusted.returncode in (0, 2) and "d1" in trusted.stdout, trusted.stderr
        untrusted = subprocess.run([*cli, "--agent-ca", pki["other_ca"]], capture_output=True, text=True, timeout=60)
        assert untrusted.returncode == 3 and "CERTIFICATE_VERIFY_FAILED" in untrusted.stderr, untrusted.stderr
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)  # plain HTTP to the TLS port: no answer
        with pytest.raises((http.client.HTTPException, OSError)):
            conn.request("GET", "/v1/agent", headers={"Authorization": f"Bearer {TOKEN}"})
            conn.getresponse().read()
        conn.close()
        assert agent.terminate(client=c) == 0
    finally:
        agent.kill()


def test_bad_and_oversized_requests_get_json_errors(tmp_path: Path, sim: Simulator) -> None:
    inv = write_site(tmp_path, {"d1": sim.url})
    agent = AgentProcess(inv, tmp_path / "state")
    try:
        url = agent.url
        json_h = {"Content-Type": "application/json", "Authorization": f"Bearer {agent.client.token}"}
        cases: list[tuple[str, str, bytes | None, int, str]] = [
            ("POST", "/v1/runs", b"{not json", 400, "usage"),
            ("POST", "/v1/runs", b"[1, 2]", 400, "usage"),
            ("POST", "/v1/runs", b'{"command": 7}', 400, "usage"),
            ("POST", "/v1/runs", b"\xff\xfe\x00", 400, "usage"),
            ("POST", "/v1/runs", b'{"a": "' + b"x" * (2 << 20) + b'"}', 413, "usage"),
            ("POST", "/v1/check", b'{"limit": "nothing-like-this"}', 400, "usage"),
            ("GET", "/v1/events?limit=many", None, 400, "usage"),
            ("GET", "/v1/events?after=-5", None, 400, "usage"),
            ("GET", "/v1/devices/%ff%00", None, 404, "not-found"),
            ("DELETE", "/v1/devices", None, 405, "usage"),
        ]
        for method, path, body, status, kind in cases:
            got, hdrs, answer = raw(url + path, method, body, json_h)
            assert got == status and hdrs["Content-Type"].startswith("application/json"), (path, got, answer)
            assert error_of(answer)["kind"] == kind, (path, answer)
        # not HTTP at all: a short answer, never a traceback; the agent keeps serving
        host, port = url.removeprefix("http://").rsplit(":", 1)
        with socket.create_connection((host, int(port)), timeout=10) as s:
            s.sendall(b"\x16\x03\x01 garbage \r\n\r\n")
            answer_b = s.recv(65536)
        assert b"Traceback" not in answer_b
        with socket.create_connection((host, int(port)), timeout=10) as s:
            s.sendall(b"GET /v1/agent HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Big: " + b"a" * 70000 + b"\r\n\r\n")
            answer_b = s.recv(65536)
        assert answer_b.startswith(b"HTTP/1.") and b" 4" in answer_b[:13] and b"application/json" in answer_b
        assert agent.client.info()["api"] == 1
        assert agent.terminate() == 0
    finally:
        agent.kill()
    assert "Traceback" not in agent.log()


def test_the_operations_page_shows_the_unit_as_shipped() -> None:
    root = Path(__file__).resolve().parent.parent
    unit = (root / "docs/examples/deployer-agent.service").read_text()
    page = (root / "docs/operations.md").read_text()
    assert f"```ini\n{unit}```" in page
    for option in ("--token-file", "--tls-cert", "--tls-key", "--state-dir", "--listen", "--notify"):
        assert option in unit
    assert "DEPLOYER_LOCK_DIR" in unit and "ExecReload=/bin/kill -HUP $MAINPID" in unit


def test_the_served_openapi_document_states_the_security_and_the_errors(tmp_path: Path, sim: Simulator) -> None:
    """The document the agent serves is the one in the package, versioned, with the bearer scheme on every
    operation, a 401 answer on every operation, and every error kind the server can answer."""
    import re

    doc_path = Path(server.__file__).with_name("openapi.json")
    doc = json.loads(doc_path.read_text())
    assert doc["openapi"].startswith("3.") and doc["info"]["version"] == "1"
    assert doc["components"]["securitySchemes"]["bearer"] == {
        **doc["components"]["securitySchemes"]["bearer"],
        "type": "http",
        "scheme": "bearer",
    }
    # a credential in every mode (the agent makes a token when given none): a token, or a user's client certificate
    assert doc["security"] == [{"bearer": []}, {"clientCertificate": []}]
    assert doc["components"]["securitySchemes"]["clientCertificate"]["type"] == "mutualTLS"
    kinds = set(doc["components"]["schemas"]["Error"]["properties"]["error"]["properties"]["kind"]["enum"])
    sources = "".join(p.read_text() for p in Path(server.__file__).parent.glob("*.py"))
    raised = {
        k
        for pattern in (r'ApiError\("([a-z-]+)"', r'error_body\("([a-z-]+)"', r'"error": \{"kind": "([a-z-]+)"')
        for k in re.findall(pattern, sources)
    }
    assert raised and raised <= kinds, raised - kinds
    for path, ops in doc["paths"].items():
        for method, op in ops.items():
            assert op["responses"]["401"] == {"$ref": "#/components/responses/Unauthorized"}, (method, path)
            assert op["responses"]["403"] == {"$ref": "#/components/responses/Forbidden"}, (method, path)
            if method != "get":  # a body only as application/json
                assert op["responses"]["415"] == {"$ref": "#/components/responses/UnsupportedMediaType"}
                schema = op.get("requestBody", {}).get("content", {}).get("application/json", {}).get("schema")
                if schema is not None:  # the one the agent checks bodies against: no key it does not know
                    name = schema["$ref"].rsplit("/", 1)[1]
                    assert doc["components"]["schemas"][name]["additionalProperties"] is False, name
            assert op.get("operationId"), (method, path)
    inv = write_site(tmp_path, {"d1": sim.url})
    agent = AgentProcess(inv, tmp_path / "state", "--token-file", str(token_file(tmp_path)))
    try:
        c = Agent(agent.url, token=TOKEN)
        assert c.get("/v1/openapi.json") == doc and c.info()["api"] == int(doc["info"]["version"])
        status, _, _ = raw(agent.url + "/v1/openapi.json")
        assert status == 401
        assert agent.terminate() == 0
    finally:
        agent.kill()
