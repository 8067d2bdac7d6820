"""The malformed-file corpus: every file gets its exact FILE:LINE:COL and message, never a traceback."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from deployer.cli.files import validate_file
from deployer.errors import InputError

BAD = Path(__file__).parent / "bad"


def _expectations() -> list[tuple[str, str, str]]:
    out = []
    for line in (BAD / "expected.txt").read_text(encoding="utf-8").splitlines():
        if line.strip() and not line.startswith("#"):
            f, where, fragment = (part.strip() for part in line.split(" | ", 2))
            out.append((f, where, fragment))
    return out


EXPECTED = _expectations()


def test_corpus_is_complete() -> None:
    """Every file in tests/bad has an expectation, and there are at least 40 of them."""
    files = {p.name for p in BAD.glob("*.yaml")}
    assert files == {f for f, _, _ in EXPECTED}
    assert len(files) >= 40


@pytest.mark.parametrize(("name", "where", "fragment"), EXPECTED, ids=[f"{f}@{w}" for f, w, _ in EXPECTED])
def test_bad_file(name: str, where: str, fragment: str) -> None:
    path = str(BAD / name)
    with pytest.raises(InputError) as err:
        validate_file(path)
    parts = where.split(":")
    file = str(BAD / parts[0]) if len(parts) == 3 else path
    line, col = int(parts[-2]), int(parts[-1])
    got = [(os.path.normpath(d.path), d.line, d.col, d.message) for d in err.value.diagnostics]
    said = (fragment, fragment.replace("/", os.sep))  # a path in a message is the system's own spelling
    assert any(
        p == os.path.normpath(file) and ln == line and c == col and any(f in m for f in said) for p, ln, c, m in got
    ), got


def test_deeper_than_libyaml_allows(tmp_path: Path) -> None:
    """2,000 nested lists in a mapping (libyaml stops at 1,000 with its own message): our limit, at the
    list that is the 65th level."""
    from deployer.load import yamlsrc

    f = tmp_path / "deep.yaml"
    f.write_text("a: " + "[" * 2000 + "]" * 2000 + "\n")
    with pytest.raises(InputError) as err:
        yamlsrc.load(f)
    (d,) = err.value.diagnostics
    assert (d.line, d.col, d.message) == (1, 3 + yamlsrc.MAX_DEPTH, f"nested deeper than {yamlsrc.MAX_DEPTH} levels")


def test_huge_file(tmp_path: Path) -> None:
    """A file beyond the size limit (32 MiB) is refused up front with a position, not parsed."""
    from deployer.load.yamlsrc import MAX_FILE_BYTES

    big = tmp_path / "huge.yaml"
    with big.open("w") as f:
        f.write("recipe: x\nprofile: omron-m1\nparameters:\n")
        f.write("  # padding\n" * (MAX_FILE_BYTES // 12 + 1))
    with pytest.raises(InputError) as err:
        validate_file(str(big))
    (d,) = err.value.diagnostics
    assert (d.line, d.col) == (1, 1) and "file too large" in d.message


def test_cli_validate_all_bad_files_at_once() -> None:
    """One run over the whole corpus: exit 1, every file reported, no traceback."""
    files = sorted(str(p) for p in BAD.glob("*.yaml"))
    proc = subprocess.run(
        [sys.executable, "-m", "deployer", "validate", *files], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 1
    assert "Traceback" not in proc.stderr + proc.stdout
    assert f"{len(files)} of {len(files)} files invalid" in proc.stderr
    for f in files:
        assert f"{f}:" in proc.stderr


def test_cli_each_bad_file_exits_1(capsys: pytest.CaptureFixture[str]) -> None:
    """`deployer validate FILE` on each file alone (in-process: the same main() the script runs)."""
    from deployer.cli import main

    for p in sorted(BAD.glob("*.yaml")):
        with pytest.raises(SystemExit) as exc:
            main(["validate", str(p)])
        err = capsys.readouterr().err
        assert exc.value.code == 1, p
        assert ": error: " in err and "Traceback" not in err, err
