"""Robot I/O: drivers for the real devices and emulators that speak their protocols.

* :mod:`engine.devices.rplidar` / :mod:`engine.devices.emulated_rplidar` — Slamtec RPLIDAR (serial);
* :mod:`engine.devices.opencr` / :mod:`engine.devices.emulated_opencr` — TurtleBot3 OpenCR
  (DYNAMIXEL Protocol 2.0 through ``dynamixel_sdk``);
* :mod:`engine.devices.oakd` — Luxonis OAK-D (depthai 3, optional extra, imported lazily);
* :mod:`engine.devices.base` — the shared driver lifecycle; :mod:`engine.devices.conformance`
  — the checker every driver passes against its emulator;
* :mod:`engine.devices.ptyserial` — the pty edge (stable paths, modem lines).

Drivers publish through a plain ``publish(topic, msg)`` callable.
"""

from engine.devices.base import DeviceDriver, DeviceError, DeviceTimeout, DriverStats, Publish

__all__ = ["DeviceDriver", "DeviceError", "DeviceTimeout", "DriverStats", "Publish"]
