"""Conformance checker for device drivers, run against an emulated device.

:func:`check_driver` drives a :class:`~isac_twin.devices.base.DeviceDriver`
through what a real robot does to it and reports each step:

1. ``data``: it opens the port and publishes every declared topic;
2. ``garbage`` / ``corrupt`` / ``truncate``: after ``bursts`` injected faults
   of each kind it keeps publishing without dropping the connection, and
   corrupt/truncated frames show up in ``stats.frames_bad`` (or
   ``timeouts``/``bytes_dropped``), not as a crash or a "lost device";
3. ``unplug``: when the port disappears it notices (``stats.disconnects``),
   retries with backoff, and publishes again after the device comes back;
   its ``DiagnosticArray`` topic (if it declares one) says ERROR while the
   device is away and OK once it is back;
4. ``silent``: when the device stops answering it notices and recovers;
5. ``types``: everything it published is on a declared topic with the
   declared message type;
6. ``truthful``: everything it published -- also during the faults -- is what
   the device measured: the emulator's ``check_message(topic, msg)`` (which
   knows the truth) returns ``""`` for every message. A driver that spreads a
   partial turn over 360 deg or publishes a garbage frame fails here even if
   its counters moved;
7. ``stop``: its thread ends within the timeout.

The emulator must offer ``start()``, ``url``, ``unplug()``, ``replug()``,
``silent``, ``inject_fault(kind)`` (see :class:`~isac_twin.devices.emulated.EmulatedSerialDevice`)
and ``check_message(topic, msg) -> str`` (what is wrong with ``msg``; ``""``
if nothing; an emulator without it fails the ``truthful`` step).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from ..bus.msgs import DiagnosticArray, DiagnosticStatus
from .base import DeviceDriver, Publish

log = logging.getLogger(__name__)

DriverFactory = Callable[[str, Publish], DeviceDriver]


@dataclass
class CheckResult:
    name: str
    ok: bool
    detail: str
    seconds: float


@dataclass
class ConformanceReport:
    driver: str
    results: list[CheckResult] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return bool(self.results) and all(r.ok for r in self.results)

    def __str__(self) -> str:
        lines = [f"conformance of {self.driver}: {'PASS' if self.ok else 'FAIL'}"]
        lines += [f"  [{'ok' if r.ok else 'FAIL'}] {r.name:9s} {r.seconds:5.2f} s  {r.detail}" for r in self.results]
        return "\n".join(lines)


class _Recorder:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.messages: list[tuple[str, Any]] = []

    def __call__(self, topic: str, msg: Any) -> None:
        with self.lock:
            self.messages.append((topic, msg))


def _wait(cond: Callable[[], bool], timeout: float, poll: float = 0.01) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(poll)
    return cond()


def check_driver(driver_factory: DriverFactory, emulator: Any, *, timeout: float = 5.0,
                 faults: tuple[str, ...] = ("garbage", "corrupt", "truncate"), bursts: int = 5,
                 unplug_s: float = 0.3, check_silent: bool = True) -> ConformanceReport:
    """Run the conformance steps; never raises for a failing driver (see the report).

    Args:
        driver_factory: ``f(url, publish) -> driver`` (not started).
        emulator: emulated device (started here if it is not running).
        timeout: s allowed for each step to show its effect.
        faults: fault kinds to inject, each must be supported by the emulator.
        bursts: faults of each kind injected, 20 ms apart.
        unplug_s: s the device stays unplugged (and silent).
        check_silent: also run the "device stops answering" step.
    """
    if getattr(emulator, "_thread", None) is None:
        emulator.start()
    rec = _Recorder()
    driver = driver_factory(emulator.url, rec)
    report = ConformanceReport(type(driver).__name__)
    driver.start()  # declares its diagnostics topic
    topics = [t for t, typ in driver.MESSAGE_TYPES.items() if typ is not DiagnosticArray]  # data topics
    diag_topics = [t for t, typ in driver.MESSAGE_TYPES.items() if typ is DiagnosticArray]
    stats = driver.stats

    def step(name: str, fn: Callable[[], tuple[bool, str]]) -> bool:
        t0 = time.monotonic()
        try:
            ok, detail = fn()
        except Exception as exc:  # noqa: BLE001 - a check that raises is a failed check
            log.exception("conformance step %s raised", name)
            ok, detail = False, f"raised {type(exc).__name__}: {exc}"
        report.results.append(CheckResult(name, ok, detail, time.monotonic() - t0))
        return ok

    def counts() -> dict[str, int]:
        return {t: stats.published.get(t, 0) for t in topics}

    def more_on_all(before: dict[str, int], n: int = 2) -> Callable[[], bool]:
        return lambda: all(stats.published.get(t, 0) >= before[t] + n for t in topics)

    try:
        def data() -> tuple[bool, str]:
            ok = _wait(more_on_all({t: 0 for t in topics}, 1), timeout)
            return ok, f"published {counts()} (declared {topics})"

        if not step("data", data):
            return report

        for kind in faults:
            def fault(kind: str = kind) -> tuple[bool, str]:
                bad0 = stats.frames_bad + stats.timeouts + stats.bytes_dropped
                disc0 = stats.disconnects
                before = counts()
                for k in range(bursts):
                    if k:
                        time.sleep(0.02)
                    emulator.inject_fault(kind)
                ok = _wait(more_on_all(before, 3), timeout)
                bad = stats.frames_bad + stats.timeouts + stats.bytes_dropped - bad0
                alive = driver.running
                kept = stats.disconnects == disc0  # a bad frame is not a lost device
                if kind == "garbage":
                    good = ok and alive and kept
                else:
                    good = ok and alive and kept and _wait(
                        lambda: stats.frames_bad + stats.timeouts + stats.bytes_dropped > bad0, 0.5)
                return good, (f"data resumed={ok}, thread alive={alive}, connection kept={kept}, "
                              f"frames_bad={stats.frames_bad}, timeouts={stats.timeouts}, "
                              f"bytes_dropped={stats.bytes_dropped} (+{bad})")

            step(kind, fault)

        def diag_levels(since: int, until: int | None = None) -> list[int]:
            with rec.lock:
                return [st.level for t, msg in rec.messages[since:until] if t in diag_topics for st in msg.status]

        def unplug() -> tuple[bool, str]:
            disc0, conn0 = stats.disconnects, stats.connects
            with rec.lock:
                n0 = len(rec.messages)
            emulator.unplug()
            noticed = _wait(lambda: stats.disconnects > disc0, timeout)
            time.sleep(unplug_s)
            with rec.lock:
                n1 = len(rec.messages)
            before = counts()
            emulator.replug()
            resumed = _wait(lambda: stats.connects > conn0 and more_on_all(before, 2)(), timeout + driver.backoff_max)
            said_lost = said_up = True
            if diag_topics:  # diagnostics must say ERROR while unplugged and OK once back
                said_lost = DiagnosticStatus.ERROR in diag_levels(n0, n1)
                said_up = _wait(lambda: DiagnosticStatus.OK in diag_levels(n1), timeout + driver.diagnostics_period_s)
            return noticed and resumed and said_lost and said_up, (
                f"noticed={noticed}, resumed={resumed}, diagnostics said lost={said_lost} and up again={said_up}, "
                f"disconnects={stats.disconnects}, connects={stats.connects}, last_error={stats.last_error!r}")

        step("unplug", unplug)

        if check_silent:
            def silent() -> tuple[bool, str]:
                disc0 = stats.disconnects
                emulator.silent = True
                noticed = _wait(lambda: stats.disconnects > disc0, timeout + driver.stale_timeout)
                time.sleep(unplug_s)
                before = counts()
                emulator.silent = False
                resumed = _wait(more_on_all(before, 2), timeout + driver.backoff_max)
                return noticed and resumed, f"noticed={noticed}, resumed={resumed}, disconnects={stats.disconnects}"

            step("silent", silent)

        def types() -> tuple[bool, str]:
            with rec.lock:
                msgs = list(rec.messages)
            wrong = [(t, type(m).__name__) for t, m in msgs
                     if t not in driver.MESSAGE_TYPES or not isinstance(m, driver.MESSAGE_TYPES[t])]
            return not wrong, f"{len(msgs)} messages, {len(wrong)} off-contract {wrong[:3]}"

        step("types", types)

        def truthful() -> tuple[bool, str]:
            check = getattr(emulator, "check_message", None)
            if check is None:
                return False, f"{type(emulator).__name__} offers no check_message(topic, msg): nothing verified"
            with rec.lock:
                msgs = list(rec.messages)
            wrong = []
            for topic, msg in msgs:
                if topic in diag_topics:  # judged in the unplug step
                    continue
                problem = check(topic, msg)
                if problem:
                    wrong.append(f"{topic}: {problem}")
            return not wrong, f"{len(msgs)} messages, {len(wrong)} not what the device measured {wrong[:3]}"

        step("truthful", truthful)
    finally:
        def stop() -> tuple[bool, str]:
            driver.stop(timeout)
            return not driver.running, "thread joined" if not driver.running else "thread still running"

        step("stop", stop)
    return report
