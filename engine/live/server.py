"""The live link server: a twin stepping in a thread plus a TCP server for viewers.

Two threads, one lock:

* the *loop* thread owns the twin: it drains the inbox (edits and commands
  from viewers), applies them between steps, steps while running (at most
  ``rate_hz`` steps per second), encodes each step's messages once and hands
  the frames to every viewer;
* the *I/O* thread runs a ``selectors`` loop over the listening socket, the
  viewers' sockets and a wake-up socket pair; it never touches the twin.

A slow viewer never stalls the twin: per viewer, ``state``/``paths``/
``metrics``/``status`` are coalesced (a newer frame replaces an unsent one,
the drop is counted per type); only ``hello``/``scene``/``error`` are queued
in order. A viewer that leaves, or is dropped, leaves the loop running.

What a viewer can do (the security model, docs/wire.md): before its ``hello``
is accepted it may send frames of at most :data:`PRE_HELLO_MAX_FRAME` bytes
and must say hello within the handshake timeout; the token (when set) is
checked first, in constant time, before anything else is answered; any frame
that cannot be handled closes only that viewer's connection; at most
``max_viewers`` are connected. After the hello it may send edits and commands,
which the twin validates completely (:meth:`~isac_twin.twin.twin.Twin.validate_edit`,
:meth:`~isac_twin.twin.twin.Twin.validate_command`) before anything changes; a bad one
is answered ``error{code: "rejected", ref}`` to the sender only. Meshes named
by ``add`` edits are read only from the scene folder or an asset folder.
"""

from __future__ import annotations

import collections
import hmac
import ipaddress
import json
import logging
import queue
import selectors
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Protocol, runtime_checkable

from ..twin.edits import public_reason
from ..twin.state import Command, Edit, StepResult
from . import protocol
from .protocol import wire

log = logging.getLogger(__name__)

#: Seconds a viewer has to send its ``hello``.
HANDSHAKE_TIMEOUT_S = 10.0
#: Largest frame accepted before a viewer's ``hello`` is accepted, bytes.
PRE_HELLO_MAX_FRAME = 64 * 1024
#: Connected viewers at most (more are answered ``busy`` and closed).
MAX_VIEWERS = 32
#: In-order frames a viewer may have pending before it is dropped as stuck.
MAX_QUEUED_FRAMES = 256
_CAPABILITIES = ("state", "paths", wire.RAYS_CAPABILITY, "metrics", "status", "edit",
                 "command")


@runtime_checkable
class LiveTwin(Protocol):
    """What the server needs from a twin (``isac_twin.twin.twin.Twin`` satisfies it).

    The twin owns the command semantics: :meth:`command` validates and applies
    every op (``run``/``pause`` set :attr:`running`, ``step`` adds to
    :attr:`pending_steps`, each :meth:`step` takes one); the server steps while
    ``running or pending_steps``.
    """

    scene: object
    running: bool
    pending_steps: int

    def step(self) -> StepResult: ...

    def apply_edit(self, edit: Edit, *, on_result=None) -> None: ...

    def command(self, cmd: Command) -> None: ...


def is_loopback(host: str) -> bool:
    """Whether ``host`` (name or address) is a loopback address."""
    if host in ("localhost", ""):
        return host == "localhost"
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        try:
            return all(ipaddress.ip_address(a[4][0]).is_loopback
                       for a in socket.getaddrinfo(host, None))
        except OSError:
            return False


class _Viewer:
    """One connected viewer: its socket, decoder and outgoing frames."""

    def __init__(self, sock: socket.socket, addr):
        self.sock = sock
        self.addr = f"{addr[0]}:{addr[1]}" if isinstance(addr, tuple) else str(addr)
        self.decoder = wire.Decoder("v2e", peer=f"viewer {self.addr}",
                                    max_frame=PRE_HELLO_MAX_FRAME)
        self.name = ""
        self.ready = False          # hello accepted
        self.rays = False           # takes packed ``rays`` instead of ``paths`` (wire 1.3)
        self.closing = False        # close once the queue is flushed
        self.opened = time.monotonic()
        self.queue: collections.deque[bytes] = collections.deque()
        self.latest: dict[str, bytes] = {}
        self.drops: collections.Counter = collections.Counter()
        self.wbuf = b""
        self.woff = 0
        self.sent_frames = 0

    def has_output(self) -> bool:
        return bool(self.wbuf) or bool(self.queue) or bool(self.latest)

    def next_frame(self) -> bytes | None:
        if self.queue:
            return self.queue.popleft()
        for t in wire.COALESCED_TYPES:
            if t in self.latest:
                return self.latest.pop(t)
        return None


class LiveServer:
    """Serve a twin to viewers over TCP.

    Args:
        twin: a :class:`LiveTwin`.
        host, port: where to listen (port 0 = any free port; see :attr:`address`).
        token: shared secret viewers must send in ``hello``; required when
            ``host`` is not a loopback address.
        rate_hz: at most this many steps per second while running (0 = as fast as possible).
        max_steps: pause after this many steps (None = run until paused).
        running: start running (else wait for a ``run`` or ``step`` command).
        max_paths: ray polylines per link in ``paths`` messages (strongest first).
        step_log: append one JSON line per step (:func:`protocol.step_summary`) here.
        on_step: called with each :class:`StepResult` in the loop thread.
        viewer_sndbuf: kernel send buffer per viewer socket, bytes (None = OS default;
            small values make a slow viewer's backlog coalesce sooner).
        max_viewers: connections served at once.
        handshake_timeout_s: seconds a new connection has to send its ``hello``.

    Raises:
        ValueError: a non-loopback ``host`` without a ``token``.
    """

    def __init__(self, twin: LiveTwin, host: str = "127.0.0.1", port: int = 0, *,
                 token: str | None = None, rate_hz: float = 10.0, max_steps: int | None = None,
                 running: bool = True, max_paths: int = wire.DEFAULT_MAX_PATHS_PER_LINK,
                 step_log: str | Path | None = None,
                 on_step: Callable[[StepResult], None] | None = None,
                 viewer_sndbuf: int | None = None, max_viewers: int = MAX_VIEWERS,
                 handshake_timeout_s: float = HANDSHAKE_TIMEOUT_S):
        if not is_loopback(host) and not token:
            raise ValueError(f"refusing to listen on non-loopback address {host!r} without an "
                             "auth token (pass --token)")
        self.twin = twin
        self.host, self.port = host, int(port)
        self.token = token or None
        self.rate_hz = float(rate_hz)
        self.max_steps = max_steps
        self.max_paths = int(max_paths)
        self.step_log = Path(step_log) if step_log else None
        self.on_step = on_step
        self.viewer_sndbuf = viewer_sndbuf
        self.max_viewers = int(max_viewers)
        self.handshake_timeout_s = float(handshake_timeout_s)
        twin.running = bool(running)
        self.steps_done = 0
        self.edits_applied = 0
        self.last_result: StepResult | None = None
        self.done = threading.Event()       # max_steps reached
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._inbox: queue.Queue = queue.Queue()
        self._wake_loop = threading.Event()
        self._viewers: dict[int, _Viewer] = {}
        self._latest: dict[str, bytes] = {}  # for viewers that join later
        # the last step's rays as a ``paths`` frame for viewers without the "rays"
        # capability: (result, frame or None), the frame built on first need
        self._paths_src: tuple[StepResult, bytes | None] | None = None
        self._scene_frame = b""
        self._scene_hash = ""
        self._sel: selectors.BaseSelector | None = None
        self._lsock: socket.socket | None = None
        self._wake_r = self._wake_w = None
        self._threads: list[threading.Thread] = []
        self.stats = collections.Counter()

    # ------------------------------------------------------------------ lifecycle

    @property
    def address(self) -> tuple[str, int]:
        """``(host, port)`` actually listened on."""
        return self._lsock.getsockname()[:2]

    def start(self) -> "LiveServer":
        """Bind, listen and start the loop and I/O threads."""
        fam = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        ls = socket.socket(fam, socket.SOCK_STREAM)
        ls.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        ls.bind((self.host, self.port))
        ls.listen(16)
        ls.setblocking(False)
        self._lsock = ls
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._sel = selectors.DefaultSelector()
        self._sel.register(ls, selectors.EVENT_READ, "listen")
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._refresh_scene()
        self._threads = [threading.Thread(target=self._io_main, name="live-io", daemon=True),
                         threading.Thread(target=self._loop_main, name="live-loop", daemon=True)]
        for t in self._threads:
            t.start()
        log.info("live server listening on %s:%d", *self.address)
        return self

    def stop(self, timeout: float = 10.0) -> None:
        """Stop both threads and close every socket."""
        self._stop.set()
        self._wake_loop.set()
        self._wake()
        for t in self._threads:
            t.join(timeout)
            if t.is_alive():
                log.warning("live server: thread %s did not stop within %g s", t.name, timeout)
        with self._lock:
            viewers = list(self._viewers.values())
            self._viewers.clear()
        for v in viewers:
            v.sock.close()
        for s in (self._lsock, self._wake_r, self._wake_w):
            if s is not None:
                s.close()
        if self._sel is not None:
            self._sel.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    @property
    def running(self) -> bool:
        """Whether the twin keeps stepping (the twin's own flag; ``run``/``pause``)."""
        return bool(self.twin.running)

    def viewers(self) -> list[dict]:
        """A snapshot of the connected viewers: name, address, frames sent, drops per type."""
        with self._lock:
            return [{"name": v.name, "addr": v.addr, "ready": v.ready, "sent": v.sent_frames,
                     "drops": dict(v.drops), "rejected": dict(v.decoder.rejections)}
                    for v in self._viewers.values()]

    # ------------------------------------------------------------------ publishing

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"x")
        except (BlockingIOError, OSError):
            pass  # already awake (buffer full) or shutting down

    def publish(self, msg: dict) -> None:
        """Encode ``msg`` once and hand it to every ready viewer (coalesced per type)."""
        frame = wire.encode(msg)
        t = msg["type"]
        coalesce = t in wire.COALESCED_TYPES
        with self._lock:
            if coalesce:
                self._latest[t] = frame
            for v in self._viewers.values():
                if not v.ready or v.closing:
                    continue
                if coalesce:
                    if t in v.latest:
                        v.drops[t] += 1
                    v.latest[t] = frame
                else:
                    v.queue.append(frame)
        self._wake()

    def _paths_frame(self) -> bytes | None:
        """The last step's ``paths`` frame (JSON polylines), built on first need: only
        viewers without the ``rays`` capability (wire <= 1.2) get it. Call with the lock."""
        if self._paths_src is None:
            return None
        res, frame = self._paths_src
        if frame is None:
            frame = wire.encode(protocol.paths_message(res, self.max_paths))
            self._paths_src = (res, frame)
        return frame

    def publish_rays(self, res: StepResult) -> None:
        """A step's rays: packed (``rays``) to viewers that announced the ``rays``
        capability, as a ``paths`` message to the others (coalesced per viewer)."""
        frame = wire.encode(protocol.rays_message(res, self.max_paths))
        with self._lock:
            self._latest["rays"] = frame
            self._paths_src = (res, None)
            for v in self._viewers.values():
                if not v.ready or v.closing:
                    continue
                t, f = ("rays", frame) if v.rays else ("paths", self._paths_frame())
                if t in v.latest:
                    v.drops[t] += 1
                v.latest[t] = f
        self._wake()

    def _send_to(self, v: _Viewer, msg: dict, *, close: bool = False) -> None:
        with self._lock:
            v.queue.append(wire.encode(msg))
            if close:
                v.closing = True
        self._wake()

    def _status(self, message: str = "") -> dict:
        return {"type": "status", "running": self.running, "step": self.steps_done,
                "rate_hz": self.rate_hz, "edits_applied": self.edits_applied,
                "viewers": len(self._viewers), "message": message}

    # ------------------------------------------------------------------ the loop thread

    def _loop_main(self) -> None:
        next_t = time.monotonic()
        while not self._stop.is_set():
            self._drain_inbox()
            if self._stop.is_set():
                break
            twin = self.twin
            if twin.running or twin.pending_steps:
                now = time.monotonic()
                if twin.running and self.rate_hz > 0 and now < next_t and not twin.pending_steps:
                    self._wake_loop.wait(next_t - now)
                    self._wake_loop.clear()
                    continue
                next_t = max(now, next_t) + (1.0 / self.rate_hz if self.rate_hz > 0 else 0.0)
                self._do_step()
            else:
                self._wake_loop.wait(0.1)
                self._wake_loop.clear()

    def _do_step(self) -> None:
        try:
            res = self.twin.step()
        except Exception as exc:  # noqa: BLE001 - report, pause, keep serving
            log.exception("twin step failed")
            self.twin.running = False
            self.twin.pending_steps = 0
            self.publish(wire.error("step", f"twin step failed: {exc}"))
            self.publish(self._status("paused after a failed step"))
            return
        self.steps_done += 1
        self.last_result = res
        if res.scene_hash != self._scene_hash:  # an edit was applied in this step
            self._refresh_scene()
        # the step's log line before its messages: a client that has a step's rays can
        # read its line (after, the CI dry run once read the previous step 0's line)
        if self.step_log is not None:
            with self.step_log.open("a") as f:
                f.write(json.dumps(protocol.step_summary(res)) + "\n")
        for build in (protocol.state_message, protocol.metrics_message):
            self.publish(build(res))
        self.publish_rays(res)
        if self.on_step is not None:
            self.on_step(res)
        if self.max_steps is not None and self.steps_done >= self.max_steps:
            if self.twin.running:
                log.info("reached %d steps: pausing", self.steps_done)
            self.twin.running = False
            self.done.set()
        self.publish(self._status())

    def _refresh_scene(self) -> bytes:
        """The ``scene`` frame new viewers get: the room as it is now (edits included),
        so its ``content_hash`` is the engine's truth on every (re)connect."""
        msg = protocol.scene_message(self.twin.scene)
        frame = wire.encode(msg)
        with self._lock:
            self._scene_frame, self._scene_hash = frame, msg["content_hash"]
        return frame

    def _drain_inbox(self) -> None:
        """Apply queued edits and commands (the twin validates each; a bad one is
        answered ``rejected`` to its sender and changes nothing)."""
        changed = False
        while True:
            try:
                viewer, item = self._inbox.get_nowait()
            except queue.Empty:
                break
            try:
                if isinstance(item, Edit):
                    self.twin.apply_edit(item, on_result=self._edit_answer(viewer))
                else:
                    self.twin.command(item)
                    if item.op == "reset":
                        self.steps_done = 0
                        self.done.clear()
                        self._refresh_scene()
                        self.publish(protocol.scene_message(self.twin.scene))
                changed = True
            except Exception as exc:  # noqa: BLE001 - a bad edit must not stop the twin
                what = f"{type(item).__name__.lower()} {item.op}"
                log.warning("rejected %s from viewer %s: %s", what, viewer.addr, exc)
                self.stats["edit_errors"] += 1
                self._send_to(viewer, wire.error("rejected", f"{what}: {public_reason(exc)}",
                                                 ref=getattr(item, "target", item.op)))
        if changed:
            self.publish(self._status())

    def _edit_answer(self, viewer: _Viewer):
        """The ``on_result`` of a viewer's edit (called by the twin's step, on the loop
        thread): count it applied, or answer ``rejected`` with the reason to that
        viewer only."""
        def answer(edit: Edit, error: str | None) -> None:
            if error is None:
                self.edits_applied += 1
                return
            log.warning("edit from viewer %s not applied: %s", viewer.addr, error)
            self.stats["edit_errors"] += 1
            self._send_to(viewer, wire.error("rejected", error, ref=edit.target))
        return answer

    # ------------------------------------------------------------------ the I/O thread

    def _io_main(self) -> None:
        """Supervise the I/O loop: if it ever dies it is logged, counted
        (``stats["io_restarts"]``), reported to the viewers and started again."""
        while not self._stop.is_set():
            try:
                self._io_loop()
            except Exception as exc:  # noqa: BLE001 - the loop must outlive any bug
                log.exception("live server I/O loop crashed; restarting it")
                self.stats["io_restarts"] += 1
                try:
                    self.publish(self._status(f"I/O loop restarted after {type(exc).__name__}"))
                except Exception:  # noqa: BLE001
                    pass
                time.sleep(0.05)

    def _io_loop(self) -> None:
        while not self._stop.is_set():
            self._update_interest()
            for key, events in self._sel.select(timeout=0.2):
                if key.data == "listen":
                    self._accept()
                elif key.data == "wake":
                    try:
                        while self._wake_r.recv(4096):
                            pass
                    except (BlockingIOError, OSError):
                        pass
                else:
                    self._serve(key.data, events)
            self._check_handshakes()

    def _serve(self, v: _Viewer, events: int) -> None:
        """One viewer's I/O; whatever goes wrong closes only this viewer."""
        try:
            if events & selectors.EVENT_READ:
                self._read(v)
            if events & selectors.EVENT_WRITE and v.sock.fileno() >= 0:
                self._flush(v)
        except Exception as exc:  # noqa: BLE001
            log.exception("viewer %s: unexpected fault; closing its connection", v.addr)
            self.stats["viewer_faults"] += 1
            try:
                v.sock.send(wire.encode(wire.error(
                    "internal", f"the engine could not handle a frame ({type(exc).__name__})",
                    fatal=True)))
            except Exception:  # noqa: BLE001 - best effort before closing
                pass
            self._drop(v, f"fault: {type(exc).__name__}")

    def _update_interest(self) -> None:
        with self._lock:
            viewers = list(self._viewers.values())
        for v in viewers:
            want = selectors.EVENT_READ | (selectors.EVENT_WRITE if v.has_output() else 0)
            try:
                if self._sel.get_key(v.sock).events != want:
                    self._sel.modify(v.sock, want, v)
            except (KeyError, ValueError):
                pass
            if v.closing and not v.has_output():
                self._drop(v, "closed after a fatal error")

    def _accept(self) -> None:
        try:
            sock, addr = self._lsock.accept()
        except (BlockingIOError, OSError):
            return
        sock.setblocking(False)
        with self._lock:
            full = len(self._viewers) >= self.max_viewers
        if full:
            self.stats["refused_busy"] += 1
            try:
                sock.send(wire.encode(wire.error(
                    "busy", f"the engine serves at most {self.max_viewers} viewers",
                    fatal=True)))
            except OSError:
                pass
            sock.close()
            log.warning("refused a connection from %s: %d viewers connected", addr,
                        self.max_viewers)
            return
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        if self.viewer_sndbuf:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, int(self.viewer_sndbuf))
        v = _Viewer(sock, addr)
        with self._lock:
            self._viewers[sock.fileno()] = v
        self._sel.register(sock, selectors.EVENT_READ, v)
        self.stats["accepted"] += 1
        log.info("viewer connected from %s", v.addr)

    def _drop(self, v: _Viewer, why: str) -> None:
        with self._lock:
            if self._viewers.pop(v.sock.fileno(), None) is None:
                return
        try:
            self._sel.unregister(v.sock)
        except (KeyError, ValueError):
            pass
        v.sock.close()
        self.stats["dropped"] += 1
        log.info("viewer %s (%s) left: %s; drops %s, rejected %s", v.name or "?", v.addr, why,
                 dict(v.drops), dict(v.decoder.rejections))

    def _check_handshakes(self) -> None:
        now = time.monotonic()
        with self._lock:
            late = [v for v in self._viewers.values()
                    if not v.ready and not v.closing
                    and now - v.opened > self.handshake_timeout_s]
        for v in late:
            self._send_to(v, wire.error("handshake", "no hello within "
                                        f"{self.handshake_timeout_s:g} s", fatal=True),
                          close=True)

    def _read(self, v: _Viewer) -> None:
        try:
            data = v.sock.recv(65536)
        except BlockingIOError:
            return
        except OSError as exc:
            self._drop(v, f"receive failed: {exc}")
            return
        if not data:
            self._drop(v, "disconnected")
            return
        if v.closing:
            return  # a fatal error is on its way: read nothing more
        while True:
            # before the hello, decode one frame only: the frames behind it in the
            # same chunk are decoded under the limits of a viewer whose hello passed
            greeting = not v.ready
            msgs = v.decoder.feed(data, limit=1 if greeting else None)
            data = b""
            if greeting and v.decoder.rejections:
                # before the hello only a valid hello is acceptable: no second chance
                self._send_to(v, wire.error("handshake", "expected a valid hello first (at "
                                            f"most {PRE_HELLO_MAX_FRAME} bytes)", fatal=True),
                              close=True)
                return
            for msg in msgs:
                self._handle(v, msg)
            if not greeting or not msgs or v.closing:
                return

    def _handle(self, v: _Viewer, msg: dict) -> None:
        t = msg["type"]
        if v.closing:
            return
        if not v.ready:
            if t != "hello":
                self._send_to(v, wire.error("handshake", f"expected hello first, got {t}",
                                            fatal=True), close=True)
                return
            if self.token is not None and not hmac.compare_digest(
                    str(msg.get("token", "")).encode(), self.token.encode()):
                self._send_to(v, wire.error("auth", "missing or wrong token", fatal=True),
                              close=True)
                return
            why = wire.check_version(msg)
            if why is None and msg["role"] != "viewer":
                why = f"role {msg['role']!r}: only viewers connect to an engine"
            if why is not None:
                self._send_to(v, wire.error("version", why, fatal=True), close=True)
                return
            # printable only: the name goes into the server's log lines
            v.name = "".join(c if c.isprintable() else "?" for c in msg.get("name", "")[:64])
            v.rays = wire.RAYS_CAPABILITY in msg.get("capabilities", ())
            v.decoder.max_frame = wire.MAX_FRAME_BYTES
            with self._lock:
                v.ready = True
                v.queue.append(wire.encode(wire.hello("engine", "isac-twin",
                                                      capabilities=_CAPABILITIES)))
                v.queue.append(self._scene_frame)
                v.latest.update(self._latest)
                if not v.rays:
                    v.latest.pop("rays", None)
                    paths = self._paths_frame()
                    if paths is not None:
                        v.latest["paths"] = paths
            self.publish(self._status(f"viewer {v.name or v.addr} joined"))
            log.info("viewer %s (%s) ready", v.name, v.addr)
            return
        if t == "edit":
            try:
                edit = protocol.edit_from_message(msg)
            except ValueError as exc:
                self._send_to(v, wire.error("rejected", str(exc), ref=msg["target"]))
                return
            self._inbox.put((v, edit))
        elif t == "command":
            self._inbox.put((v, protocol.command_from_message(msg)))
        elif t == "error":
            log.warning("viewer %s reports %s: %s", v.addr, msg["code"], msg["message"])
            return
        else:  # a second hello
            return
        self._wake_loop.set()

    def _flush(self, v: _Viewer) -> None:
        while True:
            with self._lock:
                if not v.wbuf:
                    frame = v.next_frame()
                    if frame is None:
                        return
                    v.wbuf, v.woff = frame, 0
                    v.sent_frames += 1
                if len(v.queue) > MAX_QUEUED_FRAMES:
                    stuck = True
                else:
                    stuck = False
            if stuck:
                self._drop(v, f"more than {MAX_QUEUED_FRAMES} frames queued")
                return
            try:
                n = v.sock.send(memoryview(v.wbuf)[v.woff:])
            except BlockingIOError:
                return
            except OSError as exc:
                self._drop(v, f"send failed: {exc}")
                return
            v.woff += n
            if v.woff >= len(v.wbuf):
                v.wbuf, v.woff = b"", 0
            else:
                return
