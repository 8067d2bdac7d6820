# Shared by the deployer.modbus modules: which devices a task means, and the recipe for each of them.
# The modules run on the site gateway (often `connection: local`) with a Python that has deployer
# installed (ansible_python_interpreter); they call deployer's public Python API (deployer.api) only,
# never its command line or its internal modules.

from __future__ import annotations

import sys
import traceback

try:
    import deployer
    from deployer.api import (
        LIMITS,
        InputError,
        Job,
        ReadJob,
        UsageError,
        describe_url,
        device_url,
        fleet_jobs,
        inventory_from,
        pull_names,
        read_fleet,
    )
    HAS_DEPLOYER = True
    IMPORT_ERROR = ""
except ImportError:  # said clearly by the module, not as a traceback
    HAS_DEPLOYER = False
    IMPORT_ERROR = traceback.format_exc()

DEVICE_SPEC = dict(
    name=dict(type="str", required=True),
    url=dict(type="str", required=True),
    unit=dict(type="int", default=1),
    profile=dict(type="str"),
    parameters=dict(type="dict", default={}),
)

# The options of the deployer.modbus.target documentation fragment.
TARGET_ARGS = dict(
    device=dict(type="str"),
    unit=dict(type="int"),
    devices=dict(type="list", elements="dict", options=DEVICE_SPEC),
    inventory=dict(type="path"),
    limit=dict(type="str"),
    allow_broadcast=dict(type="bool", default=False),
    parallel=dict(type="int", default=8),
    timeout=dict(type="float"),
    retries=dict(type="int"),
)

TARGET_EXCLUSIVE = [("device", "devices", "inventory")]

UNIT_RANGE = (0, 247)


def check_target_args(module):
    """Refuse out-of-range and contradictory target options before anything is sent."""
    p = module.params
    problems = []
    lo, hi = UNIT_RANGE
    units = [("unit", p.get("unit"))]
    units += [(f"devices[{i}].unit", d.get("unit")) for i, d in enumerate(p.get("devices") or [])]
    for what, unit in units:
        if unit is None:
            continue
        if not lo <= unit <= hi:
            problems.append(f"{what} must be from 1 to 247 (0 is broadcast), got {unit}")
        elif unit == 0 and not p.get("allow_broadcast"):
            problems.append(f"{what} is 0, which is broadcast: nobody answers it, so nothing can be verified; "
                            "set allow_broadcast: true to send it anyway")
    # deployer's bounds (deployer.LIMITS), the same the command line and the Python API check
    for key in ("parallel", "timeout", "retries"):
        if p.get(key) is not None:
            why = getattr(LIMITS, key).problem(p[key], key)
            if why is not None:
                problems.append(why)
    if p.get("limit") and p.get("device"):
        problems.append("limit selects from devices or an inventory; device names one device already")
    names = [d["name"] for d in p.get("devices") or []]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        problems.append("devices lists " + ", ".join(repr(n) for n in twice) + " more than once")
    if problems:
        module.fail_json(msg="; ".join(problems) + "; nothing was sent", errors=problems)


def require_deployer(module):
    if not HAS_DEPLOYER:
        module.fail_json(msg=f"the deployer Python package is not importable by {sys.executable}; set "
                             "ansible_python_interpreter to a Python that has it (pip install modbus-deployer)",
                         exception=IMPORT_ERROR)


def input_error(module, e):
    """An invalid recipe, profile, inventory or option: every problem, with its position, nothing sent."""
    if isinstance(e, InputError):
        module.fail_json(msg="invalid input; nothing was sent: " + "; ".join(str(d) for d in e.diagnostics),
                         errors=[str(d) for d in e.diagnostics])
    module.fail_json(msg=f"{e}; nothing was sent")


def recipe_of(module):
    """The task's recipe: a recipe file, inline parameters over a profile, or both (parameters win);
    None with a deployer inventory and none of these: each device's recipe from the inventory."""
    p = module.params
    if p.get("inventory") and not (p.get("recipe") or p.get("profile") or p.get("parameters")):
        return None
    if p.get("recipe"):
        rec = deployer.load_recipe(p["recipe"])
        if p.get("parameters"):
            rec = deployer.recipe_from(rec.profile, p["parameters"], base=rec)
        return rec
    if not p.get("profile"):
        raise UsageError("pass recipe (a recipe file) or profile with parameters")
    return deployer.recipe_from(p["profile"], p.get("parameters") or {}, name=p.get("name") or "ansible")


def jobs_of(module, rec):
    """One job per device the task names: device/unit, a devices list (host vars), or a deployer inventory."""
    p = module.params
    if p.get("inventory"):
        return fleet_jobs(rec, p["inventory"], limit=p.get("limit"), timeout=p.get("timeout"),
                          retries=p.get("retries"), unit=p.get("unit"))
    if p.get("devices"):  # host vars: the same rules as a deployer inventory (own profile, overrides)
        if rec.path is None and any(d.get("profile") for d in p["devices"]):
            raise UsageError("a device with its own profile needs a recipe file (recipe:), not only parameters")
        inv = inventory_from([{k: v for k, v in d.items() if v is not None} for d in p["devices"]],
                             name="devices")
        return fleet_jobs(rec, inv, limit=p.get("limit"), timeout=p.get("timeout"), retries=p.get("retries"))
    url = p.get("device") or (rec.device.url if rec.device else None)
    if not url:
        raise UsageError("no device: pass device (a URL), devices, inventory, or set device.url in the recipe")
    unit = p["unit"] if p.get("unit") is not None else (
        rec.device.unit if rec.device and rec.device.unit is not None else 1)
    return [Job(p.get("name") or rec.name, rec, device_url(url, timeout=p.get("timeout"), retries=p.get("retries")),
                unit)]


def refuse_one_device_twice(jobs):
    """Two names for one device (same address and unit, any spelling) would write it twice in one run."""
    seen = {}
    for j in jobs:
        for key in ((k, j.unit) for k in j.url.lock_keys):  # resolved addresses: localhost is 127.0.0.1
            if key in seen:
                raise UsageError(f"{seen[key][0]!r} and {j.name!r} are one device ({seen[key][1]} and "
                                 f"{describe_url(j.url)}, unit {j.unit}); list it once")
            seen[key] = (j.name, describe_url(j.url))
    return jobs


READ_ARGS = dict(profile=dict(type="str"), recipe=dict(type="path"), name=dict(type="str"),
                 parameters=dict(type="list", elements="str"))


def read_devices(module):
    """Read the devices a read-only task names: (read jobs, {name: values or the exception}). Writes nothing."""
    p = module.params
    if p.get("recipe"):
        base = deployer.load_recipe(p["recipe"])
    elif p.get("profile"):
        base = deployer.recipe_from(p["profile"], {}, name=p.get("name") or "pulled")
    else:
        raise UsageError("pass profile (or recipe)")
    jobs = refuse_one_device_twice(jobs_of(module, base))
    read = []
    for j in jobs:
        prof = j.recipe.profile
        names = p.get("parameters") or ([d.name for d in j.recipe.desired] if p.get("recipe") else pull_names(prof))
        unknown = [n for n in names if prof.get(n) is None]
        if unknown:
            raise UsageError(f"unknown parameter {', '.join(unknown)} in profile {prof.id}")
        read.append(ReadJob(j.name, prof, tuple(names), j.url, j.unit))
    return read, read_fleet(read, parallel=p["parallel"])


def values_text(read, values):
    """(facts: name -> parameter -> engineering text, raw: name -> parameter -> words, unreachable lines)."""
    facts, raw, down = {}, {}, []
    for j in read:
        cur = values[j.name]
        if isinstance(cur, Exception):
            down.append(f"{j.name}: {cur}")
            continue
        facts[j.name] = {n: j.profile.parameter(n).format_registers(v) for n, v in cur.items()}
        raw[j.name] = {n: list(v) for n, v in cur.items()}
    return facts, raw, down
