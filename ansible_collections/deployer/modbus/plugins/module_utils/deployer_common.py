# Shared by the deployer.modbus modules: which devices a task means, and the recipe for each of them.
# The modules run on the site gateway (often `connection: local`) with a Python that has deployer
# installed (ansible_python_interpreter); they call deployer's Python API, never its command line.

from __future__ import annotations

import sys
import traceback

try:
    import deployer
    from deployer.api import device_url, load_inventory
    from deployer.fleet.inventory import FleetDevice, Inventory, fleet_jobs
    from deployer.fleet.rollout import Job
    from deployer.load.diagnostics import InputError, UsageError
    from deployer.load.yamlsrc import Source
    from deployer.recipe.loader import Entry
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

TARGET_ARGS = dict(
    device=dict(type="str"),
    unit=dict(type="int"),
    devices=dict(type="list", elements="dict", options=DEVICE_SPEC),
    inventory=dict(type="path"),
    limit=dict(type="str"),
    parallel=dict(type="int", default=8),
    timeout=dict(type="float"),
    retries=dict(type="int"),
)


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
    given = [k for k in ("device", "devices", "inventory") if p.get(k)]
    if len(given) > 1:
        raise UsageError(f"pass only one of device, devices and inventory (got {', '.join(given)})")
    if p.get("inventory"):
        jobs = fleet_jobs(load_inventory(p["inventory"]), rec, p.get("limit"), timeout=p.get("timeout"),
                          retries=p.get("retries"), unit=p.get("unit"))
        if not jobs:
            raise UsageError(f"no device selected from {p['inventory']}")
        return jobs
    if p.get("devices"):  # host vars: the same rules as a deployer inventory (own profile, overrides)
        src = Source("<devices>")
        inv = Inventory("<devices>", tuple(
            FleetDevice(d["name"], d["url"], d.get("unit") or 1, d.get("profile"),
                        overrides=tuple(Entry(k, v, src, ("devices", d["name"], "parameters", k))
                                        for k, v in (d.get("parameters") or {}).items()))
            for d in p["devices"]))
        if rec.path is None and any(d.profile for d in inv.devices):
            raise UsageError("a device with its own profile needs a recipe file (recipe:), not only parameters")
        return fleet_jobs(inv, rec, None, timeout=p.get("timeout"), retries=p.get("retries"))
    url = p.get("device") or (rec.device.url if rec.device else None)
    if not url:
        raise UsageError("no device: pass device (a URL), devices, inventory, or set device.url in the recipe")
    unit = p.get("unit") or (rec.device.unit if rec.device and rec.device.unit is not None else 1)
    return [Job(p.get("name") or rec.name, rec, device_url(url, timeout=p.get("timeout"), retries=p.get("retries")),
                unit)]
