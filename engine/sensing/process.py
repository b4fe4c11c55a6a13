"""``SensingProcess``: the twin's radar frames computed in a child process.

The :class:`~isac_twin.sensing.worker.SensingWorker` computes a frame on a thread
of the twin's process. It shares the twin's Python interpreter (the GIL) and
Dr.Jit's one thread pool, so while a frame is out the twin's own steps wait
behind it: on the lab with 4 robots and its radar, the step after a frame is
submitted took 136 ms on average against 31 ms without a radar (unpaced,
2 cores), and a paced run at 20 Hz overran ~150 times in 1,000 steps.

``SensingProcess`` has the worker's interface (``submit``, ``due``,
``collect``, ``wait``, ``close``, ``latency``) but computes in a child process
(``python -m isac_twin.sensing.process``): its own interpreter, its own Dr.Jit, its own
replica of the twin's scene, at a lower CPU priority (``nice``), so the
operating system gives the twin's steps the cores first and the frame the
time left between them.

The replica. The child loads the scene from the twin's folder and replays the
scene's edits (:attr:`isac_twin.scene.twin_scene.TwinScene.edits`: those made before the
twin was built and, with every job, those made since); each job carries the
twin's :meth:`~isac_twin.scene.twin_scene.TwinScene.content_hash`, and a child whose replica
hashes otherwise refuses the frame (an error raised on the twin's thread by
:meth:`collect`) rather than sensing another room. The robot targets of a
frame are posed in the replica from the job (``SensingJob.targets``), as the
twin posed them in its own scene.

Determinism: the child runs the same :class:`~isac_twin.sensing.estimator.
RadarEstimator` (same links, same seed) on the same jobs in the same order, so
it computes the frames the synchronous radar computes, delivered on the
worker's schedule (tested, bit for bit).

Messages (a socket pair, ``multiprocessing.connection``, pickled): twin ->
child ``("init", scene path, edits, links, seed, nice)`` once, ``("job", job,
edits, scene hash)``, ``("reset", links, seed)``, ``("close",)``; child ->
twin ``("ready", None)`` once, then ``("frame", SensingStep)`` or ``("error",
exception)`` per job.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import socket
import subprocess
import sys
import weakref
from multiprocessing.connection import Connection
from pathlib import Path

__all__ = ["SensingProcess"]

#: niceness of the child (19, the lowest priority: its frames take only the
#: time the twin's steps leave on the cores)
DEFAULT_NICE = 19

#: seconds :meth:`SensingProcess.close` waits for the child before killing it
_CLOSE_TIMEOUT_S = 10.0


class SensingProcess:
    """Radar frames of ``scene``'s ``[[sensing]]`` links in a child process,
    delivered ``latency`` steps after the step they sense.

    Args:
        scene: the twin's :class:`~isac_twin.scene.twin_scene.TwinScene` (the child loads its
            folder, ``scene.config.path``, and replays ``scene.edits``).
        links: the radar's :class:`~isac_twin.sensing.link.SensingLinkSpec` list.
        seed: the radar's seed (as the twin's own ``RadarEstimator``).
        latency: steps between the sensed step and the step that delivers it (>= 1).
        nice: niceness of the child process (0..19, at least the twin's own).
    """

    #: frames trace the child's replica: the twin's edits need not wait for them
    shares_scene = False

    def __init__(self, scene, links, seed: int, latency: int, *,
                 nice: int = DEFAULT_NICE) -> None:
        if int(latency) < 1:
            raise ValueError(f"latency: expected >= 1 step, got {latency!r}")
        if not 0 <= int(nice) <= 19:
            raise ValueError(f"nice: expected 0..19, got {nice!r}")
        self.scene = scene
        self.latency = int(latency)
        self._sent_edits = len(scene.edits)
        self._pending: int | None = None  # delivery step of the frame out
        # A child of its own interpreter (``python -m isac_twin.sensing.process``), not
        # multiprocessing's spawn, which runs the parent's main script again in the
        # child (a script without a ``__main__`` guard would build a second twin).
        ours, theirs = socket.socketpair()
        env = dict(os.environ)
        root = str(Path(__file__).resolve().parents[2])  # the engine's folder on sys.path
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "isac_twin.sensing.process", str(theirs.fileno())],
            pass_fds=(theirs.fileno(),), env=env, stdin=subprocess.DEVNULL)
        theirs.close()
        self._conn = Connection(ours.detach())
        self._conn.send(("init", str(scene.config.path), list(scene.edits), list(links),
                         int(seed), int(nice)))
        self._ready = self._closed = False
        self._finalizer = weakref.finalize(self, _stop, self._conn, self._proc)

    @property
    def pending(self) -> bool:
        """A frame is out (submitted, not yet collected)."""
        return self._pending is not None

    def due(self, step: int) -> bool:
        """The frame out must be delivered on ``step``."""
        return self._pending is not None and step >= self._pending

    def submit(self, job, step: int) -> None:
        """Send ``job`` (a :class:`~isac_twin.sensing.estimator.SensingJob`) to the
        child, with the scene's edits since the last job; due on ``step + latency``."""
        if self._pending is not None:
            raise RuntimeError("SensingProcess.submit: collect the frame out first")
        edits = self.scene.edits[self._sent_edits:]
        self._send(("job", dataclasses.replace(job, contains=None), list(edits),
                    self.scene.content_hash()))
        self._sent_edits += len(edits)
        self._pending = int(step) + self.latency

    def wait(self) -> None:
        """Wait until the frame out (if any) is finished, without collecting it."""
        if self._pending is not None:
            self._wait_ready()
            self._conn.poll(None)

    def collect(self):
        """Wait for the frame out and return its ``SensingStep`` (None if none is
        out); an error of the frame (or of the child) is raised here."""
        if self._pending is None:
            return None
        self._pending = None
        self._wait_ready()
        kind, value = self._recv()
        if kind == "error":
            raise value
        return value

    def reset(self, links, seed: int) -> None:
        """Drop the frame out; the child starts a new radar (``links``, ``seed``)
        on its replica, as the twin does on a reset."""
        if self._pending is not None:
            self._pending = None
            self._wait_ready()
            self._recv()  # the dropped frame (or its error)
        self._send(("reset", list(links), int(seed)))

    def close(self) -> None:
        """Drop the frame out and end the child (with it the radar's state: a
        later :meth:`submit` raises). Idempotent."""
        self._pending = None
        self._closed = True
        self._finalizer()

    # ------------------------------------------------------------------ pipe

    def _send(self, msg) -> None:
        if self._closed:
            raise RuntimeError("sensing process: closed (Twin.close()); the radar's state "
                               "ended with its child")
        try:
            self._conn.send(msg)
        except OSError:
            raise RuntimeError(f"sensing process: the child ended (exit code "
                               f"{self._proc.poll()})") from None

    def _recv(self):
        try:
            return self._conn.recv()
        except (EOFError, OSError):
            try:
                code = self._proc.wait(1.0)
            except subprocess.TimeoutExpired:
                code = None
            raise RuntimeError(f"sensing process: the child ended without a frame (exit code "
                               f"{code}; its error, if any, is on stderr above)") from None

    def _wait_ready(self) -> None:
        """The child's first message: loaded (or the error that stopped it)."""
        if self._ready:
            return
        kind, value = self._recv()
        if kind == "error":
            raise RuntimeError(f"sensing process: the child could not start: {value}") \
                from value
        self._ready = True


def _stop(conn, proc) -> None:
    """End the child: ask, then wait, then kill."""
    try:
        if proc.poll() is None:
            conn.send(("close",))
    except (OSError, ValueError):
        pass
    try:
        proc.wait(_CLOSE_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    conn.close()


def _child_main(conn) -> None:
    """The child: load the replica, then compute the frames it is sent, in order."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is for the twin, which ends us
    _, scene_path, edits, links, seed, nice = conn.recv()
    os.nice(max(0, nice - os.nice(0)))  # before Dr.Jit starts its threads: they inherit it
    try:
        from ..scene.twin_scene import load_scene
        from .estimator import RadarEstimator

        scene = load_scene(scene_path)
        scene.replay(edits)

        def new_radar(links, seed):
            radar = RadarEstimator(links, seed=seed, publish=False)
            radar.setup(scene)
            return radar

        radar = new_radar(links, seed)
    except Exception as exc:  # noqa: BLE001  (reported to the twin, which raises it)
        conn.send(("error", _portable(exc)))
        return
    conn.send(("ready", None))
    while True:
        try:
            msg = conn.recv()
        except EOFError:  # the twin is gone
            return
        if msg[0] == "close":
            return
        try:
            if msg[0] == "reset":
                radar = new_radar(msg[1], msg[2])
                continue
            _, job, new_edits, scene_hash = msg
            scene.replay(new_edits)
            if scene.content_hash() != scene_hash:
                raise RuntimeError(
                    f"sensing process: its replica of {scene_path} hashes "
                    f"{scene.content_hash()[:12]}, the twin's scene {scene_hash[:12]}: the twin's "
                    f"scene was changed other than by TwinScene's edit methods")
            radar.pose_targets(job.targets)
            out = radar.compute(dataclasses.replace(job, contains=scene.contains))
            conn.send(("frame", out))
        except Exception as exc:  # noqa: BLE001
            conn.send(("error", _portable(exc)))


def _portable(exc: BaseException) -> BaseException:
    """``exc`` if it pickles, else a RuntimeError with its text."""
    import pickle

    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:  # noqa: BLE001
        return RuntimeError(f"{type(exc).__name__}: {exc}")


if __name__ == "__main__":  # the child: python -m isac_twin.sensing.process FD
    _child_main(Connection(int(sys.argv[1])))
