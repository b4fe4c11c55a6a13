"""An emulated OAK-D for the conformance checker: a :class:`~isac_twin.devices.oakd.ReplaySource`
that can be unplugged, fall silent and send faulty frames.

It feeds :class:`~isac_twin.devices.oakd.OakD` through the driver's own device
path (host-only depthai pipeline, real ``dai.ImgFrame``/``dai.IMUData``;
needs depthai). It offers what :func:`isac_twin.devices.conformance.check_driver`
drives: ``start()``, ``url``, ``unplug()``/``replug()`` (the driver's connect
then fails with :class:`~isac_twin.devices.oakd.OakDNotFound`, as with no camera
on the bus), ``silent``, ``inject_fault(kind)`` and ``check_message``.

Faults (each on the next frame): ``truncate`` a colour frame whose buffer is
half its header's size (a cut USB transfer); ``corrupt`` a depth frame whose
header claims twice its width; ``garbage`` a colour frame of a type the driver
does not convert (NV12). Use ``OakD(replay=emu)``.
"""

from __future__ import annotations

import threading

import numpy as np

from ..bus.msgs import Image, Imu
from .oakd import Frame, ReplaySource, generated_frames


class EmulatedOakD(ReplaySource):
    """Generated frames (:func:`~isac_twin.devices.oakd.generated_frames`) at ``fps``.

    Args:
        color_size, depth_size: (width, height) px.
        fps: frames per second.
    """

    def __init__(self, color_size: tuple[int, int] = (32, 16), depth_size: tuple[int, int] = (16, 8),
                 fps: float = 30.0) -> None:
        self._gen = generated_frames(color_size, depth_size)
        super().__init__(self._gen, fps, name="emulated")
        self.color_size, self.depth_size = color_size, depth_size
        self.silent = False
        self._lock = threading.Lock()
        self._faults: list[str] = []
        self._thread = None  # nothing to start: the driver's pipeline runs the frames

    def start(self) -> "EmulatedOakD":
        return self

    def stop(self) -> None:
        pass

    def __enter__(self) -> "EmulatedOakD":
        return self

    def __exit__(self, *exc: object) -> None:
        pass

    def unplug(self) -> None:
        self.present = False

    def replug(self) -> None:
        self.present = True

    def inject_fault(self, kind: str) -> None:
        if kind not in ("garbage", "corrupt", "truncate"):
            raise ValueError(f"emulated OAK-D: unknown fault kind {kind!r}")
        with self._lock:
            self._faults.append(kind)

    def frame(self, k: int) -> Frame | None:
        if self.silent or not self.present:
            return None
        fr = dict(self._gen(k))
        with self._lock:
            fault = self._faults.pop(0) if self._faults else None
        if fault == "truncate":
            fr["color_header"] = (self.color_size[0], self.color_size[1] * 2)
        elif fault == "corrupt":
            fr["depth_header"] = (self.depth_size[0] * 2, self.depth_size[1])
        elif fault == "garbage":
            fr["color_type"] = "NV12"
        return fr

    def check_message(self, topic: str, msg: object) -> str:
        """What is wrong with a message the driver published (``""`` if nothing):
        a colour image must be generated frame ``k`` (k read from its first
        pixel, mod 256), a depth image a wall at ``1500 + k % 100`` mm of the
        depth size, an IMU sample gravity at rest."""
        if isinstance(msg, Imu):
            ok = (np.allclose(msg.linear_acceleration, [0, 0, 9.80665], atol=1e-4)
                  and np.allclose(msg.angular_velocity, 0) and np.allclose(msg.orientation, [0, 0, 0, 1]))
            return "" if ok else f"IMU {msg.linear_acceleration} {msg.angular_velocity} is not the camera at rest"
        if not isinstance(msg, Image):
            return f"unexpected {type(msg).__name__}"
        if msg.encoding == "rgb8":
            want = self._gen(int(msg.data[0, 0, 0]))["color"] if msg.data.ndim == 3 and msg.data.size else None
            if want is None or msg.data.shape != want.shape or not np.array_equal(msg.data, want):
                return f"colour image {msg.data.shape} is not a frame the camera sent"
            return ""
        if msg.encoding == "16UC1":
            w, h = self.depth_size
            d = np.asarray(msg.data)
            if d.shape != (h, w) or not (np.all(d == d.flat[0]) and 1500 <= int(d.flat[0]) < 1600):
                return f"depth image {d.shape} is not a frame the camera sent"
            return ""
        return f"unexpected encoding {msg.encoding!r}"


__all__ = ["EmulatedOakD"]
