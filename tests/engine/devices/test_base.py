"""DeviceDriver lifecycle: a device that never appears is said loudly (issue 21)."""

from __future__ import annotations

import logging
import time

from engine.devices.emulated_rplidar import EmulatedRPLidar
from engine.devices.rplidar import RPLidar


def test_never_present_device_is_a_warning_and_the_summary_says_so(tmp_path, caplog):
    """A port that does not exist: a WARNING (at default verbosity) within
    ``connect_warn_s``, once, naming the port and the error; the summary says
    the device never connected."""
    url = str(tmp_path / "ttyUSB9")
    lidar = RPLidar(url, connect_warn_s=0.3, backoff_max=0.1)
    with caplog.at_level(logging.WARNING, logger="engine.devices"):
        lidar.start()
        try:
            time.sleep(0.8)
        finally:
            lidar.stop()
    warns = [r for r in caplog.records if r.levelno >= logging.WARNING and "never connected" in r.getMessage()]
    assert len(warns) == 1, [r.getMessage() for r in caplog.records]
    assert url in warns[0].getMessage() and "No such file" in warns[0].getMessage()
    assert not lidar.ever_connected
    assert lidar.summary().startswith(f"{url}: NEVER connected")


def test_summary_of_a_device_that_connected():
    with EmulatedRPLidar() as emu:
        lidar = RPLidar(emu.url, connect_warn_s=0.3)
        lidar.start()
        try:
            assert lidar.wait_published("scan", 1, 3)
        finally:
            lidar.stop()
    assert lidar.ever_connected
    s = lidar.summary()
    assert s.startswith(f"{emu.url}: connected 1 time") and "scan: " in s
