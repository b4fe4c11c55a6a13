"""Robot I/O: drivers for the real devices and emulators that speak their protocols.

* :mod:`isac_twin.devices.rplidar` / :mod:`isac_twin.devices.emulated_rplidar` — Slamtec RPLIDAR (serial);
* :mod:`isac_twin.devices.opencr` / :mod:`isac_twin.devices.emulated_opencr` — TurtleBot3 OpenCR
  (DYNAMIXEL Protocol 2.0 through ``dynamixel_sdk``);
* :mod:`isac_twin.devices.oakd` — Luxonis OAK-D (depthai 3, optional extra, imported lazily);
* :mod:`isac_twin.devices.base` — the shared driver lifecycle; :mod:`isac_twin.devices.conformance`
  — the checker every driver passes against its emulator;
* :mod:`isac_twin.devices.ptyserial` — the pty edge (stable paths, modem lines).

Drivers publish through a plain ``publish(topic, msg)`` callable.
"""

from ..errors import DeviceError, DeviceTimeout
from .base import DeviceDriver, DriverStats, Publish

__all__ = ["DeviceDriver", "DeviceError", "DeviceTimeout", "DriverStats", "Publish"]
