# Shared by the deployer.modbus modules: which devices a task means, and the recipe for each of them.
# The modules run on the site gateway (often `connection: local`) with a Python that has deployer
# installed (ansible_python_interpreter); they call deployer's public Python API only (the names of
# deployer.__all__, and the error tree of deployer.errors), never its command line or its internal modules.

from __future__ import annotations

import sys
import traceback

try:
    import deployer
    from deployer.api import LIMITS, InputError, UsageError

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
            problems.append(
                f"{what} is 0, which is broadcast: nobody answers it, so nothing can be verified; "
                "set allow_broadcast: true to send it anyway"
            )
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
        module.fail_json(
            msg=f"the deployer Python package is not importable by {sys.executable}; set "
            "ansible_python_interpreter to a Python that has it (pip install modbus-deployer)",
            exception=IMPORT_ERROR,
        )


def input_error(module, e):
    """An invalid recipe, profile, inventory or option: every problem, with its position, nothing sent."""
    if isinstance(e, InputError):
        module.fail_json(
            msg="invalid input; nothing was sent: " + "; ".join(str(d) for d in e.diagnostics),
            errors=[str(d) for d in e.diagnostics],
        )
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


def targets_of(module, rec):
    """The devices the task names, as deployer.plan, apply and pull take them: an inventory (a deployer
    inventory file; a devices list, host vars, checked as one; or the one device) and what selects from it."""
    p = module.params
    common = {"limit": p.get("limit"), "timeout": p.get("timeout"), "retries": p.get("retries")}
    if p.get("inventory"):
        return {"inventory": p["inventory"], "unit": p.get("unit"), **common}
    if p.get("devices"):  # host vars: the same rules as a deployer inventory (own profile, overrides)
        if rec is not None and rec.path is None and any(d.get("profile") for d in p["devices"]):
            raise UsageError("a device with its own profile needs a recipe file (recipe:), not only parameters")
        devices = [{k: v for k, v in d.items() if v is not None} for d in p["devices"]]
        return {"inventory": deployer.load_inventory(devices, name="devices"), **common}
    url = p.get("device") or (rec.device.url if rec is not None and rec.device else None)
    if not url:
        raise UsageError("no device: pass device (a URL), devices, inventory, or set device.url in the recipe")
    unit = (
        p["unit"]
        if p.get("unit") is not None
        else (rec.device.unit if rec.device and rec.device.unit is not None else 1)
    )
    one = [{"name": p.get("name") or rec.name, "url": url, "unit": unit}]
    return {"inventory": deployer.load_inventory(one, name="device"), **common}


READ_ARGS = dict(
    profile=dict(type="str"),
    recipe=dict(type="path"),
    name=dict(type="str"),
    parameters=dict(type="list", elements="str"),
)


def read_devices(module):
    """Read the devices a read-only task names: {name: deployer.pull's values (with their profile and device), or
    the exception that stopped the device's read}. Writes nothing."""
    p = module.params
    if p.get("recipe"):
        base = deployer.load_recipe(p["recipe"])
    elif p.get("profile"):
        base = deployer.recipe_from(p["profile"], {}, name=p.get("name") or "pulled")
    else:
        raise UsageError("pass profile (or recipe)")
    # a recipe's parameters, or with only a profile every setting it has; parameters: only those
    return deployer.pull(base, names=p.get("parameters") or None, parallel=p["parallel"], **targets_of(module, base))


def values_text(values):
    """(facts: name -> parameter -> engineering text, raw: name -> parameter -> words, unreachable lines)."""
    facts, raw, down = {}, {}, []
    for name, cur in values.items():
        if isinstance(cur, Exception):
            down.append(f"{name}: {cur}")
            continue
        facts[name] = cur.texts()
        raw[name] = {n: list(v) for n, v in cur.items()}
    return facts, raw, down
