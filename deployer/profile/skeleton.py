"""`deployer profiles new`: a commented profile skeleton that validates as written.

Every key the schema knows appears, set to its default or commented out, with a one-line hint;
`deployer explain KEY` and docs/reference/profile.md say the rest.
"""

from __future__ import annotations

import json

_SKELETON = """\
# Device profile: the device's holding registers, one entry per parameter.
# Fill it in from the manual's communication chapter, then: deployer validate {file}
# Every key: docs/reference/profile.md, or `deployer explain KEY` (e.g. deployer explain addressing).
profile: {id}
description: >-
  Which device, and which manual pages this profile comes from (say what they do not give).

# How the numbers under `register` are written - copy the manual's numbers as they are:
#   address          0-based protocol address, as sent on the wire ("register address 1102h")
#   register-number  1-based number; wire address = number - 1 ("register number 1103h")
#   modicon          4xxxx / 4xxxxx reference; wire address = reference - 40001 ("44355")
addressing: address
# Multi-register values: big = upper word first (most manuals), little = lower word first.
word_order: big
# (Or byte_order: ABCD / CDAB / BADC / DCBA, as manuals name layouts, instead of word_order.)
# rounding: nearest        # let recipe values round to the resolution instead of being refused

limits:                    # what the device accepts per request (defaults: the protocol maximums)
  max_write_registers: 123 # registers per FC16 write (manual: "up to N registers")
  max_read_registers: 125  # registers per FC03 read
  max_frame_bytes: 256     # whole RTU frame incl. unit id and CRC; a 64-byte buffer -> 64
  # max_ascii_chars: 513   # whole ASCII frame in characters (':' ... CR LF), for devices that count so
  write_function: 16       # 6 for devices without FC16 (one register per request)
  # max_read_gap: 0        # reads may span this many undeclared registers (if the device allows it)

# identity:                # read before any write; another value means the wrong device: nothing is written
#   - {{register: 0, raw: 0x0000, description: model code}}

parameters:
  # The key is the name recipes use: the manual's code (F07) or a word (acceleration_time).
  example_parameter:
    description: the manual's name for it
    register: 0            # its first register, written as `addressing` says: 4355, 0x1103 or "1103h"
    type: uint16           # uint16 int16 (1 register), uint32 int32 float32 (2), uint64 int64 float64 (4)
    # unit: s              # engineering unit after scaling (s, ms, Hz, rpm, degC, percent, A ...)
    # scale: 0.01          # resolution: engineering = raw x scale + offset ("0.01 s units")
    # offset: 0
    # min: 0               # range in engineering units, inclusive (from the manual's parameter list)
    # max: 600
    # access: read-write   # read-only: recipes may not set it; write-only: cannot be read back
    # values: {{ramp: 0, coast: 1}}   # enumeration labels recipes may use instead of numbers
    # stage: 0             # lower stages are written first (e.g. a control mode before what it changes)
    # word_order: big      # overrides the profile's word_order
    # (A bit field sets bits: 3..5 - only those bits of the register; type: bool for one bit.)
    # default: 0           # the simulator's power-on value

# tables:                  # repeated blocks: point tables, operation data No.0..255
#   operation_data:        # entry i's field f is the parameter operation_data[i].f
#     count: 256
#     base: 0x1800         # register of entry 0
#     stride: 0x40         # registers from one entry to the next
#     fields:
#       position: {{offset: 2, type: int32}}

# preconditions:           # read before anything is written; another value refuses the device
#   - {{register: 0x0010, bits: 3, equals: 0, description: drive stopped}}

# commit:                  # written after an apply whose every value verified, e.g. store to EEPROM
#   - {{register: 0x0900, raw: 1, description: store parameters to EEPROM}}

# health:                  # read after the write while apply --soak watches; a failed check rolls back
#   - {{register: 0x0030, equals: 0, description: drive fault code is zero}}
#   - {{register: 0x0031, register_type: input, max: 850, description: DC bus below 850 V}}
"""


def profile_skeleton(profile_id: str, file: str = "FILE") -> str:
    """The skeleton's text for a profile named ``profile_id``."""
    return _SKELETON.format(id=json.dumps(profile_id) if profile_id[:1].isdigit() else profile_id, file=file)
