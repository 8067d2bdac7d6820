"""Every command keeps a profile's pauses: one way to a device (``deployer/execute/connect.py``) for all of them.

The simulated device drops a request that comes sooner than 60 ms after a connection opened or 60 ms after its
last answer (a gateway that needs its pauses); the profile asks for 150 ms and 80 ms. With no retries and a
short timeout, a command that did not keep them would lose a request and fail; the device's request log shows
the gaps (its timestamps) and no request "too soon".
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest

from deployer.profile import load_profile
from deployer.testing.simulator import Quirks, Simulator, SimulatorThread
from tests.agent_helpers import PROFILE, RECIPE, AgentProcess, until, write_site
from tests.helpers import cli

pytestmark = pytest.mark.timeout(120)

PACED = PROFILE.replace(
    "endurance: 1000\n", "endurance: 1000\nlimits: {pause_after_connect: 150ms, pause_between_requests: 80}\n"
)
# The device dates a connection when its event loop accepts it, which can be well after the client's connect
# returned (under Wine, on a loaded machine: more than 30 ms), so the pause after connect has a wide margin. A
# command that keeps no pause sends within a millisecond or two of connecting and is still caught.
QUIRKS = Quirks(pause_after_connect_ms=60, request_gap_ms=60)


def _site(tmp: Path) -> tuple[str, str]:
    (tmp / "drive.yaml").write_text(PACED)
    (tmp / "r.yaml").write_text(RECIPE)
    return str(tmp / "drive.yaml"), str(tmp / "r.yaml")


def _log(sim: Simulator) -> list[tuple[float, int, int, str]]:
    return [(round(e.time, 3), e.function, e.address, e.result) for e in sim.log]


def _kept(sim: Simulator, *, at_least: int = 2) -> None:
    """No request came too soon, and consecutive requests are at least the profile's gap apart."""
    assert not [e for e in sim.log if e.result == "too soon"], _log(sim)
    assert len(sim.log) >= at_least
    gaps = [b.time - a.time for a, b in zip(sim.log, sim.log[1:], strict=False)]
    assert min(gaps) >= 0.06, gaps


def _apply(capsys: pytest.CaptureFixture[str], recipe: str, url: str, state: str, *args: str) -> dict[str, object]:
    code, out, err = cli(capsys, "apply", recipe, "--device", url, "--yes", "--json", "--state-dir", state, *args)
    assert code == 0, (out, err)
    return json.loads(out)  # type: ignore[no-any-return]


COMMANDS: dict[str, Callable[[pytest.CaptureFixture[str], Path, str, str, str], None]] = {}


def command(name: str) -> Callable[[Callable[..., None]], Callable[..., None]]:
    def register(f: Callable[..., None]) -> Callable[..., None]:
        COMMANDS[name] = f
        return f

    return register


@command("apply")
def _(capsys: pytest.CaptureFixture[str], tmp: Path, recipe: str, profile: str, url: str) -> None:
    _apply(capsys, recipe, url, str(tmp / "s"))


@command("plan --device")
def _(capsys: pytest.CaptureFixture[str], tmp: Path, recipe: str, profile: str, url: str) -> None:
    code, out, err = cli(capsys, "plan", recipe, "--device", url, "--detailed-exitcode")
    assert code == 2, (out, err)


@command("diff")
def _(capsys: pytest.CaptureFixture[str], tmp: Path, recipe: str, profile: str, url: str) -> None:
    code, out, err = cli(capsys, "diff", recipe, "--device", url)
    assert code == 2, (out, err)


@command("pull")
def _(capsys: pytest.CaptureFixture[str], tmp: Path, recipe: str, profile: str, url: str) -> None:
    code, out, err = cli(capsys, "pull", "--profile", profile, "--device", url, "-o", str(tmp / "pulled.yaml"))
    assert code == 0, (out, err)


@command("rollback")
def _(capsys: pytest.CaptureFixture[str], tmp: Path, recipe: str, profile: str, url: str) -> None:
    snapshot = _apply(capsys, recipe, url, str(tmp / "s"))["devices"][0]["snapshot"]  # type: ignore[index]
    code, out, err = cli(capsys, "rollback", str(snapshot), "--yes", "--state-dir", str(tmp / "s"))
    assert code == 0, (out, err)


@command("apply --soak (health reads)")
def _(capsys: pytest.CaptureFixture[str], tmp: Path, recipe: str, profile: str, url: str) -> None:
    doc = _apply(capsys, recipe, url, str(tmp / "s"), "--soak", "1s", "--health-interval", "0.2s")
    assert doc["devices"][0]["commit"] == "sent"  # type: ignore[index]


@command("the window's commit (confirm)")
def _(capsys: pytest.CaptureFixture[str], tmp: Path, recipe: str, profile: str, url: str) -> None:
    import threading

    state = str(tmp / "s")

    def confirm_when_waiting() -> None:
        until(lambda: cli(capsys, "confirm", "--state-dir", state)[0] == 0 or None, timeout=30)

    t = threading.Thread(target=confirm_when_waiting, daemon=True)
    t.start()
    doc = _apply(capsys, recipe, url, state, "--confirm-within", "20s")
    t.join(timeout=30)
    assert doc["devices"][0]["commit"] == "sent"  # type: ignore[index]


@command("the window's rollback (not confirmed)")
def _(capsys: pytest.CaptureFixture[str], tmp: Path, recipe: str, profile: str, url: str) -> None:
    _, out, err = cli(
        capsys,
        "apply",
        recipe,
        "--device",
        url,
        "--yes",
        "--json",
        "--state-dir",
        str(tmp / "s"),
        "--confirm-within",
        "0.5s",
    )
    assert json.loads(out)["devices"][0]["status"] == "rolled-back", (out, err)


@command("probe")
def _(capsys: pytest.CaptureFixture[str], tmp: Path, recipe: str, profile: str, url: str) -> None:
    code, out, err = cli(capsys, "probe", profile, "--device", url)
    assert code in (0, 2), (out, err)


@pytest.mark.parametrize("name", list(COMMANDS))
def test_every_command_keeps_the_profiles_pauses(name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    profile, recipe = _site(tmp_path)
    with SimulatorThread(load_profile(profile), quirks=QUIRKS) as sim:
        # No retries: a request sent too soon is dropped and fails the command. The timeout only bounds the wait
        # for an answer that was not dropped: 0.3 s lost one under Wine on a loaded machine.
        try:
            COMMANDS[name](capsys, tmp_path, recipe, profile, sim.url + "?timeout=2&retries=0")
        except AssertionError as e:
            raise AssertionError(f"{e}\nthe device's log: {_log(sim)}") from None
        _kept(sim)


def test_scan_keeps_the_urls_pauses(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """scan knows no profile: the URL's pauses are the bus's."""
    profile, _ = _site(tmp_path)
    with SimulatorThread(load_profile(profile), quirks=QUIRKS) as sim:
        code, out, err = cli(
            capsys,
            "scan",
            sim.url + "?pause_after_connect=150ms&pause_between_requests=80ms",
            "--unit",
            "1-2",
            "--timeout",
            "1",
        )
        assert code == 0 and "1 of 2 unit ids answered" in out, (out, err)
        _kept(sim)


def test_the_agents_reads_keep_the_profiles_pauses(tmp_path: Path) -> None:
    (tmp_path / "site").mkdir()
    with SimulatorThread(load_profile(_site(tmp_path)[0]), quirks=QUIRKS) as sim:
        inv = write_site(tmp_path / "site", {"d1": sim.url + "?timeout=2&retries=0"}, profile=PACED)
        agent = AgentProcess(inv, tmp_path / "state", "--on-drift", "report")
        try:
            until(
                lambda: len([e for e in sim.log if e.function == 3]) >= 6 or None,
                timeout=30,
                why="the agent reads its device",
            )
        finally:
            agent.terminate()
        _kept(sim)


def test_a_rollback_from_a_snapshot_talks_to_the_device_as_its_apply_did(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The pauses, timeout and retries the apply's URL gave are in the snapshot: ``rollback SNAPSHOT`` keeps them
    (a gateway that needs them is not lost to the defaults); a timeout given to the rollback goes over them."""
    from deployer.run.rollback import snapshot_job

    (tmp_path / "drive.yaml").write_text(PROFILE)
    (tmp_path / "r.yaml").write_text(RECIPE)
    paced = "?pause_after_connect=150ms&pause_between_requests=80ms&timeout=2&retries=0"
    with SimulatorThread(load_profile(str(tmp_path / "drive.yaml")), quirks=QUIRKS) as sim:
        doc = _apply(capsys, str(tmp_path / "r.yaml"), sim.url + paced, str(tmp_path / "s"))
        snapshot = str(doc["devices"][0]["snapshot"])  # type: ignore[index]
        assert doc["devices"][0]["url"] == sim.url  # type: ignore[index]  # the report's URL as ever
        text = Path(snapshot).read_text()
        assert "pause_between_requests=80ms" in text and "timeout=2" in text and "retries=0" in text, text
        del sim.log[:]
        code, out, err = cli(capsys, "rollback", snapshot, "--yes", "--state-dir", str(tmp_path / "s"))
        assert code == 0, (out, err)
        _kept(sim)
    job, _, _ = snapshot_job(snapshot)
    assert (job.url.timeout, job.url.retries) == (2.0, 0)
    job, _, _ = snapshot_job(snapshot, timeout=5.0, retries=3)
    assert (job.url.timeout, job.url.retries) == (5.0, 3)
    assert job.url.options["pause_between_requests"] == "80ms"


def test_a_saved_plan_keeps_the_pauses_it_was_made_with(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The pauses a saved plan was made with are part of it (its ``pacing``, and its URL's options):
    ``apply PLAN.json`` keeps them without being given the URL again."""
    monkeypatch.chdir(tmp_path)  # plan --out records in the state folder's audit trail: here
    (tmp_path / "drive.yaml").write_text(PROFILE)  # no pauses of its own: the URL's are the device's
    (tmp_path / "r.yaml").write_text(RECIPE)
    paced = "?pause_after_connect=150ms&pause_between_requests=80ms&timeout=2&retries=0"
    with SimulatorThread(load_profile(str(tmp_path / "drive.yaml")), quirks=QUIRKS) as sim:
        plan = str(tmp_path / "p.json")
        code, out, err = cli(capsys, "plan", str(tmp_path / "r.yaml"), "--device", sim.url + paced, "--out", plan)
        assert code == 0, (out, err)
        assert json.loads(Path(plan).read_text())["pacing"] == {"after_connect": 0.15, "between_requests": 0.08}
        del sim.log[:]
        code, out, err = cli(
            capsys, "apply", plan, "--yes", "--timeout", "2", "--retries", "0", "--state-dir", str(tmp_path / "s")
        )
        assert code == 0, (out, err, _log(sim))
        _kept(sim)
