"""The conformance checker run on both serial drivers against their emulators,
and on deliberately broken drivers (the checker must catch them)."""

from __future__ import annotations

import numpy as np
import pytest

from isac_twin.bus.msgs import BatteryState
from isac_twin.devices import rplidar as rp
from isac_twin.devices.conformance import check_driver
from isac_twin.devices.emulated_opencr import EmulatedOpenCR
from isac_twin.devices.emulated_rplidar import EmulatedRPLidar
from isac_twin.devices.opencr import OpenCR
from isac_twin.devices.rplidar import RPLidar

FAST = dict(stale_timeout=0.4, backoff_initial=0.05, backoff_max=0.3)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["standard", "express"])
def test_rplidar_conforms(mode):
    with EmulatedRPLidar(scan_rate_hz=10) as emu:
        report = check_driver(lambda url, pub: RPLidar(url, pub, scan_mode=mode, **FAST), emu, timeout=3)
    assert report.ok, str(report)
    names = [r.name for r in report.results]
    assert names == ["data", "garbage", "corrupt", "truncate", "unplug", "silent", "types", "truthful", "stop"]


@pytest.mark.slow
def test_opencr_conforms():
    with EmulatedOpenCR() as emu:
        report = check_driver(lambda url, pub: OpenCR(url, pub, **FAST), emu, timeout=3)
    assert report.ok, str(report)


class _WrongType(RPLidar):
    def _publish(self, topic, msg):
        super()._publish(topic, {"ranges": msg.ranges} if topic == self.topic else msg)


class _Stretching(rp.ScanAssembler):
    """The assembler before issue 21: one beam per node, spread uniformly from
    the first to the last node, so a turn with lost nodes is stretched."""

    def to_laser_scan(self, nodes, stamp, scan_time, **_):
        ang = np.sort(rp.device_to_ros_angle(np.array([n.angle_deg for n in nodes]), self.angle_offset))
        order = np.argsort(rp.device_to_ros_angle(np.array([n.angle_deg for n in nodes]), self.angle_offset))
        dist = np.array([nodes[k].distance_mm for k in order]) / 1000.0
        inc = (ang[-1] - ang[0]) / (len(nodes) - 1)
        return rp.LaserScan(angle_min=float(ang[0]), angle_max=float(ang[-1]), angle_increment=float(inc),
                            ranges=np.where(dist > 0, dist, np.inf))


class _StretchingLidar(RPLidar):
    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.assembler = _Stretching(stats=self.stats)


class _WrongBattery(OpenCR):
    def _publish(self, topic, msg):
        if isinstance(msg, BatteryState):
            msg.voltage *= 1.1
        super()._publish(topic, msg)


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
    assert failed == {"types", "truthful"}, str(report)

    with EmulatedOpenCR() as emu:
        report = check_driver(lambda url, pub: _NoReconnect(url, pub, **FAST), emu, timeout=1,
                              faults=("corrupt",), check_silent=False)
    failed = {r.name for r in report.results if not r.ok}
    assert failed == {"unplug"}, str(report)


@pytest.mark.slow
def test_checker_catches_untruthful_drivers():
    """Counters that move are not enough: a driver that stretches a turn with
    lost nodes over 360 deg (the RPLIDAR driver before issue 21), or scales a
    value, keeps publishing through every fault and fails only ``truthful``."""
    with EmulatedRPLidar(scan_rate_hz=10) as emu:
        report = check_driver(lambda url, pub: _StretchingLidar(url, pub, **FAST), emu, timeout=3,
                              faults=("garbage", "truncate"), check_silent=False)
    failed = {r.name for r in report.results if not r.ok}
    assert failed == {"truthful"}, str(report)

    with EmulatedOpenCR() as emu:
        report = check_driver(lambda url, pub: _WrongBattery(url, pub, **FAST), emu, timeout=2,
                              faults=(), check_silent=False)
    failed = {r.name for r in report.results if not r.ok}
    assert failed == {"truthful"}, str(report)


class _SilentDiagnostics(OpenCR):
    """Reports OK whatever happens."""

    def diagnostic_status(self):
        st = super().diagnostic_status()
        st.level, st.message = st.OK, "connected"
        return st


@pytest.mark.slow
def test_checker_catches_diagnostics_that_hide_a_loss():
    with EmulatedOpenCR() as emu:
        report = check_driver(lambda url, pub: _SilentDiagnostics(url, pub, diagnostics_period_s=0.1, **FAST), emu,
                              timeout=2, faults=(), check_silent=False)
    failed = {r.name for r in report.results if not r.ok}
    assert failed == {"unplug"}, str(report)
    assert "diagnostics said lost=False" in next(r.detail for r in report.results if r.name == "unplug")


@pytest.mark.slow
def test_oakd_conforms():
    """The OAK-D driver through its device path on an emulated camera: faulty
    frames are dropped and counted (not a lost device), unplug/silence noticed,
    every published image one the camera sent, diagnostics truthful."""
    pytest.importorskip("depthai", reason="depthai (optional extra 'oakd') is not installed")
    from isac_twin.devices.emulated_oakd import EmulatedOakD
    from isac_twin.devices.oakd import OakD

    emu = EmulatedOakD()
    report = check_driver(lambda url, pub: OakD(publish=pub, replay=emu, stale_timeout=0.4, backoff_initial=0.05,
                                                backoff_max=0.3), emu, timeout=3)
    assert report.ok, str(report)
    assert "disconnects=0" not in next(r.detail for r in report.results if r.name == "unplug")
