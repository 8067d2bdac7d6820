"""`deployer demo`: the whole story against the built-in simulated device, step by step.

Everything runs for real: the simulator serves Modbus/TCP on 127.0.0.1 in a background
thread and each step runs the same command a user would type, with its real output.
"""

from __future__ import annotations

import os
import shlex
import tempfile
import time
from collections.abc import Sequence

import click

from ..testing.simulator import Faults, SimulatorThread, parse_fault_rule

BASE = """\
# Settings shared by every conveyor inverter; line recipes extend this file.
recipe: conveyor-base
profile: example-inverter
parameters:
  control_mode: sensorless-vector
  max_frequency: 60 Hz
  stop_mode: ramp
  torque_limit: 150 %
"""

LINE3 = """\
# Line 3: the shared base plus this line's ramps and presets, in engineering units.
recipe: conveyor-line3
extends: conveyor-base.yaml
device: {{url: "{url}", unit: 1}}
parameters:
  F07: 10 s                 # acceleration time; pint converts units:
  F08: 8000 ms              #   8000 ms -> 8 s -> raw 800 at 0.01 s
  stop_mode: coast          # an enumeration label; overrides the base
  base_speed: 1750 rpm
  pid_gain: 2.5
  motor_temperature_limit: 135 degC
  preset[0]: {{speed: 300 rpm, time: 2 s}}
  preset[1]: {{speed: 900 rpm, time: 2.5 s}}
"""

RETUNE = """\
# A retune that the device will partly refuse: the simulated drive rejects speed_offset.
recipe: line3-retune
extends: conveyor-line3.yaml
parameters:
  base_speed: 1800 rpm
  speed_offset: -25 rpm     # the simulated drive answers exception 04 for this register
  pid_gain: 3.0
  motor_temperature_limit: 140 degC
"""


FAST_RAMP = """\
# A faster ramp that the drive cannot run with: it trips (fault code 7) once F07 is below 2 s.
recipe: line3-fast-ramp
extends: conveyor-line3.yaml
parameters:
  F07: 1.5 s
"""


# the lock folder's variable, a documented interface (docs/locks.md) as the agent's systemd unit sets it; a test
# checks it is the one the locks read
LOCK_DIR_ENV = "DEPLOYER_LOCK_DIR"


def run_demo(*, fast: bool = False, keep: str | None = None) -> int:
    """Run the story in a folder of its own: ``keep`` (created if need be, left in place), else a
    temporary folder removed at the end. The demo's device lives only as long as the demo, so its
    locks go in that folder too, not in the machine's lock folder: nothing is left in /tmp."""
    if keep is not None:
        os.makedirs(keep, exist_ok=True)
        return _story(os.path.abspath(keep), fast=fast, kept=True, lock_env=LOCK_DIR_ENV)
    with tempfile.TemporaryDirectory(prefix="deployer-demo-") as work:
        return _story(work, fast=fast, kept=False, lock_env=LOCK_DIR_ENV)


def _story(work: str, *, fast: bool, kept: bool, lock_env: str) -> int:
    before = os.environ.get(lock_env)
    os.environ[lock_env] = os.path.join(work, "locks")
    try:
        return _steps(work, fast=fast, kept=kept)
    finally:
        if before is None:
            os.environ.pop(lock_env, None)
        else:
            os.environ[lock_env] = before


def _steps(work: str, *, fast: bool, kept: bool) -> int:
    from ..api import load_profile
    from ..cli import cli

    profile = load_profile("example-inverter")
    bad = profile.parameter("speed_offset").address
    state = os.path.join(work, ".deployer")
    faults = Faults()
    with SimulatorThread(profile, listen="tcp://127.0.0.1:0", faults=faults) as sim:
        url = sim.url
        files = {
            "conveyor-base.yaml": BASE,
            "conveyor-line3.yaml": LINE3.format(url=url),
            "line3-retune.yaml": RETUNE,
            "line3-fast-ramp.yaml": FAST_RAMP,
        }
        for name, text in files.items():
            with open(os.path.join(work, name), "w", encoding="utf-8") as f:
                f.write(text)
        line3 = os.path.join(work, "conveyor-line3.yaml")
        retune = os.path.join(work, "line3-retune.yaml")
        fast_ramp = os.path.join(work, "line3-fast-ramp.yaml")

        def step(title: str, explain: str) -> None:
            click.echo()
            click.secho(f"== {title}", bold=True)
            click.echo(explain)
            if not fast:
                time.sleep(0.3)

        def run(args: Sequence[str]) -> int:
            click.secho("$ deployer " + " ".join(shlex.quote(a.replace(work + os.sep, "")) for a in args), fg="cyan")
            rv = cli.main(args=list(args), standalone_mode=False)
            code = rv if isinstance(rv, int) else 0
            click.secho(f"(exit code {code})", dim=True)
            return code

        click.secho("deployer demo", bold=True)
        where = (
            f"Files are in {work}."
            if kept
            else "Files are in a temporary folder, removed at the end (deployer demo --keep DIR keeps them)."
        )
        click.echo(f"A simulated example-inverter listens on {url} (unit 1). {where}")
        step(
            "1. Validate",
            "Recipes and profiles are checked before anything is sent: schema, units, ranges, "
            "resolution. This recipe extends a shared base:",
        )
        click.echo(LINE3.format(url=url))
        codes = [run(["validate", line3])]
        step("2. Plan, offline", "The planner packs contiguous registers into the fewest FC16 requests.")
        codes.append(run(["plan", line3]))
        step(
            "3. Plan against the device",
            "With --device the plan reads what the device holds and shows only what changes (current -> desired).",
        )
        codes.append(run(["plan", line3, "--device", url]))
        step(
            "4. Apply",
            "A snapshot of the current values is saved (and made durable) before the first write; "
            "then the writes, a read-back of every parameter and the report.",
        )
        codes.append(run(["apply", line3, "--yes", "--state-dir", state]))
        snapshots = sorted(n for n in os.listdir(os.path.join(state, "snapshots")) if n.endswith(".yaml"))
        first_snapshot = os.path.join(state, "snapshots", snapshots[0]) if snapshots else None
        step("5. Apply again", "Diff-aware: the device already holds every value, so nothing is written.")
        codes.append(run(["apply", line3, "--yes", "--state-dir", state]))
        step("6. Drift", "Someone changes F07 on the panel; diff notices (exit code 2).")
        sim.write("F07", profile.parameter("F07").encode(1234))
        codes.append(run(["diff", line3]))
        step(
            "7. A partial failure",
            "The drive rejects one register (exception 04). The report says exactly "
            "which parameter failed; the ones after it go out in a follow-up request.",
        )
        faults.fail_registers = frozenset({bad})
        codes.append(run(["apply", retune, "--yes", "--state-dir", state, "--device", url]))
        faults.fail_registers = frozenset()
        if first_snapshot:
            step(
                "8. Rollback",
                "The first snapshot is a recipe that knows its device and profile: rollback "
                "writes back exactly the registers the device held, to that device.",
            )
            codes.append(run(["rollback", first_snapshot, "--yes", "--state-dir", state]))
            step("9. Verify", "Diff against the snapshot: no drift left.")
            codes.append(run(["diff", first_snapshot, "--device", url]))
        faults.rules = (parse_fault_rule("F07 < 2 s: 0x2000=7", profile),)
        step(
            "10. A change the drive does not survive",
            "The write reads back right, but the drive trips on the "
            "new ramp. --soak watches the profile's health checks "
            "(fault code zero) after the write; the first failed check "
            "rolls the device back from its snapshot, and the commit "
            "(store to EEPROM) is never sent.",
        )
        codes.append(
            run(
                [
                    "apply",
                    fast_ramp,
                    "--yes",
                    "--state-dir",
                    state,
                    "--device",
                    url,
                    "--soak",
                    "1s" if fast else "3s",
                    "--health-interval",
                    "250ms",
                ]
            )
        )
        if kept:
            click.echo()
            click.echo(f"Audit log: {os.path.join(state, 'audit.jsonl')}")
    expected = [0, 0, 0, 0, 0, 2, 4, 0, 0, 4]
    if codes != expected:
        click.secho(f"demo: unexpected exit codes {codes} (expected {expected})", fg="red", err=True)
        return 1
    click.secho("demo finished: every step behaved as described.", fg="green")
    return 0
