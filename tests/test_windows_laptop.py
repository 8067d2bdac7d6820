"""What a commissioning engineer's Windows laptop does differently (docs/windows.md), each run on every system and
meant for the Windows Python of ``make test-windows``: the agent stopped as Windows stops it (Ctrl-C and Ctrl-Break
in its console, a service manager's stop route), Ctrl-C during a soak and a confirm window, a file another program
holds open when deployer replaces it, Windows paths in recipes, CRLF files, the state folder, non-ASCII names."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from deployer.agent.client import Agent
from deployer.errors import AgentError
from deployer.profile import load_profile
from deployer.testing.simulator import Simulator, SimulatorThread
from deployer.window.confirm import awaiting
from tests import console
from tests.agent_helpers import PROFILE, AgentProcess, event, until, write_site

pytestmark = pytest.mark.timeout(120)
TOKEN = "a-token-for-the-service-manager-0123"


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[Simulator]:
    (tmp_path / "drive.yaml").write_text(PROFILE)
    with SimulatorThread(load_profile(str(tmp_path / "drive.yaml"))) as s:
        yield s


def commits(sim: Simulator) -> int:
    return sum(1 for e in sim.log if e.function in (6, 16) and e.address == 30)


# ---- the agent stopped as Windows stops it ------------------------------------------------------------------


def test_the_stop_route_ends_a_window_and_the_agent_cleanly(tmp_path: Path, sim: Simulator) -> None:
    """A service manager's stop (what the stop signal does on Linux; Windows has none): only with the agent's
    token; then the window rolls back, the store closes with its 'stopped' event, and the agent exits 0."""
    inv = write_site(tmp_path, {"d1": sim.url})
    (tmp_path / "token").write_text(TOKEN + "\n")
    agent = AgentProcess(inv, tmp_path / "state", "--token-file", str(tmp_path / "token"))
    try:
        c = Agent(agent.url, token=TOKEN, timeout=20)
        run = c.start_run(confirm_within="10m")["id"]
        until(lambda: c.run(run)["state"] == "waiting", why="the confirm window")
        assert sim.read("accel") == (20,)
        with pytest.raises(AgentError) as refused:
            Agent(agent.url, timeout=20).post("/v1/stop")
        assert refused.value.kind == "unauthorized" and agent.proc.poll() is None
        assert c.run(run)["state"] == "waiting"
        assert c.post("/v1/stop") == {"stopping": True}
        assert agent.proc.wait(timeout=60) == 0, agent.log()
    finally:
        agent.kill()
    assert sim.read("accel") == (50,) and commits(sim) == 0  # rolled back, never committed
    again = AgentProcess(inv, tmp_path / "state", "--token-file", str(tmp_path / "token"))
    try:
        c = Agent(again.url, token=TOKEN, timeout=20)
        assert c.windows() == [] and event(c, "stopped") is not None
        assert [r["state"] for r in c.runs() if r["id"] == run] == ["interrupted"]
        assert again.terminate() == 0
    finally:
        again.kill()


@pytest.mark.parametrize("key", console.keys())
def test_ctrl_c_and_ctrl_break_in_the_agents_console_end_it_cleanly(tmp_path: Path, sim: Simulator, key: str) -> None:
    inv = write_site(tmp_path, {"d1": sim.url})
    proc = console.start(
        "agent", str(inv), "--state-dir", str(tmp_path / "state"), "--listen", "127.0.0.1:0", "--check-every", "0.2s"
    )
    try:
        assert proc.stderr is not None
        seen = ""
        for line in proc.stderr:
            seen += line
            if line.startswith("listening on "):
                break
        url = seen.split("listening on ", 1)[1].split()[0]
        c = Agent(url, timeout=20)
        run = c.start_run(confirm_within="10m")["id"]
        until(lambda: c.run(run)["state"] == "waiting", why="the confirm window")
        console.press(proc, key)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, seen + err
    assert "Traceback" not in seen + err
    assert sim.read("accel") == (50,) and commits(sim) == 0
    again = AgentProcess(inv, tmp_path / "state")
    try:
        assert again.client.windows() == [] and event(again.client, "stopped") is not None
        assert again.terminate() == 0
    finally:
        again.kill()


# ---- Ctrl-C in a console during a soak and a confirm window ---------------------------------------------------


SOAK_RECIPE = "recipe: r\nprofile: drive.yaml\nparameters:\n  accel: 2 s\n"


@pytest.mark.parametrize("key", console.keys())
@pytest.mark.parametrize(
    "held", [["--soak", "1h", "--health-interval", "100ms"], ["--confirm-within", "1h"]], ids=["soak", "confirm"]
)
def test_a_console_key_during_a_soak_or_a_confirm_window_rolls_back(
    tmp_path: Path, sim: Simulator, key: str, held: list[str]
) -> None:
    (tmp_path / "r.yaml").write_text(SOAK_RECIPE)
    state, report = tmp_path / "s", tmp_path / "r.json"
    proc = console.start(
        "apply",
        str(tmp_path / "r.yaml"),
        "--device",
        sim.url,
        "--yes",
        *held,
        "--report",
        str(report),
        "--state-dir",
        str(state),
    )
    try:
        audit = state / "audit.jsonl"
        until(
            lambda: (
                bool(awaiting(str(state)))
                or (audit.exists() and "soak-started" in audit.read_text("utf-8"))
                or proc.poll() is not None
            ),
            60,
            why="the window",
        )
        console.press(proc, key)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 4, out + err
    assert f"interrupted ({key})" in err and "Traceback" not in err
    assert sim.read("accel") == (50,) and commits(sim) == 0
    (dev,) = json.loads(report.read_text(encoding="utf-8"))["devices"]
    assert dev["status"] == "rolled-back" and dev["commit"] == "not sent"
    events = [json.loads(x)["event"] for x in (state / "audit.jsonl").read_text(encoding="utf-8").splitlines()]
    assert "rolled-back" in events and events[-1] == "run-finished"


# ---- a file another program holds open ------------------------------------------------------------------------


def deployer(*args: str, cwd: Path, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "deployer", *args], capture_output=True, text=True, timeout=120, cwd=cwd, env=env
    )


def _held_until_a_write_begins(path: Path, done: threading.Event) -> threading.Thread:
    """``path`` open (as an editor or a virus scanner holds it: Windows' open shares reading and writing, not
    deleting) until deployer's temporary file for it appears beside it (on Windows it stays while deployer retries
    the replace), or deployer is done (POSIX replaced it at once); then let go."""
    f = open(path, "rb")  # noqa: SIM115 (held across the thread's life)

    def hold() -> None:
        try:
            while not done.wait(0.005):
                if any(p.name.startswith(f".{path.name}.") for p in path.parent.iterdir()):
                    return
        finally:
            f.close()

    t = threading.Thread(target=hold, daemon=True)
    t.start()
    return t


def test_a_report_and_the_learned_file_held_open_are_replaced_once_let_go(tmp_path: Path, sim: Simulator) -> None:
    """Windows refuses to replace a file another program has open; deployer retries while it is held briefly (a
    scanner), so the run ends whole: report, page and learned limits written."""
    (tmp_path / "r.yaml").write_text(SOAK_RECIPE)
    first = deployer(
        "apply",
        "r.yaml",
        "--device",
        sim.url,
        "--yes",
        "--report",
        "r.json",
        "--html",
        "r.html",
        "--state-dir",
        "s",
        cwd=tmp_path,
    )
    assert first.returncode == 0, first.stderr
    held = [tmp_path / "r.json", tmp_path / "r.html"]
    done = threading.Event()
    threads = [_held_until_a_write_begins(p, done) for p in held]
    sim.write("accel", (50,))
    again = deployer(
        "apply",
        "r.yaml",
        "--device",
        sim.url,
        "--yes",
        "--report",
        "r.json",
        "--html",
        "r.html",
        "--state-dir",
        "s",
        cwd=tmp_path,
    )
    done.set()
    for t in threads:
        t.join(timeout=60)
    assert again.returncode == 0, again.stdout + again.stderr
    assert json.loads((tmp_path / "r.json").read_text(encoding="utf-8"))["devices"][0]["status"] == "ok"
    # the learned limits' file, saved the same way (write_atomic) by whichever run learns a limit
    from deployer.state import learned

    state = str(tmp_path / "s")
    learned._save(state, [])
    done = threading.Event()
    holder = _held_until_a_write_begins(Path(learned.path_of(state)), done)
    learned._save(state, [])
    done.set()
    holder.join(timeout=60)
    assert json.loads(Path(learned.path_of(state)).read_text(encoding="utf-8"))["devices"] == []


def test_a_report_held_open_throughout_is_said_plainly(tmp_path: Path, sim: Simulator) -> None:
    (tmp_path / "r.yaml").write_text(SOAK_RECIPE)
    (tmp_path / "r.json").write_text("{}\n")
    with open(tmp_path / "r.json", "rb"):
        done = deployer(
            "apply", "r.yaml", "--device", sim.url, "--yes", "--report", "r.json", "--state-dir", "s", cwd=tmp_path
        )
    said = done.stdout + done.stderr
    assert "Traceback" not in said
    if sys.platform == "win32":  # Windows replaces no file that is open: the report's first state cannot be
        # written, so the run is refused before its first request, said with what to do, and journaled as refused
        assert done.returncode == 1 and "cannot write the report r.json" in said, said
        assert "close the program" in said, said
        assert sim.read("accel") == (50,) and sim.log == []  # nothing sent
        last = json.loads((tmp_path / "s" / "audit.jsonl").read_text(encoding="utf-8").splitlines()[-1])
        assert last["event"] == "run-finished" and "cannot write the report" in last["refused"]
    else:  # POSIX replaces it: the holder keeps the old text
        assert done.returncode == 0, said
        assert json.loads((tmp_path / "r.json").read_text())["devices"][0]["status"] == "ok"


# ---- Windows paths, CRLF files, the per-user folders, names that are not ASCII -------------------------------


DRIVE = PROFILE


@pytest.mark.skipif(sys.platform != "win32", reason="backslashes and drive letters are Windows' path syntax")
def test_backslashes_and_drive_letters_in_recipes_and_options(tmp_path: Path, sim: Simulator) -> None:
    (tmp_path / "profiles").mkdir()
    (tmp_path / "recipes").mkdir()
    (tmp_path / "profiles" / "drive.yaml").write_text(DRIVE)
    relative = tmp_path / "recipes" / "rel.yaml"
    relative.write_text("recipe: rel\nprofile: ..\\profiles\\drive.yaml\nparameters: {accel: 2 s}\n")
    absolute = tmp_path / "recipes" / "abs.yaml"  # a drive letter, single-quoted as YAML wants backslashes
    absolute.write_text(f"recipe: abs\nprofile: '{tmp_path / 'profiles' / 'drive.yaml'}'\nparameters: {{accel: 3 s}}\n")
    assert str(tmp_path)[1:3] == ":\\"
    assert deployer("validate", "recipes\\rel.yaml", str(absolute), cwd=tmp_path).returncode == 0
    done = deployer(
        "apply",
        "recipes\\rel.yaml",
        "--device",
        sim.url,
        "--yes",
        "--report",
        "out\\..\\r.json",
        "--state-dir",
        ".\\state",
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr
    assert sim.read("accel") == (20,) and (tmp_path / "r.json").exists()
    # the extended-length form of a path (\\?\C:\...), as UNC tools write it, for the state folder and the report
    long_form = "\\\\?\\" + str(tmp_path / "state2")
    done = deployer(
        "apply",
        str(absolute),
        "--device",
        sim.url,
        "--yes",
        "--state-dir",
        long_form,
        "--report",
        "\\\\?\\" + str(tmp_path / "r2.json"),
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr
    assert sim.read("accel") == (30,) and (tmp_path / "r2.json").exists()
    snaps = list((tmp_path / "state2" / "snapshots").iterdir())
    assert len(snaps) == 1
    back = deployer("rollback", str(snaps[0]), "--yes", "--state-dir", long_form, cwd=tmp_path)
    assert back.returncode == 0, back.stderr
    assert sim.read("accel") == (20,)


@pytest.mark.skipif(sys.platform != "win32", reason="UNC paths (a server's share) are Windows' path syntax")
def test_a_file_server_out_of_reach_is_said_by_its_unc_path_before_anything_is_sent(
    tmp_path: Path, sim: Simulator
) -> None:
    """Recipes, the state folder and the report on a share (\\\\server\\share\\...) the laptop cannot reach: each
    said by its path, nothing sent. (A share that answers is not tested: Wine has no SMB client; docs/windows.md.)"""
    share = "\\\\nohost.invalid\\plant"
    said = deployer("validate", share + "\\recipes\\r.yaml", cwd=tmp_path)
    assert said.returncode == 1 and said.stderr.startswith(share + "\\recipes\\r.yaml:"), said.stderr
    (tmp_path / "drive.yaml").write_text(DRIVE)
    (tmp_path / "r.yaml").write_text(SOAK_RECIPE)
    for extra, what in (
        (["--state-dir", share + "\\state"], "the journal " + share + "\\state\\audit.jsonl"),
        (["--report", share + "\\r.json", "--state-dir", "s"], "the report " + share + "\\r.json"),
    ):
        done = deployer("apply", "r.yaml", "--device", sim.url, "--yes", *extra, cwd=tmp_path)
        out = done.stdout + done.stderr
        assert done.returncode == 1 and f"cannot write {what}: " in out and "Traceback" not in out, out
    assert sim.log == [] and sim.read("accel") == (50,)


def test_crlf_files_read_as_lf_files_and_errors_at_the_same_place(tmp_path: Path, sim: Simulator) -> None:
    """Notepad and Excel write CRLF: recipes, profiles and inventories read the same, errors at the same LINE:COL."""
    lf = "recipe: r\nprofile: drive.yaml\nparameters:\n  accel: 2 s\n  decel: 900 s\n"
    for name, ends in (("lf", b"\n"), ("crlf", b"\r\n")):
        (tmp_path / name).mkdir()
        (tmp_path / name / "drive.yaml").write_bytes(DRIVE.encode().replace(b"\n", ends))
        (tmp_path / name / "r.yaml").write_bytes(lf.encode().replace(b"\n", ends))
        (tmp_path / name / "inv.yaml").write_bytes(
            f"devices:\n  d1: {{url: '{sim.url}', recipe: r.yaml}}\n".encode().replace(b"\n", ends)
        )
    said = {n: deployer("validate", "r.yaml", "inv.yaml", cwd=tmp_path / n) for n in ("lf", "crlf")}
    assert said["lf"].returncode == said["crlf"].returncode == 1
    assert said["crlf"].stderr == said["lf"].stderr and "r.yaml:5:10: error: decel" in said["lf"].stderr
    for name in ("lf", "crlf"):
        r = tmp_path / name / "r.yaml"
        r.write_bytes(r.read_bytes().replace(b"900 s", b"3 s"))
        done = deployer("apply", "--inventory", "inv.yaml", "--yes", "--state-dir", "s", cwd=tmp_path / name)
        assert done.returncode == 0, done.stdout + done.stderr
        sim.write("accel", (50,))


def test_non_ascii_user_and_folder_names_and_the_per_user_cache(tmp_path: Path, sim: Simulator) -> None:
    """A user Jürgen with his site under 'Anlage Süd': apply, an edited snapshot refused, rollback; the units
    cache in his %LOCALAPPDATA%\\deployer on Windows (XDG_CACHE_HOME or ~/.cache elsewhere)."""
    home = tmp_path / "Users" / "Jürgen Müller"
    site = home / "Anlage Süd – Linie 3"
    site.mkdir(parents=True)
    (site / "drive.yaml").write_text(DRIVE, encoding="utf-8")
    (site / "Rezept ä.yaml").write_text(SOAK_RECIPE, encoding="utf-8")
    env = {k: v for k, v in os.environ.items() if k != "XDG_CACHE_HOME"}
    env.update(
        {
            "HOME": str(home),
            "USERPROFILE": str(home),
            "LOCALAPPDATA": str(home / "AppData" / "Local"),
            "USERNAME": "Jürgen",
            "USER": "Jürgen",
        }
    )
    done = deployer(
        "apply",
        "Rezept ä.yaml",
        "--device",
        sim.url,
        "--yes",
        "--report",
        "Bericht ü.json",
        "--state-dir",
        "Zustand ö",
        cwd=site,
        env=env,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert sim.read("accel") == (20,)
    cache = home / "AppData" / "Local" / "deployer" if sys.platform == "win32" else home / ".cache" / "deployer"
    assert any(p.name.startswith("units-") for p in cache.iterdir()), list(home.rglob("*"))
    report = json.loads((site / "Bericht ü.json").read_text(encoding="utf-8"))
    snap = Path(report["devices"][0]["snapshot"])
    assert snap.parent == site / "Zustand ö" / "snapshots" and snap.exists()
    snap.write_bytes(snap.read_bytes().replace(b"accel: 5 s", b"accel: 9 s"))
    refused = deployer("rollback", str(snap), "--yes", "--state-dir", "Zustand ö", cwd=site, env=env)
    assert refused.returncode == 1 and "was changed after it was written" in refused.stderr, refused.stderr
    snap.write_bytes(snap.read_bytes().replace(b"accel: 9 s", b"accel: 5 s"))
    back = deployer(
        "rollback", "--from-report", "Bericht ü.json", "--yes", "--state-dir", "Zustand ö", cwd=site, env=env
    )
    assert back.returncode == 0, back.stdout + back.stderr
    assert sim.read("accel") == (50,)
