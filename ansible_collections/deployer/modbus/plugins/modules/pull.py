#!/usr/bin/python
# Keep Modbus devices' parameters as recipe files on the target, with deployer.
# Copyright: deployer maintainers. MIT License (see the project's LICENSE).

from __future__ import annotations

DOCUMENTATION = r"""
module: pull
short_description: Write what Modbus devices hold as recipe files, one per device
description:
  - Reads every readable, writable parameter of the profile (or only O(parameters), or only the
    parameters O(recipe) names) from each device and writes one recipe per device, C(NAME.yaml) in
    O(dest), that applies back as a no-op.
  - Writes nothing to any device. C(changed) is true when a recipe file was written or changed; in
    check mode no file is written and C(changed) says whether one would be.
  - For the values as facts only, use M(deployer.modbus.info).
version_added: 0.1.0
author:
  - deployer maintainers (@deployer)
extends_documentation_fragment:
  - ansible.builtin.action_common_attributes
  - deployer.modbus.target
attributes:
  check_mode:
    support: full
  diff_mode:
    support: none
  platform:
    platforms: posix
options:
  dest:
    description: A folder on the target for the recipe files (created if missing).
    type: path
    required: true
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
    description: The device's name (and file name), for O(device).
    type: str
seealso:
  - module: deployer.modbus.info
"""

EXAMPLES = r"""
- name: Keep what the drives hold as recipes
  deployer.modbus.pull:
    profile: example-inverter
    devices: "{{ modbus_devices }}"
    dest: /srv/recipes/as-found
"""

RETURN = r"""
files:
  description: The recipe files written (or, in check mode, that would be written).
  type: list
  elements: str
  returned: success
values:
  description: Device name -> parameter -> value text (for example V(10 s)).
  type: dict
  returned: success
"""

import os  # noqa: E402
import tempfile  # noqa: E402

from ansible.module_utils.basic import AnsibleModule  # noqa: E402

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
        argument_spec=dict(dest=dict(type="path", required=True), **READ_ARGS, **TARGET_ARGS),
        mutually_exclusive=TARGET_EXCLUSIVE,
        supports_check_mode=True,
    )
    require_deployer(module)
    check_target_args(module)
    from deployer.api import InputError, UsageError

    p = module.params
    if os.path.exists(p["dest"]) and not os.path.isdir(p["dest"]):
        module.fail_json(msg=f"dest {p['dest']} is not a folder; nothing was read")
    try:
        values = read_devices(module)
    except (InputError, UsageError) as e:
        input_error(module, e)
    facts, down = values_text(values)[::2]  # not the raw words
    files, changed = [], False
    for name, cur in values.items():
        if isinstance(cur, Exception):
            continue
        path = os.path.join(p["dest"], f"{name}.yaml")
        text = cur.recipe_text(name=f"pulled-{name}", relative_to=path)
        old = None
        if os.path.isfile(path):
            with open(path, encoding="utf-8") as f:
                old = f.read()
        if old == text:
            continue
        files.append(path)
        changed = True
        if not module.check_mode:
            try:
                os.makedirs(p["dest"], exist_ok=True)
                module.atomic_move(_written(module, text), path)
            except OSError as e:
                module.fail_json(msg=f"cannot write {path}: {e.strerror or e}", values=facts, files=files)
    result = {"changed": changed, "files": files, "values": facts}
    if down:
        module.fail_json(msg="unreachable: " + "; ".join(down), **result)
    module.exit_json(**result)


def _written(module, text):
    """The text in a temporary file of Ansible's, for atomic_move to put in place."""
    fd, tmp = tempfile.mkstemp(dir=module.tmpdir)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(text)
    return tmp


if __name__ == "__main__":
    main()
