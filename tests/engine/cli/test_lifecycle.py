"""isac_twin.cli.lifecycle: signals to a stop event (a second one during start-up ends
the process at once), the main thread's wait, the bounded shutdown."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time

from isac_twin.cli.lifecycle import bounded_stop, wait_for_stop

from .conftest import ROOT

_CHILD = """
import os, signal, sys, time
from isac_twin.cli.lifecycle import StopSignals
before = signal.getsignal(signal.SIGTERM)
with StopSignals() as life:
    life.starting = sys.argv[1] == "starting"
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(0.1)  # the handler runs between bytecodes of the main thread
    print("stop", life.stop.is_set(), flush=True)
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(0.1)
    print("still here", flush=True)
print("restored", signal.getsignal(signal.SIGTERM) is before, flush=True)
"""


def _child(mode: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", _CHILD, mode], capture_output=True, text=True,
                          cwd=ROOT, timeout=60)


def test_signals_set_the_stop_and_a_second_one_while_starting_exits():
    r = _child("running")
    assert r.returncode == 0, r.stderr
    assert r.stdout.split("\n")[:3] == ["stop True", "still here", "restored True"]
    r = _child("starting")
    assert r.returncode == 128 + signal.SIGTERM, (r.returncode, r.stdout, r.stderr)
    assert r.stdout == "stop True\n"  # the second signal ended it at once


def test_wait_for_stop_returns_on_stop_or_after_lingering():
    """Exact bounds only (no "fast enough"): a wait ends no earlier than its cause, and
    a stop ends a linger before the linger would have ended it."""
    stop, done = threading.Event(), threading.Event()
    threading.Timer(0.3, stop.set).start()
    t0 = time.monotonic()
    wait_for_stop(stop, done)  # no linger: done alone does not end the wait
    assert stop.is_set() and time.monotonic() - t0 >= 0.25
    stop.clear()
    done.set()
    t0 = time.monotonic()
    wait_for_stop(stop, done, linger_s=0.4)
    assert not stop.is_set() and time.monotonic() - t0 >= 0.35
    t0 = time.monotonic()
    threading.Timer(0.1, stop.set).start()
    wait_for_stop(stop, done, linger_s=30.0)  # a stop ends the lingering
    assert stop.is_set() and time.monotonic() - t0 < 30.0


def test_bounded_stop_says_where_a_stuck_shutdown_is(capsys):
    assert bounded_stop(lambda: None, 5.0, "isac-twin test")
    assert capsys.readouterr().err == ""
    hang = threading.Event()
    t0 = time.monotonic()
    assert not bounded_stop(hang.wait, 0.2, "isac-twin test", stage=lambda: "driver X")
    assert not hang.is_set() and time.monotonic() - t0 >= 0.15  # gave up, after its bound
    hang.set()
    assert capsys.readouterr().err == ("isac-twin test: warning: shutdown did not finish in "
                                       "0.2 s (stuck in driver X); exiting anyway\n")
