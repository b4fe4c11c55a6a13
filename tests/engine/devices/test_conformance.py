"""The conformance checker run on both serial drivers against their emulators,
and on deliberately broken drivers (the checker must catch them)."""

from __future__ import annotations

import pytest

from engine.devices.conformance import check_driver
from engine.devices.emulated_opencr import EmulatedOpenCR
from engine.devices.emulated_rplidar import EmulatedRPLidar
from engine.devices.opencr import OpenCR
from engine.devices.rplidar import RPLidar

FAST = dict(stale_timeout=0.4, backoff_initial=0.05, backoff_max=0.3)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["standard", "express"])
def test_rplidar_conforms(mode):
    with EmulatedRPLidar(scan_rate_hz=10) as emu:
        report = check_driver(lambda url, pub: RPLidar(url, pub, scan_mode=mode, **FAST), emu, timeout=3)
    assert report.ok, str(report)
    names = [r.name for r in report.results]
    assert names == ["data", "garbage", "corrupt", "truncate", "unplug", "silent", "types", "stop"]


@pytest.mark.slow
def test_opencr_conforms():
    with EmulatedOpenCR() as emu:
        report = check_driver(lambda url, pub: OpenCR(url, pub, **FAST), emu, timeout=3)
    assert report.ok, str(report)


class _WrongType(RPLidar):
    def _publish(self, topic, msg):
        super()._publish(topic, {"ranges": msg.ranges})


class _NoReconnect(OpenCR):
    def _connect(self):
        if self.stats.connects:
            raise OSError("this driver never reconnects")
        super()._connect()


@pytest.mark.slow
def test_checker_catches_broken_drivers():
    with EmulatedRPLidar(scan_rate_hz=10) as emu:
        report = check_driver(lambda url, pub: _WrongType(url, pub, **FAST), emu, timeout=2,
                              faults=(), check_silent=False)
    failed = {r.name for r in report.results if not r.ok}
    assert failed == {"types"}, str(report)

    with EmulatedOpenCR() as emu:
        report = check_driver(lambda url, pub: _NoReconnect(url, pub, **FAST), emu, timeout=1,
                              faults=("corrupt",), check_silent=False)
    failed = {r.name for r in report.results if not r.ok}
    assert failed == {"unplug"}, str(report)
