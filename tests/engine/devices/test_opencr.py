"""OpenCR: the emulator against the official ``dynamixel_sdk`` (independent
client), and our driver against the emulator, over ptys."""

from __future__ import annotations

import math
import struct
import time

import numpy as np
import pytest

from isac_twin.bus.msgs import BatteryState, Imu, Odometry, Twist
from isac_twin.devices import opencr as oc
from isac_twin.devices.emulated_opencr import (
    DiffDriveRobot,
    EmulatedOpenCR,
    build_packet,
    crc16,
    stuff,
    unstuff,
)
from isac_twin.utils.geometry import quaternion_to_yaw

from .test_rplidar import run_with_timeout

dxl = pytest.importorskip("dynamixel_sdk")


@pytest.fixture
def emu():
    e = EmulatedOpenCR().start()
    yield e
    e.stop()


@pytest.fixture
def sdk(emu):
    """dynamixel_sdk's own PortHandler on the pty slave path (no URL handler involved)."""
    port = dxl.PortHandler(emu.path)
    assert port.openPort() and port.setBaudRate(1_000_000)
    yield port, dxl.PacketHandler(2.0)
    port.closePort()


def test_framing_agrees_with_the_sdk():
    pk = dxl.PacketHandler(2.0)
    for data in (b"\x01\x02\x03", b"\xff\xff\xfd\x00", bytes(range(256))):
        assert crc16(data) == pk.updateCRC(0, list(data), len(data))
    body = bytes((0x55, 0x00, 0xFF, 0xFF, 0xFD, 0x07))
    assert stuff(b"\x00\x00", body) == bytes((0x55, 0x00, 0xFF, 0xFF, 0xFD, 0xFD, 0x07))
    assert unstuff(b"\x00\x00", stuff(b"\x00\x00", body)) == body
    pkt = build_packet(200, 0x55, bytes((0, 0xFF, 0xFF, 0xFD, 1)))
    ours = list(pkt)
    assert pk.removeStuffing(list(pkt))[:12] == list(pkt[:5]) + [8, 0] + [0x55, 0, 0xFF, 0xFF, 0xFD]
    assert crc16(pkt[:-2]) == struct.unpack("<H", pkt[-2:])[0] == pk.updateCRC(0, ours, len(ours) - 2)


def test_sdk_ping_read_block_and_errors(sdk, emu):
    port, pk = sdk

    def client():
        model, res, err = pk.ping(port, 200)
        block, res2, err2 = pk.readTxRx(port, 200, oc.BLOCK_ADDR, oc.BLOCK_LEN)
        wrong_id = pk.ping(port, 7)[1]
        ro = pk.write1ByteTxRx(port, 200, oc.Addr.MILLIS, 1)
        return model, res, err, block, res2, err2, wrong_id, ro

    model, res, err, block, res2, err2, wrong_id, ro = run_with_timeout(client, 5)
    assert (model, res, err) == (0x5000, dxl.COMM_SUCCESS, 0)
    assert res2 == dxl.COMM_SUCCESS and err2 == 0 and len(block) == 172
    st = oc.OpenCRState.from_block(bytes(block))
    assert st.device_status == 0 and st.torque_enabled and st.battery_voltage == pytest.approx(12.1)
    assert st.linear_acceleration[2] == pytest.approx(9.80665, rel=1e-6)
    assert wrong_id == dxl.COMM_RX_TIMEOUT  # nobody answers ID 7
    assert ro == (dxl.COMM_SUCCESS, 7)  # millis is read-only: data-access error


def test_no_replies_the_firmware_does_not_give(sdk, emu):
    """The TurtleBot3 firmware answers through ROBOTIS' Dynamixel2Arduino slave
    (``src/utility/slave.cpp``): a packet with a bad CRC never parses (no reply),
    broadcast PING/READ/WRITE get no status, and only PING, READ and WRITE are
    processed: SYNC_READ, BULK_READ, REBOOT... get nothing back."""
    port, pk = sdk

    def client():
        sync = dxl.GroupSyncRead(port, pk, oc.Addr.MODEL_NUMBER, 2)
        sync.addParam(200)
        r1 = sync.txRxPacket()
        bulk = dxl.GroupBulkRead(port, pk)
        bulk.addParam(200, oc.Addr.BATTERY_VOLTAGE, 4)
        r2 = bulk.txRxPacket()
        found, _ = pk.broadcastPing(port)
        reboot = pk.reboot(port, 200)[0]
        bcast_write = pk.write1ByteTxOnly(port, dxl.BROADCAST_ID, oc.Addr.MOTOR_TORQUE_ENABLE, 0)
        port.clearPort()
        good = build_packet(200, 0x02, struct.pack("<HH", oc.Addr.MODEL_NUMBER, 2))
        port.writePort(list(good[:-1] + bytes((good[-1] ^ 0x5A,))))  # READ with a bad CRC
        time.sleep(0.1)
        after_bad_crc = port.readPort(64)
        still = pk.read2ByteTxRx(port, 200, oc.Addr.MODEL_NUMBER)
        torque = pk.read1ByteTxRx(port, 200, oc.Addr.MOTOR_TORQUE_ENABLE)[0]
        return r1, r2, found, reboot, bcast_write, after_bad_crc, still, torque

    r1, r2, found, reboot, bcast_write, after_bad_crc, still, torque = run_with_timeout(client, 8)
    assert r1 == dxl.COMM_RX_TIMEOUT and r2 == dxl.COMM_RX_TIMEOUT
    assert not found  # broadcast PING: no status from the board
    assert reboot == dxl.COMM_RX_TIMEOUT
    assert bcast_write == dxl.COMM_SUCCESS and torque == 1  # broadcast WRITE ignored
    assert list(after_bad_crc) == []  # bad CRC: silence, not error 0x03
    assert still == (0x5000, dxl.COMM_SUCCESS, 0)  # and the board keeps answering
    assert emu.stats.bad_requests >= 1


def test_sdk_cmd_vel_moves_the_robot_and_watchdog_stops_it(sdk, emu):
    port, pk = sdk

    def client():
        pos0 = [pk.read4ByteTxRx(port, 200, a)[0] for a in (oc.Addr.PRESENT_POSITION, oc.Addr.PRESENT_POSITION + 4)]
        res = pk.writeTxRx(port, 200, oc.Addr.CMD_VELOCITY, 24, list(struct.pack("<6i", 10, 0, 0, 0, 0, 50)))
        hb = 0
        t_end = time.monotonic() + 0.4
        while time.monotonic() < t_end:  # heartbeat keeps the command alive
            hb += 1
            pk.write1ByteTxRx(port, 200, oc.Addr.HEARTBEAT, hb & 0xFF)
            time.sleep(0.1)
        raw = pk.readTxRx(port, 200, oc.Addr.PRESENT_VELOCITY, 16)[0]
        x_moving = emu.robot.x
        time.sleep(0.7)  # no heartbeat: firmware watchdog zeroes cmd_vel after 0.5 s
        cmd_after = pk.readTxRx(port, 200, oc.Addr.CMD_VELOCITY, 24)[0]
        return pos0, res, raw, x_moving, cmd_after

    pos0, res, raw, x_moving, cmd_after = run_with_timeout(client, 5)
    assert res == (dxl.COMM_SUCCESS, 0)
    vel_l, vel_r, pos_l, pos_r = struct.unpack("<4i", bytes(raw))
    r, sep = oc.WHEEL_RADIUS, oc.WHEEL_SEPARATION["burger"]
    wl, wr = oc.velocity_units_to_rad_s([vel_l, vel_r])
    assert wl == pytest.approx((0.1 - 0.5 * sep / 2) / r, rel=0.02)
    assert wr == pytest.approx((0.1 + 0.5 * sep / 2) / r, rel=0.02)
    assert pos_r - pos0[1] > pos_l - pos0[0] > 0  # turning left: right wheel ran further
    assert x_moving > 0.03
    assert struct.unpack("<6i", bytes(cmd_after)) == (0,) * 6 and emu.watchdog_trips == 1


def test_cmd_vel_is_kept_raw_and_limited_when_applied(sdk, emu):
    """The firmware keeps the written cmd_vel in its table and limits the
    speed when it drives the wheels (burger 0.211 m/s): 1.00 m/s reads back as 100."""
    port, pk = sdk

    def client():
        res = pk.writeTxRx(port, 200, oc.Addr.CMD_VELOCITY, 24, list(struct.pack("<6i", 100, 0, 0, 0, 0, -900)))
        time.sleep(0.2)
        back = pk.readTxRx(port, 200, oc.Addr.CMD_VELOCITY, 24)[0]
        vel = pk.readTxRx(port, 200, oc.Addr.PRESENT_VELOCITY, 8)[0]
        return res, back, vel

    res, back, vel = run_with_timeout(client, 5)
    assert res == (dxl.COMM_SUCCESS, 0)
    assert struct.unpack("<6i", bytes(back)) == (100, 0, 0, 0, 0, -900)
    wl, wr = oc.velocity_units_to_rad_s(list(struct.unpack("<2i", bytes(vel))))
    r = oc.WHEEL_RADIUS
    assert abs(r * (wl + wr) / 2) <= oc.MAX_LINEAR["burger"] + 1e-3
    assert emu.cmd_vel == (1.0, -9.0)


def test_driver_odometry_imu_battery(emu):
    got: dict[str, list] = {}
    drv = oc.OpenCR(emu.url, lambda t, m: got.setdefault(t, []).append(m))
    t0 = time.monotonic()
    drv.start()
    try:
        assert drv.wait_published("odom", 2, 3)
        drv.on_cmd_vel(Twist(linear=np.array([0.15, 0, 0]), angular=np.array([0, 0, 0.6])))
        time.sleep(1.2)  # heartbeat keeps the command alive past the 0.5 s watchdog
        assert emu.cmd_vel == (0.15, 0.6) and emu.watchdog_trips == 0
        drv.set_cmd_vel(0.0, 0.0)
        time.sleep(0.15)
        n = drv.stats.published["odom"]
        assert drv.wait_published("odom", n + 2, 1)
    finally:
        drv.stop()
    ran_s = time.monotonic() - t0
    assert not drv.running
    assert drv.model_number == 0x5000
    odom, imu, bat = got["odom"][-1], got["imu"][-1], got["battery_state"][-1]
    assert isinstance(odom, Odometry) and isinstance(imu, Imu) and isinstance(bat, BatteryState)
    robot = emu.robot
    # odometry integrated from tick deltas tracks the emulated robot (1 tick = 0.05 mm of travel)
    assert odom.pose.position[0] == pytest.approx(robot.x, abs=0.01)
    assert odom.pose.position[1] == pytest.approx(robot.y, abs=0.01)
    assert quaternion_to_yaw(odom.pose.orientation) == pytest.approx(robot.yaw, abs=0.02)
    assert quaternion_to_yaw(imu.orientation) == pytest.approx(robot.yaw, abs=1e-3)
    assert robot.x > 0.1 and robot.yaw > 0.4
    moving = [m for m in got["odom"] if m.twist.linear[0] > 0.1]
    assert moving and moving[-1].twist.angular[2] == pytest.approx(0.6, rel=0.05)
    assert bat.voltage == pytest.approx(12.1)
    # 20 Hz like the ROS node: the reads are scheduled 50 ms apart, so never more
    # messages than the time it ran allows (an exact bound; how close a loaded
    # machine comes to it is bench_devices' business)
    assert drv.read_rate_hz == 20.0
    assert 2 <= len(got["odom"]) <= ran_s * drv.read_rate_hz + 2


def test_the_driver_waits_for_the_board_without_spinning(emu):
    """dynamixel_sdk waits for an answer by calling ``readPort`` in a loop until its
    packet timeout (34 ms + bytes). On a port opened with read timeout 0 each call
    returned at once: the driver's thread spun, holding the GIL, and starved the
    other threads of the robot's process (the camera's, the emulated board's), so
    answers came late (with the OAK-D streaming: 37 timeouts in 10 s instead of 1).
    The port now blocks in ``select`` up to ``READ_POLL_S`` per call, so a
    transaction makes at most ``packet timeout / READ_POLL_S + 3`` calls, whatever
    the load (before: hundreds)."""
    drv = oc.OpenCR(emu.url)
    drv.open()
    try:
        ser = drv.port.ser
        assert 0 < ser.timeout == oc.READ_POLL_S
        calls = {"n": 0}
        read = ser.read

        def counting(n=1):
            calls["n"] += 1
            return read(n)

        ser.read = counting
        n = 20
        for _ in range(n):
            drv.read_block()
        timeout_ms = drv.port.tx_time_per_byte * (oc.BLOCK_LEN + 11) + 16 * 2.0 + 2.0
        bound = math.ceil(timeout_ms / 1e3 / oc.READ_POLL_S) + 3
        assert calls["n"] <= n * bound, calls["n"]
    finally:
        drv.close()


def test_cmd_vel_scaling_truncates_like_the_ros_node():
    assert struct.unpack("<6i", oc.encode_cmd_vel(0.129, -1.239)) == (12, 0, 0, 0, 0, -123)


def test_odometry_integration_and_wraparound():
    odo = oc.DiffDriveOdometry(0.033, 0.160)
    odo.update(np.array([2**31 - 10, 5]))
    ticks_per_m = 1 / (oc.TICK_TO_RAD * 0.033)
    odo.update(np.array([2**31 - 10 + int(ticks_per_m), 5 + int(ticks_per_m)]) % 2**32)
    assert odo.x == pytest.approx(1.0, abs=1e-3) and odo.y == pytest.approx(0.0, abs=1e-9)
    quarter = 0.160 * math.pi / 2 / 2  # each wheel's arc for a 90 deg spin in place
    t = int(quarter * ticks_per_m)
    last = odo._last_ticks
    odo.update(last + np.array([-t, t]))
    assert odo.yaw == pytest.approx(math.pi / 2, abs=1e-3)


def test_custom_step_callback_plugs_in():
    calls = []

    def step(v, w, dt):
        calls.append((v, w, dt))
        return (1.0, 2.0, 0.5, 0.6, np.array([0, 0, 0.1]), np.array([0, 0, 9.8]), np.array([0, 0, 0, 1.0]))

    with EmulatedOpenCR(step) as emu:
        port = dxl.PortHandler(emu.path)
        port.openPort()
        try:
            pk = dxl.PacketHandler(2.0)
            time.sleep(0.05)
            raw = run_with_timeout(lambda: pk.readTxRx(port, 200, oc.BLOCK_ADDR, oc.BLOCK_LEN), 3)[0]
        finally:
            port.closePort()
    st = oc.OpenCRState.from_block(bytes(raw))
    assert calls and all(dt <= 0.01 + 1e-9 for _, _, dt in calls)
    assert st.angular_velocity[2] == pytest.approx(0.1, rel=1e-6)
    assert tuple(st.wheel_ticks) == (0, 0)  # encoders count from power-on


def test_default_robot_limits():
    r = DiffDriveRobot("waffle")
    lp, rp_, wl, wr, gyro, acc, quat = r(1.0, 5.0, 0.1)
    assert gyro[2] == pytest.approx(1.85) and (wl + wr) / 2 * 0.033 == pytest.approx(0.266)
