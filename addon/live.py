"""The live link's client side: a non-blocking socket client driven by ``tick()``.

``bpy.app.timers`` never fire when Blender runs as a Python module, so nothing
here starts a thread or a timer: :class:`LiveClient` (standard library only)
does one bounded slice of work per :meth:`LiveClient.tick` — connect, read what
is there, decode, send what is queued — and :class:`LiveSession` adds the
Blender glue (apply messages to the scene, send viewport edits, run a local
engine process). The GUI registers :func:`timer_tick` as a timer; tests and
headless scripts call ``tick()`` themselves.
"""

from __future__ import annotations

import collections
import errno
import logging
import os
import select
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .contract import wire

log = logging.getLogger(__name__)

#: Seconds between timer ticks in the GUI.
TICK_INTERVAL_S = 1.0 / 30.0
#: Connection states.
IDLE, CONNECTING, HANDSHAKE, CONNECTED, WAITING, REFUSED = (
    "idle", "connecting", "handshake", "connected", "waiting", "refused")


class LiveClient:
    """A viewer's connection to an engine (``isac-twin serve``).

    Args:
        host, port: the engine's address.
        token: auth token the engine expects (None = none).
        name: viewer name sent in ``hello``.
        auto_reconnect: after a lost connection, retry with exponential backoff.
        backoff_s: ``(first, max)`` delay between reconnect attempts, s.
        connect_timeout_s: give up a connection attempt after this long, s.
        max_outbox: frames kept while disconnected (oldest dropped first).
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, *, token: str | None = None,
                 name: str = "blender", auto_reconnect: bool = True,
                 backoff_s: tuple[float, float] = (0.2, 5.0), connect_timeout_s: float = 3.0,
                 max_outbox: int = 1000):
        self.host, self.port = host, int(port)
        self.token = token or None
        self.name = name
        self.auto_reconnect = auto_reconnect
        self.backoff_s = backoff_s
        self.connect_timeout_s = connect_timeout_s
        self.state = IDLE
        self.last_error = ""
        self.peer_hello: dict | None = None
        self.outbox: collections.deque[bytes] = collections.deque(maxlen=max_outbox)
        self.received: collections.Counter = collections.Counter()
        #: messages queued to send, by type (sent once :attr:`outbox` is empty)
        self.sent: collections.Counter = collections.Counter()
        self.connects = 0
        self.decoder = wire.Decoder("e2v", peer="engine")
        self._sock: socket.socket | None = None
        self._wbuf = b""
        self._t_attempt = 0.0
        self._next_attempt = 0.0
        self._failures = 0

    # ------------------------------------------------------------------ control

    @property
    def connected(self) -> bool:
        """Whether the handshake is done and messages flow."""
        return self.state == CONNECTED

    def connect(self) -> None:
        """Start connecting (returns at once; :meth:`tick` finishes the job)."""
        self._failures = 0
        self._next_attempt = 0.0
        if self.state in (IDLE, WAITING, REFUSED):
            self.state = WAITING
            self._attempt()

    def disconnect(self) -> None:
        """Close the connection and stop reconnecting."""
        self._close("disconnected by the user")
        self.state = IDLE

    def send(self, msg: dict) -> None:
        """Queue ``msg`` (validated and framed now, sent by the next ticks)."""
        self.outbox.append(wire.encode(msg))
        self.sent[msg["type"]] += 1

    # ------------------------------------------------------------------ the tick

    def tick(self, budget_s: float = 0.004, max_bytes: int = 8 << 20) -> list[dict]:
        """Do one bounded, non-blocking slice of work.

        Returns the messages that arrived, in order, except that of the
        coalescable types (``state``, ``paths``/``rays``, ``metrics``, ``status``)
        only the newest of each is kept: a viewer that falls behind skips to
        the latest state instead of replaying history.

        Args:
            budget_s: stop reading after this long, s (the rest waits for the next tick).
            max_bytes: stop reading after this many bytes.
        """
        now = time.monotonic()
        if self.state == WAITING and now >= self._next_attempt:
            self._attempt()
        if self.state == CONNECTING:
            self._check_connect(now)
        if self.state not in (HANDSHAKE, CONNECTED):
            return []
        msgs = self._read(now + budget_s, max_bytes)
        if self._sock is not None:
            self._write()
        if not msgs:
            return []
        ordered, latest = [], {}
        for m in msgs:
            t = m["type"]
            self.received[t] += 1
            if t == "hello":
                if not self._on_hello(m):
                    return []
                ordered.append(m)
            elif t == "error" and m.get("fatal"):
                self.last_error = f"{m['code']}: {m['message']}"
                log.warning("engine refused the connection: %s", self.last_error)
                self._close(self.last_error, refused=True)
                ordered.append(m)
                return ordered
            elif t in wire.COALESCED_TYPES:
                latest[t] = m
            else:
                ordered.append(m)
        return ordered + [latest[t] for t in wire.COALESCED_TYPES if t in latest]

    # ------------------------------------------------------------------ internals

    def _attempt(self) -> None:
        self._t_attempt = time.monotonic()
        try:
            info = socket.getaddrinfo(self.host, self.port, type=socket.SOCK_STREAM)[0]
            sock = socket.socket(info[0], socket.SOCK_STREAM)
            sock.setblocking(False)
            err = sock.connect_ex(info[4])
        except OSError as exc:
            self._fail(f"cannot connect to {self.host}:{self.port}: {exc}")
            return
        if err not in (0, errno.EINPROGRESS, errno.EWOULDBLOCK, errno.EALREADY):
            sock.close()
            self._fail(f"cannot connect to {self.host}:{self.port}: {os.strerror(err)}")
            return
        self._sock = sock
        self.state = CONNECTING

    def _check_connect(self, now: float) -> None:
        try:
            _, w, _ = select.select([], [self._sock], [], 0)
        except (OSError, ValueError) as exc:
            self._fail(f"connect failed: {exc}")
            return
        if not w:
            if now - self._t_attempt > self.connect_timeout_s:
                self._fail(f"connect to {self.host}:{self.port} timed out")
            return
        err = self._sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
        if err:
            self._fail(f"cannot connect to {self.host}:{self.port}: {os.strerror(err)}")
            return
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.decoder = wire.Decoder("e2v", peer=f"engine {self.host}:{self.port}")
        self.state = HANDSHAKE
        self._wbuf = wire.encode(wire.hello("viewer", self.name, token=self.token,
                                            capabilities=("edit", "command",
                                                          wire.RAYS_CAPABILITY)))
        self._write()

    def _on_hello(self, m: dict) -> bool:
        why = wire.check_version(m)
        if why is not None:
            self.last_error = f"engine refused: {why}"
            log.warning("%s", self.last_error)
            self._close(self.last_error, refused=True)
            return False
        self.peer_hello = m
        self.state = CONNECTED
        self.connects += 1
        self._failures = 0
        self.last_error = ""
        log.info("connected to engine %s:%d", self.host, self.port)
        return True

    def _read(self, deadline: float, max_bytes: int) -> list[dict]:
        msgs: list[dict] = []
        got = 0
        while got < max_bytes:
            try:
                data = self._sock.recv(1 << 20)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:
                self._fail(f"connection lost: {exc}")
                break
            if not data:
                self._fail("the engine closed the connection")
                break
            got += len(data)
            msgs.extend(self.decoder.feed(data))
            if time.monotonic() > deadline:
                break
        return msgs

    def _write(self) -> None:
        while True:
            if not self._wbuf:
                if not self.outbox or self.state != CONNECTED:
                    return
                self._wbuf = self.outbox.popleft()
            try:
                n = self._sock.send(self._wbuf)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                self._fail(f"send failed: {exc}")
                return
            self._wbuf = self._wbuf[n:]
            if self._wbuf:
                return

    def _close(self, why: str, refused: bool = False) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            except OSError:
                pass
            self._sock = None
        self._wbuf = b""
        if refused:
            self.state = REFUSED

    def _fail(self, why: str) -> None:
        was = self.state
        self._close(why)
        self.last_error = why
        self._failures += 1
        if self.auto_reconnect:
            first, most = self.backoff_s
            delay = min(most, first * 2 ** min(self._failures - 1, 10))
            self._next_attempt = time.monotonic() + delay
            self.state = WAITING
        else:
            self.state = IDLE
        if was == CONNECTED:
            log.warning("live link lost (%s); reconnecting", why)
        else:
            log.debug("live link: %s", why)


class EngineProcess:
    """A local ``isac-twin serve`` child process on a free port.

    Args:
        python: the engine's interpreter (must have the ``engine`` package installed).
        scene: scene folder; empty = the engine's bundled default.
        args: more ``serve`` arguments.
    """

    def __init__(self, python: str = "", scene: str = "", args: tuple[str, ...] = ()):
        self.python = python or sys.executable
        self._dir = tempfile.TemporaryDirectory(prefix="isac-live-")
        self.port_file = Path(self._dir.name) / "port"
        self.log_file = Path(self._dir.name) / "engine.log"
        cmd = [self.python, "-m", "isac_twin.cli", "serve", "--port", "0",
               "--port-file", str(self.port_file), *args]
        if scene:
            cmd.insert(4, scene)
        self.cmd = cmd
        self._log = open(self.log_file, "wb")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(cmd, stdout=self._log, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL)
        log.info("started engine: %s (pid %d)", " ".join(cmd), self.proc.pid)

    @property
    def port(self) -> int | None:
        """The port once the engine listens (None before)."""
        try:
            return int(self.port_file.read_text().strip())
        except (OSError, ValueError):
            return None

    def alive(self) -> bool:
        return self.proc.poll() is None

    def log_tail(self, n: int = 2000) -> str:
        try:
            return self.log_file.read_bytes()[-n:].decode(errors="replace")
        except OSError:
            return ""

    def stop(self, timeout: float = 5.0) -> None:
        """Terminate the engine (SIGTERM, then SIGKILL after ``timeout``)."""
        if self.alive():
            self.proc.terminate()
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout)
        self._log.close()
        self._dir.cleanup()


class LiveSession:
    """Client + scene glue: what the Live panel drives and what tests tick.

    Args:
        scene: the ``bpy.types.Scene`` to show the twin in.
        host, port, token: the engine's address and token.
        engine: an :class:`EngineProcess` whose port to wait for (host/port then ignored).
    """

    def __init__(self, scene, host: str = "127.0.0.1", port: int = 8765,
                 token: str | None = None, engine: EngineProcess | None = None):
        from . import live_view

        self.scene_name = scene.name
        self.engine = engine
        self.client = LiveClient(host, port, token=token, name=f"blender:{scene.name}")
        self.view = live_view.LiveView()
        self.tracker = live_view.EditTracker()
        self.applied: collections.Counter = collections.Counter()
        self.last_tick_s = 0.0
        self._scene_hash = ""
        #: the engine's scene content hash as it last reported it (``scene``/``state``)
        self.engine_scene_hash = ""
        #: a warning for the panel (e.g. edits re-sent after an engine restart)
        self.notice = ""
        self._connects = 0  # the client's connects when the panel's error was last reset
        if engine is None:
            self.client.connect()

    @property
    def scene(self):
        import bpy

        return bpy.data.scenes.get(self.scene_name)

    def send_command(self, op: str, **args) -> None:
        self.client.send(wire.command(op, **args))

    def tick(self) -> list[dict]:
        """Connect/read/apply/send once; returns the messages applied."""
        from . import live_view, radiomap_view

        t0 = time.perf_counter()
        if self.engine is not None and self.client.state == IDLE:
            port = self.engine.port
            if port is not None:
                self.client.port = port
                self.client.connect()
            elif not self.engine.alive():
                self.client.last_error = "engine exited: " + self.engine.log_tail(300)
        scene = self.scene
        if scene is not None and self.client.connected:
            # Poll before applying: a scene message below must not absorb unsent edits.
            for e in self.tracker.poll(scene):
                self.client.send(e)
        msgs = self.client.tick()
        if scene is None:
            return msgs
        if self.client.connects != self._connects:
            # (re)connected: the panel's error was about the connection before this one
            self._connects = self.client.connects
            self.notice = ""
            live_view.clear_error(scene)
        for m in msgs:
            if m["type"] == "radiomap":
                radiomap_view.apply_radiomap(scene, m, self.view)
            else:
                live_view.apply_message(scene, m, self.view)
            self.applied[m["type"]] += 1
            if m["type"] == "state" and m.get("scene_hash"):
                self.engine_scene_hash = m["scene_hash"]
            elif m["type"] == "scene":
                self._on_scene(scene, m)
        live_view.store_connection(scene, self.client.state,
                                   self.client.last_error or self.notice,
                                   dict(self.client.decoder.rejections))
        self.last_tick_s = time.perf_counter() - t0
        return msgs

    def _on_scene(self, scene, m: dict) -> None:
        """A ``scene`` (on every (re)connect and after a reset): keep Blender and the
        engine one truth. The engine announcing the scene this session baselined while
        it had reported another (edited) one since means it restarted and lost the
        edits: they are sent again and the panel says so. Any other new scene becomes
        the new baseline."""
        h = m["content_hash"]
        if (self.tracker.tracked and h == self._scene_hash
                and self.engine_scene_hash not in ("", h)):
            names = self.tracker.resend()
            self.notice = (f"the engine came back without {len(names)} edit(s) made here "
                           f"({', '.join(sorted(names)[:5])}): sent again")
            log.warning("live: %s", self.notice)
        elif h != self._scene_hash or not self.tracker.tracked:
            self._scene_hash = h
            self.tracker.baseline(scene, {o["name"] for o in m["objects"]},
                                  {d["name"] for d in m["devices"]})
        self.engine_scene_hash = h

    def close(self) -> None:
        self.client.disconnect()
        if self.engine is not None:
            self.engine.stop()
            self.engine = None


# --------------------------------------------------------------------------- the GUI's session

_SESSION: LiveSession | None = None


def session() -> LiveSession | None:
    """The session the Live panel controls (None when not connected)."""
    return _SESSION


def timer_tick() -> float | None:
    """``bpy.app.timers`` callback: tick the session; None unregisters the timer."""
    if _SESSION is None:
        return None
    try:
        _SESSION.tick()
    except Exception:  # noqa: BLE001 - a timer that raises is silently unregistered
        log.exception("live tick failed")
    return TICK_INTERVAL_S


def network_refusal(host: str, online_access: bool | None = None) -> str | None:
    """Why connecting to ``host`` is not allowed now (None: it is).

    An engine on this machine (a loopback address) is always reachable; any other
    host needs Blender's *Allow Online Access* (``bpy.app.online_access``).

    Args:
        online_access: the setting (None: read ``bpy.app.online_access``; True without bpy).
    """
    import ipaddress

    try:
        if host == "localhost" or ipaddress.ip_address(host).is_loopback:
            return None
    except ValueError:
        pass
    if online_access is None:
        try:
            import bpy

            online_access = bool(getattr(bpy.app, "online_access", True))
        except ImportError:
            online_access = True
    if online_access:
        return None
    return (f"not connecting to {host}: Blender's online access is off (Preferences > "
            "System > Network); only an engine on this machine (127.0.0.1) can be reached")


def open_session(scene, host: str, port: int, token: str | None = None,
                 engine: EngineProcess | None = None) -> LiveSession:
    """Replace the GUI's session with a new one and register its timer.

    Raises:
        ValueError: :func:`network_refusal` (the reason is also shown in the panel).
    """
    global _SESSION
    why = network_refusal(host)
    if why is not None:
        from . import live_view

        live_view.store_connection(scene, "refused", why, {})
        raise ValueError(why)
    close_session()
    _SESSION = LiveSession(scene, host, port, token, engine)
    try:
        import bpy

        if not bpy.app.timers.is_registered(timer_tick):
            bpy.app.timers.register(timer_tick, first_interval=TICK_INTERVAL_S, persistent=True)
    except ImportError:
        pass
    return _SESSION


def close_session() -> None:
    """Disconnect and stop the GUI's session (and its engine process, if it started one)."""
    global _SESSION
    if _SESSION is not None:
        _SESSION.close()
        _SESSION = None
