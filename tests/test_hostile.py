"""Hostile and odd input (issue #11): limits end in FILE:LINE:COL errors, both YAML parsers agree, fuzzing."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from decimal import Decimal
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from deployer.errors import InputError
from deployer.load import yamlsrc
from deployer.profile import units
from deployer.recipe import text as recipe_text_module
from tests.helpers import without_coverage

ROOT = Path(__file__).resolve().parent.parent
BAD = ROOT / "tests" / "bad"
HOSTILE = [
    "yaml-alias-bomb.yaml",
    "yaml-deep-nesting.yaml",
    "yaml-recursive-alias.yaml",
    "recipe-100000-digits.yaml",
    "recipe-100000-digit-string.yaml",
    "recipe-extends-dev-zero.yaml",
    "profile-table-bomb.yaml",
    "recipe-extends-diamond.yaml",
]


def _limited() -> None:  # a child that tries to take gigabytes fails instead of taking the machine
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))


LIMITED = None if sys.platform == "win32" else _limited  # Windows has no rlimits


def validate(*paths: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "deployer", "validate", *paths],
        capture_output=True,
        text=True,
        timeout=60,
        preexec_fn=LIMITED,
        cwd=ROOT,
    )


@pytest.mark.parametrize("name", HOSTILE)
def test_hostile_file_ends_in_a_positioned_error(name: str) -> None:
    proc = validate(str(BAD / name))
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    first = proc.stderr.splitlines()[0]
    assert first.split(": error: ")[0].count(":") >= 2, first
    assert max(len(line) for line in proc.stderr.splitlines()) < 400  # no value echoed whole


def test_not_regular_files(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    via = tmp_path / "via-fifo.yaml"
    via.write_text("recipe: x\nprofile: omron-m1\nextends: fifo.yaml\nparameters: {F07: 10 s}\n")
    proc = validate(str(fifo), "/dev/zero", str(via))
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert f"{fifo}:0:0: error: not a regular file" in proc.stderr
    assert "/dev/zero:0:0: error: not a regular file" in proc.stderr
    assert f"{via}:3:10: error: cannot load 'fifo.yaml'" in proc.stderr


def test_too_many_parameters(tmp_path: Path) -> None:
    f = tmp_path / "many.yaml"
    f.write_text("recipe: many\nprofile: omron-m1\nparameters:\n" + "".join(f"  p{i}: 1\n" for i in range(70_000)))
    with pytest.raises(InputError) as err:
        yamlsrc.load(f)
    (d,) = err.value.diagnostics
    assert (d.line, d.col) == (4 + 65_536, 3) and "more than 65536 entries" in d.message


def test_file_too_large_is_not_read(tmp_path: Path) -> None:
    f = tmp_path / "big.yaml"
    with f.open("wb") as out:
        out.truncate(yamlsrc.MAX_FILE_BYTES + 1)  # sparse: nothing to read if it were read
    with pytest.raises(InputError) as err:
        yamlsrc.load(f)
    assert "file too large" in err.value.diagnostics[0].message


def test_anchors_within_limits_keep_positions(tmp_path: Path) -> None:
    f = tmp_path / "r.yaml"
    f.write_text("common: &c {value: 10 s, rounding: nearest}\nparameters:\n  F07: *c\n  F08: *c\n")
    value, src = yamlsrc.load(f)
    assert value["parameters"] == {
        "F07": {"value": "10 s", "rounding": "nearest"},
        "F08": {"value": "10 s", "rounding": "nearest"},
    }
    assert value["parameters"]["F07"] is not value["parameters"]["F08"]  # a copy per alias
    assert src.pos(("parameters", "F08", "rounding")) == (1, 36)  # where the anchored value is written
    assert src.pos(("parameters", "F08"), key=True) == (4, 3)


def _yaml_files() -> list[Path]:
    pats = ("recipes/**/*.yaml", "deployer/profiles/*.yaml", "tests/bad/**/*.yaml")
    return [p for pat in pats for p in sorted(ROOT.glob(pat))]


def _outcome(path: Path, loader: type) -> object:
    try:
        value, src = yamlsrc.load(path, loader=loader)
    except InputError as e:
        return [str(d) for d in e.diagnostics]
    return value, src.values, src.keys


@pytest.mark.parametrize("path", _yaml_files(), ids=lambda p: p.name)
def test_libyaml_and_pure_python_parsers_agree(path: Path) -> None:
    """Values, every position and every message are the same whichever parser PyYAML has."""
    assert _outcome(path, yaml.SafeLoader) == _outcome(path, yamlsrc.FastLoader)


@given(st.text(alphabet=st.sampled_from(list("ab1 .-/%°:#'\"_,[]{}!&*|>@`?~=+\tyesnoul")), min_size=1, max_size=10))
@settings(max_examples=500, deadline=None)
def test_reads_back_never_claims_a_plain_string_wrongly(text: str) -> None:
    if recipe_text_module._reads_back(text):
        try:
            Decimal(text)
        except ArithmeticError:
            assert yaml.safe_load(f"k: {text}") == {"k": text}


@pytest.mark.parametrize(
    ("a", "b"),
    [
        ("ms", "s"),
        ("min", "s"),
        ("rpm", "Hz"),
        ("%", "dimensionless"),
        ("in", "mm"),
        ("degC", "K"),
        ("degF", "degC"),
        ("psi", "kPa"),
    ],
)
@given(st.decimals(min_value=-(10**6), max_value=10**6, places=4, allow_nan=False, allow_infinity=False))
@settings(max_examples=50, deadline=None)
def test_cached_conversions_equal_pint(a: str, b: str, x: Decimal) -> None:
    """The factor kept (in memory and on disk) gives what pint's own arithmetic gives, both with the guard digits,
    at the working precision."""
    with units.precise():
        ureg = units.registry()
        exact = Decimal(ureg.Quantity(x, units._pint_text(a)).to(units._pint_text(b)).magnitude)
    assert units.convert(x, a, b) == units._tidy(+exact)


def _fuzzed(*args: str) -> dict[str, Any]:
    """A bounded fuzzing run (``python -m ARGS``), its JSON figures."""
    proc = subprocess.run(
        [sys.executable, "-m", *args],
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=LIMITED,
        cwd=ROOT,
        # without make test's coverage: its bounds (time, memory) are the loaders', and coverage's tracer made the
        # run 2-3x slower (the suite's longest CPU after Ansible's); its random inputs would move the figure
        env=without_coverage(),
    )
    return json.loads(proc.stdout)  # type: ignore[no-any-return]


def test_fuzz_bounded() -> None:
    """A bounded mutation-fuzz run (`make fuzz` runs a longer one): no crash, no runaway time or memory."""
    res = _fuzzed("tests.fuzz", "--files", "1500", "--seconds", "40")
    assert res["crashes"] == 0, res["crash_details"]
    assert res["files_tried"] >= 200
    assert res["peak_rss_mb"] < 400
    assert res["slowest_file_seconds"] < 10  # a hang guard, not a speed target


def test_plan_fuzz_bounded() -> None:
    """A bounded run of the saved plans' fuzzer (`make fuzz` runs a longer one): an edited plan or fleet plan is
    refused or runs, never a crash, and never writes a register or coil its honest plan does not write."""
    res = _fuzzed("tests.plan_fuzz", "--mutants", "100", "--seconds", "60")
    assert res["crashes"] == 0, res["crash_details"]
    assert res["surprises"] == 0, res["surprise_details"]
    # some edited plans ran (seed 1: 2 of the first 30 mutants)
    assert res["mutants_tried"] >= 30 and res["exit_codes"].get("apply 0", 0) > 0, res


def test_values_per_file_are_bounded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An 8 MB file of small lists would build millions of values: the count stops it (here at 1,000)."""
    monkeypatch.setattr(yamlsrc, "MAX_NODES", 1000)
    f = tmp_path / "wide.yaml"
    f.write_text("junk:\n" + "".join(f"  - [{', '.join(['1'] * 100)}]\n" for _ in range(20)))
    with pytest.raises(InputError) as err:
        yamlsrc.load(f)
    (d,) = err.value.diagnostics
    assert "more than 1000 values in one file" in d.message
    # the 1,001st value: root, list, 9 rows of 1 + 100, row 10 itself, then its 89th entry (column 6 + 3 x 88)
    assert (d.line, d.col) == (11, 6 + 3 * 88)
