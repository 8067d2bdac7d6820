"""deployer: deploy parameter sets (recipes) to Modbus devices; plan, apply, verify, report."""

import logging as _logging

__version__ = "0.1.0"

# pymodbus logs every timeout and unknown unit through the root logger's last-resort handler;
# deployer reports those itself, so the library stays quiet unless the user configures logging.
_log = _logging.getLogger("pymodbus")
_log.addHandler(_logging.NullHandler())
_log.propagate = False
