# Which devices a deployer.modbus task talks to: the options every module of the collection shares.

from __future__ import annotations


class ModuleDocFragment:
    DOCUMENTATION = r"""
options:
  device:
    description:
      - One device's URL, for example V(tcp://10.0.0.11:502) or V(rtu:///dev/ttyUSB0?baudrate=19200).
      - Without O(device), O(devices) or O(inventory), the recipe's C(device.url) is used.
      - Mutually exclusive with O(devices) and O(inventory).
    type: str
  unit:
    description:
      - Modbus unit id (slave address) of O(device), from 1 to 247; the default is the recipe's, else 1.
      - With O(inventory), overrides every device's unit.
      - V(0) is broadcast, refused unless O(allow_broadcast=true).
    type: int
  devices:
    description:
      - Several devices, for example from host vars; the same rules as a deployer inventory.
      - Names and devices must be unique, whatever the spelling of the URL.
      - Mutually exclusive with O(device) and O(inventory).
    type: list
    elements: dict
    suboptions:
      name:
        description: The device's name in the report and the facts.
        type: str
        required: true
      url:
        description: The device's URL.
        type: str
        required: true
      unit:
        description: Modbus unit id, from 1 to 247 (V(0), broadcast, only with O(allow_broadcast=true)).
        type: int
        default: 1
      profile:
        description: The device's own profile (a built-in id or a file on the target), over the recipe's.
        type: str
      parameters:
        description: The device's own parameter values, over the recipe's.
        type: dict
        default: {}
  inventory:
    description:
      - A deployer inventory file on the target; all its devices, or those O(limit) selects.
      - Mutually exclusive with O(device) and O(devices).
    type: path
  limit:
    description:
      - Which devices of O(inventory) or O(devices) this task means - names, groups, globs, V(!NAME) to
        exclude, or V(@REPORT.json) for the devices that did not end ok in an earlier run.
      - Refused with O(device), which names one device already.
    type: str
  allow_broadcast:
    description: Allow unit V(0) (broadcast). Nobody answers a broadcast, so nothing can be verified.
    type: bool
    default: false
  parallel:
    description: Devices at once on this gateway, from 1 to 1024. One bus is always one device at a time.
    type: int
    default: 8
  timeout:
    description: Seconds per request attempt, more than 0 and at most 600; the default is the URL's, else 1.
    type: float
  retries:
    description: Retries after a timeout or a busy answer, from 0 to 20; the default is the URL's, else 2.
    type: int
"""

    # deployer.modbus.target.agent: the modules that can go through a site agent instead of Modbus
    AGENT = r"""
options:
  agent:
    description:
      - Go through the site agent (C(deployer agent)) at O(agent.url) instead of talking Modbus from this module.
      - The agent's inventory says where its devices are, so not with O(device), O(devices), O(inventory),
        O(profile), O(parameters), O(name), O(unit), O(timeout) or O(retries); O(limit) selects its devices.
    type: dict
    suboptions:
      url:
        description: The agent's address, for example V(https://gw-line3:8470).
        type: str
        required: true
      token:
        description: The agent's token (C(deployer agent --token-file)); keep it in Ansible Vault.
        type: str
      token_file:
        description:
          - A file on the target whose first line is the token (when O(agent.token) is not given).
          - With neither, for a loopback O(agent.url), the token an agent of the same user on the target made itself
            (C(deployer agent) without C(--token-file)), as the C(deployer) commands find it.
        type: path
      ca:
        description: A CA certificate (PEM) on the target that the agent's TLS certificate is checked against.
        type: path
      cert:
        description:
          - A client certificate (PEM) on the target, for an agent that maps certificates to its users
            (C(deployer agent --tls-client-ca) with C(--users)); with O(agent.key), instead of a token.
        type: path
      key:
        description: The private key (PEM) of O(agent.cert), on the target.
        type: path
      timeout:
        description: Seconds to wait for each answer of the agent.
        type: float
        default: 30.0
"""
