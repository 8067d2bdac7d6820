"""Snapshots that restore the right values (issue #13) and exact rollback (issue #11).

Devices are in-process simulators on 127.0.0.1; their register state is read from the
simulator (and its state dump), so "restored" means bit for bit on the device.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import subprocess
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from deployer.execute.device import apply_device
from deployer.execute.session import ApplyOptions
from deployer.profile import load_profile
from deployer.recipe.loader import load_recipe
from deployer.testing.simulator import Simulator, SimulatorThread
from deployer.transport.clients import parse_url
from tests.helpers import cli, umodbus_server

pytestmark = pytest.mark.timeout(120)

# Two profiles of one register layout with different resolutions: A (0.01 s) and B (0.1 s).
PROFILE = """profile: {id}
parameters:
  accel: {{register: 0x100, type: uint32, unit: s, scale: {scale}, min: 0, max: {max}}}
  decel: {{register: 0x102, type: uint32, unit: s, scale: {scale}, min: 0, max: {max}}}
  mode: {{register: 0x104, type: uint16, values: {{ramp: 0, coast: 1}}}}
  gain: {{register: 0x105, type: float32}}
"""


@pytest.fixture
def layout(tmp_path: Path) -> dict[str, Path]:
    """profiles/ (A, B and the devices' own wide-range truth), recipes/ elsewhere, an inventory elsewhere."""
    prof = tmp_path / "profiles"
    prof.mkdir()
    (prof / "a.yaml").write_text(PROFILE.format(id="drive-a", scale=0.01, max=6000))
    (prof / "b.yaml").write_text(PROFILE.format(id="drive-b", scale=0.1, max=60000))
    # what the devices accept: factory values beyond the documented range included
    (prof / "device.yaml").write_text(
        PROFILE.format(id="device", scale=1, max=4294967295).replace(
            "gain: {register: 0x105, type: float32}", "gain: {register: 0x105, type: uint32}"
        )
    )  # NaN too
    rec = tmp_path / "recipes" / "line"
    rec.mkdir(parents=True)
    (rec / "r.yaml").write_text(
        "recipe: line\nprofile: ../../profiles/a.yaml\n"
        "parameters:\n  accel: 10 s\n  decel: 12 s\n  mode: coast\n  gain: 2.5\n"
    )
    return {"profiles": prof, "recipe": rec / "r.yaml", "root": tmp_path}


@pytest.fixture
def devices(layout: dict[str, Path]) -> Iterator[list[Simulator]]:
    truth = load_profile(layout["profiles"] / "device.yaml")
    with ExitStack() as stack:
        yield [stack.enter_context(SimulatorThread(truth)) for _ in range(3)]


# device states before the fleet apply: raw 300000 in accel (3000 s in A, 30000 s in B); the first
# device also holds 700000 (7000 s in A: beyond A's documented 6000 s) and a NaN gain
BEFORE = [
    {"accel": (4, 0x93E0), "decel": (0x000A, 0xAE60), "mode": (0,), "gain": (0x7FC0, 0)},
    {"accel": (4, 0x93E0), "decel": (0, 500), "mode": (1,), "gain": (0x3F80, 0)},
    {"accel": (4, 0x93E0), "decel": (0, 7), "mode": (0,), "gain": (0x4000, 0)},
]


def _set(sim: Simulator, state: dict[str, tuple[int, ...]]) -> dict[int, int]:
    for name, regs in state.items():
        sim.write(name, regs)
    return dict(sim.registers())


def _state(sim: Simulator, path: Path) -> dict[str, int]:
    """The device's registers from the simulator's own state dump."""
    sim.dump_state(str(path))
    units: dict[str, dict[str, int]] = json.loads(path.read_text())["units"]
    return units["1"]


def test_fleet_apply_then_rollback_each_snapshot_from_elsewhere(
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    layout: dict[str, Path],
    devices: list[Simulator],
) -> None:
    root = layout["root"]
    before = [
        _state_after_set(s, b, root / f"before{i}.json") for i, (s, b) in enumerate(zip(devices, BEFORE, strict=True))
    ]
    inv = root / "site" / "inventory.yaml"
    inv.parent.mkdir()
    inv.write_text(
        "devices:\n"
        f"  drive-a: {{url: '{devices[0].url}', unit: 1}}\n"
        f"  drive-b: {{url: '{devices[1].url}', unit: 1, profile: ../profiles/b.yaml}}\n"
        f"  drive-o: {{url: '{devices[2].url}', unit: 1, parameters: {{decel: 20 s}}}}\n"
    )
    work1 = root / "work1"
    work1.mkdir()
    monkeypatch.chdir(work1)
    code, out, err = cli(
        capsys,
        "apply",
        str(os.path.relpath(layout["recipe"], work1)),
        "--inventory",
        str(os.path.relpath(inv, work1)),
        "--yes",
        "--state-dir",
        "state",
        "--report",
        "run.json",
    )
    assert code == 0, out + err
    report = json.loads((work1 / "run.json").read_text())
    by_name = {d["name"]: d for d in report["devices"]}
    # the profile used per device is one well-defined thing, in the report and in the snapshot
    assert by_name["drive-b"]["profile_ref"] == str(layout["profiles"] / "b.yaml")
    assert by_name["drive-a"]["profile_ref"] == by_name["drive-o"]["profile_ref"] == str(layout["profiles"] / "a.yaml")
    snap_b = Path(by_name["drive-b"]["snapshot"])
    assert snap_b.is_absolute()
    text_b = snap_b.read_text()
    assert f"profile: {json.dumps(str(layout['profiles'] / 'b.yaml'))}" in text_b and "accel: 30000 s" in text_b
    assert "accel: [4, 37856]" in text_b  # the raw registers beside the engineering values
    text_a = Path(by_name["drive-a"]["snapshot"]).read_text()
    assert "decel: {raw: 700000}" in text_a  # outside A's range: raw, not dropped
    assert all(_state(s, root / "mid.json") != b for s, b in zip(devices, before, strict=True))

    # roll back each device from its own snapshot, from a third working directory
    work3 = root / "elsewhere" / "work3"
    work3.mkdir(parents=True)
    monkeypatch.chdir(work3)
    for name in ("drive-a", "drive-b", "drive-o"):
        code, out, err = cli(capsys, "rollback", by_name[name]["snapshot"], "--yes", "--state-dir", "st3")
        assert code == 0, (name, out, err)
    for i, s in enumerate(devices):
        assert _state(s, root / f"after{i}.json") == before[i], f"device {i} not restored bit for bit"


def _state_after_set(sim: Simulator, state: dict[str, tuple[int, ...]], path: Path) -> dict[str, int]:
    _set(sim, state)
    return _state(sim, path)


def test_rollback_report_restores_every_device_of_a_run(
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    layout: dict[str, Path],
    devices: list[Simulator],
) -> None:
    root = layout["root"]
    before = [_state_after_set(s, b, root / f"b{i}.json") for i, (s, b) in enumerate(zip(devices, BEFORE, strict=True))]
    inv = root / "inventory.yaml"
    inv.write_text(
        "devices:\n"
        + "".join(
            f"  d{i}: {{url: '{s.url}', profile: profiles/{'b' if i == 1 else 'a'}.yaml}}\n"
            for i, s in enumerate(devices)
        )
    )
    monkeypatch.chdir(root)
    code, _, err = cli(
        capsys,
        "apply",
        str(layout["recipe"]),
        "--inventory",
        str(inv),
        "--yes",
        "--state-dir",
        "s",
        "--report",
        "run.json",
    )
    assert code == 0, err
    monkeypatch.chdir(layout["profiles"])
    code, out, err = cli(
        capsys,
        "rollback",
        "--report",
        str(root / "run.json"),
        "--yes",
        "--state-dir",
        "s2",
        "--save-report",
        str(root / "undo.json"),
        "--json",
    )
    assert code == 0, out + err
    undo = json.loads((root / "undo.json").read_text())
    assert [d["name"] for d in undo["devices"]] == ["d0", "d1", "d2"]
    for i, s in enumerate(devices):
        assert _state(s, root / f"a{i}.json") == before[i]


def test_changed_profile_is_refused_then_forced(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, layout: dict[str, Path], devices: list[Simulator]
) -> None:
    sim = devices[0]
    before = _state_after_set(sim, BEFORE[1], tmp_path / "b.json")
    url = sim.url
    code, _, err = cli(
        capsys, "apply", str(layout["recipe"]), "--device", url, "--yes", "--state-dir", str(tmp_path / "s"), "--json"
    )
    assert code == 0, err
    snap = next((tmp_path / "s" / "snapshots").iterdir())
    # someone edits the profile afterwards: A's resolution becomes 0.1 s
    a = layout["profiles"] / "a.yaml"
    a.write_text(a.read_text().replace("scale: 0.01", "scale: 0.1"))
    requests = len(sim.log)
    code, out, err = cli(capsys, "rollback", str(snap), "--yes", "--state-dir", str(tmp_path / "s"))
    assert code == 1, out + err
    assert "changed since this snapshot was taken" in err and "--force" in err
    assert len(sim.log) == requests  # nothing sent
    code, out, err = cli(capsys, "rollback", str(snap), "--yes", "--force", "--state-dir", str(tmp_path / "s"))
    assert code == 0, out + err
    assert _state(sim, tmp_path / "after.json") == before  # the recorded raw registers, not re-scaled values


def test_snapshot_restores_only_where_it_was_taken(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, layout: dict[str, Path], devices: list[Simulator]
) -> None:
    first, other = devices[0], devices[1]
    _set(first, BEFORE[1])
    code, _, err = cli(
        capsys, "apply", str(layout["recipe"]), "--device", first.url, "--yes", "--state-dir", str(tmp_path / "s")
    )
    assert code == 0, err
    snap = str(next((tmp_path / "s" / "snapshots").iterdir()))
    other_log = len(other.log)
    inv = tmp_path / "inv.yaml"
    inv.write_text(f"devices:\n  x: {{url: '{other.url}'}}\n  y: {{url: '{first.url}'}}\n")
    code, _, err = cli(
        capsys, "rollback", snap, "--inventory", str(inv), "--limit", "x,y", "--yes", "--state-dir", str(tmp_path / "s")
    )
    assert code == 1 and "rollback --from-report REPORT.json" in err
    # another device named explicitly: without a terminal it is not done without its own consent
    code, _, err = cli(capsys, "rollback", snap, "--device", other.url, "--state-dir", str(tmp_path / "s"))
    assert code == 1 and "--to-other-device" in err
    # --yes (do not ask) is not that consent
    code, _, err = cli(capsys, "rollback", snap, "--device", other.url, "--yes", "--state-dir", str(tmp_path / "s"))
    assert code == 1 and "was taken from" in err and "needs --to-other-device" in err and "nothing was sent" in err
    assert len(other.log) == other_log
    # with --to-other-device it goes there, saying so
    code, _, err = cli(
        capsys,
        "rollback",
        snap,
        "--device",
        other.url,
        "--yes",
        "--to-other-device",
        "--state-dir",
        str(tmp_path / "s"),
    )
    err = " ".join(err.split())  # the console wraps long lines (a long state folder's path: Windows')
    assert code == 0 and "was taken from" in err and "restoring it there" in err
    assert any(e.function == 16 for e in other.log[other_log:])


def test_rollback_to_another_device_asks_on_a_terminal(
    tmp_path: Path, layout: dict[str, Path], devices: list[Simulator]
) -> None:
    from tests.test_cli import _run_on_a_terminal

    first, other = devices[0], devices[1]
    code, _, _ = _run(
        ["apply", str(layout["recipe"]), "--device", first.url, "--yes", "--state-dir", str(tmp_path / "s")]
    )
    assert code == 0
    snap = str(next((tmp_path / "s" / "snapshots").iterdir()))
    other_log = len(other.log)
    code, out = _run_on_a_terminal(
        ["rollback", snap, "--device", other.url, "--state-dir", str(tmp_path / "s")], b"n\n", prompt=b"other device?"
    )
    assert code == 1 and "was taken from" in out, out
    assert len(other.log) == other_log


def _run(args: list[str]) -> tuple[int, str, str]:
    import sys

    p = subprocess.run([sys.executable, "-m", "deployer", *args], capture_output=True, text=True, timeout=60)
    return p.returncode, p.stdout, p.stderr


# ---- exact rollback: a property over random device states -------------------------------------

WIDE = """profile: wide
parameters:
  a: {register: 10, type: uint16}
  b: {register: 11, type: int32}
  c: {register: 13, type: uint32}
  d: {register: 15, type: int16}
  e: {register: 16, type: uint32}
"""  # the device takes any bits in e (a NaN included); the profile below calls it a float
NARROW = """profile: narrow
parameters:
  a: {register: 10, type: uint16, min: 0, max: 100, values: {off: 0}}
  b: {register: 11, type: int32, scale: 0.1, unit: s, min: -50, max: 50}
  c: {register: 13, type: uint32, scale: 0.01, unit: mm, min: 0, max: 1000}
  d: {register: 15, type: int16, offset: -40, unit: degC, min: -40, max: 150}
  e: {register: 16, type: float32, min: 0, max: 10}
"""


@pytest.fixture(scope="module")
def wide_device(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Simulator, Path]]:
    d = tmp_path_factory.mktemp("exact")
    (d / "wide.yaml").write_text(WIDE)
    (d / "narrow.yaml").write_text(NARROW)
    with SimulatorThread(load_profile(d / "wide.yaml")) as sim:
        yield sim, d


words = st.integers(0, 0xFFFF)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    state=st.fixed_dictionaries(
        {
            "a": st.tuples(words),
            "b": st.tuples(words, words),
            "c": st.tuples(words, words),
            "d": st.tuples(words),
            "e": st.tuples(words, words),
        }
    ),
    new=st.fixed_dictionaries(
        {},
        optional={
            "a": st.integers(0, 100).map(str),
            "b": st.integers(-500, 500).map(lambda x: f"{x / 10} s"),
            "c": st.integers(0, 10000).map(lambda x: f"{x * 10} um"),
            "d": st.integers(-40, 150).map(lambda x: f"{x} degC"),
            "e": st.sampled_from(["0.5", "2.25", "10"]),
        },
    ),
)
def test_apply_then_rollback_leaves_the_device_bit_for_bit(
    wide_device: tuple[Simulator, Path], state: dict[str, tuple[int, ...]], new: dict[str, str]
) -> None:
    """Whatever the device held (out-of-range factory values and NaNs included), apply then rollback restores it."""
    sim, d = wide_device
    _set(sim, state)
    before = dict(sim.registers())
    recipe = d / "r.yaml"
    body = "".join(f"  {k}: {v}\n" for k, v in new.items())
    recipe.write_text(f"recipe: r\nprofile: narrow.yaml\nparameters:{' {}' if not body else ''}\n{body}")
    state_dir = d / "state"
    shutil.rmtree(state_dir, ignore_errors=True)
    url = parse_url(sim.url)
    opts = ApplyOptions(state_dir=str(state_dir), backoff=0.01)
    res = asyncio.run(apply_device(load_recipe(recipe), url, 1, options=opts))
    assert res.status == "ok", res
    if res.snapshot is None:  # nothing to change: nothing written
        assert dict(sim.registers()) == before
        return
    back = asyncio.run(apply_device(load_recipe(res.snapshot), url, 1, options=opts))
    assert back.status == "ok", back
    assert dict(sim.registers()) == before


def test_out_of_range_values_roll_back_on_a_device_we_did_not_write(tmp_path: Path) -> None:
    """umodbus as the device: what it held beyond the profile's range comes back exactly."""
    (tmp_path / "narrow.yaml").write_text(NARROW)
    store = {10: 500, 11: 0x8000, 12: 1, 13: 0x0007, 14: 0x0007, 15: 0x7FFF, 16: 0xFF80, 17: 0}
    held = dict(store)
    (tmp_path / "r.yaml").write_text(
        "recipe: r\nprofile: narrow.yaml\nparameters:\n  a: 7\n  b: 1 s\n  c: 5 mm\n  d: 20 degC\n  e: 1\n"
    )
    with umodbus_server(store) as port:
        url = parse_url(f"tcp://127.0.0.1:{port}")
        opts = ApplyOptions(state_dir=str(tmp_path / "s"), backoff=0.01)
        res = asyncio.run(apply_device(load_recipe(tmp_path / "r.yaml"), url, 1, options=opts))
        assert res.status == "ok" and store != held
        assert res.snapshot is not None
        text = Path(res.snapshot).read_text()
        assert "a: {raw: 500}" in text and "c: {raw: 458759}" in text
        back = asyncio.run(apply_device(load_recipe(res.snapshot), url, 1, options=opts))
        assert back.status == "ok", back
    assert store == held
    mbpoll = shutil.which("mbpoll")
    if mbpoll is None:
        return
    # and read back by libmodbus too (mbpoll), from the simulator that held the same values
    (tmp_path / "wide.yaml").write_text(WIDE)
    with SimulatorThread(load_profile(tmp_path / "wide.yaml")) as sim:
        for name, p in ((n, sim.profile.parameter(n)) for n in "abcde"):
            sim.write(name, [held[a] for a in range(p.address, p.end)])
        url = parse_url(sim.url)
        res = asyncio.run(apply_device(load_recipe(tmp_path / "r.yaml"), url, 1, options=opts))
        assert res.snapshot is not None
        back = asyncio.run(apply_device(load_recipe(res.snapshot), url, 1, options=opts))
        assert back.status == "ok"
        sim_port = sim.url.rsplit(":", 1)[1]
        out = subprocess.run(
            [mbpoll, "-m", "tcp", "-p", sim_port, "-a", "1", "-0", "-r", "10", "-c", "8", "-t", "4", "-1", "127.0.0.1"],
            capture_output=True,
            text=True,
            timeout=20,
        )
        assert out.returncode == 0, out.stderr
        for a, v in held.items():
            assert f"[{a}]: \t{v if v < 0x8000 else v - 0x10000}" in out.stdout or f"[{a}]: \t{v}" in out.stdout, (
                a,
                v,
                out.stdout,
            )


def test_edited_snapshot_is_refused(tmp_path: Path, devices: list[Simulator], layout: dict[str, Path]) -> None:
    sim = devices[0]
    _set(sim, BEFORE[1])
    url = parse_url(sim.url)
    res = asyncio.run(
        apply_device(load_recipe(layout["recipe"]), url, 1, options=ApplyOptions(state_dir=str(tmp_path / "s")))
    )
    assert res.snapshot is not None
    snap = Path(res.snapshot)
    snap.write_text(snap.read_text().replace("  accel: 3000 s", "  accel: 12 s"))
    from deployer.errors import InputError

    with pytest.raises(InputError, match="does not match the registers the snapshot recorded"):
        load_recipe(snap)


def test_last_identity_lists_the_snapshot_folder_once_for_a_fleet(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from deployer.state import snapshot

    folder = tmp_path / "snapshots"
    folder.mkdir()
    for i in range(50):  # devices d0..d49, two snapshots each; d7's newer one recorded an identity
        (folder / f"d{i}-20261101T000000Z.yaml").write_text('snapshot:\n  identity: {"vendor": "OLD"}\n')
        (folder / f"d{i}-20261102T000000Z.yaml").write_text("snapshot:\n  taken: x\nparameters: {}\n")
    (folder / "d7-20261103T000000Z-2.yaml").write_text('snapshot:\n  identity: {"vendor": "ACME"}\n')
    listed: list[str] = []
    real = os.listdir

    def listdir(p: str) -> list[str]:
        listed.append(str(p))
        return real(p)

    monkeypatch.setattr(os, "listdir", listdir)
    monkeypatch.setattr(snapshot, "_FILES", {})
    found = {i: snapshot.last_identity(str(tmp_path), f"d{i}") for i in range(60)}
    assert listed == [str(folder)]  # once, not once per device
    assert found[7] == (str(folder / "d7-20261103T000000Z-2.yaml"), {"vendor": "ACME"})
    assert found[3] == (str(folder / "d3-20261101T000000Z.yaml"), {"vendor": "OLD"}) and found[55] is None
    newer = folder / "d3-20261104T000000Z.yaml"  # this process writes a newer snapshot of d3
    newer.write_text('snapshot:\n  identity: {"vendor": "NEW"}\n')
    snapshot.written(str(newer))
    assert snapshot.last_identity(str(tmp_path), "d3") == (str(newer), {"vendor": "NEW"}) and len(listed) == 1
