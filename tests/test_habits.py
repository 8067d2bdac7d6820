"""The habits make test keeps (issue #46 item 7): the pre-commit hooks run what `make lint` runs, and `make test`
runs those checks too, so a commit that passes its hooks passes CI's lint and the other way round."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent


def _recipe(target: str) -> list[str]:
    """The Makefile's recipe lines of ``target`` (continuations joined)."""
    text = (ROOT / "Makefile").read_text(encoding="utf-8").replace("\\\n", " ")
    found = re.search(rf"^{re.escape(target)}:[^\n]*\n((?:\t[^\n]*\n)+)", text, re.M)
    assert found, f"no target {target} in the Makefile"
    return [line.strip() for line in found.group(1).splitlines()]


def _tools(lines: list[str]) -> list[list[str]]:
    """Each ``$(BIN)/tool args`` command of ``lines`` (one that starts a line, a subshell or follows a ``;``), as
    argv without the venv's folder (comments, redirections, ``|| rc=1`` and other shell around it left out)."""
    out = []
    for line in lines:
        for cmd in re.findall(r"(?:^|[;&]|(?<!\$)\()\s*\$\(BIN\)/([^|;#&>]+)", line):  # not $(...) in an echo
            out.append(shlex.split(cmd))
    return out


def _hooks() -> list[list[str]]:
    doc = yaml.safe_load((ROOT / ".pre-commit-config.yaml").read_text(encoding="utf-8"))
    (local,) = [r for r in doc["repos"] if r["repo"] == "local"]
    out = []
    for hook in local["hooks"]:
        assert hook["language"] == "system" and hook["pass_filenames"] is False, hook
        argv = shlex.split(hook["entry"])
        assert argv[0].startswith(".venv/bin/"), hook  # the project's tools, at constraints.txt's versions
        out.append([argv[0].removeprefix(".venv/bin/"), *argv[1:]])
    return out


def test_the_pre_commit_hooks_are_make_lints_commands() -> None:
    assert _hooks() == _tools(_recipe("lint"))


def test_make_test_runs_every_lint_check() -> None:
    check = _tools(_recipe("check"))
    assert [c for c in _tools(_recipe("lint")) if c not in check] == []
    assert ["ruff", "format", "--check", "deployer", "tests", "benchmarks", "ansible_collections", "tools"] in check
