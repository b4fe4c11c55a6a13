"""OAK-D: fast clear error without a device; frame conversion through a
host-only depthai pipeline (real ``dai.ImgFrame`` objects, no device)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from isac_twin.bus.msgs import Image, Imu
from isac_twin.devices import oakd

from .test_rplidar import run_with_timeout

dai = pytest.importorskip("depthai", reason="depthai (optional extra 'oakd') is not installed")


def test_no_device_fails_fast_with_a_clear_error():
    if dai.Device.getAllAvailableDevices():
        pytest.skip("an OAK device is attached")
    cam = oakd.OakD()
    # fast by construction, not by a stopwatch: the device list is asked first (no
    # search), and depthai's own search is cut short unless the user set its timeout
    with pytest.raises(oakd.OakDNotFound, match=r"getAllAvailableDevices\(\) returned \[\]"):
        run_with_timeout(cam.open, 10)
    import os

    assert "DEPTHAI_SEARCH_TIMEOUT" in os.environ  # the driver's short one, or the user's


def test_threaded_driver_keeps_retrying_without_device():
    cam = oakd.OakD(backoff_initial=0.05, backoff_max=0.1)
    cam.start()
    try:
        deadline = time.monotonic() + 3
        while "no OAK device" not in cam.stats.last_error and time.monotonic() < deadline:
            time.sleep(0.02)
        assert "no OAK device found" in cam.stats.last_error and cam.running
    finally:
        cam.stop(5)
    assert not cam.running


class _Source(dai.node.ThreadedHostNode):
    """Host node emitting colour and depth frames like the device would."""

    def __init__(self) -> None:
        super().__init__()
        self.color = self.createOutput()
        self.depth = self.createOutput()

    def run(self) -> None:
        i = 0
        while self.isRunning():
            c = dai.ImgFrame()
            c.setType(dai.ImgFrame.Type.RGB888i)
            c.setWidth(8)
            c.setHeight(4)
            rgb = np.zeros((4, 8, 3), np.uint8)
            rgb[..., 0] = 200  # red
            rgb[0, 0] = (1, 2, 3)
            c.setData(rgb.reshape(-1))
            c.setSequenceNum(i)
            c.setTimestamp(dai.Clock.now())
            self.color.send(c)
            d = dai.ImgFrame()
            d.setType(dai.ImgFrame.Type.RAW16)
            d.setWidth(8)
            d.setHeight(4)
            d.setData(np.full((4, 8), 1234, np.uint16).view(np.uint8).reshape(-1))
            d.setTimestamp(dai.Clock.now())
            self.depth.send(d)
            i += 1
            time.sleep(0.005)


def test_host_only_pipeline_frames_convert_to_images():
    t_before = time.time()

    def run():
        p = dai.Pipeline(createImplicitDevice=False)
        src = p.create(_Source)
        qc = src.color.createOutputQueue(maxSize=4, blocking=False)
        qd = src.depth.createOutputQueue(maxSize=4, blocking=False)
        p.start()
        try:
            return qc.get(), qd.get()
        finally:
            p.stop()
            p.wait()  # join the host node's thread before the pipeline is destroyed:
            # ~Pipeline joins it while holding the GIL and would deadlock

    c, d = run_with_timeout(run, 10)
    img = oakd.imgframe_to_image(c, "camera_color_optical_frame")
    assert isinstance(img, Image) and img.encoding == "rgb8" and img.data.shape == (4, 8, 3)
    assert tuple(img.data[0, 0]) == (1, 2, 3) and img.data[1, 1, 0] == 200
    assert t_before - 0.01 <= img.header.stamp <= time.time() + 0.01  # stamped on the host clock
    dep = oakd.imgframe_to_image(d, "camera_depth_optical_frame")
    assert dep.encoding == "16UC1" and dep.data.dtype == np.uint16 and np.all(dep.data == 1234)


def test_imu_packet_conversion():
    pk = dai.IMUPacket()
    pk.acceleroMeter.x, pk.acceleroMeter.z = 0.1, 9.8
    pk.gyroscope.z = 0.5
    pk.rotationVector.real = 1.0
    m = oakd.imu_packet_to_imu(pk, "camera_imu_frame", stamp=1.0)
    assert isinstance(m, Imu)
    np.testing.assert_allclose(m.linear_acceleration, [0.1, 0, 9.8], rtol=1e-6)
    np.testing.assert_allclose(m.orientation, [0, 0, 0, 1])
    assert m.angular_velocity[2] == pytest.approx(0.5)


# ----------------------------------------------------------------------------- replay at the driver boundary
def _collect(cam, until, guard_s: float = 60.0):
    """What ``cam`` publishes from its start until ``until(got)`` holds (``guard_s``:
    only against a hang); returns ``(got, seconds it ran)``."""
    got: list = []
    cam.publish_fn = lambda t, m: got.append((t, m))
    t0 = time.monotonic()
    cam.start()
    try:
        deadline = t0 + guard_s
        while not until(got) and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        cam.stop(5)
    return got, time.monotonic() - t0


def _count(got, topic: str) -> int:
    return sum(1 for t, _ in got if t == topic)


@pytest.mark.slow
def test_replay_of_generated_frames_goes_through_the_device_path():
    """Generated RGB, depth and IMU frames are sent as real ``dai.ImgFrame`` /
    ``dai.IMUData`` from a host node and leave the driver through the same
    queues, conversion and stamps as a camera's, paced at ``fps``."""
    src = oakd.ReplaySource(oakd.generated_frames((16, 8), (8, 4)), fps=20)
    cam = oakd.OakD(replay=src, backoff_initial=0.05)
    assert cam.url == "replay://generated"
    t_before = time.time()
    got, ran_s = _collect(cam, lambda g: _count(g, "camera/color/image_raw") >= 5)
    by = {}
    for t, m in got:
        by.setdefault(t, []).append(m)
    color, depth, imu = by["camera/color/image_raw"], by["camera/depth/image_raw"], by["camera/imu"]
    assert cam.stats.connects == 1 and cam.stats.disconnects == 0
    # paced at 20 fps: never more frames than the time it ran allows (exact under load)
    assert 5 <= len(color) <= 20 * ran_s + 2 and len(depth) == pytest.approx(len(color), abs=2)
    assert color[0].encoding == "rgb8" and color[0].data.shape == (8, 16, 3)
    assert depth[0].encoding == "16UC1" and depth[0].data.dtype == np.uint16 and depth[0].data.shape == (4, 8)
    # the generated frame k carries k in its first pixel: frames in order, none invented
    seq = [int(c.data[0, 0, 0]) for c in color]
    assert seq == list(range(seq[0], seq[0] + len(seq)))
    np.testing.assert_array_equal(depth[0].data, oakd.generated_frames((16, 8), (8, 4))(seq[0])["depth"])
    assert len(imu) >= len(color) and np.allclose(imu[0].linear_acceleration, [0, 0, 9.80665])
    stamps = [c.header.stamp for c in color]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert t_before - 0.01 <= stamps[0] and stamps[-1] <= time.time() + 0.01


@pytest.mark.slow
def test_replay_of_recorded_messages_publishes_them_unchanged():
    """Recorded ``Image``/``Imu`` messages (as read back from an MCAP) replay
    through the device path unchanged; when the recording ends the camera
    falls silent and the driver says so, as with an unplugged camera."""
    rng = np.random.default_rng(0)
    rec = []
    for k in range(4):
        rec.append(Image(height=4, width=6, encoding="rgb8", data=rng.integers(0, 255, (4, 6, 3), dtype=np.uint8)))
        rec.append(Image(height=4, width=6, encoding="16UC1", data=rng.integers(0, 5000, (4, 6)).astype(np.uint16)))
        rec.append(Imu(angular_velocity=np.array([0, 0, 0.1 * k]), linear_acceleration=np.array([0, 0, 9.8]),
                       orientation=np.array([0, 0, 0, 1.0])))
    frames = oakd.recorded_frames(rec)
    assert len(frames) == 4
    cam = oakd.OakD(replay=oakd.ReplaySource(frames, fps=20, name="run.mcap"), stale_timeout=0.3,
                    backoff_initial=0.05, backoff_max=0.1)
    got, _ = _collect(cam, lambda g: _count(g, "camera/color/image_raw") >= 4
                      and _count(g, "camera/depth/image_raw") >= 4
                      and cam.stats.disconnects >= 1)
    color = [m for t, m in got if t == "camera/color/image_raw"]
    depth = [m for t, m in got if t == "camera/depth/image_raw"]
    imu = [m for t, m in got if t == "camera/imu"]
    assert len(color) >= 4 and len(depth) >= 4
    for k in range(4):
        np.testing.assert_array_equal(color[k].data, rec[3 * k].data)
        np.testing.assert_array_equal(depth[k].data, rec[3 * k + 1].data)
        assert imu[k].angular_velocity[2] == pytest.approx(0.1 * k)
    assert cam.stats.disconnects >= 1 and "no valid frame" in cam.stats.last_error


def test_recorded_frames_refuses_what_it_cannot_replay():
    with pytest.raises(ValueError, match="encoding 'bgr16'.*rgb8"):
        oakd.recorded_frames([Image(height=1, width=1, encoding="bgr16", data=np.zeros((1, 1, 3), np.uint16))])


@pytest.mark.slow
def test_emulated_runtime_runs_the_camera_on_generated_frames(tmp_path):
    """robot.toml with emulated = true and oakd = true: the camera topics carry
    generated frames through the driver, and /diagnostics says it is connected."""
    import socket

    from isac_twin.bus.msgs import DiagnosticArray
    from isac_twin.devices.runtime import RobotRuntime, robot_config_from_dict

    with socket.socket() as sk:
        sk.bind(("127.0.0.1", 0))
        port = sk.getsockname()[1]
    cfg = robot_config_from_dict({"robot": {"emulated": True}, "drivers": {"oakd": True},
                                  "network": {"listen": [f"tcp/127.0.0.1:{port}"]}})
    rt = RobotRuntime(cfg, diagnostics_period_s=0.2)
    probe = rt.bus.node("probe")
    color = probe.subscribe("/robot1/camera/color/image_raw", Image)
    diags = probe.subscribe("/diagnostics", DiagnosticArray)
    rt.start()
    try:
        deadline = time.monotonic() + 5
        while len(color) < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)
    finally:
        rt.stop()
    assert len(color) >= 3 and color.drain()[-1].data.shape == (400, 640, 3)
    cam = [st for st in diags.drain()[-1].status if st.name == "robot1: OAK-D"]
    assert cam and cam[0].level == 0 and cam[0].hardware_id == "replay://generated"


def test_truncated_frame_is_a_clear_device_error():
    f = dai.ImgFrame()
    f.setType(dai.ImgFrame.Type.RGB888i)
    f.setWidth(32)
    f.setHeight(32)
    f.setData(np.zeros((16, 32, 3), np.uint8).reshape(-1))
    with pytest.raises(oakd.DeviceError, match=r"RGB888i frame 32x32 needs 3072 bytes, got 1536 \(truncated"):
        oakd.imgframe_to_image(f, "camera_color_optical_frame")
