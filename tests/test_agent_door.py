"""No write through an open door (issue 48, item 0), against a real agent process and a simulator: a cross-origin
POST (curl, as an attacker sends it; with and without the token), a hostile page in headless Chromium, a rebound
name; the token an agent makes itself when given none, found by its user's clients; malformed bodies a 400 that
names what is wrong, never a traceback."""

from __future__ import annotations

import http.server
import json
import os
import re
import shutil
import socket
import stat
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from deployer.agent import local_token
from deployer.agent.client import Agent
from deployer.errors import AgentError
from deployer.profile import load_profile
from deployer.testing.simulator import Simulator, SimulatorThread
from tests.agent_helpers import PROFILE, AgentProcess, until, write_site, writes_in_log
from tests.test_agent_security import TOKEN, error_of, raw, token_file

pytestmark = pytest.mark.timeout(180)
CHROMIUM = next((p for p in (shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome")) if p), None)
CURL = shutil.which("curl")


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[Simulator]:
    (tmp_path / "drive.yaml").write_text(PROFILE)
    with SimulatorThread(load_profile(str(tmp_path / "drive.yaml"))) as s:
        yield s


def curl(*args: str) -> tuple[int, dict[str, Any]]:
    """curl as the issue's attacker ran it: (HTTP status, the JSON answer)."""
    assert CURL is not None
    p = subprocess.run(
        [CURL, "-s", "-o", "-", "-w", "\n%{http_code}", *args], capture_output=True, text=True, timeout=60
    )
    body, _, status = p.stdout.rpartition("\n")
    return int(status), json.loads(body) if body.strip() else {}


def refused(c: Agent, why: str) -> float:
    """``deployer_http_refused_requests_total{why=...}`` now."""
    for line in c.metrics().splitlines():
        if line.startswith(f'deployer_http_refused_requests_total{{why="{why}"}}'):
            return float(line.split()[-1])
    return 0.0


def nothing_ran(c: Agent, sim: Simulator) -> None:
    assert c.runs() == [] and not [e for e in c.events() if e["kind"] in ("run-started", "run-finished")]
    assert writes_in_log(sim.log) == {}, "a write reached the device"


@pytest.mark.skipif(CURL is None, reason="no curl")
def test_a_cross_origin_post_starts_nothing_with_or_without_the_token(tmp_path: Path, sim: Simulator) -> None:
    inv = write_site(tmp_path, {"d1": sim.url})
    agent = AgentProcess(inv, tmp_path / "state", "--allowed-host", "gw-line3.example")
    try:
        url, c = agent.url, agent.client
        port = url.rsplit(":", 1)[1]
        auth = ["-H", f"Authorization: Bearer {c.token}"]
        evil = ["-X", "POST", "-H", "Content-Type: text/plain", "-H", "Origin: http://evil.example", "--data", "{}"]
        status, body = curl(*evil, url + "/v1/runs")  # the request, word for word: 202 before
        assert status == 403 and body["error"]["kind"] == "forbidden" and "evil.example" in body["error"]["message"]
        status, body = curl(*evil, *auth, url + "/v1/runs")  # the token does not open the door for another origin
        assert status == 403 and "is not this agent" in body["error"]["message"]
        json_evil = ["-X", "POST", "-H", "Content-Type: application/json", "-H", "Origin: http://evil.example"]
        assert curl(*json_evil, *auth, "--data", "{}", url + "/v1/runs")[0] == 403
        assert curl(*json_evil, *auth, "--data", "{}", url + "/v1/reload")[0] == 403
        # the same origin on another port is another origin; "null" (a sandboxed frame, a file) too
        for origin in ("http://127.0.0.1:1", "null", f"https://127.0.0.1:{port}", f"http://127.0.0.1:{port}/x"):
            assert (
                curl(
                    "-X",
                    "POST",
                    "-H",
                    "Content-Type: application/json",
                    "-H",
                    f"Origin: {origin}",
                    *auth,
                    "--data",
                    "{}",
                    url + "/v1/runs",
                )[0]
                == 403
            ), origin
        # a simple request without an Origin (an old browser, a form posted from a file) lacks the content type
        status, body = curl("-X", "POST", "-H", "Content-Type: text/plain", *auth, "--data", "{}", url + "/v1/runs")
        said = body["error"]["message"]
        assert status == 415 and "application/json" in said and "text/plain" in said
        status, _ = curl("-X", "POST", *auth, "--data", "command=apply", url + "/v1/runs")  # a form's urlencoding
        assert status == 415
        # DNS rebinding: a hostile name resolved to 127.0.0.1, the browser's own origin then: the Host tells
        status, body = curl("-H", f"Host: evil.example:{port}", *auth, url + "/v1/devices")
        assert status == 403 and "DNS rebinding" in body["error"]["message"]
        assert (
            curl(
                "-X",
                "POST",
                "-H",
                f"Host: evil.example:{port}",
                "-H",
                "Content-Type: application/json",
                *auth,
                "--data",
                "{}",
                url + "/v1/runs",
            )[0]
            == 403
        )
        assert curl("-H", "Host: 127.0.0.1:1", *auth, url + "/v1/devices")[0] == 403  # another port
        assert curl("-H", "Sec-Fetch-Site: cross-site", *auth, url + "/v1/devices")[0] == 403
        nothing_ran(c, sim)
        assert refused(c, "origin") == 8 and refused(c, "content-type") == 2 and refused(c, "host") == 3
        assert refused(c, "fetch-site") == 1
        audit = [e for e in c.events() if e["kind"] == "request-refused"]
        assert {e["detail"]["why"] for e in audit} == {"origin", "content-type", "host", "fetch-site"}
        origin_rec = next(e for e in audit if e["detail"]["why"] == "origin")
        assert origin_rec["detail"]["origin"] == "http://evil.example" and origin_rec["detail"]["path"] == "/v1/runs"

        # the agent's own names and origin pass: the same request with them starts the run
        for host in (
            f"localhost:{port}",
            f"127.0.0.1:{port}",
            f"[::1]:{port}",
            f"gw-line3.example:{port}",
            f"GW-LINE3.example:{port}",
            f"{socket.gethostname()}:{port}",
        ):
            assert curl("-H", f"Host: {host}", *auth, url + "/v1/agent")[0] == 200, host
        assert curl("-H", f"Host: gw-line4.example:{port}", *auth, url + "/v1/agent")[0] == 403  # not given
        status, body = curl(
            "-X",
            "POST",
            "-H",
            "Content-Type: application/json",
            "-H",
            f"Origin: {url}",
            *auth,
            "--data",
            '{"confirm_within": "10m"}',
            url + "/v1/runs",
        )
        assert status == 202, body
        until(lambda: c.windows(), why="the run waits in its window")
        assert writes_in_log(sim.log) != {}  # the control: this one did reach the device
        assert agent.terminate() == 0
    finally:
        agent.kill()
    assert "Traceback" not in agent.log()


HOSTILE = """<!doctype html><html><head><title>cat pictures</title></head><body>
<iframe name="sink"></iframe>
<form id="f" method="POST" enctype="text/plain" target="sink" action="AGENT/v1/runs">
<input name='{"command": "apply", "x": "' value='"}'></form>
<script>
var agent = "AGENT", token = "TOKEN", out = [];
function settle(p, what) {
  return p.then(function (r) { out.push(what + " answered " + (r.type === "opaque" ? "opaque" : r.status)); },
                function (e) { out.push(what + " failed"); });
}
document.getElementById("f").submit();
Promise.all([
  settle(fetch(agent + "/v1/runs", {method: "POST", mode: "no-cors", headers: {"Content-Type": "text/plain"},
                                     body: '{"command": "apply"}'}), "no-cors"),
  settle(fetch(agent + "/v1/runs", {method: "POST", headers: {"Content-Type": "application/json",
                                     "Authorization": "Bearer " + token}, body: "{}"}), "cors with the token"),
  settle(fetch(agent + "/v1/reload", {method: "POST", mode: "no-cors", body: new URLSearchParams("a=b")}), "form-like"),
]).then(function () {
  out.push("beacon " + navigator.sendBeacon(agent + "/v1/runs", new Blob(["{}"], {type: "text/plain"})));
  setTimeout(function () { document.body.setAttribute("data-done", out.join("; ")); }, 1500);
});
</script></body></html>"""


def chromium(url: str, profile: Path, *more: str) -> str:
    assert CHROMIUM is not None
    p = subprocess.run(
        [
            CHROMIUM,
            "--headless=new",
            "--no-sandbox",
            "--disable-gpu",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            f"--user-data-dir={profile}",
            "--virtual-time-budget=15000",
            *more,
            "--dump-dom",
            url,
        ],
        capture_output=True,
        text=True,
        timeout=150,
    )
    assert p.returncode == 0, p.stderr
    return p.stdout


class _Hostile(http.server.BaseHTTPRequestHandler):
    page = b""

    def do_GET(self) -> None:
        self.send_response(200)
        self.send_header("Content-Type", "text/html; charset=utf-8")
        self.end_headers()
        self.wfile.write(self.page)

    def log_message(self, *args: Any) -> None:
        pass


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium (CI installs it: apt-get install chromium)")
def test_a_hostile_page_in_chromium_starts_nothing(tmp_path: Path, sim: Simulator) -> None:
    """A page from another loopback port (any site the gateway's browser opens) posts to the agent every way a page
    can, even with the token (as if it had leaked); and a rebound name loads the agent's page as its own."""
    inv = write_site(tmp_path, {"d1": sim.url})
    agent = AgentProcess(inv, tmp_path / "state")
    handler = type(
        "Hostile",
        (_Hostile,),
        {"page": HOSTILE.replace("AGENT", agent.url).replace("TOKEN", str(agent.client.token)).encode()},
    )
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        c = agent.client
        dom = chromium(f"http://127.0.0.1:{server.server_address[1]}/", tmp_path / "profile")
        done = re.search(r'data-done="([^"]*)"', dom)
        assert done, dom
        said = done.group(1)
        assert "cors with the token failed" in said and "no-cors answered opaque" in said, said
        nothing_ran(c, sim)
        # they reached the agent and were refused at the door: the form, the two no-cors fetches, the beacon and
        # the preflight of the one with the token (whose POST the browser then never sent)
        assert refused(c, "origin") >= 4, c.metrics()
        assert "agent: request-refused: refused POST /v1/runs" in agent.log()

        # DNS rebinding: evil.example resolves to 127.0.0.1, so the agent's page would be evil.example's own
        port = agent.url.rsplit(":", 1)[1]
        dom = chromium(
            f"http://evil.example:{port}/#token={c.token}",
            tmp_path / "profile2",
            "--host-resolver-rules=MAP evil.example 127.0.0.1",
        )
        assert "is not this agent's name" in dom and "data-ready" not in dom, dom
        assert refused(c, "host") >= 1
        nothing_ran(c, sim)
        assert agent.terminate() == 0
    finally:
        server.shutdown()
        server.server_close()
        agent.kill()
    assert "Traceback" not in agent.log()


def _access_list(path: str) -> str | None:
    """A file's access list as SDDL on Windows (None elsewhere)."""
    if sys.platform == "win32":
        import ctypes

        advapi32 = ctypes.WinDLL("advapi32", use_last_error=True)
        kernel32 = ctypes.WinDLL("kernel32", use_last_error=True)
        sd, text = ctypes.c_void_p(), ctypes.c_wchar_p()
        err = advapi32.GetNamedSecurityInfoW(
            ctypes.c_wchar_p(path), 1, 0x00000004, None, None, None, None, ctypes.byref(sd)
        )
        if err:
            raise ctypes.WinError(err)
        try:
            if not advapi32.ConvertSecurityDescriptorToStringSecurityDescriptorW(
                sd, 1, 0x00000004, ctypes.byref(text), None
            ):
                raise ctypes.WinError(ctypes.get_last_error())
            said = str(text.value)
            kernel32.LocalFree(text)
            return said
        finally:
            kernel32.LocalFree(sd)
    return None


@pytest.mark.skipif(sys.platform != "win32", reason="access lists are Windows' (POSIX: mode 0600, the test below)")
def test_the_agents_own_token_is_kept_to_its_owner_on_windows(tmp_path: Path) -> None:
    """Windows has no modes: the token file gets an access list of its own, for its owner, SYSTEM and the
    administrators (a state folder in C:\\site would hand every local user read access)."""
    from deployer import portable

    path, new = local_token.ensure(str(tmp_path))
    said = _access_list(path) or ""
    assert (
        new
        and said.startswith("D:P")
        and sorted(re.findall(r"\([^)]*\)", said)) == sorted(re.findall(r"\([^)]*\)", portable.PRIVATE_SDDL))
    ), said  # not inherited; these three, nobody else


def test_an_agent_given_no_token_makes_one_and_its_users_clients_find_it(tmp_path: Path, sim: Simulator) -> None:
    inv = write_site(tmp_path, {"d1": sim.url})
    state = tmp_path / "state"
    agent = AgentProcess(inv, state)
    made = state / "agent" / "token"
    try:
        assert f"every request needs the token in {made} (made now, {local_token.PROTECTION})" in agent.log()
        assert len(made.read_text().strip()) >= 40
        if sys.platform != "win32":  # Windows: an access list (the test below)
            assert made.stat().st_mode & 0o777 == 0o600
        token = made.read_text().strip()
        assert agent.client.token == token  # deployer.Agent found it by itself
        status, _, body = raw(agent.url + "/v1/devices")
        assert status == 401 and error_of(body)["kind"] == "unauthorized"
        env = {k: v for k, v in os.environ.items() if k != "DEPLOYER_AGENT_TOKEN"}
        cli = subprocess.run(
            [sys.executable, "-m", "deployer", "status", "--agent", agent.url],
            capture_output=True,
            text=True,
            timeout=60,
            env=env,
        )
        assert cli.returncode in (0, 2) and "d1" in cli.stdout, cli.stderr
        # another user's clients (another runtime folder here) find nothing, and are refused
        other = {**env, "DEPLOYER_RUNTIME_DIR": str(tmp_path / "elsewhere")}
        cli = subprocess.run(
            [sys.executable, "-m", "deployer", "status", "--agent", agent.url],
            capture_output=True,
            text=True,
            timeout=60,
            env=other,
        )
        assert cli.returncode == 1 and "needs its token" in cli.stderr and "Traceback" not in cli.stderr
        cli = subprocess.run(
            [sys.executable, "-m", "deployer", "status", "--agent", agent.url, "--agent-token-file", str(made)],
            capture_output=True,
            text=True,
            timeout=60,
            env=other,
        )
        assert cli.returncode in (0, 2) and "d1" in cli.stdout, cli.stderr
        note = Path(os.environ["DEPLOYER_RUNTIME_DIR"]) / f"agent-{agent.url.rsplit(':', 1)[1]}.json"
        assert json.loads(note.read_text())["token_file"] == str(made)
        assert sys.platform == "win32" or stat.S_IMODE(note.stat().st_mode) == 0o600
        assert agent.terminate() == 0
    finally:
        agent.kill()
    assert not note.exists()  # withdrawn at the stop
    # a restart keeps the token; a note left by a process that is gone is not believed
    again = AgentProcess(inv, state)
    try:
        assert f"(kept, {local_token.PROTECTION})" in again.log() and again.client.token == token
        port = again.url.rsplit(":", 1)[1]
        note = Path(os.environ["DEPLOYER_RUNTIME_DIR"]) / f"agent-{port}.json"
        note.write_text(json.dumps({"url": again.url, "pid": 2**22 + 1, "token_file": str(made)}))
        assert Agent(again.url).token is None
        with pytest.raises(AgentError) as e:
            Agent(again.url).devices()
        assert e.value.kind == "unauthorized"
        assert again.terminate() == 0
    finally:
        again.kill()
    # beyond loopback only with a token given (and TLS)
    p = subprocess.run(
        [sys.executable, "-m", "deployer", "agent", str(inv), "--state-dir", str(state), "--listen", "0.0.0.0:0"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert p.returncode == 1 and "without --token-file or --users the agent listens on loopback only" in p.stderr


def test_malformed_bodies_get_400_naming_what_is_wrong(tmp_path: Path, sim: Simulator) -> None:
    inv = write_site(tmp_path, {"d1": sim.url})
    agent = AgentProcess(inv, tmp_path / "state", "--token-file", str(token_file(tmp_path)))
    try:
        h = {"Content-Type": "application/json", "Authorization": f"Bearer {TOKEN}"}
        cases: list[tuple[str, bytes, str]] = [
            ("/v1/runs", b"[" * 100_000 + b"]" * 100_000, "nests deeper than 32 levels"),
            ("/v1/runs", b'{"a": ' * 100_000 + b"1" + b"}" * 100_000, "nests deeper than 32 levels"),
            ("/v1/runs", b'{"limit": ' + b"[" * 40 + b"]" * 40 + b"}", "nests deeper than 32 levels"),
            ("/v1/runs", b'{"parallel": NaN}', "NaN is not a number JSON allows"),
            ("/v1/runs", b'{"parallel": Infinity}', "Infinity is not a number JSON allows"),
            ("/v1/runs", b'{"parallel": -Infinity}', "-Infinity is not a number JSON allows"),
            ("/v1/runs", b'{"parallel": 1e999}', "1e999 is beyond the numbers the agent takes"),
            ("/v1/runs", b'{"parallel": "eight"}', "parallel: 'eight' is not of type 'integer'"),
            ("/v1/runs", b'{"parallel": 0}', "parallel: 0 is less than the minimum of 1"),
            ("/v1/runs", b'{"parallel": 8.5}', "parallel: 8.5 is not of type 'integer'"),
            ("/v1/runs", b'{"paralel": 8}', "paralel: not a key of this request"),
            ("/v1/runs", b'{"soak": [1]}', "soak: [1] is not of type 'string', 'number'"),
            ("/v1/runs", b'{"command": "erase"}', "command: 'erase' is not one of ['apply', 'restore']"),
            ("/v1/runs", b'{"client": "me@there"}', "client: not taken any more"),
            ("/v1/runs", b'{"limit": 7, "write_all": "yes"}', "limit: 7 is not of type 'string'"),
            ("/v1/check", b'{"limit": null}', "limit: None is not of type 'string'"),
            ("/v1/confirm", b'{"run": 12}', "run: 12 is not of type 'string'"),
            ("/v1/reload", b'{"x": 1}', "this route takes no body"),
            ("/v1/runs", b'"apply"', "must be a JSON object"),
            ("/v1/runs", b'{"a" 1}', "not JSON: Expecting ':' delimiter"),  # Python's words (3.13 changed some)
            ("/v1/runs", b"\xff", "not UTF-8"),
        ]
        for path, body, said in cases:
            status, _, answer = raw(agent.url + path, "POST", body, h)
            err = error_of(answer)
            assert status == 400 and err["kind"] == "usage", (path, body[:60], answer[:300])
            assert said in err["message"], (said, err["message"])
        both = error_of(raw(agent.url + "/v1/runs", "POST", b'{"limit": 7, "write_all": "yes"}', h)[2])["message"]
        assert "write_all: 'yes' is not of type 'boolean'" in both  # every problem at once
        c = Agent(agent.url, token=TOKEN)
        assert c.runs() == [] and c.info()["api"] == 1  # still serving, nothing started
        assert agent.terminate() == 0
    finally:
        agent.kill()
    assert "Traceback" not in agent.log() and "internal error" not in agent.log()
