"""Base of the emulated serial devices: a thread serving a pty master.

A subclass implements the device's protocol in :meth:`EmulatedSerialDevice.on_bytes`
(requests from the host) and :meth:`EmulatedSerialDevice.on_tick` (streaming,
physics). Faults a real device shows are built in: :meth:`unplug` /
:meth:`replug` (the port disappears and comes back under the same path),
``silent`` (the device stops answering), :meth:`inject_fault`.
"""

from __future__ import annotations

import logging
import os
import random
import select
import shutil
import tempfile
import threading
import time
from dataclasses import dataclass

from .ptyserial import PtyPort, register_modem_listener, unregister_modem_listener

log = logging.getLogger(__name__)


@dataclass
class EmulatorStats:
    bytes_in: int = 0
    bytes_out: int = 0
    bytes_overflow: int = 0  #: output dropped because the host was not reading
    requests: int = 0  #: well-formed requests handled
    bad_requests: int = 0  #: requests with a bad checksum/CRC or unknown framing
    ignored: int = 0  #: well-framed requests the device does not answer (broadcast, unsupported)
    unplugs: int = 0


class EmulatedSerialDevice:
    """A device on a pty. Use as a context manager or call start()/stop().

    Args:
        link_path: stable path the host opens; default a fresh temp dir's ``tty<name>0``.
        tick_s: s between :meth:`on_tick` calls.
        max_out_buffer: bytes queued for a host that is not reading before
            the oldest are dropped (a UART does not wait for its reader).
    """

    name = "EMU"

    def __init__(self, link_path: str | None = None, *, tick_s: float = 0.002,
                 max_out_buffer: int = 1 << 16) -> None:
        self._tmpdir: str | None = None
        if link_path is None:
            self._tmpdir = tempfile.mkdtemp(prefix="isac-twin-pty-")
            link_path = os.path.join(self._tmpdir, f"tty{self.name}0")
        self.port = PtyPort(link_path)
        self.tick_s = tick_s
        self.max_out_buffer = max_out_buffer
        self.silent = False
        self.stats = EmulatorStats()
        self._out = bytearray()
        self._lock = threading.RLock()
        self._stop_evt = threading.Event()
        self._thread: threading.Thread | None = None
        self._rng = random.Random(1234)

    # -- addresses ------------------------------------------------------------
    @property
    def path(self) -> str:
        """Stable path of the port (a symlink to the current ``/dev/pts/N``)."""
        return self.port.link_path

    @property
    def url(self) -> str:
        """pyserial URL with recorded modem lines: ``pty://<path>``."""
        return "pty://" + self.port.link_path

    # -- lifecycle ------------------------------------------------------------
    def start(self) -> "EmulatedSerialDevice":
        with self._lock:
            self._plug()
        self._stop_evt.clear()
        self._thread = threading.Thread(target=self._serve, name=f"emulated-{self.name}", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        self._stop_evt.set()
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.error("emulated %s did not stop within %.1f s", self.name, timeout)
            self._thread = None
        with self._lock:
            self._unplug()
        if self._tmpdir is not None:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None

    def __enter__(self) -> "EmulatedSerialDevice":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- faults -----------------------------------------------------------------
    def unplug(self) -> None:
        """Pull the USB cable: the path disappears, open handles get EIO."""
        with self._lock:
            self._unplug()
            self.stats.unplugs += 1
        log.info("emulated %s unplugged", self.name)

    def replug(self) -> None:
        """Plug back in: a fresh pty under the same path, device state reset."""
        with self._lock:
            self._plug()
        log.info("emulated %s replugged at %s", self.name, self.path)

    def inject_fault(self, kind: str) -> None:
        """Inject a fault: ``"garbage"`` (random bytes into the stream); subclasses add
        ``"corrupt"`` (next frame fails its check) and ``"truncate"`` (next frame cut short)."""
        if kind == "garbage":
            self.send(bytes(self._rng.randrange(256) for _ in range(37)))
        else:
            raise ValueError(f"emulated {self.name}: unknown fault kind {kind!r}")

    # -- for subclasses ---------------------------------------------------------
    def on_bytes(self, data: bytes, now: float) -> None:
        """Bytes the host wrote (any chunking)."""

    def on_tick(self, now: float) -> None:
        """Called every ``tick_s`` while plugged (``now`` = monotonic s)."""

    def on_plug(self) -> None:
        """Power-on state (called on start and replug)."""

    def on_modem(self, line: str, state: bool) -> None:
        """The host set a modem line (``pty://`` URLs only)."""

    def send(self, data: bytes) -> None:
        """Queue bytes to the host (dropped while silent or unplugged)."""
        if self.silent or not self.port.plugged or not data:
            return
        with self._lock:
            self._out += data
            excess = len(self._out) - self.max_out_buffer
            if excess > 0:
                del self._out[:excess]
                self.stats.bytes_overflow += excess

    # -- internals --------------------------------------------------------------
    def _plug(self) -> None:
        if self.port.plugged:
            return
        self.port.plug()
        register_modem_listener(self.port.slave_name, self.on_modem)
        self._out.clear()
        self.on_plug()

    def _unplug(self) -> None:
        if self.port.slave_name:
            unregister_modem_listener(self.port.slave_name)
        self.port.unplug()
        self._out.clear()

    def _serve(self) -> None:
        while not self._stop_evt.is_set():
            fd = self.port.master_fd
            if fd is None:
                self._stop_evt.wait(self.tick_s)
                continue
            try:
                want_write = [fd] if self._out else []
                r, w, _ = select.select([fd], want_write, [], self.tick_s)
            except (OSError, ValueError):  # fd closed under us by unplug()
                continue
            now = time.monotonic()
            with self._lock:
                if self.port.master_fd != fd:
                    continue
                if r:
                    data = self.port.read()
                    if data:
                        self.stats.bytes_in += len(data)
                        if not self.silent:
                            try:
                                self.on_bytes(data, now)
                            except Exception:
                                log.exception("emulated %s: error handling %r", self.name, data[:32])
                try:
                    self.on_tick(now)
                except Exception:
                    log.exception("emulated %s: error in tick", self.name)
                if self._out:
                    n = self.port.write(bytes(self._out[:4096]))
                    del self._out[:n]
                    self.stats.bytes_out += n
