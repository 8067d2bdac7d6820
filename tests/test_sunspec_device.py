"""SunSpec from a device (issue #22): the whole model chain from 'SunS' into one profile, its scale factors
and group counts as the device reports them, checked against pysunspec2's own client (an implementation we
did not write) reading the same simulated device over Modbus/TCP on 127.0.0.1."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from deployer.planning.model import Target
from deployer.planning.steps import make_plan
from deployer.profile import Profile, load_profile
from deployer.profile.emit import Draft, Origin, check
from deployer.recipe.loader import load_recipe
from deployer.testing.simulator import SimulatorThread
from tests.helpers import cli

pytestmark = pytest.mark.timeout(120)
sunspec2 = pytest.importorskip("sunspec2", reason="pysunspec2 is the optional 'sunspec' extra")


def sunspec_device(models: list[tuple[str, dict[str, int], dict[str, int]]], base: int = 40000) -> Profile:
    """A simulated SunSpec device: 'SunS' at ``base``, the models one after the other (scale factors and group
    counts as given), the end marker 0xFFFF. Built with the importer's own model reader, one model at a time."""
    from deployer.profile.importers.sunspec import read_model

    at = base + 2
    params: list[tuple[str, dict[str, Any], Origin]] = []
    tables: list[tuple[str, dict[str, Any], Origin]] = []
    for model, sfs, counts in models:
        draft, _ = read_model(model, at=at, scale_factors=sfs, counts=counts, prefix=f"m{at}.")
        params += [p for p in draft.parameters if p[0] != "SunS"]
        tables += draft.tables
        at += 2 + next(s["default"] for n, s, _ in draft.parameters if n == f"m{at}.L")
    here = Origin("device", 1, 1)
    params.insert(
        0, ("SunS", {"register": base, "type": "string", "count": 2, "default": "SunS", "access": "read-only"}, here)
    )
    params.append(("end", {"register": at, "type": "uint16", "access": "read-only", "default": 0xFFFF}, here))
    return check(Draft({"profile": "device", "addressing": "address"}, params, tables), "device.yaml")[1]


def test_device_model_chain_into_one_profile(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from sunspec2.modbus.client import SunSpecModbusClientDeviceTCP

    # common (1), three-phase inverter (103) with its scale factors, MPPT (160) with 2 modules: a count
    # the model leaves to the device's length L
    device = sunspec_device(
        [
            ("1", {}, {}),
            ("103", {"A_SF": -2, "V_SF": -1, "W_SF": 1}, {}),
            ("160", {"DCA_SF": -2, "DCV_SF": -1}, {"module": 2}),
        ]
    )
    out = tmp_path / "dev.yaml"
    with SimulatorThread(device) as sim:
        code, _, err = cli(capsys, "profiles", "import", "sunspec", "--device", sim.url, "-o", str(out))
        assert code == 0, err
        assert "models on" in err and "1 at 40002 (L=66), 103 at 40070 (L=50), 160 at 40122 (L=48)" in err
        host, port = sim.url.split("//")[1].rsplit(":", 1)
        theirs = SunSpecModbusClientDeviceTCP(slave_id=1, ipaddr=host, ipport=int(port))
        try:
            theirs.scan()
            found = {mid: (ms[0].model_addr, ms[0].len) for mid, ms in theirs.models.items() if isinstance(mid, int)}
            their_w_sf = theirs.models[103][0].W_SF.value
            their_modules = len(theirs.models[160][0].module)
        finally:
            theirs.close()
    prof = load_profile(out)
    # the same models at the same addresses as pysunspec2 finds them
    assert found == {1: (40002, 66), 103: (40070, 50), 160: (40122, 48)}
    assert [(c.address, c.raw) for c in prof.identity] == [
        (40000, 0x5375),
        (40001, 0x6E53),
        (40002, 1),
        (40070, 103),
        (40122, 160),
    ]
    assert prof.parameter("common.Mn").address == 40004
    w = prof.parameter("inverter_three_phase.W")
    assert (w.address, w.unit, w.scale) == (40070 + 14, "W", 10**their_w_sf)
    a = prof.parameter("inverter_three_phase.A")
    assert (a.unit, str(a.scale)) == ("A", "0.01")
    assert their_modules == 2 and prof.parameter("mppt_module[1].DCA").address == 40122 + 10 + 20 + 9
    assert str(prof.parameter("mppt_module[1].DCA").scale) == "0.01"
    assert prof.parameter("end.ID").address == 40172 and prof.parameter("end.ID").default == 0xFFFF
    # the imported profile is itself a SunSpec device: importing from a simulation of it gives it back
    with SimulatorThread(prof) as sim:
        code, _, err = cli(capsys, "profiles", "import", "sunspec", "--device", sim.url, "-o", str(tmp_path / "2.yaml"))
        assert code == 0, err
    again = load_profile(tmp_path / "2.yaml")
    assert [(p.name, p.address, p.unit, p.scale) for p in again.parameters] == [
        (p.name, p.address, p.unit, p.scale) for p in prof.parameters
    ]
    # and a recipe plans onto it: the common model's device address (DA, read-write) at 40002 + 66
    (tmp_path / "r.yaml").write_text("recipe: r\nprofile: dev.yaml\nparameters:\n  common.DA: 5\n")
    plan = make_plan(load_recipe(tmp_path / "r.yaml"), Target(None, 1, str(out)))
    assert [(w.address, w.registers) for w in plan.writes] == [(40068, (5,))]


def test_device_scale_factors_and_counts_of_one_model(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """MODEL with --device: the model's scale factors and its group counts (from its count point N) read
    from the device; a scale factor the device does not implement (8000h) leaves its points raw."""
    device = sunspec_device([("1", {}, {}), ("160", {"DCA_SF": -2}, {"module": 3})])
    addr_dcv_sf = next(p.address for p in device.parameters if p.name == "m40070.DCV_SF")
    out = tmp_path / "mppt.yaml"
    with SimulatorThread(device, init={addr_dcv_sf: 0x8000}) as sim:
        code, _, err = cli(
            capsys, "profiles", "import", "sunspec", "160", "--at", "40070", "--device", sim.url, "-o", str(out)
        )
        assert code == 0, err
        assert (
            "DCV_SF at 40073: the device reports not implemented (8000h): the points it scales are imported raw" in err
        )
        assert "scale factors from" in err and "DCA_SF=-2" in err
        # a MODEL that is not where --at points
        code, _, err = cli(capsys, "profiles", "import", "sunspec", "103", "--at", "40070", "--device", sim.url)
        assert code == 1 and "the device has model 160 at 40070, not model 103: check --at" in err
        # --at where the device has nothing: the device's exception 02 and what to check
        code, _, err = cli(capsys, "profiles", "import", "sunspec", "--at", "2", "--device", sim.url)
        assert code == 3 and "answered exception 02 (illegal data address): check --at" in err
    prof = load_profile(out)
    assert prof.parameter("module[2].DCA").address == 40070 + 10 + 2 * 20 + 9
    dcv = prof.parameter("module[2].DCV")
    assert dcv.unit is None and dcv.scale == 1 and "raw" in dcv.description


def test_device_chain_found_where_devices_put_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Without --at the importer looks for 'SunS' at 40000, 0 and 50000, as devices put it (this one: at 0);
    with --at it reads there only."""
    device = sunspec_device([("1", {}, {})], base=0)
    out = tmp_path / "at0.yaml"
    with SimulatorThread(device) as sim:
        code, _, err = cli(capsys, "profiles", "import", "sunspec", "--device", sim.url, "-o", str(out))
        assert code == 0, err
        assert "1 at 2 (L=66)" in err
        code, _, err = cli(capsys, "profiles", "import", "sunspec", "--device", sim.url, "--at", "40002")
        assert (
            code == 3 and "reading 2 registers at 40000 answered exception 02 (illegal data address): check --at" in err
        )
    prof = load_profile(out)
    assert prof.parameter("SunS").address == 0 and prof.parameter("common.Mn").address == 4
