"""``deployer agent --notify URL``: a local HTTP receiver gets a JSON POST for each event kind (drift, restored,
replaced, run finished, window waiting and expired, endurance warning); a receiver that is down (connection
refused) or fails (503) is retried until it takes the event, and one that hangs does not hold up device work.
A real agent process, simulators, a real aiohttp receiver."""

from __future__ import annotations

import asyncio
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from aiohttp import web
from prometheus_client.parser import text_string_to_metric_families

from deployer.agent.notify import PAYLOAD_VERSION
from deployer.profile import load_profile
from deployer.testing.simulator import Quirks, SimulatorThread
from tests.agent_helpers import PROFILE, AgentProcess, until, write_site
from tests.conftest import dead_port
from tests.test_agent_replace import ACME, on_port

pytestmark = pytest.mark.timeout(120)


class Receiver:
    """An HTTP server on 127.0.0.1 (port 0) in a thread: records every POST; can fail or hang on purpose."""

    def __init__(self) -> None:
        self.attempts: list[dict[str, Any]] = []
        self.got: list[dict[str, Any]] = []
        self.fail = 0  # answer 503 to the next N requests
        self.release = threading.Event()  # cleared: requests hang until it is set again
        self.release.set()
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        assert self._ready.wait(10)

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        self._loop.run_until_complete(self._listen(0))
        self.url = f"http://127.0.0.1:{self._runner.addresses[0][1]}/hook"
        self._ready.set()
        self._loop.run_forever()

    async def _listen(self, port: int) -> None:
        app = web.Application()
        app.router.add_post("/hook", self._handle)
        self._runner = web.AppRunner(app, access_log=None)
        await self._runner.setup()
        await web.TCPSite(self._runner, "127.0.0.1", port).start()

    def down(self) -> None:
        """Stop listening: connections are refused (the port stays this receiver's to take again)."""
        asyncio.run_coroutine_threadsafe(self._runner.cleanup(), self._loop).result(10)

    def up(self) -> None:
        """Listen again on the same port. The agent keeps connecting there meanwhile, and Linux may make such a
        connection its own source port (connected to itself) for a moment: binding is tried again for a while."""
        port = int(self.url.rsplit(":", 1)[1].split("/")[0])
        for _ in range(100):
            try:
                asyncio.run_coroutine_threadsafe(self._listen(port), self._loop).result(10)
                return
            except OSError:
                time.sleep(0.1)
        raise AssertionError(f"port {port} stayed taken")

    async def _handle(self, request: web.Request) -> web.Response:
        body = await request.json()
        assert request.headers["Content-Type"].startswith("application/json")
        self.attempts.append(body)
        if self.fail > 0:
            self.fail -= 1
            return web.Response(status=503)
        await self._loop.run_in_executor(None, self.release.wait)
        self.got.append(body)
        return web.json_response({"ok": True})

    def kinds(self) -> set[str]:
        return {str(b["kind"]) for b in self.got}

    def close(self) -> None:
        self.release.set()
        asyncio.run_coroutine_threadsafe(self._runner.cleanup(), self._loop).result(10)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(10)


def test_each_event_kind_is_posted_retried_and_never_holds_up_the_devices(tmp_path: Path) -> None:
    (tmp_path / "drive.yaml").write_text(PROFILE)
    prof = load_profile(str(tmp_path / "drive.yaml"))
    first = SimulatorThread(prof, quirks=Quirks(identity=dict(ACME)))
    sim = first.__enter__()
    port = sim.url.rsplit(":", 1)[1]
    rec = Receiver()
    dead = f"http://127.0.0.1:{dead_port()}/hook"  # a receiver that never answers holds up no other
    inv = write_site(tmp_path, {"d1": sim.url})
    agent = AgentProcess(
        inv,
        tmp_path / "state",
        "--on-drift",
        "restore",
        "--on-replace",
        "restore",
        "--endurance-warn",
        "0.001",
        "--notify",
        rec.url,
        "--notify",
        dead,
    )
    second = None
    try:
        c = agent.client
        # the simulator starts at the profile's defaults: drift from the adopted files, restored
        until(lambda: {"drift", "restored"} <= rec.kinds(), why="drift and restored posted")
        end = c.apply(write_all=True)
        assert end["exit_code"] == 0, end
        run = c.start_run(write_all=True, confirm_within="0.3s")["id"]  # never confirmed: it expires
        until(
            lambda: any(b["kind"] == "window-expired" and b["detail"]["run"] == run for b in rec.got),
            why="window-expired posted",
        )
        assert {"run-finished", "window-waiting", "endurance-warning"} <= rec.kinds()

        # a receiver that hangs: the run goes on and ends; what waits is sent once it answers again
        rec.release.clear()
        end = c.apply(write_all=True)
        assert end["exit_code"] == 0 and not rec.release.is_set()
        assert not any(b["kind"] == "run-finished" and b["detail"]["run"] == end["run"] for b in rec.got)
        rec.release.set()
        until(
            lambda: any(b["kind"] == "run-finished" and b["detail"]["run"] == end["run"] for b in rec.got),
            why="the run's end posted after the receiver came back",
        )

        # a receiver that is down (connection refused): the run is not held up; retried until it is up again
        rec.down()
        end = c.apply(write_all=True)
        assert end["exit_code"] == 0
        until(
            lambda: any(
                line.startswith(f"agent: notify {rec.url}: ") and "retrying with back-off" in line
                for line in agent.stderr
            ),
            why="the agent says it retries",
        )
        rec.up()
        until(
            lambda: any(b["kind"] == "run-finished" and b["detail"]["run"] == end["run"] for b in rec.got),
            why="the run's end posted once the receiver was up again",
        )
        until(lambda: f"notify {rec.url}: delivered again" in agent.log(), why="the agent says so")  # after the answer

        # a receiver that fails (HTTP 503): the same event is sent again, with back-off, until it is taken
        rec.fail = 2
        sim.write("accel", [77])
        drift = until(
            lambda: [b for b in rec.got if b["kind"] == "drift" and b["id"] > end_id(rec, end["run"])],
            why="the second drift posted",
        )[0]
        assert sum(1 for a in rec.attempts if a["id"] == drift["id"]) == 3

        # the drive is swapped for another unit of the same model: replaced (and restored)
        first.__exit__(None, None, None)
        until(lambda: "unreachable" in rec.kinds(), why="unreachable posted")
        second = on_port(prof, port, quirks=Quirks(identity={**ACME, 2: "1.1"}))
        until(lambda: "replaced" in rec.kinds(), why="replaced posted")

        for b in rec.got:  # the documented payload
            assert set(b) == {"version", "agent", "id", "time", "device", "kind", "message", "detail"}
            assert b["version"] == PAYLOAD_VERSION and b["agent"] == agent.url
        ids = [b["id"] for b in rec.got]
        assert ids == sorted(ids) and len(set(ids)) == len(ids)  # in order, each once
        assert ids == [e["id"] for e in c.events(limit=10000) if e["id"] in set(ids)]
        metrics = {
            (f.name, tuple(sm.labels.values())): sm.value
            for f in text_string_to_metric_families(c.metrics())
            for sm in f.samples
        }
        assert 10 <= metrics[("deployer_notify_sent", (rec.url,))] <= len(rec.got)
        assert metrics[("deployer_notify_failing", (dead,))] == 1.0
        assert metrics[("deployer_notify_waiting", (dead,))] >= len(rec.got)  # the dead one: all of them wait
        assert agent.terminate() == 0
        assert "stopped" in rec.kinds()  # sent while the agent ends
    finally:
        agent.kill()
        if second is not None:
            second.__exit__(None, None, None)
        rec.close()
    assert f"notify {dead}" in agent.log() and "Traceback" not in agent.log()


def end_id(rec: Receiver, run: str) -> int:
    return max(int(b["id"]) for b in rec.got if b["kind"] == "run-finished" and b["detail"]["run"] == run)


def test_a_receiver_behind_basic_auth_gets_it_and_the_password_is_shown_nowhere() -> None:
    """``--notify https://user:password@host/...``: sent as HTTP basic auth; /metrics and the log hide it."""
    import base64
    import types

    from deployer.agent.notify import Notifier

    seen: list[tuple[str, dict[str, Any]]] = []

    async def main() -> None:
        async def handle(request: web.Request) -> web.Response:
            seen.append((request.headers.get("Authorization", ""), await request.json()))
            return web.json_response({})

        app = web.Application()
        app.router.add_post("/hook", handle)
        runner = web.AppRunner(app, access_log=None)
        await runner.setup()
        await web.TCPSite(runner, "127.0.0.1", 0).start()
        url = f"http://ops:s3cret@127.0.0.1:{runner.addresses[0][1]}/hook"
        fake = types.SimpleNamespace(on_event=[])  # the hook list is all the notifier touches of the agent
        n = Notifier(fake, [url])  # type: ignore[arg-type]
        n.start("http://127.0.0.1:8470")
        for hook in fake.on_event:
            hook({"id": 1, "time": "t", "device": "d1", "kind": "drift", "message": "m", "detail": {}})
        await n.stop(grace=5)
        labels = [s.labels["url"] for f in n.collect() for s in f.samples]
        await runner.cleanup()
        assert labels and all("s3cret" not in x and "ops:***@" in x for x in labels)

    asyncio.run(main())
    assert seen == [
        (
            "Basic " + base64.b64encode(b"ops:s3cret").decode(),
            {
                "version": 1,
                "agent": "http://127.0.0.1:8470",
                "id": 1,
                "time": "t",
                "device": "d1",
                "kind": "drift",
                "message": "m",
                "detail": {},
            },
        )
    ]
