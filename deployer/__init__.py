"""deployer: declarative parameter-set deployment to Modbus devices."""

__version__ = "0.1.0"
