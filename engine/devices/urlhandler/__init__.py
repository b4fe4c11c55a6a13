"""pyserial URL handlers (``serial.serial_for_url``) registered by :mod:`engine.devices.ptyserial`."""
