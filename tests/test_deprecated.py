"""The names the Python API exported before it became 30 still work for one release, each with a
DeprecationWarning naming what stands for it now; CHANGELOG.md lists every one with its replacement."""

from __future__ import annotations

import importlib
import re
import warnings
from pathlib import Path

import pytest

import deployer
from deployer import api
from deployer.api.deprecated import REMOVED, replacement
from deployer.testing.simulator import Simulator
from tests.helpers import Simulators

ROOT = Path(__file__).resolve().parent.parent
PROFILE = deployer.load_profile("example-inverter")


def _served(module: object, name: str) -> object:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = getattr(module, name)
    assert [w.category for w in caught] == [DeprecationWarning], name
    message = str(caught[0].message)
    assert message.startswith(f"deployer.{name} is deprecated and goes in the next release; "), message
    assert replacement(name) in message, message
    assert caught[0].filename == __file__, (name, caught[0].filename)  # the caller's line, not ours
    return got


@pytest.mark.parametrize("name", sorted(REMOVED))
def test_every_removed_name_still_works_with_a_warning_naming_its_replacement(name: str) -> None:
    module, _, attr = REMOVED[name][0].partition(":")
    there = getattr(importlib.import_module(module), attr)
    assert _served(deployer, name) is there
    assert _served(api, name) is there
    assert name not in api.__all__ and name not in dir(deployer)


def test_the_from_import_of_a_removed_name_warns_at_the_import() -> None:
    with pytest.warns(DeprecationWarning, match=r"deployer\.plan_to_json is deprecated .*use Plan\.to_json\(\)"):
        from deployer.api import plan_to_json  # noqa: F401


def test_a_name_never_exported_is_no_attribute() -> None:
    with pytest.raises(AttributeError, match="has no attribute 'nope'"):
        deployer.nope  # noqa: B018
    with pytest.raises(AttributeError, match="has no attribute 'nope'"):
        api.nope  # noqa: B018


def test_the_changelog_lists_every_removed_name_with_its_replacement() -> None:
    text = (ROOT / "CHANGELOG.md").read_text()
    unreleased = text[text.index("## [Unreleased]") : text.index("\n## [", text.index("## [Unreleased]") + 5)]
    deprecated = unreleased[unreleased.index("### Deprecated") :]
    rows = dict(re.findall(r"^  \| `(\w+)` \| (.+) \|$", deprecated, re.M))
    assert sorted(rows) == sorted(REMOVED)
    for name, said in rows.items():
        words = re.sub(r"[`]", "", said)
        wanted = replacement(name)
        assert (
            ("command line" in words)
            if wanted.startswith("no replacement")
            else (wanted.split(" (")[0] in words or name in words)
        ), (name, said)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_the_old_calls_still_run(tmp_path: Path) -> None:
    """The removed functions as callers used them: the fleet calls with ApplyOptions, the jobs, the prepared runs."""
    import asyncio

    old = deployer.api
    recipe = deployer.recipe_from("example-inverter", {"F07": "10 s"})
    with Simulators([Simulator(PROFILE) for _ in range(2)]) as sims:
        inv = old.inventory_from([{"name": f"d{i}", "url": s.url} for i, s in enumerate(sims, 1)])
        jobs = old.fleet_jobs(recipe, inv)
        assert [j.name for j in jobs] == ["d1", "d2"]
        plans = old.plan_fleet(jobs, state_dir=str(tmp_path))
        assert all(p.writes for p in plans.values())
        values = old.read_fleet(old.read_jobs(jobs))
        assert old.diff_values(recipe, values["d1"])[0].name == "F07"
        options = old.safe_options(old.ApplyOptions(state_dir=str(tmp_path)), soak=None)
        report = old.apply_fleet(recipe, inv, parallel=2, options=options)
        assert report.exit_code == 0 and all(s.read("F07") == (0, 1000) for s in sims)
        report = old.run_fleet(jobs, options=options)
        assert report.exit_code == 0
        one = asyncio.run(old.apply_async(recipe, sims[0].url, options=options))
        assert one.devices[0].status == "ok" and asyncio.run(old.diff_async(recipe, sims[0].url)) == []
        request = old.RunRequest(None, inventory=None, device=sims[1].url, state_dir=str(tmp_path))
        with pytest.raises(deployer.UsageError, match="pass RECIPE"):
            old.prepare_run(request)
        assert old.run_status(str(tmp_path)).runs == []
        plan = deployer.plan(recipe, sims[0].url, state_dir=tmp_path)
        assert old.plan_to_json(plan) == plan.to_json()
        assert len(old.plan_frames(plan, "rtu")) == len(plan.steps)
        assert "F07: 10 s" in old.pulled_recipe(PROFILE, {"F07": (0, 1000)}, name="p", url=sims[0].url, unit=1)
