"""An agent's device is the agent's whatever lock folder each process was given (DEPLOYER_LOCK_DIR): the agent
marks the devices it owns in a folder no setting moves (lock.owner_dir), every run holds a mark on the units
it writes there, and each side finds the other."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from deployer.profile import load_profile
from deployer.state import lock
from deployer.testing.simulator import Simulator, SimulatorThread
from tests.agent_helpers import PROFILE, AgentProcess, until, write_site

pytestmark = pytest.mark.timeout(120)
WRITES = (5, 6, 15, 16)


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[Simulator]:
    (tmp_path / "drive.yaml").write_text(PROFILE)
    with SimulatorThread(load_profile(str(tmp_path / "drive.yaml"))) as s:
        yield s


def deployer(*args: str, lock_dir: Path | None) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != lock.ENV}
    if lock_dir is not None:
        env[lock.ENV] = str(lock_dir)
    return subprocess.run(
        [sys.executable, "-m", "deployer", *args], capture_output=True, text=True, timeout=60, env=env
    )


@contextmanager
def owned(tmp: Path, sim: Simulator) -> Iterator[AgentProcess]:
    """An agent (in the test's DEPLOYER_LOCK_DIR) owning d1, checked once; killed at the end."""
    agent = AgentProcess(write_site(tmp, {"d1": sim.url}), tmp / "state")
    try:
        until(lambda: agent.client.device("d1")["last_check"], why="a check")
        yield agent
    finally:
        agent.kill()


def test_an_apply_with_another_lock_folder_is_refused_nothing_sent(tmp_path: Path, sim: Simulator) -> None:
    """The agent runs with the test's DEPLOYER_LOCK_DIR; the shell's apply is given another one."""
    with owned(tmp_path, sim) as agent:
        seen = len(sim.log)
        cli = deployer(
            "apply",
            str(tmp_path / "r.yaml"),
            "--device",
            sim.url,
            "--yes",
            "--state-dir",
            str(tmp_path / "cli"),
            lock_dir=tmp_path / "another-lock-folder",
        )
        assert cli.returncode == 3, cli.stderr
        said = " ".join((cli.stdout + cli.stderr).split())
        assert f"owned by the deployer agent at {agent.url}" in said and "--agent" in said, said
        assert "nothing was sent" in said
        # the simulator's request log: nothing from the shell (the agent itself only reads, in report mode)
        assert [e for e in sim.log[seen:] if e.function in WRITES] == []
        assert (tmp_path / "another-lock-folder").is_dir()  # the apply took its own lock there: not enough
        assert agent.terminate() == 0
    ok = deployer(
        "apply",
        str(tmp_path / "r.yaml"),
        "--device",
        sim.url,
        "--yes",
        "--state-dir",
        str(tmp_path / "cli"),
        lock_dir=tmp_path / "another-lock-folder",
    )
    assert ok.returncode == 0, ok.stderr  # the agent gone, its marks went with it


def test_a_broadcast_with_another_lock_folder_is_refused(tmp_path: Path, sim: Simulator) -> None:
    with owned(tmp_path, sim) as agent:
        seen = len(sim.log)
        cli = deployer(
            "apply",
            str(tmp_path / "r.yaml"),
            "--device",
            sim.url,
            "--unit",
            "0",
            "--allow-broadcast",
            "--yes",
            "--state-dir",
            str(tmp_path / "cli"),
            lock_dir=tmp_path / "another",
        )
        said = " ".join((cli.stdout + cli.stderr).split())
        assert cli.returncode == 3 and "the site agent at " + agent.url in said, said
        assert [e for e in sim.log[seen:] if e.function in WRITES] == []


def test_a_device_being_written_under_another_lock_folder_is_not_taken_by_an_agent(
    tmp_path: Path, sim: Simulator
) -> None:
    """A run holds its mark until its window ends: an agent starting meanwhile (restoring drift) does not own the
    device and writes nothing to it, then owns it once the run is over and restores the files' state."""
    inv = write_site(tmp_path, {"d1": sim.url})
    (tmp_path / "other.yaml").write_text((tmp_path / "r.yaml").read_text().replace("accel: 2 s", "accel: 4 s"))
    env = {k: v for k, v in os.environ.items() if k != lock.ENV}
    env[lock.ENV] = str(tmp_path / "shell-locks")
    run = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "deployer",
            "apply",
            str(tmp_path / "other.yaml"),
            "--device",
            sim.url,
            "--yes",
            "--confirm-within",
            "1h",
            "--state-dir",
            str(tmp_path / "cli"),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    agent: AgentProcess | None = None
    try:
        until(lambda: sim.read("accel") == (40,), why="the run's write")
        # the run's last write (a commit, a lock) may follow the value's: counted once the run waits in its window
        until(lambda: list((tmp_path / "cli" / "pending").glob("*.json")), why="the run in its window")
        written = len([e for e in sim.log if e.function in WRITES])
        agent = AgentProcess(inv, tmp_path / "state", "--on-drift", "restore")
        c = agent.client
        d1 = until(
            lambda: c.device("d1") if c.device("d1")["status"] == "not-owned" else None,
            why="not owned while the run holds it",
        )
        assert "a run on this machine is writing it" in d1["not_owned"]
        checks = c.info()["checks"]
        until(lambda: c.info()["checks"] >= checks + 3, why="more rounds of checks")
        assert len([e for e in sim.log if e.function in WRITES]) == written  # the agent wrote nothing meanwhile
        confirmed = deployer("confirm", "--state-dir", str(tmp_path / "cli"), lock_dir=tmp_path / "shell-locks")
        assert confirmed.returncode == 0, confirmed.stderr
        assert run.wait(timeout=60) == 0
        until(lambda: sim.read("accel") == (20,), why="owned once the run is over: the drift restored")
    finally:
        if agent is not None:
            agent.kill()
        if run.poll() is None:
            run.kill()
        run.communicate(timeout=30)


def test_the_owners_folder_follows_no_setting(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    first = lock.owner_dir()
    monkeypatch.setenv(lock.ENV, str(tmp_path / "x"))
    monkeypatch.setenv("TMPDIR", str(tmp_path / "y"))
    assert lock.owner_dir() == first
    if sys.platform.startswith("linux"):
        assert first == "/dev/shm/deployer-owners"  # a service's private /tmp does not hide it
    elif sys.platform == "win32":
        assert first.endswith(os.path.join("deployer", "owners"))


def test_a_run_leaves_no_mark_behind(tmp_path: Path, sim: Simulator) -> None:
    """Marks go with their last holder: the owners' folder (RAM on Linux) keeps no file per device ever written."""
    import hashlib

    from deployer.transport.clients import parse_url

    names = [
        hashlib.sha256(lock.device_key(b, 1).encode()).hexdigest()[:24] + ".lock" for b in parse_url(sim.url).lock_keys
    ]
    write_site(tmp_path, {"d1": sim.url})
    ok = deployer(
        "apply",
        str(tmp_path / "r.yaml"),
        "--device",
        sim.url,
        "--yes",
        "--state-dir",
        str(tmp_path / "cli"),
        lock_dir=tmp_path / "locks",
    )
    assert ok.returncode == 0, ok.stderr
    assert names and not [n for n in names if os.path.exists(os.path.join(lock.owner_dir(), n))]


def test_status_lists_the_devices_an_agent_owns_whatever_the_lock_folders(tmp_path: Path, sim: Simulator) -> None:
    """``deployer status`` in a shell given another lock folder still sees the agent's devices (its marks)."""
    import json

    with owned(tmp_path, sim) as agent:
        st = deployer("status", "--state-dir", str(tmp_path / "cli"), lock_dir=tmp_path / "another")
        said = " ".join(st.stdout.split())
        assert st.returncode == 0, st.stderr
        assert "devices site agents of this machine own" in said and f"the site agent at {agent.url}" in said, said
        doc = json.loads(
            deployer("status", "--json", "--state-dir", str(tmp_path / "cli"), lock_dir=tmp_path / "another").stdout
        )
        assert [r["agent"] for r in doc["owned"]] == [agent.url] * len(doc["owned"]) and doc["owned"], doc
        # given the agent's own lock folder, its locks say it: not twice
        same = deployer("status", "--state-dir", str(tmp_path / "cli"), lock_dir=Path(os.environ[lock.ENV]))
        assert "devices held on this machine now" in same.stdout, same.stdout
        assert "devices site agents of this machine own" not in same.stdout, same.stdout
