"""This system's serial ports, as pyserial's ``list_ports`` sees them (``deployer scan --list-ports``).

On Windows the names are COM ports (``rtu://COM3``); on Linux /dev/ttyUSB0, /dev/ttyACM0 and the
stable /dev/serial/by-id/ links; on macOS /dev/cu.usbserial-*. USB adapters say their vendor and
product: that is how the laptop's RS-485 adapter is told from a modem or a Bluetooth port.
"""

from __future__ import annotations

from dataclasses import dataclass

from .urls import windows_port


@dataclass(frozen=True)
class SerialPort:
    device: str  # what the URL names: COM3, /dev/ttyUSB0
    description: str
    hwid: str  # USB VID:PID and serial number, where the adapter is on USB
    manufacturer: str | None = None

    @property
    def url(self) -> str:
        return f"rtu://{windows_port(self.device) or self.device}"

    def to_json(self) -> dict[str, str | None]:
        return {
            "device": self.device,
            "url": self.url,
            "description": self.description,
            "hwid": self.hwid,
            "manufacturer": self.manufacturer,
        }


def serial_ports() -> list[SerialPort]:
    """Every serial port pyserial finds, sorted by name (COM2 before COM10)."""
    import re

    from serial.tools import list_ports

    def order(p: SerialPort) -> tuple[object, ...]:
        return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.device))

    found = [
        SerialPort(str(p.device), str(p.description or ""), str(p.hwid or ""), p.manufacturer)
        for p in list_ports.comports()
    ]
    return sorted(found, key=order)
