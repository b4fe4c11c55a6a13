"""Luxonis OAK-D driver (depthai 3.x): colour, stereo depth and IMU -> ``Image``/``Imu``.

depthai is an optional extra (``pip install 'isac-twin[oakd]'``, ~100 MB) and
is imported only when a driver is opened. With no device attached,
:meth:`OakD.open` fails fast (``getAllAvailableDevices()`` is checked first;
``DEPTHAI_SEARCH_TIMEOUT`` is set short unless the user set it) with
:class:`OakDNotFound` instead of the library's multi-second search.

Published topics (names configurable): ``camera/color/image_raw``
(``rgb8``), ``camera/depth/image_raw`` (``16UC1``, mm), ``camera/imu``.
The frame conversions (:func:`imgframe_to_image`, :func:`imu_packet_to_imu`)
work on real ``dai.ImgFrame``/``dai.IMUPacket`` objects and are tested with
a host-only pipeline (no device).

Testable without a camera: ``OakD(replay=ReplaySource(...))`` feeds recorded
(:func:`recorded_frames`, e.g. ``Image``/``Imu`` messages read back from an
MCAP) or generated (:func:`generated_frames`) frames at the driver boundary:
a host-only depthai pipeline whose node sends real ``dai.ImgFrame`` (RGB888i,
RAW16) and ``dai.IMUData`` at ``fps``, read by the same queues, converted by
the same functions and stamped by the same clock arithmetic as the device's.
When a recording ends the "camera" falls silent, as an unplugged one would.

Not verified against hardware: the device pipeline in :meth:`OakD._connect`
follows the depthai v3 API (``Camera.build``/``requestOutput``,
``StereoDepth``, ``IMU``) but has only run up to "no device found" here.
Without a device the driver retries; after ``connect_warn_s`` a WARNING and
its diagnostics (ERROR "never connected") say what to do.
"""

from __future__ import annotations

import functools
import logging
import os
import time
from typing import Any, Callable, Sequence

import numpy as np

from ..bus.msgs import Header, Image, Imu
from ..errors import DeviceError, OakDNotFound, OakDUnavailable
from .base import DeviceDriver, Publish

log = logging.getLogger(__name__)

DEFAULT_SEARCH_TIMEOUT_MS = 500


def import_depthai(search_timeout_ms: int = DEFAULT_SEARCH_TIMEOUT_MS) -> Any:
    """Import depthai lazily, with a short device-search timeout unless one is set.

    Raises:
        OakDUnavailable: depthai is not installed.
    """
    os.environ.setdefault("DEPTHAI_SEARCH_TIMEOUT", str(int(search_timeout_ms)))
    try:
        import depthai as dai  # noqa: PLC0415 - optional extra
    except ImportError as exc:
        raise OakDUnavailable("depthai is not installed; install the optional extra: "
                              "pip install 'isac-twin[oakd]' (depthai==3.12.0)") from exc
    return dai


def _host_stamp(dai: Any, msg: Any) -> float:
    """Epoch s of a depthai message (its timestamp is on the host steady clock)."""
    try:
        age = (dai.Clock.now() - msg.getTimestamp()).total_seconds()
    except Exception:  # noqa: BLE001 - unset timestamps
        age = 0.0
    return time.time() - max(0.0, age)


def imgframe_to_image(frame: Any, frame_id: str, stamp: float | None = None) -> Image:
    """``dai.ImgFrame`` -> ``Image``: RGB888i/BGR888i -> ``rgb8`` ``[h, w, 3]``,
    GRAY8 -> ``mono8`` ``[h, w]``, RAW16 (depth, mm) -> ``16UC1`` ``[h, w]`` uint16.

    Raises:
        DeviceError: for frame types not handled here (names the type), or a
            buffer shorter than the frame's header says.
    """
    dai = import_depthai()
    t = frame.getType()
    T = dai.ImgFrame.Type
    bpp = {T.RGB888i: 3, T.BGR888i: 3, T.GRAY8: 1, T.RAW16: 2}.get(t)
    if bpp is not None:
        need = int(frame.getWidth()) * int(frame.getHeight()) * bpp
        have = int(np.asarray(frame.getData()).size)
        if have < need:
            raise DeviceError(f"OAK-D: {t.name} frame {frame.getWidth()}x{frame.getHeight()} needs {need} bytes, "
                              f"got {have} (truncated transfer)")
    arr = np.asarray(frame.getFrame())
    if t == T.RGB888i:
        data, enc = arr.reshape(frame.getHeight(), frame.getWidth(), 3).copy(), "rgb8"
    elif t == T.BGR888i:
        data, enc = arr.reshape(frame.getHeight(), frame.getWidth(), 3)[..., ::-1].copy(), "rgb8"
    elif t == T.GRAY8:
        data, enc = arr.reshape(frame.getHeight(), frame.getWidth()).copy(), "mono8"
    elif t == T.RAW16:
        data, enc = arr.reshape(frame.getHeight(), frame.getWidth()).astype(np.uint16, copy=True), "16UC1"
    else:
        raise DeviceError(f"OAK-D: ImgFrame type {t.name} is not converted (request RGB888i, GRAY8 or RAW16)")
    return Image(header=Header(stamp=_host_stamp(dai, frame) if stamp is None else stamp, frame_id=frame_id),
                 height=int(frame.getHeight()), width=int(frame.getWidth()), encoding=enc, data=data)


def imu_packet_to_imu(packet: Any, frame_id: str, stamp: float | None = None) -> Imu:
    """``dai.IMUPacket`` -> ``Imu`` (rad/s, m/s^2, quaternion ``[x, y, z, w]``)."""
    dai = import_depthai()
    a, g, q = packet.acceleroMeter, packet.gyroscope, packet.rotationVector
    return Imu(header=Header(stamp=_host_stamp(dai, a) if stamp is None else stamp, frame_id=frame_id),
               orientation=np.array([q.i, q.j, q.k, q.real], dtype=float),
               angular_velocity=np.array([g.x, g.y, g.z], dtype=float),
               linear_acceleration=np.array([a.x, a.y, a.z], dtype=float))


# --------------------------------------------------------------------------- replay source
#: One frame: ``{"color": [h, w, 3] uint8 RGB, "depth": [h, w] uint16 mm,
#: "imu": [(accel [3] m/s^2, gyro [3] rad/s, quaternion [x, y, z, w]), ...]}``
#: (any key may be missing).
Frame = dict


def generated_frames(color_size: tuple[int, int] = (640, 400),
                     depth_size: tuple[int, int] = (640, 400)) -> Callable[[int], Frame]:
    """Frame ``k`` of a synthetic camera at rest: colour a green gradient with
    ``k % 256`` in the red channel of pixel (0, 0) (so frames can be counted),
    depth a wall at ``1500 + k % 100`` mm, one IMU sample of gravity only.

    Args:
        color_size, depth_size: (width, height) px.
    """
    (cw, ch), (dw, dh) = color_size, depth_size

    def frame(k: int) -> Frame:
        rgb = np.zeros((ch, cw, 3), np.uint8)
        rgb[..., 1] = (np.arange(cw) * 255 // max(cw - 1, 1)).astype(np.uint8)
        rgb[0, 0, 0] = k % 256
        depth = np.full((dh, dw), 1500 + k % 100, np.uint16)
        imu = [(np.array([0.0, 0.0, 9.80665]), np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))]
        return {"color": rgb, "depth": depth, "imu": imu}

    return frame


def recorded_frames(messages) -> list[Frame]:
    """Group recorded ``Image``/``Imu`` messages (in recording order) into frames:
    an ``rgb8`` image starts a new frame, a ``16UC1``/``mono16`` image is its
    depth, ``Imu`` samples go with the frame before them.

    Raises:
        ValueError: a message that cannot be replayed (names its index and what is accepted).
    """
    frames: list[Frame] = []
    cur: Frame = {}
    for k, msg in enumerate(messages):
        if isinstance(msg, Imu):
            cur.setdefault("imu", []).append((np.asarray(msg.linear_acceleration, float),
                                              np.asarray(msg.angular_velocity, float),
                                              np.asarray(msg.orientation, float)))
            continue
        if not isinstance(msg, Image):
            raise ValueError(f"recorded_frames: message {k} is a {type(msg).__name__}; only Image and Imu replay")
        key = {"rgb8": "color", "16UC1": "depth", "mono16": "depth"}.get(msg.encoding)
        if key is None:
            raise ValueError(f"recorded_frames: message {k}: Image encoding {msg.encoding!r} cannot be replayed "
                             "(rgb8 colour, 16UC1/mono16 depth)")
        if key in cur:
            frames.append(cur)
            cur = {}
        cur[key] = np.asarray(msg.data, np.uint8 if key == "color" else np.uint16)
    if cur:
        frames.append(cur)
    return frames


class ReplaySource:
    """Frames for :class:`OakD` instead of a camera.

    Args:
        frames: ``f(k) -> Frame`` (endless, e.g. :func:`generated_frames`) or a
            sequence of frames (e.g. :func:`recorded_frames`).
        fps: frames per second sent (the camera's rate).
        loop: restart a sequence at its end (else the camera falls silent).
        name: shown in the driver's url ``replay://<name>``.
    """

    def __init__(self, frames: Callable[[int], Frame] | Sequence[Frame], fps: float = 15.0, *,
                 loop: bool = False, name: str | None = None) -> None:
        if not fps > 0:
            raise ValueError(f"fps must be > 0, got {fps!r}")
        self.frames, self.fps, self.loop = frames, float(fps), loop
        self.name = name or ("generated" if callable(frames) else "recorded")
        self.present = True  #: False: the driver's connect fails as with no camera attached

    @property
    def url(self) -> str:
        return f"replay://{self.name}"

    def frame(self, k: int) -> Frame | None:
        """Frame ``k`` (``None`` after the end of a sequence that does not loop)."""
        if callable(self.frames):
            return self.frames(k)
        n = len(self.frames)
        if n == 0 or (k >= n and not self.loop):
            return None
        return self.frames[k % n]


def _dai_timestamp(dai: Any, td: Any) -> Any:
    ts = dai.Timestamp()
    us = int(round(td.total_seconds() * 1e6))
    ts.sec, ts.nsec = us // 1_000_000, (us % 1_000_000) * 1000
    return ts


@functools.lru_cache(maxsize=None)
def _replay_node_class(dai: Any) -> type:
    """The host node class (made once; depthai is imported lazily)."""

    class ReplayNode(dai.node.ThreadedHostNode):
        """Sends a :class:`ReplaySource`'s frames as the camera's nodes would."""

        def __init__(self) -> None:
            super().__init__()
            self.color = self.createOutput()
            self.depth = self.createOutput()
            self.imu = self.createOutput()
            self.source: ReplaySource | None = None

        def _img(self, arr: np.ndarray, typ: Any, now: Any, k: int, header: tuple[int, int] | None = None) -> Any:
            f = dai.ImgFrame()
            f.setType(typ)
            w, h = header if header is not None else (arr.shape[1], arr.shape[0])
            f.setWidth(int(w))
            f.setHeight(int(h))
            f.setData(np.ascontiguousarray(arr).view(np.uint8).reshape(-1))
            f.setSequenceNum(k)
            f.setTimestamp(now)
            return f

        def run(self) -> None:
            src = self.source
            period = 1.0 / src.fps
            k = 0
            t_next = time.monotonic()
            while self.isRunning():
                fr = src.frame(k)
                if fr is None:  # the recording ended: the camera is silent
                    time.sleep(0.01)
                    continue
                now = dai.Clock.now()
                if "color" in fr:  # *_header / color_type: faulty frames (emulated_oakd)
                    typ = getattr(dai.ImgFrame.Type, fr.get("color_type", "RGB888i"))
                    self.color.send(self._img(fr["color"], typ, now, k, fr.get("color_header")))
                if "depth" in fr:
                    self.depth.send(self._img(fr["depth"], dai.ImgFrame.Type.RAW16, now, k, fr.get("depth_header")))
                if fr.get("imu"):
                    data = dai.IMUData()
                    packets = []
                    for acc, gyro, quat in fr["imu"]:
                        pk = dai.IMUPacket()
                        ts = _dai_timestamp(dai, now)
                        pk.acceleroMeter.x, pk.acceleroMeter.y, pk.acceleroMeter.z = map(float, acc)
                        pk.gyroscope.x, pk.gyroscope.y, pk.gyroscope.z = map(float, gyro)
                        q = pk.rotationVector
                        q.i, q.j, q.k, q.real = map(float, quat)
                        pk.acceleroMeter.timestamp = pk.gyroscope.timestamp = ts
                        packets.append(pk)
                    data.packets = packets
                    data.setTimestamp(now)
                    self.imu.send(data)
                k += 1
                t_next += period
                time.sleep(max(0.0, t_next - time.monotonic()))

    return ReplayNode


class OakD(DeviceDriver):
    """OAK-D colour + stereo depth + IMU.

    Args:
        device_id: device id (MxId) or ``""`` for the first one found.
        publish: ``publish(topic, msg)``.
        color_size: (width, height) px of the colour stream.
        depth_size: (width, height) px of each mono camera / depth.
        fps: frames per second.
        imu_rate_hz: IMU report rate.
        search_timeout_ms: ``DEPTHAI_SEARCH_TIMEOUT`` if the user did not set it.
        topics: override of ``{"color": ..., "depth": ..., "imu": ...}``.
        replay: frames to publish instead of a camera's (:class:`ReplaySource`);
            the url becomes ``replay://<name>``.
    """

    MESSAGE_TYPES = {"camera/color/image_raw": Image, "camera/depth/image_raw": Image, "camera/imu": Imu}

    def __init__(self, device_id: str = "", publish: Publish | None = None, *,
                 color_size: tuple[int, int] = (640, 400), depth_size: tuple[int, int] = (640, 400),
                 fps: float = 15.0, imu_rate_hz: int = 100, search_timeout_ms: int = DEFAULT_SEARCH_TIMEOUT_MS,
                 topics: dict[str, str] | None = None, stale_timeout: float = 2.0,
                 backoff_initial: float = 0.5, backoff_max: float = 5.0, connect_warn_s: float = 3.0,
                 diagnostics_topic: str | None = "diagnostics", diagnostics_period_s: float = 1.0,
                 replay: ReplaySource | None = None) -> None:
        super().__init__(replay.url if replay is not None else device_id or "oak://first", publish, stale_timeout=stale_timeout,
                         backoff_initial=backoff_initial, backoff_max=backoff_max, connect_warn_s=connect_warn_s,
                         diagnostics_topic=diagnostics_topic, diagnostics_period_s=diagnostics_period_s)
        self.device_id = device_id
        self.replay = replay
        self.color_size, self.depth_size, self.fps = color_size, depth_size, fps
        self.imu_rate_hz = imu_rate_hz
        self.search_timeout_ms = search_timeout_ms
        names = {"color": "camera/color/image_raw", "depth": "camera/depth/image_raw", "imu": "camera/imu"}
        names.update(topics or {})
        self.topics = names
        self.MESSAGE_TYPES = {names["color"]: Image, names["depth"]: Image, names["imu"]: Imu}
        self._pipeline: Any = None
        self._queues: dict[str, Any] = {}

    def find_device(self) -> Any:
        """The ``dai.DeviceInfo`` to use; raises :class:`OakDNotFound` at once if none."""
        dai = import_depthai(self.search_timeout_ms)
        found = dai.Device.getAllAvailableDevices()
        if not found:
            raise OakDNotFound(f"no OAK device found (depthai {dai.__version__}: getAllAvailableDevices() "
                               "returned []); check the USB cable and the udev rule for vendor 03e7, or remove "
                               "'oakd' from robot.toml to run without the camera")
        if not self.device_id:
            return found[0]
        for info in found:
            if self.device_id in (info.getDeviceId(), getattr(info, "name", None)):
                return info
        raise OakDNotFound(f"OAK device {self.device_id!r} not found; available: "
                           f"{[i.getDeviceId() for i in found]}")

    def open(self) -> None:
        """Find the device and start its pipeline (raises fast with no device)."""
        self._connect()

    def close(self) -> None:
        self._disconnect()

    def _connect(self) -> None:
        dai = import_depthai(self.search_timeout_ms)
        if self.replay is not None:
            self._connect_replay(dai)
            return
        info = self.find_device()
        device = dai.Device(info)
        p = dai.Pipeline(device)
        color = p.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_A)
        self._queues["color"] = color.requestOutput(self.color_size, dai.ImgFrame.Type.RGB888i,
                                                    fps=self.fps).createOutputQueue(maxSize=4, blocking=False)
        left = p.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_B)
        right = p.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_C)
        stereo = p.create(dai.node.StereoDepth)
        left.requestOutput(self.depth_size, fps=self.fps).link(stereo.left)
        right.requestOutput(self.depth_size, fps=self.fps).link(stereo.right)
        self._queues["depth"] = stereo.depth.createOutputQueue(maxSize=4, blocking=False)
        imu = p.create(dai.node.IMU)
        imu.enableIMUSensor([dai.IMUSensor.ACCELEROMETER_RAW, dai.IMUSensor.GYROSCOPE_RAW,
                             dai.IMUSensor.ROTATION_VECTOR], self.imu_rate_hz)
        imu.setBatchReportThreshold(1)
        imu.setMaxBatchReports(10)
        self._queues["imu"] = imu.out.createOutputQueue(maxSize=50, blocking=False)
        p.start()
        self._pipeline = p
        log.info("OAK-D %s: pipeline started", info.getDeviceId())

    def _connect_replay(self, dai: Any) -> None:
        """A host-only pipeline whose node sends the replay frames (same queues as the device)."""
        if not self.replay.present:
            raise OakDNotFound(f"{self.url}: replay source not present (unplugged)")
        p = dai.Pipeline(createImplicitDevice=False)
        node = p.create(_replay_node_class(dai))
        node.source = self.replay
        self._queues["color"] = node.color.createOutputQueue(maxSize=4, blocking=False)
        self._queues["depth"] = node.depth.createOutputQueue(maxSize=4, blocking=False)
        self._queues["imu"] = node.imu.createOutputQueue(maxSize=50, blocking=False)
        p.start()
        self._pipeline = p
        log.info("OAK-D replay %s: pipeline started (%.1f fps)", self.replay.name, self.replay.fps)

    def _disconnect(self) -> None:
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
                self._pipeline.wait()  # join node threads now, not in ~Pipeline (holds the GIL)
            except Exception:  # noqa: BLE001
                pass
        self._pipeline = None
        self._queues.clear()

    def _poll(self) -> None:
        got = False
        for key in ("color", "depth"):
            q = self._queues.get(key)
            frame = q.tryGet() if q is not None else None
            if frame is None:
                continue
            try:
                img = imgframe_to_image(frame, f"camera_{key}_optical_frame")
            except (DeviceError, ValueError) as exc:  # a bad frame, not a lost camera: drop and count it
                self.stats.frames_bad += 1
                self.stats.last_error = f"{self.url}: {key} frame dropped: {exc}"
                log.debug("%s", self.stats.last_error)
                continue
            self.stats.frames_ok += 1
            self._publish(self.topics[key], img)
            got = True
        q = self._queues.get("imu")
        data = q.tryGet() if q is not None else None
        if data is not None:
            for packet in data.packets:
                self._publish(self.topics["imu"], imu_packet_to_imu(packet, "camera_imu_frame"))
            self.stats.frames_ok += 1
            got = True
        if got:
            self._mark_valid()
        else:
            time.sleep(0.002)
