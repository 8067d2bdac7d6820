"""One error tree (deployer/errors.py): documented as it is, exit codes by class, no decisions on message text."""

from __future__ import annotations

import ast
import asyncio
import inspect
import re
from pathlib import Path

import pytest

from deployer import errors
from deployer.errors import (
    DeployerError,
)
from deployer.state import lock
from tests.helpers import cli

ROOT = Path(__file__).resolve().parent.parent


def _classes() -> dict[str, type[DeployerError]]:
    return {
        n: c
        for n, c in vars(errors).items()
        if inspect.isclass(c) and issubclass(c, DeployerError) and c.__module__ == errors.__name__
    }


def test_the_documented_tree_is_the_tree() -> None:
    """The drawing in the module's docstring: every class, its parent (by indentation) and its exit code."""
    doc = errors.__doc__ or ""
    drawn = [
        (m.start(1) - len(line) + len(line.lstrip()), m.group(1), int(m.group(2)))
        for line in doc.splitlines()
        if (m := re.search(r"([A-Z]\w+) +(\d)  \S", line))
    ]
    classes = _classes()
    assert [name for _, name, _ in drawn] and {name for _, name, _ in drawn} == set(classes)
    parents: dict[int, str] = {}
    for col, name, code in drawn:
        cls = classes[name]
        assert cls.exit_code == code, name
        parents[col] = name
        above = [parents[c] for c in parents if c < col]
        if above:
            assert classes[above[-1]] in cls.__bases__, f"{name} is drawn under {above[-1]}"
        else:
            assert cls is DeployerError
        for c in [c for c in parents if c > col]:
            del parents[c]
    assert set(errors.__all__) >= set(classes)


@pytest.mark.parametrize("name", sorted(_classes()))
def test_every_error_is_a_deployer_error_with_an_exit_code(name: str) -> None:
    cls = _classes()[name]
    assert issubclass(cls, DeployerError)
    assert cls.exit_code in (errors.EXIT_INVALID, errors.EXIT_UNREACHABLE, errors.EXIT_FAILED)


def test_errors_are_importable_from_deployer_errors_only() -> None:
    """No module hands the errors on (the old paths through transport, session, codec, lock and
    load.diagnostics are gone): an error has one import path, deployer.errors (deployer.api re-exports
    its public ones on purpose)."""
    import importlib

    for mod in (
        "deployer.transport.clients",
        "deployer.transport.urls",
        "deployer.execute.session",
        "deployer.profile.codec",
        "deployer.state.lock",
    ):
        m = importlib.import_module(mod)
        handed_on = [
            n
            for n in errors.__all__
            if n[0].isupper() and n in vars(m) and n not in m.__dict__.get("__all__", ()) and n not in _used_names(m)
        ]
        assert handed_on == [], (mod, handed_on)
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("deployer.load.diagnostics")


def _used_names(module: object) -> set[str]:
    """Names a module's own code uses (an import it needs is not a re-export)."""
    source = Path(module.__file__).read_text()  # type: ignore[attr-defined]
    tree = ast.parse(source)
    return {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)} | {
        n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)
    }


def test_a_codec_error_says_its_kind() -> None:
    from decimal import Decimal

    from deployer.profile import codec

    with pytest.raises(errors.CodecError) as e:
        codec.to_raw(Decimal("1.005"), "uint16", Decimal("0.01"))
    assert e.value.kind == "resolution"
    with pytest.raises(errors.CodecError) as e:
        codec.to_raw(Decimal("70000"), "uint16")
    assert e.value.kind == ""


def _text_decisions(tree: ast.AST) -> list[int]:
    """Lines deciding on an exception's text: ``str(e).startswith(...)``, ``"x" in str(e)``, ``.error.startswith``."""

    def is_str_of_name(node: ast.AST) -> bool:
        return (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Name)
            and node.func.id == "str"
            and len(node.args) == 1
            and isinstance(node.args[0], ast.Name)
        )

    out = []
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr in ("startswith", "endswith")
        ):
            obj = node.func.value
            if is_str_of_name(obj) or (isinstance(obj, ast.Attribute) and obj.attr in ("error", "message")):
                out.append(node.lineno)
        if (
            isinstance(node, ast.Compare)
            and any(isinstance(op, ast.In | ast.NotIn) for op in node.ops)
            and any(is_str_of_name(c) for c in node.comparators)
        ):
            out.append(node.lineno)
    return out


def test_no_decision_is_taken_on_message_text() -> None:
    found = []
    for path in sorted((ROOT / "deployer").rglob("*.py")):
        found += [f"{path.relative_to(ROOT)}:{n}" for n in _text_decisions(ast.parse(path.read_text()))]
    assert found == []


def test_the_text_check_finds_what_it_looks_for() -> None:
    code = (
        'try:\n    pass\nexcept Exception as e:\n    if str(e).startswith("cannot") or "x" in str(e):\n        pass\n'
    )
    assert _text_decisions(ast.parse(code)) == [4, 4]


def test_an_unusable_lock_directory_is_not_waited_for(tmp_path: Path) -> None:
    not_a_dir = tmp_path / "file"
    not_a_dir.write_text("")
    with pytest.raises(errors.Locked) as err:
        asyncio.run(lock.acquire("k", timeout=600, directory=str(not_a_dir)))
    assert err.value.busy is False and "still locked" not in str(err.value)
    assert err.value.exit_code == errors.EXIT_UNREACHABLE


def test_a_held_lock_is_busy(tmp_path: Path) -> None:
    held = lock.try_lock("k", directory=str(tmp_path))
    try:
        with pytest.raises(errors.Locked) as err:
            lock.try_lock("k", directory=str(tmp_path))
        assert err.value.busy is True
    finally:
        held.release()


def test_a_bad_url_exits_1_as_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    code, _out, err = cli(capsys, "plan", str(ROOT / "recipes/examples/conveyor-line3.yaml"), "--device", "tcpx://h:1")
    assert code == errors.EXIT_INVALID
    assert err.startswith("error: ") and "Traceback" not in err
