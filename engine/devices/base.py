"""What every device driver shares: lifecycle, read loop, reconnect, stats.

A driver owns one serial-like connection and one thread. The thread connects
(:meth:`DeviceDriver._connect`), then calls :meth:`DeviceDriver._poll` until
the device is lost (an exception, or no valid frame for ``stale_timeout``
seconds), then disconnects and retries with exponential backoff. Messages go
out through a plain ``publish(topic, msg)`` callable, so the bus's
``node.publish`` plugs straight in.

Each driver declares the topics it publishes and their message types in
``MESSAGE_TYPES``; :mod:`isac_twin.devices.conformance` checks that it keeps to
them. A started driver also publishes ``diagnostic_msgs/DiagnosticArray`` on
``diagnostics_topic`` every ``diagnostics_period_s`` and at once when it
connects or loses the device, connected or not (:meth:`DeviceDriver.diagnostic_status`).
"""

from __future__ import annotations

import logging
import termios
import threading
import time
from dataclasses import dataclass, field, fields
from typing import Any, Callable, ClassVar

from ..bus.msgs import DiagnosticArray, DiagnosticStatus, Header
from ..errors import DeviceError, DeviceTimeout

log = logging.getLogger(__name__)

#: ``publish(topic, msg)``: where drivers send their messages.
Publish = Callable[[str, Any], None]


def _discard(topic: str, msg: Any) -> None:
    pass


@dataclass
class DriverStats:
    """Counters a driver keeps; read them from any thread (plain ints)."""

    frames_ok: int = 0  #: valid frames decoded (nodes, capsules, status packets)
    frames_bad: int = 0  #: frames dropped: check bit, checksum/CRC, truncation
    bytes_dropped: int = 0  #: bytes skipped while resynchronising
    timeouts: int = 0  #: requests that got no answer in time
    connects: int = 0  #: successful connections (1 + reconnects)
    disconnects: int = 0  #: connections lost (device unplugged, silent, I/O error)
    published: dict[str, int] = field(default_factory=dict)  #: messages per topic
    last_error: str = ""

    @property
    def reconnects(self) -> int:
        return max(0, self.connects - 1)


class DeviceDriver:
    """Base of the serial device drivers (RPLIDAR, OpenCR).

    Args:
        url: serial port path or pyserial URL (``pty://...`` for emulators).
        publish: ``publish(topic, msg)``; messages are dropped if ``None``.
        stale_timeout: s without a valid frame before the device counts as lost.
        backoff_initial: s before the first reconnect attempt.
        backoff_max: s, cap of the doubling reconnect delay.
        connect_warn_s: s after :meth:`start` without a connection before a
            WARNING names the port and the last error (once; every further
            failure stays at INFO).
        diagnostics_topic: where :meth:`start` ed drivers publish their
            ``DiagnosticArray`` (``None``: not published; a runtime may collect
            :meth:`diagnostic_status` itself).
        diagnostics_period_s: s between diagnostics messages.
    """

    #: topic -> message class published there.
    MESSAGE_TYPES: ClassVar[dict[str, type]] = {}

    def __init__(
        self,
        url: str,
        publish: Publish | None = None,
        *,
        stale_timeout: float = 1.0,
        backoff_initial: float = 0.05,
        backoff_max: float = 2.0,
        connect_warn_s: float = 3.0,
        diagnostics_topic: str | None = "diagnostics",
        diagnostics_period_s: float = 1.0,
    ) -> None:
        self.url = url
        self.publish_fn: Publish = publish or _discard
        self.stale_timeout = stale_timeout
        self.backoff_initial = backoff_initial
        self.backoff_max = backoff_max
        self.connect_warn_s = connect_warn_s
        self.stats = DriverStats()
        self._started_at: float | None = None
        self._warned_absent = False
        self.diagnostics_topic = diagnostics_topic
        self.diagnostics_period_s = diagnostics_period_s
        self._next_diag = 0.0
        self._diag_bad = 0
        self._stop_evt = threading.Event()
        self._thread: threading.Thread | None = None
        self._connected = False
        self._last_valid = time.monotonic()
        self._pub_cond = threading.Condition()

    # -- to implement -------------------------------------------------------
    def _connect(self) -> None:
        """Open the port and bring the device into streaming state."""
        raise NotImplementedError

    def _disconnect(self) -> None:
        """Close the port; must not raise."""
        raise NotImplementedError

    def _poll(self) -> None:
        """One read-loop iteration: read, decode, publish. Raise if the port is gone."""
        raise NotImplementedError

    # -- lifecycle ------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def connected(self) -> bool:
        return self._connected

    @property
    def ever_connected(self) -> bool:
        return self.stats.connects > 0

    def summary(self) -> str:
        """One line for the end of a run: whether the device ever connected,
        reconnects, frames, messages per topic, the last error."""
        st = self.stats
        if not st.connects:
            return f"{self.url}: NEVER connected; last error: {st.last_error or 'none'}"
        pub = ", ".join(f"{t}: {n}" for t, n in sorted(st.published.items())) or "nothing published"
        return (f"{self.url}: connected {st.connects} time{'s' if st.connects > 1 else ''}, "
                f"{st.disconnects} lost; frames {st.frames_ok} ok / {st.frames_bad} bad; {pub}"
                + (f"; last error: {st.last_error}" if st.last_error else ""))

    def start(self) -> "DeviceDriver":
        """Start the read-loop thread (returns at once; connection is retried)."""
        if self.running:
            return self
        self._stop_evt.clear()
        self._started_at = time.monotonic()
        self._warned_absent = False
        if self.diagnostics_topic:
            self.MESSAGE_TYPES = {**self.MESSAGE_TYPES, self.diagnostics_topic: DiagnosticArray}
        self._thread = threading.Thread(target=self._run, name=f"{type(self).__name__}({self.url})", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the thread and close the port; waits at most ``timeout`` s."""
        self._stop_evt.set()
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.error("%s: read loop did not stop within %.1f s", self.url, timeout)
            self._thread = None

    def __enter__(self) -> "DeviceDriver":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def wait_published(self, topic: str, count: int, timeout: float) -> bool:
        """Block until ``stats.published[topic] >= count``; False on timeout (s)."""
        deadline = time.monotonic() + timeout
        with self._pub_cond:
            while self.stats.published.get(topic, 0) < count:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._pub_cond.wait(remaining)
        return True

    def diagnostic_status(self) -> DiagnosticStatus:
        """The driver's health now: OK connected; WARN connected but frames were
        bad since the last report, or still connecting within ``connect_warn_s``;
        ERROR never connected (with the error) or lost (reconnecting). Values:
        every counter of ``stats``, messages per topic, the last error."""
        st = self.stats
        if self._connected:
            bad = st.frames_bad - self._diag_bad
            level, msg = ((DiagnosticStatus.OK, "connected") if bad <= 0 else
                          (DiagnosticStatus.WARN, f"connected; {bad} bad frames since the last report"))
        elif not st.connects:
            waited = time.monotonic() - (self._started_at or time.monotonic())
            if waited < self.connect_warn_s:
                level, msg = DiagnosticStatus.WARN, f"connecting ({waited:.1f} s)"
            else:
                level, msg = DiagnosticStatus.ERROR, f"never connected: {st.last_error or 'no attempt finished'}"
        else:
            level, msg = DiagnosticStatus.ERROR, f"lost: {st.last_error}; reconnecting"
        values = [(f.name, str(getattr(st, f.name))) for f in fields(st) if f.name not in ("published", "last_error")]
        values += [(f"published {t}", str(n)) for t, n in sorted(st.published.items())]
        values.append(("last_error", st.last_error))
        return DiagnosticStatus(level, type(self).__name__, msg, self.url, values)

    def _publish_diagnostics(self, force: bool = False) -> None:
        if not self.diagnostics_topic:
            return
        now = time.monotonic()
        if not force and now < self._next_diag:
            return
        status = self.diagnostic_status()
        self._next_diag = now + self.diagnostics_period_s
        self._diag_bad = self.stats.frames_bad
        self._publish(self.diagnostics_topic, DiagnosticArray(Header(stamp=time.time(), frame_id=""), [status]))

    # -- helpers for subclasses -------------------------------------------------
    def _publish(self, topic: str, msg: Any) -> None:
        try:
            self.publish_fn(topic, msg)
        except Exception:
            log.exception("%s: publish(%r) raised; message dropped", self.url, topic)
        with self._pub_cond:
            self.stats.published[topic] = self.stats.published.get(topic, 0) + 1
            self._pub_cond.notify_all()

    def _mark_valid(self) -> None:
        """Note that a valid frame arrived (resets the stale timer)."""
        self._last_valid = time.monotonic()

    def _safe_disconnect(self) -> None:
        try:
            self._disconnect()
        except Exception:
            log.exception("%s: error while closing", self.url)
        self._connected = False

    def _run(self) -> None:
        backoff = self.backoff_initial
        while not self._stop_evt.is_set():
            self._publish_diagnostics()
            if not self._connected:
                try:
                    self._connect()
                except Exception as exc:  # noqa: BLE001 - any failure means "retry later"
                    self.stats.last_error = f"{self.url}: connect failed: {exc}"
                    waited = time.monotonic() - (self._started_at or time.monotonic())
                    if not self.stats.connects and not self._warned_absent and waited >= self.connect_warn_s:
                        self._warned_absent = True
                        log.warning("%s: never connected in %.1f s (%s); still retrying every <= %.1f s",
                                    self.url, waited, exc, self.backoff_max)
                    else:
                        log.info("%s; retry in %.2f s", self.stats.last_error, backoff)
                    self._safe_disconnect()
                    self._stop_evt.wait(backoff)
                    backoff = min(backoff * 2, self.backoff_max)
                    continue
                self._connected = True
                self.stats.connects += 1
                self._last_valid = time.monotonic()
                backoff = self.backoff_initial
                log.info("%s: connected (connection #%d)", self.url, self.stats.connects)
                self._publish_diagnostics(force=True)
            try:
                self._poll()
                idle = time.monotonic() - self._last_valid
                if idle > self.stale_timeout:
                    raise DeviceTimeout(f"{self.url}: no valid frame for {idle:.2f} s")
            except Exception as exc:  # noqa: BLE001
                expected = isinstance(exc, (OSError, DeviceError, termios.error)) or type(exc).__name__ == "SerialException"
                self.stats.disconnects += 1
                self.stats.last_error = f"{self.url}: {exc}"
                log.warning("%s: device lost (%s); reconnecting in %.2f s", self.url, exc, backoff,
                            exc_info=not expected)
                self._safe_disconnect()
                self._publish_diagnostics(force=True)
                self._stop_evt.wait(backoff)
                backoff = min(backoff * 2, self.backoff_max)
        self._safe_disconnect()
