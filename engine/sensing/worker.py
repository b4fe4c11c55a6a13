"""``SensingWorker``: the twin's radar frames computed off the stepping thread.

A radar frame (:class:`~isac_twin.sensing.estimator.RadarEstimator`) costs far more
than a twin step (the lab with 4 robots: ~0.2 s of CPU against a 50 ms period at
20 Hz), so a paced twin that sensed on its stepping thread overran on every
sensing step. With the worker the stepping thread only *prepares* a frame (the
targets posed in the Sionna scene from step ``k``'s truth, a snapshot of the
device poses: :meth:`RadarEstimator.prepare`); one worker thread traces, receives,
processes and tracks it (:meth:`RadarEstimator.compute`) while steps ``k + 1, ...``
run, and the frame is *delivered* on a fixed later step:

* step ``k + latency`` (``latency``: the shortest ``every`` of the sensing links,
  i.e. just before the next frame is prepared), or earlier if another frame
  becomes due first;
* on delivery the stepping thread waits for the frame if it is not finished yet,
  publishes it (``/sensing/detections`` stamped with step ``k``'s time) and sets
  ``result.sensing`` of the delivering step to it (``SensingStep.step == k``).

Determinism: when a frame is delivered depends on step numbers only, never on
timing, frames are computed one at a time in step order, and the worker reads
only the prepared snapshot and the Sionna scene, which nothing changes while a
frame is out (the stepping thread waits for it before edits, a reset or posing
the next targets; :meth:`SensingWorker.wait`). So a twin with the worker publishes
the same frames as a synchronous one (``Twin(sync_sensing=True)``), each on the
step ``latency`` later, and a recording or replay of it is as deterministic as
one of the synchronous twin (tested).
"""

from __future__ import annotations

import threading
import weakref
from concurrent.futures import Future, ThreadPoolExecutor

__all__ = ["SensingWorker", "wait_all"]

#: Every SensingWorker not yet collected (for :func:`wait_all`).
_LIVE: "weakref.WeakSet[SensingWorker]" = weakref.WeakSet()


class SensingWorker:
    """One thread computing radar frames, delivered ``latency`` steps later.

    Args:
        radar: the :class:`~isac_twin.sensing.estimator.RadarEstimator` (its
            ``compute`` runs on the worker).
        latency: steps between the sensed step and the step that delivers it (>= 1).
    """

    #: frames trace the twin's own scene: edits wait for the frame out
    shares_scene = True

    def __init__(self, radar, latency: int) -> None:
        if int(latency) < 1:
            raise ValueError(f"latency: expected >= 1 step, got {latency!r}")
        self.radar = radar
        self.latency = int(latency)
        self._pool: ThreadPoolExecutor | None = None
        #: (delivery step, future) of the frame out, or None
        self._pending: tuple[int, Future] | None = None
        _LIVE.add(self)

    @property
    def pending(self) -> bool:
        """A frame is out (submitted, not yet collected)."""
        return self._pending is not None

    def due(self, step: int) -> bool:
        """The frame out must be delivered on ``step``."""
        return self._pending is not None and step >= self._pending[0]

    def submit(self, job, step: int) -> None:
        """Compute ``job`` (a :class:`~isac_twin.sensing.estimator.SensingJob`) on the
        worker; it is due on ``step + latency``. Only one frame is out at a time."""
        if self._pending is not None:
            raise RuntimeError("SensingWorker.submit: collect the frame out first")
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="isac-sensing")
            weakref.finalize(self, _shutdown, self._pool)
        _new_scope()  # the job's arrays were made in this thread's current scope
        self._pending = (int(step) + self.latency, self._pool.submit(self._compute, job))

    def _compute(self, job):
        # Dr.Jit orders work by scope ids: before this thread reads arrays the
        # stepping thread made (the prepared targets, the scene), it takes a
        # newer scope than theirs, else evaluation fails ("scope ID of
        # predecessors must be lower"; seen in a 1,000-step paced run).
        _new_scope()
        out = self.radar.compute(job)
        _new_scope()
        return out

    def collect(self):
        """Wait for the frame out and return its ``SensingStep`` (None if none is
        out); an error of the frame is raised here, on the stepping thread."""
        if self._pending is None:
            return None
        _, fut = self._pending
        self._pending = None
        out = fut.result()
        _new_scope()  # the stepping thread may now read what the worker made
        return out

    def wait(self) -> None:
        """Wait until the frame out (if any) is finished, without collecting it
        (before anything changes the Sionna scene). Its error, if any, is raised
        by :meth:`collect`."""
        if self._pending is not None:
            self._pending[1].exception()

    def close(self) -> None:
        """Wait for the frame out, drop it and stop the thread."""
        self.wait()
        self._pending = None
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None


def wait_all() -> None:
    """Wait until no worker of this process computes a frame: also the frames
    of twins dropped with a frame out and not yet collected, whose thread
    would go on using Dr.Jit beside whatever the process does next (a test
    session runs this after every test)."""
    for w in list(_LIVE):
        w.wait()


def _shutdown(pool: ThreadPoolExecutor) -> None:
    """Stop ``pool`` (a collected worker's): wait for its thread, unless this
    is that thread (the garbage collector ran there), which cannot join itself
    and ends on its own once its queue is shut."""
    pool.shutdown(wait=threading.current_thread() not in getattr(pool, "_threads", ()))


def _new_scope() -> None:
    """A new Dr.Jit scope on the calling thread (``drjit.detail.new_scope``),
    the handoff Dr.Jit requires between threads that share arrays."""
    import drjit as dr

    dr.detail.new_scope(dr.JitBackend.LLVM)
