"""pyserial URL handlers (``serial.serial_for_url``) registered by :mod:`engine.devices.ptyserial`.

No public names: pyserial finds :mod:`~engine.devices.urlhandler.protocol_pty` by
its module name (``pty://``).
"""

__all__: list[str] = []
