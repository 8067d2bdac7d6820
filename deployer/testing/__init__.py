"""Test doubles for users of deployer: the simulated Modbus device."""
