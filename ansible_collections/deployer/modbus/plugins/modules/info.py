#!/usr/bin/python
# Read Modbus devices' parameters as Ansible facts with deployer; writes nothing anywhere.
# Copyright: deployer maintainers. MIT License (see the project's LICENSE).

from __future__ import annotations

DOCUMENTATION = r"""
module: info
short_description: Read Modbus devices' parameters (engineering units) as facts
description:
  - Reads every readable, writable parameter of the profile (or only O(parameters), or only the
    parameters O(recipe) names) from each device and returns them as facts under C(modbus_parameters)
    (device name -> parameter -> value text). The name is not C(modbus_devices), which playbooks use
    for the list of devices in host vars.
  - Writes nothing to any device or file; C(changed) is always false. To keep the values as recipe
    files, use M(deployer.modbus.pull).
  - Also available as C(deployer.modbus.facts).
  - With O(agent) the site agent (C(deployer agent)) reads its devices now (O(limit) selects them) and the
    facts are what they hold of their adopted parameters; the agent's inventory says where they are.
version_added: 0.1.0
author:
  - deployer maintainers (@deployer)
extends_documentation_fragment:
  - ansible.builtin.action_common_attributes
  - ansible.builtin.action_common_attributes.facts
  - deployer.modbus.target
  - deployer.modbus.target.agent
attributes:
  check_mode:
    support: full
  diff_mode:
    support: none
  facts:
    support: full
  platform:
    platforms: posix
options:
  profile:
    description: A built-in profile id or a profile file (without O(recipe)).
    type: str
  recipe:
    description: Read only the parameters this recipe names, with its profile.
    type: path
  parameters:
    description: Read only these parameter names.
    type: list
    elements: str
  name:
    description: The device's name in the facts, for O(device).
    type: str
notes:
  - With O(agent), O(recipe) is not taken; the facts are the adopted parameters of the agent.
seealso:
  - module: deployer.modbus.pull
"""

EXAMPLES = r"""
- name: What the drives hold now
  deployer.modbus.info:
    profile: example-inverter
    devices: "{{ modbus_devices }}"

- name: Show them
  ansible.builtin.debug:
    var: ansible_facts.modbus_parameters
"""

RETURN = r"""
ansible_facts:
  description: Facts to add to the host.
  returned: success
  type: complex
  contains:
    modbus_parameters:
      description: Device name -> parameter -> value text (for example V(10 s)).
      type: dict
      returned: success
raw:
  description: Device name -> parameter -> register words.
  type: dict
  returned: without O(agent)
devices:
  description: With O(agent), per device its status, drift, pending changes and last check as the agent says.
  type: list
  elements: dict
  returned: with O(agent)
"""

from ansible.module_utils.basic import AnsibleModule  # noqa: E402

from ansible_collections.deployer.modbus.plugins.module_utils.deployer_agent import (  # noqa: E402
    AGENT_SPEC,
    agent_exclusive,
    agent_failed,
    agent_info,
    client_of,
)
from ansible_collections.deployer.modbus.plugins.module_utils.deployer_common import (  # noqa: E402
    READ_ARGS,
    TARGET_ARGS,
    TARGET_EXCLUSIVE,
    check_target_args,
    input_error,
    read_devices,
    require_deployer,
    values_text,
)


def main():
    module = AnsibleModule(
        argument_spec=dict(**READ_ARGS, **TARGET_ARGS, agent=dict(type="dict", options=AGENT_SPEC)),
        mutually_exclusive=TARGET_EXCLUSIVE + agent_exclusive(("recipe",)),
        supports_check_mode=True,
    )
    require_deployer(module)
    check_target_args(module)
    from deployer.api import InputError, UsageError
    from deployer.errors import AgentError

    if module.params.get("agent"):
        try:
            agent_info(module, client_of(module))
        except AgentError as e:
            agent_failed(module, e)
        return

    try:
        values = read_devices(module)
    except (InputError, UsageError) as e:
        input_error(module, e)
    facts, raw, down = values_text(values)
    result = {"changed": False, "ansible_facts": {"modbus_parameters": facts}, "raw": raw}
    if down:
        module.fail_json(msg="unreachable: " + "; ".join(down), **result)
    module.exit_json(**result)


if __name__ == "__main__":
    main()
