"""The tamper-evident audit trail (docs/change-control.md): hash-chained records appended by every process that
changes or could change a device, verified by ``verify``, forwarded to syslog by ``forward``."""
