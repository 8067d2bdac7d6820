"""limits.max_ascii_chars: a device that counts its frame limit in ASCII characters is planned within it."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from deployer.cli import main
from deployer.planning.frames import request_frame, response_frame
from deployer.planning.model import Target
from deployer.planning.steps import make_plan
from deployer.profile import Limits
from deployer.recipe.loader import load_recipe
from deployer.testing.simulator import SimulatorThread
from tests.helpers import profile_from

pytestmark = pytest.mark.timeout(60)

# 40 contiguous registers: 20 x uint16, then 10 x uint32 (never split)
PROFILE = (
    "profile: ascii-dev\nlimits: {max_ascii_chars: 64}\nparameters:\n"
    + "".join(f"  p{i}: {{register: {i}, type: uint16}}\n" for i in range(20))
    + "".join(f"  d{i}: {{register: {20 + 2 * i}, type: uint32}}\n" for i in range(10))
)
RECIPE = (
    "recipe: r\nprofile: dev.yaml\nparameters:\n"
    + "".join(f"  p{i}: {i + 1}\n" for i in range(20))
    + "".join(f"  d{i}: {70000 + i}\n" for i in range(10))
)


def test_register_counts_from_the_character_limit() -> None:
    assert (Limits(max_ascii_chars=64).write_registers, Limits(max_ascii_chars=64).read_registers) == (11, 13)
    assert (Limits().write_registers, Limits().read_registers) == (123, 125)  # 513 characters: no limit
    assert Limits(max_ascii_chars=23).write_registers == 1  # the smallest FC16 frame
    # the tighter of the two frame limits wins
    assert Limits(max_ascii_chars=64, max_frame_bytes=21).write_registers == 6


def test_ascii_device_with_a_64_character_limit_is_planned_within_it(tmp_path: Path) -> None:
    profile_from(tmp_path, PROFILE)
    (tmp_path / "r.yaml").write_text(RECIPE)
    plan = make_plan(load_recipe(str(tmp_path / "r.yaml")), Target(None, 1, "dev.yaml"))
    for w in plan.writes:
        assert len(request_frame(w, 1, "ascii")) <= 64
        assert len(response_frame(w, 1, "ascii")) <= 64
    for r in plan.reads:
        assert len(request_frame(r, 1, "ascii")) <= 64
        assert len(response_frame(r, 1, "ascii")) <= 64
    # full requests: one more register would not fit (19 + 4 x 12 = 67 characters)
    assert max(w.count for w in plan.writes) == 11
    assert len(request_frame(plan.writes[0], 1, "ascii")) == 63
    # the fewest requests that fit: 20 single registers + 10 pairs in 11-register requests, pairs unsplit
    assert len(plan.writes) == math.ceil(40 / 10) == 4
    assert all(
        not (w.address <= 20 + 2 * i < w.address + w.count < 20 + 2 * i + 2) for w in plan.writes for i in range(10)
    )
    assert [r.count for r in plan.reads] == [13, 13, 12, 2]  # a read does not split a uint32 either


def test_apply_over_an_ascii_line_stays_within_the_limit(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, socat_pair: tuple[str, str]
) -> None:
    a, b = socat_pair
    prof = profile_from(tmp_path, PROFILE)
    (tmp_path / "r.yaml").write_text(RECIPE)
    # the simulator answers exception 03 to any request beyond the profile's limits
    with SimulatorThread(prof, listen=f"ascii://{a}", units=(1,)) as sim:
        with pytest.raises(SystemExit) as exc:
            main(
                [
                    "apply",
                    str(tmp_path / "r.yaml"),
                    "--device",
                    f"ascii://{b}?timeout=1",
                    "--yes",
                    "--json",
                    "--state-dir",
                    str(tmp_path / "s"),
                ]
            )
        out, _ = capsys.readouterr()
        assert exc.value.code == 0, out
        assert sim.read("d9") == (1, 70009 - 65536)
        frames = [bytes.fromhex(e.request_hex) for e in sim.log]  # unit id + PDU as received
    report = json.loads(out)
    assert {p["status"] for p in report["devices"][0]["parameters"]} == {"ok"}
    # ':' + two characters per byte + LRC + CR LF
    assert max(1 + 2 * (len(f) + 1) + 2 for f in frames) <= 64
    assert sum(1 for e in sim.log if e.function == 16) == 4
