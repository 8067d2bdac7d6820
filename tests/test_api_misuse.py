"""The Python API refuses wrong types and values with a UsageError that says what it takes, before anything is sent."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

import deployer
from deployer.profile import builtin_profile
from deployer.testing.simulator import Simulator
from tests.helpers import Simulators

PROFILE = builtin_profile("example-inverter")


def recipe() -> deployer.Recipe:
    return deployer.recipe_from("example-inverter", {"F07": "10 s"})


@pytest.mark.parametrize(("call", "words"), [
    (lambda url: deployer.load_recipe(123),  # type: ignore[arg-type]
     "load_recipe takes a path (str or os.PathLike), got int 123"),
    (lambda url: deployer.recipe_from("example-inverter", "F07=10 s"),  # type: ignore[arg-type]
     "takes the parameters as a mapping (name -> value), got str 'F07=10 s'"),
    (lambda url: deployer.recipe_from(42, {}),  # type: ignore[arg-type]
     "takes a profile id, a profile file or a Profile, got int 42"),
    (lambda url: deployer.apply("recipe.yaml", url),  # type: ignore[arg-type]
     "apply takes a Recipe (load it first: deployer.load_recipe(path)), got str 'recipe.yaml'"),
    (lambda url: deployer.plan({"F07": "10 s"}, url), "plan takes a Recipe, got dict"),  # type: ignore[arg-type]
    (lambda url: deployer.diff(None, url), "diff takes a Recipe, got NoneType None"),  # type: ignore[arg-type]
    (lambda url: deployer.device_url(None),  # type: ignore[arg-type]
     "device_url takes a URL such as tcp://10.0.0.11:502, got NoneType"),
    (lambda url: deployer.apply(recipe(), url, unit=-1), "unit must be from 1 to 247 (0 is broadcast), got -1"),
    (lambda url: deployer.apply(recipe(), url, unit=300), "unit must be from 1 to 247 (0 is broadcast), got 300"),
    (lambda url: deployer.apply(recipe(), url, unit="1"), "unit must be an int from 1 to 247"),  # type: ignore[arg-type]
    (lambda url: deployer.apply(recipe(), url, unit=True), "unit must be an int from 1 to 247"),
    (lambda url: deployer.pull("example-inverter", url, unit=1000), "got 1000"),
    (lambda url: deployer.plan(recipe(), url, unit=-3, offline=True), "got -3"),
])
def test_wrong_arguments_are_usage_errors_and_send_nothing(call: object, words: str) -> None:
    with Simulators([Simulator(PROFILE)]) as (sim,):
        with pytest.raises(deployer.UsageError) as e:
            call(sim.url)  # type: ignore[operator]
        assert words in str(e.value)
        assert sim.log == []


def test_unit_zero_refusal_speaks_to_api_callers() -> None:
    with Simulators([Simulator(PROFILE)]) as (sim,):
        report = deployer.apply(recipe(), sim.url, unit=0)
        assert report.devices[0].status != "ok"
        assert "ApplyOptions(allow_broadcast=True)" in (report.devices[0].error or "")
        assert sim.log == []


def test_a_sync_call_inside_a_running_loop_says_to_await_its_twin(tmp_path: Path) -> None:
    async def inside() -> None:
        with pytest.raises(deployer.UsageError, match=r"await deployer.plan_async\(\)"):
            deployer.plan(recipe(), offline=True)
        plan = await deployer.plan_async(recipe(), offline=True)
        assert [w.address for w in plan.writes] == [PROFILE.parameter("F07").address]

    asyncio.run(inside())
