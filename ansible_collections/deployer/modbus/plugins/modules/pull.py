#!/usr/bin/python
# Read Modbus devices' parameters as Ansible facts (and optionally as recipe files) with deployer.

from __future__ import annotations

DOCUMENTATION = r"""
module: pull
short_description: Read devices' parameters (engineering units) as facts, optionally as recipe files
description:
  - Reads every readable, writable parameter of the profile (or only I(parameters)) from each device
    and returns them as facts under C(modbus_devices) (device name -> parameter -> value text). Writes
    nothing to any device; C(changed) is true only when a recipe file was written or changed.
  - Also available as C(deployer.modbus.facts).
options:
  profile: {description: A built-in profile id or a profile file (or the recipe's profile)., type: str}
  recipe: {description: Read only the parameters this recipe names (and use its profile)., type: path}
  parameters: {description: Read only these parameter names., type: list, elements: str}
  name: {description: The device's name in the facts (one device)., type: str}
  device: {description: Device URL., type: str}
  unit: {description: Modbus unit id., type: int}
  devices: {description: Several devices, each with name, url, unit and optional profile., type: list, elements: dict}
  inventory: {description: A deployer inventory file on the target., type: path}
  limit: {description: Inventory selection., type: str}
  parallel: {description: Devices read at once., type: int, default: 8}
  timeout: {description: Seconds per request attempt., type: float}
  retries: {description: Retries after a timeout or busy answer., type: int}
  dest:
    description: A folder on the target; one recipe per device (NAME.yaml) that applies back as a no-op.
    type: path
"""

EXAMPLES = r"""
- name: What the drives hold now
  deployer.modbus.facts:
    profile: example-inverter
    devices: "{{ modbus_devices }}"
- debug: var=ansible_facts.modbus_devices
"""

RETURN = r"""
ansible_facts:
  description: 'modbus_devices: device name -> parameter -> value (e.g. "10 s").'
  type: dict
  returned: success
raw: {description: device name -> parameter -> register words., type: dict, returned: success}
"""

import os  # noqa: E402

from ansible.module_utils.basic import AnsibleModule  # noqa: E402

from ansible_collections.deployer.modbus.plugins.module_utils.deployer_common import (  # noqa: E402
    TARGET_ARGS,
    input_error,
    jobs_of,
    require_deployer,
)


def main():
    module = AnsibleModule(
        argument_spec=dict(profile=dict(type="str"), recipe=dict(type="path"), name=dict(type="str"),
                           parameters=dict(type="list", elements="str"), dest=dict(type="path"), **TARGET_ARGS),
        supports_check_mode=True,
    )
    require_deployer(module)
    import deployer
    from deployer.api import pull_names, pulled_recipe, read_fleet
    from deployer.fleet.rollout import ReadJob
    from deployer.load.diagnostics import InputError, UsageError
    from deployer.transport.clients import describe

    p = module.params
    try:
        if p.get("recipe"):
            base = deployer.load_recipe(p["recipe"])
        elif p.get("profile"):
            base = deployer.recipe_from(p["profile"], {}, name=p.get("name") or "pulled")
        else:
            raise UsageError("pass profile (or recipe)")
        jobs = jobs_of(module, base)
        read = []
        for j in jobs:
            prof = j.recipe.profile
            names = p.get("parameters") or ([d.name for d in j.recipe.desired] if p.get("recipe") else
                                            pull_names(prof))
            read.append(ReadJob(j.name, prof, tuple(names), j.url, j.unit))
        values = read_fleet(read, parallel=p["parallel"])
    except (InputError, UsageError) as e:
        input_error(module, e)
    facts, raw, down, changed = {}, {}, [], False
    for j in read:
        cur = values[j.name]
        if isinstance(cur, Exception):
            down.append(f"{j.name}: {cur}")
            continue
        facts[j.name] = {n: j.profile.parameter(n).format_registers(v) for n, v in cur.items()}
        raw[j.name] = {n: list(v) for n, v in cur.items()}
        if p.get("dest") and not module.check_mode:
            os.makedirs(p["dest"], exist_ok=True)
            path = os.path.join(p["dest"], f"{j.name}.yaml")
            text = pulled_recipe(j.profile, cur, name=f"pulled-{j.name}", url=describe(j.url), unit=j.unit,
                                 relative_to=path)
            old = None
            if os.path.exists(path):
                with open(path, encoding="utf-8") as f:
                    old = f.read()
            if old != text:
                with open(path, "w", encoding="utf-8") as f:
                    f.write(text)
                changed = True
    result = {"changed": changed, "ansible_facts": {"modbus_devices": facts}, "raw": raw}
    if down:
        module.fail_json(msg="unreachable: " + "; ".join(down), **result)
    module.exit_json(**result)


if __name__ == "__main__":
    main()
