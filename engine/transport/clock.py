"""Clock offsets between peers: NTP-style pings over the bus.

A robot's stamps come from its own clock (the Raspberry Pi's, maybe not
NTP-disciplined). To compare a robot's stamp with the twin's clock, the twin
(:class:`ClockProbe`) publishes ``ClockPing`` on ``/isac/clock/ping`` with its
send time ``t0``; each robot (:class:`ClockResponder`) answers on
``/isac/clock/pong`` with its receive time ``t1`` and send time ``t2``; the
twin stamps the arrival ``t3``. Then (all ns)::

    offset = ((t1 - t0) + (t2 - t3)) / 2     # remote clock - local clock
    rtt    = (t3 - t0) - (t2 - t1)

The estimate is the offset of the sample with the smallest RTT among the
last ``window`` ones (the least queued, so the least asymmetric). A remote
stamp converts to local time as ``t_local = t_remote - offset``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

from ..bus.bus import Bus
from ..bus.twin_msgs import ClockPing

log = logging.getLogger(__name__)

PING_TOPIC = "/isac/clock/ping"
PONG_TOPIC = "/isac/clock/pong"


class ClockResponder:
    """Answers clock pings (runs on the robot).

    Args:
        bus: a bus with a network transport.
        name: this responder's name (the robot's).
        clock_ns: the local clock, ns (default ``time.time_ns``; tests skew it).
    """

    def __init__(self, bus: Bus, name: str, clock_ns=time.time_ns):
        self.name, self.clock_ns = name, clock_ns
        self.node = bus.node(f"{name}/clock")
        self.node.advertise(PONG_TOPIC, ClockPing)
        self.node.subscribe(PING_TOPIC, ClockPing, self._on_ping)
        self.answered = 0

    def _on_ping(self, p: ClockPing) -> None:
        t1 = self.clock_ns()
        self.answered += 1
        self.node.publish(PONG_TOPIC, ClockPing(origin=p.origin, responder=self.name, seq=p.seq,
                                                t0_ns=p.t0_ns, t1_ns=t1, t2_ns=self.clock_ns()))


class ClockProbe:
    """Estimates each responder's clock offset (runs on the twin).

    Args:
        bus: a bus with a network transport.
        name: this prober's name (pongs for other probers are ignored).
        period_s: s between pings when started as a thread.
        window: samples kept per responder.
    """

    def __init__(self, bus: Bus, name: str = "twin", *, period_s: float = 0.5, window: int = 16,
                 clock_ns=time.time_ns):
        self.name, self.period_s, self.clock_ns = name, period_s, clock_ns
        self.node = bus.node(f"{name}/clock")
        self.node.advertise(PING_TOPIC, ClockPing)
        self.node.subscribe(PONG_TOPIC, ClockPing, self._on_pong)
        self._samples: dict[str, deque] = {}
        self._lock = threading.Lock()
        self._seq = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.window = window

    def ping(self) -> None:
        """Send one ping now."""
        self._seq += 1
        self.node.publish(PING_TOPIC, ClockPing(origin=self.name, seq=self._seq,
                                                t0_ns=self.clock_ns()))

    def _on_pong(self, p: ClockPing) -> None:
        if p.origin != self.name:
            return
        t3 = self.clock_ns()
        offset = ((p.t1_ns - p.t0_ns) + (p.t2_ns - t3)) / 2
        rtt = (t3 - p.t0_ns) - (p.t2_ns - p.t1_ns)
        with self._lock:
            self._samples.setdefault(p.responder, deque(maxlen=self.window)).append((rtt, offset))

    def offset_s(self, responder: str) -> float | None:
        """Estimated ``remote clock - local clock`` of ``responder``, s (None if unknown)."""
        with self._lock:
            s = self._samples.get(responder)
            if not s:
                return None
            return min(s)[1] * 1e-9

    def rtt_s(self, responder: str) -> float | None:
        """Smallest round-trip time seen in the window, s."""
        with self._lock:
            s = self._samples.get(responder)
            return min(s)[0] * 1e-9 if s else None

    def to_local(self, responder: str, stamp_s: float) -> float:
        """A ``responder`` stamp (s, its clock) on the local clock (unchanged if unknown)."""
        off = self.offset_s(responder)
        return stamp_s - off if off is not None else stamp_s

    def start(self) -> ClockProbe:
        """Ping every ``period_s`` from a daemon thread until :meth:`stop`."""
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="clock-probe", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.ping()
            except Exception:  # noqa: BLE001
                log.exception("clock ping failed")
            self._stop.wait(self.period_s)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
