"""The public surface, pinned (as httpx's tests/test_exported_members.py): a change to it is a decision.

And how every public call takes its arguments: no ``**kwargs`` in a public signature, and a misspelt keyword is a
UsageError naming it and the nearest right one (never a bare TypeError), checked for each callable by
introspection.
"""

from __future__ import annotations

import asyncio
import inspect
import re
import subprocess
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import deployer
import deployer.aio
from deployer import api

PUBLIC = [
    "LIMITS",
    "Agent",
    "DeployerError",
    "DeviceResult",
    "Drift",
    "FleetPlan",
    "InputError",
    "Inventory",
    "Plan",
    "Profile",
    "Recipe",
    "Report",
    "RunInterrupted",
    "StalePlan",
    "Step",
    "TransportError",
    "UsageError",
    "apply",
    "confirm",
    "diff",
    "load_inventory",
    "load_plan",
    "load_profile",
    "load_recipe",
    "load_report",
    "plan",
    "pull",
    "recipe_from",
    "rollback",
    "status",
]
AIO = ["apply", "confirm", "diff", "plan", "pull", "rollback", "status"]
ROOT = Path(__file__).resolve().parent.parent


def test_the_exported_names_are_pinned() -> None:
    assert api.__all__ == PUBLIC  # sorted: constants, classes, then functions
    assert len(api.__all__) <= 30
    assert deployer.__all__ is api.__all__  # one list
    assert deployer.aio.__all__ == AIO


def test_every_exported_name_resolves_from_the_package() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # none of them is a deprecated one
        for name in api.__all__:
            assert getattr(deployer, name) is getattr(api, name), name
    assert set(api.__all__) <= set(dir(deployer)) and set(api.__all__) <= set(dir(api))


def test_the_async_twins_are_the_same_operations() -> None:
    """deployer.aio's coroutines take the arguments their blocking twins take."""
    for name in AIO:
        twin = getattr(deployer.aio, name)
        assert inspect.iscoroutinefunction(twin), name
        assert not inspect.iscoroutinefunction(getattr(deployer, name)), name
        assert inspect.signature(twin) == inspect.signature(getattr(deployer, name)), name


def test_every_exported_function_and_class_is_documented() -> None:
    for name in api.__all__:
        assert inspect.getdoc(getattr(api, name)), name
    for name in AIO:
        assert inspect.getdoc(getattr(deployer.aio, name)), name


def test_functions_that_raise_say_so() -> None:
    """Every public function documents what it raises (a Raises section)."""
    for name in api.__all__:
        obj = getattr(api, name)
        if inspect.isfunction(obj):
            assert "Raises" in (obj.__doc__ or ""), name


def test_exported_errors_are_the_error_tree() -> None:
    from deployer import errors

    for name in api.__all__:
        obj = getattr(api, name)
        if inspect.isclass(obj) and issubclass(obj, BaseException):
            assert obj is getattr(errors, name) and issubclass(obj, errors.DeployerError)
    assert set(errors.__all__) >= {n for n in api.__all__ if n.endswith("Error")}


def test_load_profile_means_one_thing() -> None:
    from deployer import profile

    assert inspect.unwrap(deployer.load_profile) is profile.load_profile
    assert deployer.load_profile("example-inverter").id == "example-inverter"


def test_importing_the_package_does_not_load_the_api() -> None:
    code = (
        "import sys, deployer\nfrom deployer import errors\n"
        "print('deployer.api' in sys.modules, deployer.__version__ != '')"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.split() == ["False", "True"]


# ---- how the public calls take their arguments ------------------------------------------------------------


def _public_callables() -> list[tuple[str, Callable[..., Any]]]:
    """Every public function (deployer's, deployer.aio's) and the Agent client's methods, bound."""
    out = [(f"deployer.{n}", getattr(api, n)) for n in api.__all__ if inspect.isfunction(getattr(api, n))]
    out += [(f"deployer.aio.{n}", getattr(deployer.aio, n)) for n in AIO]
    agent = deployer.Agent("http://127.0.0.1:9")  # nothing is sent: the call is refused first
    out.append(("Agent", deployer.Agent))
    out += [
        (f"Agent.{n}", getattr(agent, n))
        for n, f in inspect.getmembers(deployer.Agent, inspect.isfunction)
        if not n.startswith("_")
    ]
    return out


def _called(f: Callable[..., Any], **kw: Any) -> Any:
    if inspect.iscoroutinefunction(f):
        return asyncio.run(f(**kw))
    got = f(**kw)
    if inspect.isgenerator(got):
        return next(got)
    return got


def test_the_public_callables_are_found() -> None:
    names = {n for n, _ in _public_callables()}
    assert {
        "deployer.apply",
        "deployer.aio.apply",
        "deployer.load_inventory",
        "Agent",
        "Agent.apply",
        "Agent.start_run",
        "Agent.get",
    } <= names
    assert len(names) >= 13 + 7 + 20


def test_no_public_signature_takes_any_keyword() -> None:
    for name, f in _public_callables():
        kinds = {p.kind for p in inspect.signature(f).parameters.values()}
        assert inspect.Parameter.VAR_KEYWORD not in kinds, name


def test_a_misspelt_keyword_is_a_usage_error_naming_the_nearest() -> None:
    """For each public callable and each of its keyword arguments: that keyword misspelt (a letter doubled)."""
    checked = 0
    for name, f in _public_callables():
        params = [
            p for p in inspect.signature(f).parameters.values() if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
        ]
        for p in params:
            typo = p.name + p.name[-1]
            with pytest.raises(deployer.UsageError) as e:
                _called(f, **{typo: 1})
            assert f"no argument {typo!r}; did you mean {p.name!r}?" in str(e.value), (name, str(e.value))
            checked += 1
        with pytest.raises(deployer.UsageError, match="has no argument 'zzzzzz'"):  # nothing near: what it takes
            _called(f, zzzzzz=1)
    assert checked > 100


def test_the_famous_typo() -> None:
    recipe = deployer.recipe_from("example-inverter", {"F07": "10 s"})
    with pytest.raises(
        deployer.UsageError, match=re.escape("deployer.apply() has no argument 'paralel'; did you mean 'parallel'?")
    ):
        deployer.apply(recipe, inventory=[{"name": "d1", "url": "tcp://127.0.0.1:9"}], paralel=4)  # type: ignore[call-arg]


@pytest.mark.parametrize(
    ("call", "words"),
    [
        (lambda: deployer.apply(), "deployer.apply() needs 'what'"),  # type: ignore[call-arg]
        (lambda: deployer.load_recipe(), "deployer.load_recipe() needs 'path'"),  # type: ignore[call-arg]
        (
            lambda: deployer.plan(None, None, None, None),  # type: ignore[call-overload]
            "takes 3 positional arguments (recipe, device and unit), got 4",
        ),
        (
            lambda: deployer.recipe_from("example-inverter", {}, "name"),  # type: ignore[call-arg]
            "takes 2 positional arguments",
        ),
        (lambda: deployer.load_report("r.json", (), profiles=()), "got 'profiles' twice"),  # type: ignore[misc]
        (
            lambda: deployer.apply(None, options=None),  # type: ignore[call-arg]
            "ApplyOptions is gone: its fields are apply's keyword arguments",
        ),
        (
            lambda: deployer.Agent("http://h:1").events(1),  # type: ignore[call-arg]
            "Agent.events() takes 0 positional arguments",
        ),
    ],
)
def test_calls_a_function_cannot_take_are_usage_errors(call: Callable[[], object], words: str) -> None:
    with pytest.raises(deployer.UsageError) as e:
        call()
    assert words in str(e.value)


def test_a_plan_needs_a_recipe() -> None:
    with pytest.raises(deployer.UsageError, match="plan takes a Recipe"):
        deployer.plan()  # type: ignore[call-overload]
