"""pyserial URL handler ``pty://<path>``: a POSIX serial port on a pty whose
modem lines (DTR, RTS) are recorded instead of raising ``ENOTTY``.

``serial.serial_for_url("pty:///tmp/x/ttyUSB0")`` finds this module because
:mod:`isac_twin.devices.ptyserial` adds ``isac_twin.devices.urlhandler`` to
``serial.protocol_handler_packages``. Each change is appended to
:attr:`Serial.modem_log` and forwarded to the emulator serving the pty.
"""

from __future__ import annotations

import time

import serial
from serial import serialposix

from ..ptyserial import notify_modem

SCHEME = "pty://"


class Serial(serialposix.Serial):
    """A pty-backed serial port with recorded modem lines."""

    def __init__(self, *args, **kwargs) -> None:
        #: ``(monotonic time s, line, state)`` for every DTR/RTS change.
        self.modem_log: list[tuple[float, str, bool]] = []
        super().__init__(*args, **kwargs)

    def from_url(self, url: str) -> str:
        """Return the filesystem path of a ``pty://<path>`` URL."""
        if not url.lower().startswith(SCHEME):
            raise serial.SerialException(f"expected a URL of the form pty://<path>, got {url!r}")
        return url[len(SCHEME):]

    def open(self) -> None:
        self.portstr = self.from_url(self._port)
        super().open()

    def _record(self, line: str, state: bool) -> None:
        self.modem_log.append((time.monotonic(), line, bool(state)))
        notify_modem(self.portstr, line, bool(state))

    def _update_dtr_state(self) -> None:
        self._record("DTR", self._dtr_state)

    def _update_rts_state(self) -> None:
        self._record("RTS", self._rts_state)

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True
