"""YAML 1.1 octal and leading-zero integers are refused at their position, by both parsers (issue #17 item 7).

`010` is 8 to PyYAML (YAML 1.1) and 10 to YAML 1.2 readers and people; `0o17` is 15 in YAML 1.2 and text
in 1.1. The corpus in tests/bad has one file per kind; here both event sources (libyaml and the
pure-Python reader) are held to the same diagnostics, keys and values alike.
"""

from __future__ import annotations

from decimal import Decimal
from pathlib import Path

import pytest
import yaml

from deployer.errors import InputError
from deployer.load import yamlsrc


def _errors(path: Path, loader: type) -> list[str]:
    try:
        yamlsrc.load(str(path), loader=loader)
    except InputError as e:
        return [str(d) for d in e.diagnostics]
    return []


@pytest.mark.parametrize("loader", [yamlsrc.FastLoader, yaml.SafeLoader], ids=["libyaml", "pure-python"])
@pytest.mark.parametrize(
    ("text", "where", "message"),
    [
        (
            "a: 010\n",
            "1:4",
            "'010' has a leading zero: YAML 1.1 reads it as octal (8), other tools as 10; write 10 "
            "(or 0x8 for 8), or quote it if it is text",
        ),
        (
            "a: -012\n",
            "1:4",
            "'-012' has a leading zero: YAML 1.1 reads it as octal (-10), other tools as -12; write -12 "
            "(or -0xA for -10), or quote it if it is text",
        ),
        (
            "a: 0o17\n",
            "1:4",
            "'0o17' is octal 15 in YAML 1.2 but text in YAML 1.1; write 15 (or 0xF), or quote it if it is text",
        ),
        ("a: 09\n", "1:4", "'09' has a leading zero; write 9, or quote it if it is text"),
        ("a: 07\n", "1:4", "'07' has a leading zero; write 7, or quote it if it is text"),
        ("a: [1, 010]\n", "1:8", "'010' has a leading zero"),
        ("010: x\n", "1:1", "'010' has a leading zero"),
        ("a: {012: x}\n", "1:5", "'012' has a leading zero"),
        ("a:\n  - 0_10\n", "2:5", "'0_10' has a leading zero"),
    ],
)
def test_leading_zero_integers_are_refused(tmp_path: Path, loader: type, text: str, where: str, message: str) -> None:
    f = tmp_path / "f.yaml"
    f.write_text(text)
    (got,) = _errors(f, loader)
    assert got.startswith(f"{f}:{where}: error: {message}")


@pytest.mark.parametrize("loader", [yamlsrc.FastLoader, yaml.SafeLoader], ids=["libyaml", "pure-python"])
def test_what_stays_allowed(tmp_path: Path, loader: type) -> None:
    f = tmp_path / "f.yaml"
    f.write_text("a: 0\nb: 0x10\nc: '010'\nd: \"0o17\"\ne: 0.5\nf: 10\ng: 1_000\nh: 010 ms\ni: -0\nj: |\n  010\n")
    data, _ = yamlsrc.load(str(f), loader=loader)
    assert data == {
        "a": 0,
        "b": 16,
        "c": "010",
        "d": "0o17",
        "e": Decimal("0.5"),
        "f": 10,
        "g": 1000,
        "h": "010 ms",
        "i": 0,
        "j": "010\n",
    }


@pytest.mark.parametrize("loader", [yamlsrc.FastLoader, yaml.SafeLoader], ids=["libyaml", "pure-python"])
def test_numbers_beyond_any_register_are_refused_not_a_crash(tmp_path: Path, loader: type) -> None:
    """1e999999999 (a number since exponents without a point are numbers) must not overflow later arithmetic."""
    f = tmp_path / "f.yaml"
    f.write_text("a: 1e999999999\nb: 1.0e-999\nc: 1e300\n")
    assert _errors(f, loader) == [
        f"{f}:1:4: error: 1e999999999 is too large (exponents -400..400)",
        f"{f}:2:4: error: 1.0e-999 is too close to 0 (exponents -400..400)",
    ]
