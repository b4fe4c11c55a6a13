"""The pty edge: pseudo-terminals standing in for USB serial ports.

An emulated device serves the *master* side of a pty; drivers and independent
clients (``pyrplidar``, ``dynamixel_sdk``) open the *slave* side as an
ordinary serial port, so every byte goes through the kernel's tty layer
exactly as it would through ``/dev/ttyUSB0``.

Two things a pty lacks are supplied here, and only here:

* a **stable path**: :class:`PtyPort` publishes the slave under a symlink
  (like ``/dev/serial/by-id/...``) that is removed on "unplug" and re-pointed
  at a fresh pty on "replug", so a driver reconnects to the same name;
* **modem lines**: pyserial sets DTR/RTS with the ``TIOCMBIS``/``TIOCMBIC``
  ioctls and reads CTS/DSR/RI/CD with ``TIOCMGET``; the kernel's pty driver
  has no modem lines and answers ``ENOTTY``. For a pty an emulator serves
  (:func:`register_modem_listener`), pyserial's POSIX port keeps the lines
  itself instead: a change is recorded (``Serial.modem_log``) and forwarded to
  the emulator, so an emulated RPLIDAR A1 starts its motor when DTR is cleared,
  and the inputs read as a USB serial adapter's (CTS, DSR, CD high, RI low).
  This holds for any pyserial client in the emulator's process, as shipped
  (``pyrplidar`` opens the path with plain ``serial.Serial``); on every other
  port, ``ENOTTY`` comes through unchanged. The URL handler ``pty://<path>``
  (``engine/devices/urlhandler/protocol_pty.py``) does the same for every pty.
"""

from __future__ import annotations

import errno
import functools
import logging
import os
import threading
import time
import tty
from typing import Callable

import serial
from serial import serialposix

log = logging.getLogger(__name__)

#: Package searched by ``serial.serial_for_url`` for ``protocol_<scheme>`` modules.
URL_HANDLER_PACKAGE = "isac_twin.devices.urlhandler"
if URL_HANDLER_PACKAGE not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append(URL_HANDLER_PACKAGE)

ModemListener = Callable[[str, bool], None]
_listeners: dict[str, ModemListener] = {}
_listeners_lock = threading.Lock()


def register_modem_listener(slave_path: str, callback: ModemListener) -> None:
    """Call ``callback(line, state)`` (line ``"DTR"``/``"RTS"``) when a client of
    ``slave_path`` (a ``/dev/pts/N``, or a symlink to one) sets a modem line."""
    with _listeners_lock:
        _listeners[os.path.realpath(slave_path)] = callback


def unregister_modem_listener(slave_path: str) -> None:
    """Forget the listener of ``slave_path`` (no error if there is none)."""
    with _listeners_lock:
        _listeners.pop(os.path.realpath(slave_path), None)


def notify_modem(port_path: str, line: str, state: bool) -> None:
    """Deliver a modem-line change made by a client of ``port_path``."""
    with _listeners_lock:
        cb = _listeners.get(os.path.realpath(port_path))
    if cb is not None:
        try:
            cb(line, state)
        except Exception:  # an emulator bug must not break the client's write
            log.exception("modem listener for %s failed on %s=%s", port_path, line, state)


def _served(port) -> bool:
    """Whether an emulator listens to the modem lines of pyserial ``port``'s device."""
    path = getattr(port, "portstr", None)
    if not path:
        return False
    with _listeners_lock:
        return os.path.realpath(path) in _listeners


def _keep_modem_line(line: str, attr: str):
    """A ``_update_<line>_state`` that sets the line by ioctl, or on a pty an
    emulator serves (``ENOTTY``), records it and tells the emulator."""
    def wrap(original):
        @functools.wraps(original)
        def update(self):
            try:
                return original(self)
            except OSError as exc:
                if exc.errno != errno.ENOTTY or not _served(self):
                    raise
            state = bool(getattr(self, attr))
            if not hasattr(self, "modem_log"):
                self.modem_log = []
            self.modem_log.append((time.monotonic(), line, state))
            notify_modem(self.portstr, line, state)
        update._isac_twin_modem = True  # installed once
        return update
    return wrap


def _input_line(name: str, level: bool):
    """A modem-input property (CTS, DSR, RI, CD) that reads ``level`` on a pty an
    emulator serves (a USB serial adapter's idle lines) and the ioctl elsewhere."""
    original = getattr(serialposix.Serial, name)

    def get(self):
        try:
            return original.fget(self)
        except OSError as exc:
            if exc.errno != errno.ENOTTY or not _served(self):
                raise
            return level
    get._isac_twin_modem = True
    return property(get, doc=original.__doc__)


def _install_modem_lines() -> None:
    """Let pyserial's POSIX port keep the modem lines of emulated ptys (module doc)."""
    cls = serialposix.Serial
    if getattr(cls._update_dtr_state, "_isac_twin_modem", False):
        return
    cls._update_dtr_state = _keep_modem_line("DTR", "_dtr_state")(cls._update_dtr_state)
    cls._update_rts_state = _keep_modem_line("RTS", "_rts_state")(cls._update_rts_state)
    for name, level in (("cts", True), ("dsr", True), ("ri", False), ("cd", True)):
        setattr(cls, name, _input_line(name, level))


_install_modem_lines()


class PtyPort:
    """One pty pair in raw mode, published under a stable symlink.

    Args:
        link_path: the path clients open (created/replaced on :meth:`plug`,
            removed on :meth:`unplug`).

    Attributes:
        master_fd: non-blocking master fd while plugged, else ``None``.
        slave_name: the current ``/dev/pts/N``.
    """

    def __init__(self, link_path: str) -> None:
        self.link_path = link_path
        self.master_fd: int | None = None
        self._slave_fd: int | None = None
        self.slave_name: str | None = None

    @property
    def plugged(self) -> bool:
        return self.master_fd is not None

    def plug(self) -> str:
        """Create a fresh pty and point ``link_path`` at it; returns the slave name."""
        if self.plugged:
            return self.slave_name  # type: ignore[return-value]
        master, slave = os.openpty()
        # Raw mode before any client opens it: the default line discipline
        # would echo device output back into the device and translate CR/LF.
        tty.setraw(slave)
        os.set_blocking(master, False)
        self.master_fd, self._slave_fd = master, slave
        self.slave_name = os.ttyname(slave)
        tmp = f"{self.link_path}.tmp{os.getpid()}"
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        os.symlink(self.slave_name, tmp)
        os.replace(tmp, self.link_path)
        log.debug("pty %s plugged at %s", self.slave_name, self.link_path)
        return self.slave_name

    def unplug(self) -> None:
        """Remove the link and close both ends: open clients see EIO, reopening fails."""
        try:
            os.unlink(self.link_path)
        except FileNotFoundError:
            pass
        for fd in (self.master_fd, self._slave_fd):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        log.debug("pty %s unplugged from %s", self.slave_name, self.link_path)
        self.master_fd = self._slave_fd = None

    def write(self, data: bytes) -> int:
        """Write to the master without blocking; returns bytes written (a full
        tty buffer drops the rest, as a UART with nobody listening would)."""
        if self.master_fd is None or not data:
            return 0
        try:
            return os.write(self.master_fd, data)
        except (BlockingIOError, OSError):
            return 0

    def read(self, n: int = 4096) -> bytes:
        """Read what the client wrote (``b""`` if nothing is pending)."""
        if self.master_fd is None:
            return b""
        try:
            return os.read(self.master_fd, n)
        except (BlockingIOError, OSError):
            return b""
