"""How a long-running command (``serve``, ``robot``, ``replay --serve``) lives and ends.

The one place for the process lifecycle those commands share:

- :class:`StopSignals`: SIGINT and SIGTERM set a :class:`threading.Event` instead of
  raising ``KeyboardInterrupt`` wherever the main thread happens to be (inside zenoh,
  a lock or a socket call, where the exception could be lost or re-raised at exit);
  a second signal while the command is still starting ends the process at once.
- :func:`wait_for_stop`: the main thread's wait, in short slices, for a stop request
  or for the work to be done (optionally lingering after it).
- :func:`bounded_stop` and :func:`exit_now`: a shutdown that may not take longer than
  a bound, and the hard exit when it did (a stuck driver or transport thread must not
  keep the process alive).
"""

from __future__ import annotations

import faulthandler
import os
import signal
import sys
import threading
from collections.abc import Callable

__all__ = ["StopSignals", "wait_for_stop", "bounded_stop", "exit_now", "POLL_S"]

#: Longest single wait of the main thread, s. A signal the kernel hands to another
#: thread (zenoh's, a driver's) only runs its Python handler once the main thread
#: executes bytecode again, so the main thread never blocks longer than this.
POLL_S = 0.2


class StopSignals:
    """SIGINT/SIGTERM -> :attr:`stop`, for the time of a ``with`` block.

    Args:
        signals: the signals that request a stop.
        dump_stacks_on: a signal (e.g. ``signal.SIGUSR1``) that prints every thread's
            stack to stderr (:mod:`faulthandler`; works even while a native call holds
            the GIL): how a stuck process says where it is. None: not registered.

    While :attr:`starting` is true, a second signal ends the process at once with
    status ``128 + signum``: start-up (opening zenoh sessions, devices) cannot be
    interrupted cleanly, and a user who asks twice means it. The handlers installed
    before are restored when the block ends.
    """

    def __init__(self, signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM), *,
                 dump_stacks_on: int | None = None):
        self.signals = signals
        self.dump_stacks_on = dump_stacks_on
        #: Set by the first signal; what the command's loops wait on.
        self.stop = threading.Event()
        #: True while the command starts up (see the class docstring).
        self.starting = False
        self._previous: dict[int, object] = {}

    def _on_signal(self, signum: int, frame) -> None:  # noqa: ARG002
        # Only flag the stop: an exception raised from here could land inside zenoh
        # or a lock and be lost or re-raised at exit.
        if self.stop.is_set() and self.starting:
            os._exit(128 + signum)
        self.stop.set()

    def __enter__(self) -> StopSignals:
        for sig in self.signals:
            self._previous[sig] = signal.signal(sig, self._on_signal)
        if self.dump_stacks_on is not None:
            faulthandler.register(self.dump_stacks_on, all_threads=True)
        return self

    def __exit__(self, *exc) -> None:
        self.starting = False
        if self.dump_stacks_on is not None:
            faulthandler.unregister(self.dump_stacks_on)
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()


def wait_for_stop(stop: threading.Event, done: threading.Event | None = None,
                  linger_s: float | None = None) -> None:
    """Block the calling (main) thread until ``stop`` is set or, when ``linger_s`` is
    given, ``linger_s`` seconds after ``done`` is set (a stop ends the lingering too).

    Args:
        stop: the stop request (e.g. :attr:`StopSignals.stop`).
        done: set by the work when it has finished (e.g. a server's last step).
        linger_s: s to stay after ``done`` (0: leave at once); None: ignore ``done``.
    """
    while not stop.is_set():
        if linger_s is not None and done is not None and done.is_set():
            stop.wait(linger_s)
            return
        stop.wait(POLL_S)


def bounded_stop(stop_fn: Callable[[], object], timeout_s: float, who: str,
                 stage: Callable[[], str] = lambda: "?") -> bool:
    """Run ``stop_fn()`` in a helper thread and wait at most ``timeout_s`` for it.

    Args:
        stop_fn: the shutdown (e.g. a runtime's ``stop``).
        timeout_s: the longest the shutdown may take, s.
        who: the prefix of the warning line (e.g. ``"isac-twin robot"``).
        stage: names the shutdown stage the helper is stuck in, for the warning.

    Returns:
        True when the shutdown finished; False (after one line on stderr naming the
        stage it is stuck in) when it did not: the caller should :func:`exit_now`.
    """
    t = threading.Thread(target=stop_fn, name="bounded-stop", daemon=True)
    t.start()
    t.join(timeout_s)
    if not t.is_alive():
        return True
    print(f"{who}: warning: shutdown did not finish in {timeout_s:g} s (stuck in "
          f"{stage()}); exiting anyway", file=sys.stderr, flush=True)
    return False


def exit_now(code: int) -> None:
    """End the process with ``code`` at once, without waiting for other threads (after a
    :func:`bounded_stop` that timed out: a stuck thread must not keep the process alive)."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
