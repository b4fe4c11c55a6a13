"""DeviceDriver lifecycle: a device that never appears is said loudly (issue 21)."""

from __future__ import annotations

import logging
import time

from isac_twin.devices.emulated_rplidar import EmulatedRPLidar
from isac_twin.devices.rplidar import RPLidar


def test_never_present_device_is_a_warning_and_the_summary_says_so(tmp_path, caplog):
    """A port that does not exist: a WARNING (at default verbosity) within
    ``connect_warn_s``, once, naming the port and the error; the summary says
    the device never connected."""
    url = str(tmp_path / "ttyUSB9")
    lidar = RPLidar(url, connect_warn_s=0.3, backoff_max=0.1)
    with caplog.at_level(logging.WARNING, logger="isac_twin.devices"):
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


def _diag(msgs):
    from isac_twin.bus.msgs import DiagnosticArray

    out = [m for t, m in msgs if t == "diagnostics"]
    assert all(isinstance(m, DiagnosticArray) and len(m.status) == 1 for m in out)
    return [m.status[0] for m in out]


def test_diagnostics_say_what_happened(tmp_path):
    """diagnostic_msgs/DiagnosticArray on ``diagnostics`` whether connected or not:
    ERROR naming the error while the device never connected, OK with the counters
    once it is, ERROR 'lost' after an unplug, OK again after the replug."""
    from isac_twin.bus.msgs import DiagnosticStatus

    got: list = []
    with EmulatedRPLidar() as emu:
        emu.unplug()
        lidar = RPLidar(emu.url, lambda t, m: got.append((t, m)), connect_warn_s=0.2, backoff_max=0.1,
                        stale_timeout=0.3, diagnostics_period_s=0.1)
        assert "diagnostics" not in lidar.MESSAGE_TYPES
        lidar.start()
        try:
            assert "diagnostics" in lidar.MESSAGE_TYPES
            time.sleep(0.5)
            absent = _diag(got)
            emu.replug()
            assert lidar.wait_published("scan", lidar.stats.published.get("scan", 0) + 2, 3)
            time.sleep(0.25)
            n_up = len(got)
            emu.unplug()
            time.sleep(0.5)
            n_lost = len(got)
            emu.replug()
            assert lidar.wait_published("scan", lidar.stats.published.get("scan", 0) + 2, 3)
            time.sleep(0.25)
        finally:
            lidar.stop()
    assert absent and absent[-1].level == DiagnosticStatus.ERROR
    assert "never connected" in absent[-1].message and "No such file" in absent[-1].message
    up = _diag(got[:n_up])[-1]
    assert up.level == DiagnosticStatus.OK and dict(up.values)["connects"] == "1"
    assert int(dict(up.values)["scans_published"]) >= 2 and up.hardware_id == emu.url
    lost = [s for s in _diag(got[n_up:n_lost]) if s.level == DiagnosticStatus.ERROR]
    assert lost and lost[-1].message.startswith("lost")
    again = _diag(got)[-1]
    assert again.level == DiagnosticStatus.OK and dict(again.values)["connects"] == "2"
