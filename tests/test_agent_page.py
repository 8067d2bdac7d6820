"""``GET /``: the agent's live page in headless Chromium against a real agent (with a token, given in the
address's fragment): devices, drift, an open window, pending changes and the last events read back from the DOM
its script built; a hostile device name shown as text; the page's own headers (CSP) and no data without the token."""

from __future__ import annotations

import json
import urllib.request
from pathlib import Path

import pytest

from deployer.profile import load_profile
from deployer.testing.simulator import SimulatorThread
from tests.agent_helpers import PROFILE, RECIPE, AgentProcess, until
from tests.test_pages import CHROMIUM, Elements, browser

pytestmark = [
    pytest.mark.timeout(180),
    pytest.mark.skipif(CHROMIUM is None, reason="no Chromium (CI installs it: apt-get install chromium)"),
]

TOKEN = "page-token-0123456789abcdef"
# device names are plain words (the inventory says so); what else a user names is not: the site's folder
HOSTILE = '<img src=x onerror="document.title=1">&amp;<svg onload="document.title=2">'


def test_the_live_page_shows_devices_drift_windows_pending_and_events(tmp_path: Path) -> None:
    tmp_path = tmp_path / HOSTILE
    tmp_path.mkdir()
    (tmp_path / "drive.yaml").write_text(PROFILE)
    prof = load_profile(str(tmp_path / "drive.yaml"))
    with SimulatorThread(prof) as s1, SimulatorThread(prof) as s2:
        (tmp_path / "r.yaml").write_text(RECIPE)
        inv = tmp_path / "inv.yaml"
        inv.write_text(
            "devices:\n"
            + "".join(
                f"  {json.dumps(n)}: {{url: {json.dumps(u)}, recipe: r.yaml}}\n"
                for n, u in (("d1", s1.url), ("d2", s2.url))
            )
        )
        (tmp_path / "token").write_text(TOKEN + "\n")
        agent = AgentProcess(inv, tmp_path / "state", "--token-file", str(tmp_path / "token"))
        try:
            from deployer.agent.client import Agent

            c = Agent(agent.url, token=TOKEN, timeout=20)
            until(lambda: any(d["drifted"] for d in c.devices()), why="the hostile-named device drifted")
            run = c.start_run(limit="d2", confirm_within="10m")["id"]
            until(lambda: c.windows(), why="d2's window open")
            (tmp_path / "r.yaml").write_text(RECIPE.replace("speed: 3000 rpm", "speed: 2500 rpm"))
            c.reload()

            with urllib.request.urlopen(agent.url + "/", timeout=20) as resp:  # the shell: no token, no data
                shell, headers = resp.read().decode(), resp.headers
            csp = headers["Content-Security-Policy"]
            assert "default-src 'none'" in csp and "connect-src 'self'" in csp and "'unsafe-inline'" not in csp
            assert headers["X-Content-Type-Options"] == "nosniff" and "d2" not in shell and "onerror" not in shell
            assert "http://" not in shell.replace(agent.url, "") and "https://" not in shell  # nothing from elsewhere

            proc = browser("--dump-dom", f"{agent.url}/#token={TOKEN}", tmp=tmp_path)
            assert proc.returncode == 0, proc.stderr
            assert 'data-ready="' in proc.stdout, "the page's script did not finish"
            doc = Elements(proc.stdout)
            rows = {str(r["data-device"]): r for r in doc.all("tr", "dev")}
            assert set(rows) == {"d1", "d2"}
            where = next(e for e in doc.found if e.get("id") == "where")
            assert HOSTILE in str(where["text"])  # the folder's name is text, read back as it is
            hostile = rows["d1"]
            assert hostile["data-drifted"] == "true" and "accel is 5 s (adopted 2 s)" in hostile["cells"][2]  # type: ignore[index]
            assert hostile["cells"][3] == "1 pending"  # type: ignore[index]
            d2 = rows["d2"]
            assert "confirm until" in d2["cells"][4]  # type: ignore[index]
            assert not doc.all("img") and not doc.all("svg") and len(doc.all("script")) == 1  # no markup from it
            assert "<title>deployer agent</title>" in proc.stdout  # no script of the name ran
            windows = [r for r in doc.all("tr") if r.get("data-run") == run]
            assert windows and "d2" in windows[0]["cells"][2]  # type: ignore[index]
            pending = [
                list(r["cells"])  # type: ignore[call-overload]
                for r in doc.all("tr")
                if r.get("data-device") and "dev" not in str(r.get("class"))
            ]
            assert sorted(p for p in pending if p[1] == "speed") == [
                ["d1", "speed", "3000 rpm", "2500 rpm"],
                ["d2", "speed", "3000 rpm", "2500 rpm"],
            ], pending
            kinds = {r.get("data-kind") for r in doc.all("tr") if r.get("data-kind")}
            assert {"started", "drift", "window-waiting", "reload"} <= kinds, kinds

            # without the token the page asks for it and shows nothing of the agent
            proc = browser("--dump-dom", f"{agent.url}/", tmp=tmp_path / "other")
            assert proc.returncode == 0 and "needs its token" in proc.stdout and "d2" not in proc.stdout
            assert agent.terminate() == 0
        finally:
            agent.kill()
