"""pyserial URL handlers (``serial.serial_for_url``) registered by :mod:`isac_twin.devices.ptyserial`.

No public names: pyserial finds :mod:`~isac_twin.devices.urlhandler.protocol_pty` by
its module name (``pty://``).
"""

__all__: list[str] = []
