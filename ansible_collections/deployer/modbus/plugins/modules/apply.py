#!/usr/bin/python
# A task that deploys a recipe to Modbus devices with deployer (run on the site gateway).

from __future__ import annotations

DOCUMENTATION = r"""
module: apply
short_description: Deploy a parameter set (recipe) to Modbus devices, verified by reading back
description:
  - Plans the fewest Modbus write requests from what each device holds now, writes only the
    parameters that differ, reads everything back and reports per parameter.
  - In check mode it reads the devices and plans, and writes nothing.
  - With C(--diff) it shows each changed parameter's value before and after, per device.
  - C(changed) is true only when something was written. The task fails when any device ends
    C(partial), C(failed), C(unreachable) or C(skipped), naming the devices and parameters.
  - Runs deployer's Python API; the target's Python (ansible_python_interpreter) needs deployer installed.
options:
  recipe:
    description: A recipe file on the target. With I(inventory) it may be left out (with I(profile) and
      I(parameters)); then each device gets the recipe the inventory gives it.
    type: path
  profile: {description: A built-in profile id or a profile file, when no recipe file is given., type: str}
  parameters: {description: Parameter values (engineering units, e.g. "10 s"); over the recipe's., type: dict}
  name: {description: The device's name in the report (one device)., type: str}
  device: {description: 'Device URL, e.g. tcp://10.0.0.11:502 or rtu:///dev/ttyUSB0?baudrate=19200.', type: str}
  unit: {description: Modbus unit id (default the recipe's, else 1)., type: int}
  devices:
    description: Several devices (e.g. from host vars), each with name, url, unit, and optional profile and parameters.
    type: list
    elements: dict
  inventory:
    description: A deployer inventory file on the target (all its devices or those I(limit) selects).
    type: path
  limit: {description: Inventory selection (names, groups, globs; @REPORT.json)., type: str}
  parallel:
    description: Devices at once on this gateway (one bus is always one device at a time).
    type: int
    default: 8
  batch: {description: 'Staged rollout within this task, e.g. "1,50%".', type: str}
  max_failures:
    description: After this many devices did not end ok (failed, partial and unreachable count, skipped ones
      never) start no new one (N or P%).
    type: str
  timeout: {description: Seconds per request attempt., type: float}
  retries: {description: Retries after a timeout or a busy answer., type: int}
  write_all: {description: Write every parameter even when the device already holds it., type: bool, default: false}
  on_error: {description: After a rejected value, send the rest (continue) or not (stop)., type: str, default: continue,
             choices: [continue, stop]}
  state_dir: {description: Where snapshots and the journal go on the target., type: path, default: .deployer}
  report: {description: Also write the report JSON to this file on the target., type: path}
"""

EXAMPLES = r"""
- name: Line 3 drives get the new ramps
  deployer.modbus.apply:
    recipe: /srv/recipes/line3.yaml
    devices: "{{ modbus_devices }}"
    state_dir: /var/lib/deployer
"""

RETURN = r"""
changed: {description: Whether any write request was sent., type: bool, returned: always}
devices: {description: Per device its status and the parameters it changed or failed., type: list, returned: always}
report: {description: The deployer report (schema deployer.report/1); not in check mode., type: dict, returned: success}
plans:
  description: 'Check mode: per device what would be written (deployer.plan/1).'
  type: list
  returned: check mode
"""

import asyncio  # noqa: E402

from ansible.module_utils.basic import AnsibleModule  # noqa: E402

from ansible_collections.deployer.modbus.plugins.module_utils.deployer_common import (  # noqa: E402
    TARGET_ARGS,
    input_error,
    jobs_of,
    recipe_of,
    require_deployer,
)


def _diff(name, rows):
    """Ansible's before/after text for one device: one line per parameter that changes."""
    return {"before_header": name, "after_header": name,
            "before": "".join(f"{n}: {b}\n" for n, b, _ in rows), "after": "".join(f"{n}: {a}\n" for n, _, a in rows)}


def check(module, jobs):
    """Check mode: read each device, plan against what it holds, write nothing."""
    from deployer.api import read_fleet, read_jobs
    from deployer.planning.model import Target
    from deployer.planning.planfile import plan_to_json
    from deployer.planning.planner import make_plan
    from deployer.transport.clients import describe

    values = read_fleet(read_jobs(jobs), parallel=module.params["parallel"])
    plans, diffs, devices, down = [], [], [], []
    for j in jobs:
        cur = values[j.name]
        if isinstance(cur, Exception):
            down.append(f"{j.name}: {cur}")
            devices.append({"name": j.name, "status": "unreachable", "error": str(cur)})
            continue
        plan = make_plan(j.recipe, Target(describe(j.url), j.unit, j.recipe.profile_ref or j.recipe.profile.id), cur,
                         write_all=module.params["write_all"])
        rows = [(pp.name, j.recipe.profile.parameter(pp.name).format_registers(pp.current_raw)
                 if pp.current_raw is not None else "?", pp.desired)
                for pp in plan.parameters if pp.action == "write"]
        plans.append({"name": j.name, "plan": plan_to_json(plan)})
        devices.append({"name": j.name, "status": "would change" if plan.writes else "ok",
                        "changes": [n for n, _, _ in rows]})
        if rows:
            diffs.append(_diff(j.name, rows))
    result = {"changed": any(p["plan"]["writes"] for p in plans), "plans": plans, "devices": devices,
              "diff": diffs}
    if down:
        module.fail_json(msg="unreachable: " + "; ".join(down), **result)
    module.exit_json(**result)


def apply(module, rec, jobs):
    from deployer.api import run_fleet_async
    from deployer.execute.session import ApplyOptions

    p = module.params
    options = ApplyOptions(on_error=p["on_error"], write_all=p["write_all"], state_dir=p["state_dir"])
    report = asyncio.run(run_fleet_async(jobs, recipe_name=None if rec is None else rec.path or rec.name,
                                         parallel=p["parallel"],
                                         batch=p.get("batch"), max_failures=p.get("max_failures"), options=options,
                                         report_path=p.get("report")))
    devices, diffs, problems = [], [], []
    for d in report.devices:
        changed = [(q.name, q.before or "?", q.after or q.desired) for q in d.parameters
                   if q.status == "ok" and q.before_raw != q.after_raw]
        bad = [q for q in d.parameters if q.status in ("failed", "mismatch", "unverified")]
        devices.append({"name": d.name, "status": d.status, "changed": [n for n, _, _ in changed],
                        "failed": {q.name: q.error for q in bad}, "error": d.error})
        if changed:
            diffs.append(_diff(d.name, changed))
        if d.status != "ok":
            what = ", ".join(f"{q.name} {q.status}" + (f" ({q.error})" if q.error else "") for q in bad)
            problems.append(f"{d.name} {d.status}" + (f": {what}" if what else "") + (f" - {d.error}" if d.error
                                                                                     else ""))
    result = {"changed": any(d.write_requests for d in report.devices), "devices": devices,
              "report": report.to_json(), "diff": diffs}
    if problems:
        module.fail_json(msg="; ".join(problems), **result)
    module.exit_json(**result)


def main():
    module = AnsibleModule(
        argument_spec=dict(
            recipe=dict(type="path"), profile=dict(type="str"), parameters=dict(type="dict"), name=dict(type="str"),
            batch=dict(type="str"), max_failures=dict(type="str"), write_all=dict(type="bool", default=False),
            on_error=dict(type="str", default="continue", choices=["continue", "stop"]),
            state_dir=dict(type="path", default=".deployer"), report=dict(type="path"), **TARGET_ARGS),
        supports_check_mode=True,
    )
    require_deployer(module)
    from deployer.load.diagnostics import InputError, UsageError

    try:
        rec = recipe_of(module)
        jobs = jobs_of(module, rec)
        if module.check_mode:
            check(module, jobs)
        else:
            apply(module, rec, jobs)
    except (InputError, UsageError) as e:
        input_error(module, e)


if __name__ == "__main__":
    main()
