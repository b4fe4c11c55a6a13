"""Pacing a twin's steps in real time, and what the stages of its steps cost.

:func:`run` is the loop behind ``Twin.run``: steps as fast as possible, or paced at a
rate with overruns counted by cause. :class:`RunStats` holds what the twin's steps
and runs measured; :class:`StageClock` times the consecutive stages (:data:`STAGES`)
of one step.
"""

from __future__ import annotations

import gc
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

from .state import StepResult

__all__ = ["STAGES", "RunStats", "StageClock", "run"]

log = logging.getLogger(__name__)

#: The timed stages of ``Twin.step``: agents (motion, sensors, their topics,
#: ``/tf``), trace, phy, publish (the step's result and the CSI for its
#: subscribers, e.g. a recorder), sense (``[[sensing]]`` radar), estimate, control.
STAGES = ("agents", "trace", "phy", "publish", "sense", "estimate", "control")


@dataclass
class RunStats:
    """What a paced run measured.

    Attributes:
        steps: steps run.
        wall_s: wall time, s.
        overruns: steps that took longer than the period (paced runs only).
        stage_s: total wall time per stage, s.
        overrun_stages: overruns per cause: the step's longest stage (one of
            :data:`STAGES`), or ``"caller"`` when the code that consumed the step
            between two steps (e.g. printing, recording) took longer than any stage.
        overrun_ms: total time by which paced steps missed their deadline, ms.
        stage_cpu_s: total CPU time of the stepping thread per stage, s (next to
            ``stage_s``: on a shared machine a stage whose wall time far exceeds
            its CPU time waited for a core; Dr.Jit's kernel threads and BLAS
            threads are not counted, so for ``trace`` it is the Python side).
        startup_s: the start-up of a paced run, s: the twin's first step
            (chain enumeration, kernel recording and compilation; with a radar
            also its first frame and the second step, see :func:`run`),
            which the schedule starts after and which is no overrun.
    """

    steps: int = 0
    wall_s: float = 0.0
    overruns: int = 0
    stage_s: dict[str, float] = field(default_factory=lambda: {s: 0.0 for s in STAGES})
    overrun_stages: dict[str, int] = field(default_factory=dict)
    overrun_ms: float = 0.0
    stage_cpu_s: dict[str, float] = field(default_factory=lambda: {s: 0.0 for s in STAGES})
    startup_s: float = 0.0

    def add_step(self, clock: StageClock) -> None:
        """Count one step whose stages ``clock`` timed."""
        for k, v in clock.wall.items():
            self.stage_s[k] = self.stage_s.get(k, 0.0) + v
        for k, v in clock.cpu.items():
            self.stage_cpu_s[k] = self.stage_cpu_s.get(k, 0.0) + v
        self.steps += 1

    def overrun_summary(self) -> str:
        """``"N overruns"`` with their causes, e.g. ``"2 overruns (trace 2; 3.1 ms late)"``,
        and the start-up's time when a paced run had one."""
        start = f" after a {self.startup_s:.2f} s start-up" if self.startup_s else ""
        if not self.overruns:
            return f"0 overruns{start}"
        causes = ", ".join(f"{k} {v}" for k, v in sorted(self.overrun_stages.items(),
                                                         key=lambda kv: -kv[1]))
        return (f"{self.overruns} overruns ({causes}; {self.overrun_ms:.1f} ms late in "
                f"total){start}")

    def table(self) -> str:
        """A per-stage timing breakdown (mean wall ms per step, share, and the
        stepping thread's CPU ms per step)."""
        n = max(self.steps, 1)
        total = sum(self.stage_s.values()) or 1e-12
        lines = [f"{self.steps} steps in {self.wall_s:.2f} s "
                 f"({self.steps / max(self.wall_s, 1e-12):.1f} steps/s), {self.overrun_summary()}",
                 f"  {'stage':<10} {'ms/step':>9} {'share':>6} {'cpu ms':>8}"]
        for s in STAGES:
            lines.append(f"  {s:<10} {1e3 * self.stage_s[s] / n:9.2f} "
                         f"{100 * self.stage_s[s] / total:5.1f}% "
                         f"{1e3 * self.stage_cpu_s.get(s, 0.0) / n:8.2f}")
        return "\n".join(lines)


class StageClock:
    """Wall time and the calling thread's CPU time of consecutive stages, s:
    :meth:`mark` closes the stage that began at the previous mark (or at creation)."""

    __slots__ = ("wall", "cpu", "_t", "_c")

    def __init__(self) -> None:
        self.wall: dict[str, float] = {}
        self.cpu: dict[str, float] = {}
        self._t, self._c = time.perf_counter(), time.thread_time()

    def mark(self, stage: str) -> None:
        t, c = time.perf_counter(), time.thread_time()
        self.wall[stage], self.cpu[stage] = t - self._t, c - self._c
        self._t, self._c = t, c


def run(twin, steps: int, *, rate_hz: float | None = None,
        on_step: Callable[[StepResult], None] | None = None) -> Iterator[StepResult]:
    """Run ``steps`` steps of ``twin``, as fast as possible or paced at ``rate_hz`` in
    real time (the loop behind ``Twin.run``; it counts into ``twin.stats``).

    A paced step that takes longer than its period is an *overrun*: it is
    counted in ``twin.stats`` with its cause (the step's longest stage, or
    ``"caller"`` when the consumer of the previous result took longer; see
    :attr:`RunStats.overrun_stages`) and logged, and the schedule restarts
    from now (no burst of catch-up steps).

    Paced with the radar in a child process (``sensing_process``), the twin's
    own Dr.Jit runs on one thread for the run (restored after it): its
    kernels are small, and the idle thread of a two-thread pool spins
    between them, taking the CPU the radar's process needs (the lab with 4
    robots: 20.1 ms wall and 40.1 ms CPU per step on two threads, 22.9 and
    22.8 ms on one).

    Paced, the twin's first step is its start-up (the tracer enumerates its
    chains and Dr.Jit records and compiles its kernels: ~1.2 s for the lab
    with 4 robots): the schedule starts when it ends
    (:attr:`RunStats.startup_s`). With a radar, the start-up also waits for
    its first frame (Sionna compiles the radar's solvers) and takes the
    second step too: the first frame put the robots' targets into the
    scene, so that step's trace enumerates its chains again (~1.5 s on the
    lab with 4 robots). Then the objects alive are moved out of
    Python's cyclic garbage collector (``gc.freeze``: they are kept for the
    process's life), so that its full collections, which walked them all
    (~30 ms on the lab, an overrun at 20 Hz), stay short.
    """
    if steps < 0:
        raise ValueError(f"steps: expected >= 0, got {steps}")
    if rate_hz is not None and not rate_hz > 0:
        raise ValueError(f"rate_hz: expected a positive rate, got {rate_hz}")
    period = 1.0 / rate_hz if rate_hz else 0.0
    jit_threads = None
    if period and twin.sensing_process and twin.radar is not None:
        import drjit as dr

        jit_threads = dr.thread_count()
        dr.set_thread_count(1)
    try:
        yield from _paced(twin, steps, period, rate_hz, on_step)
    finally:
        if jit_threads is not None:
            dr.set_thread_count(jit_threads)


def _paced(twin, steps: int, period: float, rate_hz, on_step) -> Iterator[StepResult]:
    start = time.perf_counter()
    deadline = start + period
    for _ in range(steps):
        startup = bool(period) and twin.step_index < (2 if twin.radar is not None else 1)
        res = twin.step()
        t_done = time.perf_counter()
        if on_step is not None:
            on_step(res)
        yield res
        if startup:
            if twin.sensing_worker is not None:
                twin.sensing_worker.wait()
            now = time.perf_counter()
            twin.stats.startup_s = now - start
            gc.collect()
            gc.freeze()
            deadline = time.perf_counter() + period
            log.info("start-up (step %d) took %.2f s; pacing at %.1f Hz after it",
                     res.step, now - start, rate_hz)
        elif period:
            now = time.perf_counter()
            if now > deadline:
                costs = dict(res.timings_s)
                costs["caller"] = now - t_done
                cause = max(costs, key=costs.get)
                st = twin.stats
                st.overruns += 1
                st.overrun_stages[cause] = st.overrun_stages.get(cause, 0) + 1
                st.overrun_ms += 1e3 * (now - deadline)
                log.warning("step %d overran its %.1f ms period by %.1f ms (%s %.1f ms)",
                            res.step, 1e3 * period, 1e3 * (now - deadline), cause,
                            1e3 * costs[cause])
                deadline = now + period
            else:
                time.sleep(deadline - now)
                deadline += period
    twin.stats.wall_s += time.perf_counter() - start
