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


@pytest.mark.parametrize(
    ("call", "words"),
    [
        (
            lambda url: deployer.load_recipe(123),  # type: ignore[arg-type]
            "load_recipe takes a path (str or os.PathLike), got int 123",
        ),
        (
            lambda url: deployer.recipe_from("example-inverter", "F07=10 s"),  # type: ignore[arg-type]
            "takes the parameters as a mapping (name -> value), got str 'F07=10 s'",
        ),
        (
            lambda url: deployer.recipe_from(42, {}),  # type: ignore[arg-type]
            "takes a profile id, a profile file or a Profile, got int 42",
        ),
        (
            lambda url: deployer.apply("recipe.yaml", url),  # type: ignore[arg-type]
            "apply takes a Recipe (load it first: deployer.load_recipe(path)), got str 'recipe.yaml'",
        ),
        (lambda url: deployer.plan({"F07": "10 s"}, url), "plan takes a Recipe, got dict"),  # type: ignore[call-overload]
        (lambda url: deployer.diff(None, url), "diff takes a Recipe, got NoneType None"),
        (
            lambda url: deployer.plan(recipe(), 12),  # type: ignore[call-overload]
            "device_url takes a URL such as tcp://10.0.0.11:502, got int 12",
        ),
        (
            lambda url: deployer.apply(recipe(), url, write_all="yes"),  # type: ignore[arg-type]
            "write_all takes True or False, got str 'yes'",
        ),
        (
            lambda url: deployer.apply(recipe(), url, on_error="ignore"),  # type: ignore[arg-type]
            "on_error must be 'continue' or 'stop', got str 'ignore'",
        ),
        (
            lambda url: deployer.apply(recipe(), url, batch_by="line"),  # type: ignore[arg-type]
            "batch_by must be 'profile' or 'group', got str 'line'",
        ),
        (
            lambda url: deployer.apply(recipe(), url, state_dir=None),  # type: ignore[arg-type]
            "apply takes state_dir as a path (str or os.PathLike), got NoneType None",
        ),
        (
            lambda url: deployer.apply(recipe(), url, on_done="print"),  # type: ignore[arg-type]
            "on_done takes a function, got str 'print'",
        ),
        (
            lambda url: deployer.pull("example-inverter", url, names="F07"),
            "pull takes names as a list of parameter names, got str 'F07'",
        ),
        (
            lambda url: deployer.pull("example-inverter", url, names=["F99"]),
            "profile example-inverter has no parameter 'F99'",
        ),
        (
            lambda url: deployer.pull(3.5, url),  # type: ignore[call-overload]
            "pull takes a profile id, a profile file or a Profile, got float 3.5",
        ),
        (
            lambda url: deployer.load_inventory({"d1": url}),  # type: ignore[arg-type]
            "load_inventory takes an inventory file or a list of devices (mappings), got dict",
        ),
        (
            lambda url: deployer.load_inventory(["d1"]),  # type: ignore[list-item]
            "load_inventory: device 1 of the list is not a mapping (name, url ...), got str 'd1'",
        ),
        (
            lambda url: deployer.load_report(7),  # type: ignore[arg-type]
            "load_report takes the report file as a path (str or os.PathLike), got int 7",
        ),
        (
            lambda url: deployer.rollback(5),  # type: ignore[arg-type]
            "rollback takes a snapshot file, a report file or a list of report files, got int 5",
        ),
        (
            lambda url: deployer.plan(recipe(), url, limit="d1"),  # type: ignore[call-overload]
            "limit selects devices of an inventory: pass inventory too",
        ),
        (
            lambda url: deployer.plan(recipe(), url, inventory=[{"name": "d1", "url": url}]),
            "device and inventory exclude each other",
        ),
        (lambda url: deployer.apply(recipe(), url, unit=-1), "unit must be from 1 to 247 (0 is broadcast), got -1"),
        (lambda url: deployer.apply(recipe(), url, unit=300), "unit must be from 1 to 247 (0 is broadcast), got 300"),
        (lambda url: deployer.apply(recipe(), url, unit="1"), "unit must be an int from 1 to 247"),  # type: ignore[arg-type]
        (lambda url: deployer.apply(recipe(), url, unit=True), "unit must be an int from 1 to 247"),
        (lambda url: deployer.pull("example-inverter", url, unit=1000), "got 1000"),
        (lambda url: deployer.plan(recipe(), url, unit=-3, offline=True), "got -3"),
    ],
)
def test_wrong_arguments_are_usage_errors_and_send_nothing(call: object, words: str) -> None:
    with Simulators([Simulator(PROFILE)]) as (sim,):
        with pytest.raises(deployer.UsageError) as e:
            call(sim.url)  # type: ignore[operator]
        assert words in str(e.value)
        assert sim.log == []


def test_unit_zero_refusal_speaks_to_api_callers(tmp_path: Path) -> None:
    with Simulators([Simulator(PROFILE)]) as (sim,):
        with pytest.raises(deployer.UsageError, match=r"unit 0 is broadcast .*; pass allow_broadcast=True to send it"):
            deployer.apply(recipe(), sim.url, unit=0, state_dir=tmp_path)
        assert sim.log == []


def test_a_sync_call_inside_a_running_loop_says_to_await_its_twin(tmp_path: Path) -> None:
    async def inside() -> None:
        with pytest.raises(deployer.UsageError, match=r"await deployer.aio.plan\(\)"):
            deployer.plan(recipe(), offline=True)
        plan = await deployer.aio.plan(recipe(), offline=True)
        assert [w.address for w in plan.writes] == [PROFILE.parameter("F07").address]

    asyncio.run(inside())


# ---- one set of bounds (deployer.LIMITS) for the API, the command line and Ansible (#28 item 15) ----

INVENTORY = [{"name": "d1", "url": "tcp://127.0.0.1:1"}]


@pytest.mark.parametrize(
    ("call", "words"),
    [
        (
            lambda url: deployer.plan(recipe(), url, timeout=-1),
            "timeout must be more than 0 and at most 600 seconds, got -1",
        ),
        (lambda url: deployer.diff(recipe(), url, timeout=float("nan")), "timeout must be more than 0"),
        (
            lambda url: deployer.pull("example-inverter", url, timeout=0),
            "timeout must be more than 0 and at most 600 seconds, got 0",
        ),
        (lambda url: deployer.apply(recipe(), url, timeout=float("inf")), "got inf"),
        (lambda url: deployer.plan(recipe(), url, retries=-1), "retries must be from 0 to 20, got -1"),
        (
            lambda url: deployer.apply(recipe(), url, retries="3"),  # type: ignore[arg-type]
            "retries must be a whole number from 0 to 20, got str '3'",
        ),
        (lambda url: deployer.rollback("snap.yaml", retries=10**9), "retries must be from 0 to 20, got 1000000000"),
        (lambda url: deployer.apply(recipe(), url, soak=-5), "soak must be more than 0 and at most a week, got -5"),
        (lambda url: deployer.apply(recipe(), url, soak="0s"), "soak must be more than 0"),
        (
            lambda url: deployer.apply(recipe(), url, health_interval=0, soak="1s"),
            "health_interval must be from 0.1 to 3600 seconds, got 0",
        ),
        (
            lambda url: deployer.apply(recipe(), url, confirm_within=[1]),  # type: ignore[arg-type]
            'confirm_within takes a duration such as "30s" or a number of seconds, got list [1]',
        ),
        (lambda url: deployer.apply(recipe(), url, soak=-1.0), "soak must be more than 0"),
        (
            lambda url: deployer.apply(recipe(), url, lock_timeout=-1),
            "lock_timeout must be from 0 seconds to a week, got -1",
        ),
        (lambda url: deployer.apply(recipe(), url, workers=-1), "workers must be from 0"),
        (
            lambda url: deployer.apply(recipe(), url, options={"soak": 1}),  # type: ignore[call-arg]
            "ApplyOptions is gone: its fields are apply's keyword arguments",
        ),
        (
            lambda url: deployer.recipe_from("example-inverter", {1: 2}),  # type: ignore[dict-item]
            "recipe_from takes parameter names as str keys, got int 1",
        ),
        (
            lambda url: deployer.confirm(state_dir=None),  # type: ignore[arg-type]
            "confirm takes state_dir as a path (str or os.PathLike), got NoneType None",
        ),
        (
            lambda url: deployer.confirm(42),  # type: ignore[arg-type]
            "confirm takes the run id as a str, got int 42",
        ),
        (
            lambda url: deployer.apply(recipe(), inventory={"d1": url}),  # type: ignore[arg-type]
            "apply takes the inventory as a file, a list of devices or an Inventory "
            "(deployer.load_inventory(...)), got dict",
        ),
        (
            lambda url: deployer.apply(
                recipe(), inventory=deployer.load_inventory([{"name": "d1", "url": url}]), parallel=0
            ),
            "parallel must be from 1 to 1024, got 0",
        ),
        (
            lambda url: deployer.apply(recipe(), inventory=[{"name": "d1", "url": url}], parallel=1025),
            "parallel must be from 1 to 1024, got 1025",
        ),
        (
            lambda url: deployer.plan(recipe(), inventory=[{"name": "d1", "url": url}], timeout=700),
            "timeout must be more than 0 and at most 600 seconds, got 700",
        ),
        (
            lambda url: deployer.pull("example-inverter", inventory=[{"name": "d1", "url": url}], parallel=True),
            "parallel must be a whole number from 1 to 1024",
        ),
        (
            lambda url: deployer.plan(recipe(), inventory=[{"name": "d1", "url": url}], parallel=2000),
            "parallel must be from 1 to 1024, got 2000",
        ),
        (lambda url: deployer.diff(recipe(), inventory=[{"name": "d1", "url": url}], limit="nobody"), "nobody"),
    ],
)
def test_out_of_bounds_arguments_are_usage_errors_that_name_them(call: object, words: str) -> None:
    with Simulators([Simulator(PROFILE)]) as (sim,):
        with pytest.raises(deployer.UsageError) as e:
            call(sim.url)  # type: ignore[operator]
        assert words in str(e.value)
        assert sim.log == []


def test_the_bounds_hold_at_their_edges() -> None:
    at_edges = deployer.plan(recipe(), "tcp://h:502", timeout=600, retries=20, offline=True)
    assert at_edges.device.url == "tcp://h:502?retries=20&timeout=600"  # kept: apply of the plan talks to it so
    assert deployer.plan(recipe(), "tcp://h:502", timeout=0.001, retries=0, offline=True).writes
    assert deployer.LIMITS.parallel.check(1024, "parallel") == 1024
    with pytest.raises(deployer.UsageError, match="health_interval must be from 0.1 to 3600 seconds, got 0.05"):
        deployer.apply(recipe(), "tcp://h:502", health_interval="50ms")


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--parallel", "1025"], "1<=x<=1024"),
        (["--parallel", "0"], "1<=x<=1024"),
        (["--timeout", "0"], "0<x<=600"),
        (["--timeout", "601"], "0<x<=600"),
        (["--retries", "21"], "0<=x<=20"),
        (["--soak", "0s", "--health-interval", "1s"], "'0s' must be more than 0"),
        (["--soak", "1s", "--health-interval", "0"], "'0' must be from 0.1 to 3600 seconds, got 0"),
        (["--confirm-within", "0"], "'0' must be more than 0"),
    ],
)
def test_the_command_line_refuses_what_the_api_refuses(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, args: list[str], words: str
) -> None:
    from tests.helpers import cli

    with Simulators([Simulator(PROFILE)]) as (sim,):
        r = tmp_path / "r.yaml"
        r.write_text(f"recipe: r\nprofile: example-inverter\ndevice: {{url: '{sim.url}'}}\nparameters:\n  F07: 10 s\n")
        code, _, err = cli(capsys, "apply", str(r), "--yes", "--state-dir", str(tmp_path / "s"), *args)
        assert code == 1 and words in err, err
        assert sim.log == []


def test_the_ansible_documentation_states_the_library_bounds() -> None:
    """The collection's options say the ranges deployer.LIMITS checks (its module_utils checks through them)."""
    root = Path(__file__).resolve().parent.parent / "ansible_collections/deployer/modbus/plugins"
    fragment = (root / "doc_fragments/target.py").read_text()
    for key in ("parallel", "retries"):
        assert getattr(deployer.LIMITS, key).text() in fragment, key
    assert deployer.LIMITS.timeout.text().removesuffix(" seconds") in fragment
    common = (root / "module_utils/deployer_common.py").read_text()
    assert "LIMITS" in common and "1024" not in common and "600" not in common
