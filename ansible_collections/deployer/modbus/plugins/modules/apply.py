#!/usr/bin/python
# A task that deploys a recipe to Modbus devices with deployer (run on the site gateway).
# Copyright: deployer maintainers. MIT License (see the project's LICENSE).

from __future__ import annotations

DOCUMENTATION = r"""
module: apply
short_description: Deploy a parameter set (recipe) to Modbus devices, verified by reading back
description:
  - Plans the fewest Modbus write requests from what each device holds now, writes only the
    parameters that differ, reads everything back and reports per parameter.
  - In check mode it reads the devices and plans, and writes nothing.
  - In diff mode it shows each changed parameter's value before and after, per device.
  - C(changed) is true only when something was written. The task fails when any device does not end
    C(ok), naming the devices and parameters.
  - Runs deployer's Python API on the target, whose Python (C(ansible_python_interpreter)) needs
    deployer installed. The run is journaled in O(state_dir) like a command-line run, so
    C(deployer status) sees it.
  - With O(agent) the run happens in a site agent (C(deployer agent)) over its HTTP API, through
    deployer's Python client. The agent's inventory and recipes are the desired state, O(limit)
    selects its devices, and the agent executes with every guarantee of a command-line run. In
    check mode the agent reads its files again and checks the selected devices; nothing is written
    or adopted. Roll sites out one at a time with C(serial=1) and C(max_fail_percentage=0) on the play.
version_added: 0.1.0
author:
  - deployer maintainers (@deployer)
extends_documentation_fragment:
  - ansible.builtin.action_common_attributes
  - deployer.modbus.target
  - deployer.modbus.target.agent
attributes:
  check_mode:
    support: full
    details: Reads every device and plans; sends no write request.
  diff_mode:
    support: full
  platform:
    platforms: posix
options:
  recipe:
    description:
      - A recipe file on the target.
      - With O(inventory) it may be left out (and O(profile) with O(parameters) too); then each device
        gets the recipe the inventory gives it.
    type: path
  profile:
    description: A built-in profile id or a profile file, when no recipe file is given.
    type: str
  parameters:
    description: Parameter values in engineering units (for example V(10 s)), over the recipe's.
    type: dict
  name:
    description: The device's name in the report, for O(device).
    type: str
  batch:
    description:
      - A staged rollout within this task, for example V(1,50%) (a canary device of each profile, then half of
        each profile, then the rest).
      - Each batch takes its count or share of every profile (or group, O(batch_by)); any canary device that
        does not end ok ends the rollout.
    type: str
  batch_by:
    description: What each O(batch) share is taken of, every profile or every group (a device's first group).
    type: str
    choices: [profile, group]
    default: profile
  max_failures:
    description:
      - After this many devices did not end ok (failed, partial and unreachable count, skipped ones
        never), start no new one.
      - A number V(N) or a percentage V(P%).
    type: str
  write_all:
    description: Write every parameter even when the device already holds it.
    type: bool
    default: false
  on_error:
    description: After a rejected value, send the rest (V(continue)) or not (V(stop)).
    type: str
    default: continue
    choices: [continue, stop]
  state_dir:
    description: Where snapshots, locks and the journal go on the target.
    type: path
    default: .deployer
  report:
    description: Also write the report JSON to this file on the target (a new path or a regular file).
    type: path
  soak:
    description:
      - After the verified write, read the profile's health checks for this long (for example V(30s),
        V(5m); a bare number is seconds).
      - A failed check rolls that device back from its snapshot (status C(rolled-back), the task fails);
        the profile's commit is sent only after the soak passed.
      - With O(batch), each batch soaks together and a health failure in the first batch ends the rollout.
    type: str
  health_interval:
    description: Time between two rounds of health checks during the soak.
    type: str
    default: 1s
  allow_unhealthy:
    description:
      - With O(soak), the health checks are read before the first write too, and a device already failing one
        is not written (status C(failed), "health check already failing before the change").
      - V(true) writes it anyway; its soak then does not hold the checks that were failing before against the change.
    type: bool
    default: false
  rollback_on_failure:
    description: When the rollout stops (a failed batch, O(max_failures)), roll back every device it wrote.
    type: bool
    default: false
notes:
  - With O(agent), O(report) is not taken and O(recipe), if given, must be the recipe the agent's inventory
    names for the selected devices (the agent holds one desired state; edit its files instead).
  - One bus is one device at a time whatever O(parallel) says; a device is locked for the run.
seealso:
  - module: deployer.modbus.info
"""

EXAMPLES = r"""
- name: Line 3 drives get the new ramps
  deployer.modbus.apply:
    recipe: /srv/recipes/line3.yaml
    devices: "{{ modbus_devices }}"
    state_dir: /var/lib/deployer

- name: Through the site's agent (its inventory and recipes are the desired state), one canary first
  deployer.modbus.apply:
    agent:
      url: https://gw-line3:8470
      token: "{{ vault_line3_agent_token }}"
      ca: /etc/deployer/site-ca.crt
    limit: line3
    batch: "1,100%"

- name: New ramps, kept only if the drives stay healthy for 5 minutes (one canary first)
  deployer.modbus.apply:
    recipe: /srv/recipes/line3.yaml
    inventory: /srv/inventory.yaml
    batch: "1,100%"
    soak: 5m
"""

RETURN = r"""
devices:
  description: Per device its status and the parameters it changed or failed.
  type: list
  elements: dict
  returned: always
report:
  description: The deployer report (schema C(deployer.report/3)).
  type: dict
  returned: when not in check mode
run:
  description: The run's id in the journal (C(audit.jsonl) in I(state_dir); C(deployer status) lists it).
  type: str
  returned: when not in check mode
plans:
  description: In check mode, per device every step an apply would take (schema C(deployer.plan/2)).
  type: list
  elements: dict
  returned: in check mode
"""

from ansible.module_utils.basic import AnsibleModule  # noqa: E402

from ansible_collections.deployer.modbus.plugins.module_utils.deployer_agent import (  # noqa: E402
    AGENT_SPEC,
    agent_apply,
    agent_check,
    agent_exclusive,
    agent_failed,
    client_of,
)
from ansible_collections.deployer.modbus.plugins.module_utils.deployer_common import (  # noqa: E402
    TARGET_ARGS,
    TARGET_EXCLUSIVE,
    check_target_args,
    input_error,
    recipe_of,
    require_deployer,
    targets_of,
)


def _diff(name, rows):
    """Ansible's before/after text for one device: one line per parameter that changes."""
    return {
        "before_header": name,
        "after_header": name,
        "before": "".join(f"{n}: {b}\n" for n, b, a in rows),
        "after": "".join(f"{n}: {a}\n" for n, b, a in rows),
    }


def check(module, rec):
    """Check mode: read each device, plan against what it holds, write nothing."""
    import deployer

    p = module.params
    fleet = deployer.plan(
        rec, parallel=p["parallel"], write_all=p["write_all"], state_dir=p["state_dir"], **targets_of(module, rec)
    )
    plans, diffs, devices, down = [], [], [], []
    for name, error in fleet.errors.items():
        down.append(f"{name}: {error}")
    for name in fleet:
        if name in fleet.errors:
            devices.append({"name": name, "status": "unreachable", "error": str(fleet.errors[name])})
            continue
        plan, profile = fleet[name], fleet.profile(name)
        rows = [
            (
                pp.name,
                profile.parameter(pp.name).format_registers(pp.current_raw) if pp.current_raw is not None else "?",
                pp.desired,
            )
            for pp in plan.parameters
            if pp.action == "write"
        ]
        plans.append({"name": name, "plan": plan.to_json()})
        devices.append(
            {"name": name, "status": "would change" if plan.writes else "ok", "changes": [row[0] for row in rows]}
        )
        if rows:
            diffs.append(_diff(name, rows))
    result = {
        "changed": any(s["kind"] == "write" for p in plans for s in p["plan"]["steps"]),
        "plans": plans,
        "devices": devices,
        "diff": diffs,
    }
    if down:
        module.fail_json(msg="unreachable: " + "; ".join(down), **result)
    module.exit_json(**result)


def apply(module, rec):
    import deployer
    from deployer.api import RunInterrupted

    p = module.params
    interrupted = None
    try:  # one journaled run (deployer status sees it); SIGINT/SIGTERM end it with its report
        report = deployer.apply(
            rec,
            parallel=p["parallel"],
            batch=p.get("batch"),
            batch_by=p["batch_by"],
            max_failures=p.get("max_failures"),
            on_error=p["on_error"],
            write_all=p["write_all"],
            allow_broadcast=p["allow_broadcast"],
            state_dir=p["state_dir"],
            soak=p.get("soak"),
            health_interval=p["health_interval"],
            allow_unhealthy=p["allow_unhealthy"],
            rollback_on_failure=p["rollback_on_failure"],
            report_path=p.get("report"),
            signals=True,
            caller="ansible deployer.modbus.apply",
            **targets_of(module, rec),
        )
    except RunInterrupted as e:
        report, interrupted = e.report, e
    devices, diffs, problems = [], [], []
    for d in report.devices:
        changed = [
            (q.name, q.before or "?", q.after or q.desired)
            for q in d.parameters
            if q.status == "ok" and q.before_raw != q.after_raw
        ]
        bad = [q for q in d.parameters if q.status in ("failed", "mismatch", "unverified")]
        devices.append(
            {
                "name": d.name,
                "status": d.status,
                "changed": [row[0] for row in changed],
                "failed": {q.name: q.error for q in bad},
                "error": d.error,
            }
        )
        if changed:
            diffs.append(_diff(d.name, changed))
        if d.status != "ok":
            what = ", ".join(f"{q.name} {q.status}" + (f" ({q.error})" if q.error else "") for q in bad)
            problems.append(
                f"{d.name} {d.status}" + (f": {what}" if what else "") + (f" - {d.error}" if d.error else "")
            )
    result = {
        "changed": any(d.write_requests for d in report.devices),
        "devices": devices,
        "report": report.to_json(),
        "diff": diffs,
        "run": report.run_id,
    }
    if interrupted is not None:
        problems.insert(0, f"{interrupted} (run {report.run_id} in {report.state_dir})")
    if problems:
        module.fail_json(msg="; ".join(problems), **result)
    module.exit_json(**result)


def main():
    module = AnsibleModule(
        argument_spec=dict(
            recipe=dict(type="path"),
            profile=dict(type="str"),
            parameters=dict(type="dict"),
            name=dict(type="str"),
            batch=dict(type="str"),
            batch_by=dict(type="str", default="profile", choices=["profile", "group"]),
            max_failures=dict(type="str"),
            write_all=dict(type="bool", default=False),
            on_error=dict(type="str", default="continue", choices=["continue", "stop"]),
            state_dir=dict(type="path", default=".deployer"),
            report=dict(type="path"),
            soak=dict(type="str"),
            health_interval=dict(type="str", default="1s"),
            allow_unhealthy=dict(type="bool", default=False),
            rollback_on_failure=dict(type="bool", default=False),
            agent=dict(type="dict", options=AGENT_SPEC),
            **TARGET_ARGS,
        ),
        mutually_exclusive=TARGET_EXCLUSIVE + agent_exclusive(("report",)),
        supports_check_mode=True,
    )
    require_deployer(module)
    check_target_args(module)
    from deployer.api import DeployerError, InputError, UsageError
    from deployer.errors import AgentError

    if module.params["allow_unhealthy"] and not module.params.get("soak"):
        module.fail_json(
            msg="allow_unhealthy goes with soak (only a soak reads the health checks before it "
            "writes); nothing was sent"
        )

    if module.params.get("agent"):  # the agent executes; nothing here talks Modbus or writes a state folder
        try:
            client = client_of(module)
            if module.check_mode:
                agent_check(module, client)
            else:
                agent_apply(module, client)
        except AgentError as e:
            agent_failed(module, e)
        return
    _check_outputs(module)
    try:
        rec = recipe_of(module)
        if module.check_mode:
            check(module, rec)
        else:
            apply(module, rec)
    except (InputError, UsageError) as e:
        input_error(module, e)
    except DeployerError as e:  # a device or lock error before any device's run (each one's is in the report)
        module.fail_json(msg=f"{type(e).__name__}: {e}")
    except OSError as e:  # the state folder or the report file failed during the run
        module.fail_json(
            msg=f"cannot write {e.filename or p_state(module)}: {e.strerror or e}; the report of "
            "the run is in the journal (deployer status)"
        )


def p_state(module):
    return module.params["state_dir"]


def _check_outputs(module):
    """The state folder and the report file must be usable before anything is sent."""
    import os

    p = module.params
    report = p.get("report")
    if report and os.path.lexists(report) and not os.path.isfile(report):
        module.fail_json(msg=f"report {report} exists and is not a regular file; nothing was sent")
    if report and not os.path.isdir(os.path.dirname(os.path.abspath(report))):
        module.fail_json(msg=f"report {report}: its folder does not exist; nothing was sent")
    try:
        os.makedirs(p["state_dir"], exist_ok=True)
    except OSError as e:
        module.fail_json(msg=f"state_dir {p['state_dir']}: {e.strerror or e}; nothing was sent")
    if not os.path.isdir(p["state_dir"]) or not os.access(p["state_dir"], os.W_OK | os.X_OK):
        module.fail_json(msg=f"state_dir {p['state_dir']} is not a writable folder; nothing was sent")


if __name__ == "__main__":
    main()
