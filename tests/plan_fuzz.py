"""Mutation fuzzing of saved plans: an edited plan or fleet plan is refused or runs, never a crash, and never writes
a register or coil its honest plan does not write.

    python -m tests.plan_fuzz --mutants 10000 --seconds 300     # `make fuzz` (and again with --device coils)
    python -m tests.plan_fuzz --mutants 100 --seconds 60        # what `make test` runs (tests/test_hostile.py)

Three simulated example drives (identity check, a precondition, unlock, commit and lock, bit fields) on 127.0.0.1,
or with ``--device coils`` three devices whose unlock, lock and commit are coils at the addresses of two register
parameters (``COILS_PROFILE``); a saved plan of one (`plan --device --out`) and a saved fleet plan of all three
(`plan --inventory --out`), made once. Each mutant is one to three edits of either document (a value replaced by
another type, a huge or negative number, a long string, a key dropped or added, an entry repeated, a number
nudged), given to `deployer validate` and `deployer apply --yes` with the devices reset to the values the plans
were made against, so the writes really go out. Printed as JSON: mutants tried, exit codes, crashes (with the file
kept), places written that the honest plans do not write. Exit 1 on either.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import io
import json
import random
import sys
import tempfile
import time
import traceback
from collections.abc import Iterator
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
RECIPE = str(ROOT / "recipes" / "examples" / "example-drive-axis1.yaml")
# a device whose unlock, lock and commit are coils (Function 05), with coil and register parameters and a coil
# health check: where a coil and a register share an address, writing one for the other is the mistake to catch
COILS_PROFILE = """\
profile: coils
unlock:
  - {register: 71, register_type: coil, raw: true}
lock:
  - {register: 71, register_type: coil, raw: false}
commit:
  - {register: 66, register_type: coil, raw: 1, description: store to EEPROM}
health:
  - {register: 67, register_type: coil, equals: 0, description: no alarm}
parameters:
  speed: {register: 66, type: uint16, default: 5, max: 1000}
  ramp: {register: 71, type: uint32, unit: s, scale: 0.01, max: 3600, default: 10}
  relay1: {register: 19, register_type: coil, default: true}
  relay2: {register: 20, register_type: coil}
  mode: {register: 21, register_type: coil, values: {auto: 0, manual: 1}}
"""
COILS_RECIPE = (
    "recipe: c\nprofile: coils.yaml\nparameters:\n  speed: 700\n  ramp: 2.5 s\n  relay1: false\n  mode: manual\n"
)
VALUES: list[Any] = [
    None,
    -1,
    0,
    1,
    255,
    65535,
    65536,
    2**70,
    -(2**70),
    1.5,
    "",
    "x",
    "x" * 5000,
    [],
    {},
    True,
    [1, 2, 3],
    {"a": 1},
    "0x1F",
    "tcp://127.0.0.1:1",
    [[[[[[[[]]]]]]]],
    "\u202e\x00",
]


def _cli(*args: str) -> tuple[int | str, str]:
    """The command line in this process: (its exit code, or "crash"; its stderr)."""
    from deployer.cli import main

    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        try:
            main(list(args))
        except SystemExit as e:
            return (e.code if isinstance(e.code, int) else 1), err.getvalue()
        except BaseException:
            return "crash", err.getvalue() + traceback.format_exc()
    return 0, err.getvalue()


def _paths(doc: Any, here: tuple[Any, ...] = ()) -> Iterator[tuple[Any, ...]]:
    yield here
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, (*here, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _paths(v, (*here, i))


def mutate(doc: Any, rnd: random.Random) -> Any:
    out = copy.deepcopy(doc)
    places = [p for p in _paths(out) if p]
    for _ in range(rnd.randint(1, 3)):
        path = rnd.choice(places)
        parent = out
        try:
            for k in path[:-1]:
                parent = parent[k]
            last, r = path[-1], rnd.random()
            if r < 0.15 and isinstance(parent, dict):
                parent.pop(last, None)
            elif r < 0.2 and isinstance(parent, list) and parent:
                parent.append(copy.deepcopy(parent[rnd.randrange(len(parent))]))
            elif r < 0.25 and isinstance(parent, dict):
                parent["zz_unknown"] = 1
            elif r < 0.55 and isinstance(parent[last], int) and not isinstance(parent[last], bool):
                parent[last] += rnd.choice([1, -1, 16, 256, 4096, 65535])
            else:
                parent[last] = rnd.choice(VALUES)
        except (KeyError, IndexError, TypeError):
            pass
    return out


def _written(log: list[Any]) -> set[tuple[bool, int]]:
    """The places a simulator's log shows written: (a coil?, address)."""
    return {
        (e.function in (5, 15), e.address + i)
        for e in log
        if e.function in (5, 6, 15, 16)
        for i in range(max(e.count, 1))
    }


def run(mutants: int, seconds: float, seed: int, keep: str | None = None, device: str = "drive") -> dict[str, Any]:
    """``device``: ``drive`` (the built-in example drive) or ``coils`` (``COILS_PROFILE``)."""
    from deployer.profile import builtin_profile, load_profile
    from deployer.testing.simulator import Simulator
    from tests.helpers import Simulators

    rnd = random.Random(seed)
    work = Path(tempfile.mkdtemp(prefix="deployer-plan-fuzz-"))
    recipe = RECIPE
    if device == "coils":
        (work / "coils.yaml").write_text(COILS_PROFILE)
        (work / "coils-recipe.yaml").write_text(COILS_RECIPE)
        profile, recipe = load_profile(str(work / "coils.yaml")), str(work / "coils-recipe.yaml")
    else:
        profile = builtin_profile("example-drive")
    kept = Path(keep) if keep else work
    state = str(work / "state")
    codes: dict[str, int] = {}
    crashes: list[dict[str, str]] = []
    surprises: list[dict[str, Any]] = []
    tried = 0
    with Simulators([Simulator(profile) for _ in range(3)]) as sims:
        inventory = work / "inventory.yaml"
        inventory.write_text(
            "defaults: {timeout: 0.5, retries: 0}\ndevices:\n"
            + "".join(f"  d{i}: {{url: '{s.url}'}}\n" for i, s in enumerate(sims))
        )
        single, fleet = work / "plan.json", work / "fleet.json"
        for where in (
            ("--device", sims[0].url, "--out", str(single)),
            ("--inventory", str(inventory), "--out", str(fleet)),
        ):
            code, err = _cli("plan", recipe, *where, "--state-dir", state)
            if code not in (0, 2):
                raise SystemExit(f"cannot make the plans to mutate: {err}")
        docs = [json.loads(single.read_text()), json.loads(fleet.read_text())]
        names = [p.name for p in profile.parameters]
        held = [{n: s.read(n) for n in names} for s in sims]

        def reset() -> None:  # the values the plans were made against: an honest plan writes
            for s, values in zip(sims, held, strict=True):
                for n, v in values.items():
                    s.write(n, v)
                s.log.clear()

        reset()  # what the honest plans write: the fleet plan covers the single one's device
        _cli("apply", str(fleet), "--yes", "--state-dir", state)
        allowed = set().union(*(_written(s.log) for s in sims))
        end = time.monotonic() + seconds
        while tried < mutants and time.monotonic() < end:
            tried += 1
            doc = mutate(rnd.choice(docs), rnd)
            mutant = work / "mutant.json"
            mutant.write_text(json.dumps(doc))
            reset()
            for args in (("validate", str(mutant)), ("apply", str(mutant), "--yes", "--state-dir", state)):
                code, err = _cli(*args)
                codes[f"{args[0]} {code}"] = codes.get(f"{args[0]} {code}", 0) + 1
                if code == "crash" or "Traceback" in err or "please report" in err:
                    path = kept / f"plan-crash-{len(crashes)}.json"
                    path.write_text(mutant.read_text())
                    crashes.append({"command": args[0], "kept": str(path), "error": err[-2000:]})
            extra = set().union(*(_written(s.log) for s in sims)) - allowed
            if extra:
                path = kept / f"plan-surprise-{len(surprises)}.json"
                path.write_text(mutant.read_text())
                surprises.append({"kept": str(path), "written": sorted(extra)})
    return {
        "mutants_tried": tried,
        "exit_codes": dict(sorted(codes.items())),
        "crashes": len(crashes),
        "crash_details": crashes[:10],
        "surprises": len(surprises),
        "surprise_details": surprises[:10],
        "seed": seed,
        "device": device,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--mutants", type=int, default=20_000)
    ap.add_argument("--seconds", type=float, default=300)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--keep", help="directory for the mutants that crashed or wrote where they may not")
    ap.add_argument("--device", choices=("drive", "coils"), default="drive", help="whose plans are mutated")
    a = ap.parse_args(argv)
    res = run(a.mutants, a.seconds, a.seed, a.keep, a.device)
    print(json.dumps(res, indent=1))
    return 1 if res["crashes"] or res["surprises"] else 0


if __name__ == "__main__":
    sys.exit(main())
