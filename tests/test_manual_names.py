"""A parameter as the manufacturer's manual names it ("3-41 Ramp 1 Ramp Up Time"), beside its key: in
`profiles show`, in the printed record (apply --html, report --html from the report file alone, pull --html)."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from deployer.errors import InputError
from deployer.profile import load_profile
from deployer.testing.simulator import Simulator
from tests.helpers import Simulators, cli
from tests.test_pages import CHROMIUM, Elements, browser, dom

pytestmark = pytest.mark.timeout(300)

FC102 = """\
profile: fc102
parameters:
  ramp_up_time:
    register: 3410
    type: uint32
    unit: s
    scale: 0.01
    max: 3600
    default: 10
    manual: {number: "3-41", text: Ramp 1 Ramp Up Time}
  ramp_down_time: {register: 3420, type: uint32, unit: s, scale: 0.01, max: 3600, default: 10,
                   manual: {number: 3-42, text: Ramp 1 Ramp Down Time}}
  motor_speed_low: {register: 4110, type: uint16, unit: rpm, default: 0, manual: {number: 411}}
  no_manual: {register: 5000, type: uint16, default: 0}
"""
UP = "3-41 Ramp 1 Ramp Up Time"


def files(tmp: Path) -> tuple[Path, Path]:
    (tmp / "fc102.yaml").write_text(FC102)
    r = tmp / "r.yaml"
    r.write_text("recipe: r\nprofile: fc102.yaml\nparameters:\n  ramp_up_time: 3 s\n  ramp_down_time: 4 s\n")
    return tmp / "fc102.yaml", r


def test_the_profile_carries_the_manuals_number_and_text(tmp_path: Path) -> None:
    prof = load_profile(str(files(tmp_path)[0]))
    up = prof.parameter("ramp_up_time")
    assert (up.manual_number, up.manual_text, up.manual) == ("3-41", "Ramp 1 Ramp Up Time", UP)
    assert prof.parameter("motor_speed_low").manual == "411" and prof.parameter("no_manual").manual == ""


def test_a_bare_number_is_kept_as_written(tmp_path: Path) -> None:
    """ABB numbers parameters 22.10: a float would make it 22.1."""
    (tmp_path / "p.yaml").write_text(
        "profile: p\nparameters:\n  a: {register: 1, type: uint16, manual: {number: 22.10, text: Speed ref}}\n"
    )
    assert load_profile(str(tmp_path / "p.yaml")).parameter("a").manual == "22.10 Speed ref"


def test_a_manual_without_number_or_text_is_refused(tmp_path: Path) -> None:
    (tmp_path / "p.yaml").write_text("profile: p\nparameters:\n  a: {register: 1, type: uint16, manual: {}}\n")
    with pytest.raises(InputError) as exc:
        load_profile(str(tmp_path / "p.yaml"))
    assert "p.yaml:3:" in str(exc.value)


def test_profiles_show_puts_it_beside_the_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    prof, _ = files(tmp_path)
    code, out, err = cli(capsys, "profiles", "show", str(prof))
    assert code == 0, err
    lines = out.splitlines()
    head = next(line for line in lines if line.lstrip().startswith("parameter"))
    assert head.split()[:3] == ["parameter", "manual", "address"]
    row = next(line for line in lines if "ramp_up_time" in line)
    assert row.split("ramp_up_time", 1)[1].lstrip().startswith(UP)
    assert "0x0D52 (3410)" in row.split(UP, 1)[1]  # the address follows it
    code, out, _ = cli(capsys, "profiles", "show", "example-inverter")  # no manual names: no such column
    assert "manual" not in next(line for line in out.splitlines() if line.lstrip().startswith("parameter"))


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium (CI installs it: apt-get install chromium)")
def test_the_printed_record_shows_it_beside_the_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    prof, recipe = files(tmp_path)
    page, report, again, found = (tmp_path / n for n in ("run.html", "run.json", "again.html", "found.html"))
    with Simulators([Simulator(load_profile(str(prof)))]) as (sim,):
        code, _, err = cli(
            capsys,
            "apply",
            str(recipe),
            "--device",
            sim.url,
            "--yes",
            "--state-dir",
            str(tmp_path / "s"),
            "--html",
            str(page),
            "--report",
            str(report),
        )
        assert code == 0, err
        code, _, err = cli(
            capsys,
            "pull",
            "--device",
            sim.url,
            "--profile",
            str(prof),
            "-o",
            str(tmp_path / "pulled.yaml"),
            "--html",
            str(found),
        )
        assert code == 0, err
    # the report file says it in its profile view: report --html needs no profile file
    views = json.loads(report.read_text())["profiles"]
    (view,) = views.values()
    assert view["parameters"]["ramp_up_time"]["manual_number"] == "3-41"
    (tmp_path / "fc102.yaml").unlink()
    assert cli(capsys, "report", str(report), "--html", str(again))[0] in (0, 4)
    for p in (page, again, found):
        doc = Elements(dom(p, tmp_path))
        rows = {
            r["cells"][0].split()[0]: r["cells"][0]  # type: ignore[index]
            for r in doc.all("tr")
            if r["cells"] and str(r["cells"][0]).startswith("ramp_")  # type: ignore[index]
        }
        assert rows["ramp_up_time"] == f"ramp_up_time {UP}", (p.name, rows)
        assert rows["ramp_down_time"] == "ramp_down_time 3-42 Ramp 1 Ramp Down Time"
        assert [e["text"] for e in doc.all("span", "manual")][:1] == [UP]
    pdf = tmp_path / "record.pdf"
    proc = browser(f"--print-to-pdf={pdf}", "--no-pdf-header-footer", page.as_uri(), tmp=tmp_path)
    assert proc.returncode == 0
    if shutil.which("pdftotext"):  # the printed words: the key and the manual's name on one line
        words = subprocess.run(["pdftotext", "-layout", str(pdf), "-"], capture_output=True, text=True).stdout
        assert any("ramp_up_time" in line and UP in line for line in words.splitlines()), words
