"""What a command pays for: lazy imports, and validate parsing each file once (issue #9)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from deployer.cli.files import validate_file
from deployer.load import yamlsrc

ROOT = Path(__file__).resolve().parent.parent


def _imported(*args: str) -> set[str]:
    proc = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "deployer", *args],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return {line.rsplit("|", 1)[1].strip() for line in proc.stderr.splitlines() if line.startswith("import time:")}


def test_help_imports_neither_pint_rich_nor_pymodbus() -> None:
    mods = _imported("--help")
    assert not {m for m in mods if m.split(".")[0] in ("pint", "rich", "pymodbus", "jsonschema")}
    assert "deployer.api" not in mods  # the commands import the API when they run, not for --help


def test_version_imports_no_asyncio() -> None:
    """`deployer --version` loads no event loop machinery (issue #30)."""
    mods = _imported("--version")
    assert not {m for m in mods if m.split(".")[0] in ("asyncio", "ssl", "pymodbus", "rich")}


def test_validate_and_offline_plan_do_not_import_pymodbus() -> None:
    recipe = "recipes/examples/conveyor-line3.yaml"  # it names a device URL: parsed, not connected
    for args in (("validate", recipe), ("plan", recipe, "--json")):
        mods = _imported(*args)
        assert not {m for m in mods if m.split(".")[0] in ("pymodbus", "serial")}, args
    assert not {m for m in _imported("validate", recipe) if m.startswith("rich")}


def test_a_command_imports_only_its_own_module() -> None:
    """LazyGroup: `validate` loads deployer.cli.files, not the other command modules."""
    code = (
        "import sys\nfrom deployer.cli import main\ntry:\n"
        "    main(['validate', 'recipes/examples/conveyor-line3.yaml'])\nexcept SystemExit:\n    pass\n"
        "print(' '.join(sorted(m for m in sys.modules if m.startswith('deployer.cli'))))"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert proc.stdout.split()[-3:] == ["deployer.cli", "deployer.cli.base", "deployer.cli.files"], proc.stderr


def test_validate_parses_each_file_once(monkeypatch: pytest.MonkeyPatch) -> None:
    parsed: list[str] = []
    build = yamlsrc._Builder.build

    def counting(self: yamlsrc._Builder) -> object:
        parsed.append(self.src.path)
        return build(self)

    monkeypatch.setattr(yamlsrc._Builder, "build", counting)
    validate_file(str(ROOT / "recipes/examples/omron-m1-accel.yaml"))
    assert len(parsed) == len(set(parsed)), parsed  # the recipe once, its profile once
    assert not yamlsrc._handed_over


def _cache_files(home: Path) -> list[str]:
    return sorted(str(p.relative_to(home)) for p in home.rglob("*") if p.is_file())


def test_only_the_command_line_writes_the_units_cache(tmp_path: Path) -> None:
    """The library (and so the Ansible modules) reads the disk caches but leaves no files in the user's home."""
    import os

    recipe = tmp_path / "r.yaml"
    recipe.write_text("recipe: r\nprofile: example-inverter\nparameters:\n  F07: 10000 ms\n  F08: 0.1 min\n")
    lib_home, cli_home = tmp_path / "lib", tmp_path / "cli"
    for home, code in (
        (lib_home, f"import deployer; deployer.load_recipe({str(recipe)!r})"),
        (cli_home, f"from deployer.cli import main; main(['validate', {str(recipe)!r}])"),
    ):
        home.mkdir()
        env = {**os.environ, "HOME": str(home), "XDG_CACHE_HOME": str(home / ".cache")}
        proc = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT, env=env
        )
        assert "Traceback" not in proc.stderr, proc.stderr
    assert _cache_files(lib_home) == []
    assert any(f.replace(os.sep, "/").startswith(".cache/deployer/units-") for f in _cache_files(cli_home)), (
        _cache_files(cli_home)
    )
