"""Coordinate frames (REP-105) of the twin's robots: names and transforms, one convention.

Tree of each robot (``<p>`` is the robot prefix, see :func:`robot_prefix`)::

    map -> <p>odom -> <p>base_footprint -> <p>base_link -> <p>base_scan
                                                       -> <p>imu_link
                                                       -> <p>camera_depth_optical_frame

* ``map``: the twin's world frame (shared by every robot and access point);
* ``map -> odom``: the localization correction, ``T_map_base * inv(T_odom_base)``: the
  twin knows the truth, so ``map -> odom -> base_footprint`` is the true pose while
  ``odom -> base_footprint`` is the wheel odometry (drifts);
* ``base_footprint``: the base on the ground (the OpenCR driver's and turtlebot3_node's
  odometry child frame); ``base_link`` is :data:`BASE_LINK_HEIGHT` above it (URDF
  ``base_joint``);
* ``base_scan``, ``imu_link``: the URDF mounts of :class:`isac_twin.robots.kinematics.RobotSpec`;
  the depth camera's optical frame looks along +z (x right, y down).

Frames are robot-prefixed (``robot1/odom``) when a twin has several robots, and
plain (``odom``) with one, like a real single TurtleBot3. The dynamic transforms
go on ``/tf`` every step, the mounts once on ``/tf_static`` (latched).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..utils.geometry import yaw_to_quaternion
from .msgs import Header, TFMessage, TransformStamped

#: world frame id
MAP = "map"
#: base_footprint -> base_link height, m (TurtleBot3 URDF ``base_joint``)
BASE_LINK_HEIGHT = 0.010
#: base_link -> optical frame rotation ``[x, y, z, w]`` (REP-103 optical: z forward)
OPTICAL_ROTATION = np.array([-0.5, 0.5, -0.5, 0.5])


def robot_prefix(name: str, n_robots: int) -> str:
    """``"<name>/"`` when there are several robots, ``""`` with one."""
    return f"{name}/" if n_robots > 1 else ""


@dataclass(frozen=True)
class RobotFrames:
    """The frame ids of one robot (prefix applied)."""

    prefix: str = ""

    @property
    def odom(self) -> str:
        return f"{self.prefix}odom"

    @property
    def base_footprint(self) -> str:
        return f"{self.prefix}base_footprint"

    @property
    def base_link(self) -> str:
        return f"{self.prefix}base_link"

    @property
    def base_scan(self) -> str:
        return f"{self.prefix}base_scan"

    @property
    def imu_link(self) -> str:
        return f"{self.prefix}imu_link"

    @property
    def camera_optical(self) -> str:
        return f"{self.prefix}camera_depth_optical_frame"


def planar_compose(a, b) -> np.ndarray:
    """``a * b`` of planar poses ``[x, y, yaw]`` (b expressed in a's frame)."""
    x, y, th = a
    c, s = math.cos(th), math.sin(th)
    return np.array([x + c * b[0] - s * b[1], y + s * b[0] + c * b[1], th + b[2]])


def planar_inverse(a) -> np.ndarray:
    """The inverse of a planar pose ``[x, y, yaw]``."""
    x, y, th = a
    c, s = math.cos(th), math.sin(th)
    return np.array([-c * x - s * y, s * x - c * y, -th])


def _planar_tf(stamp: float, parent: str, child: str, p) -> TransformStamped:
    return TransformStamped(Header(stamp, parent), child, np.array([p[0], p[1], 0.0]),
                            yaw_to_quaternion(float(p[2])))


def dynamic_tf(stamp: float, frames: RobotFrames, truth, odom=None) -> list[TransformStamped]:
    """``map -> odom`` and ``odom -> base_footprint`` of one robot at ``stamp`` (s).

    Args:
        truth: true planar pose ``[x, y, yaw]`` of the base in ``map``.
        odom: odometry's planar pose ``[x, y, yaw]`` of the base in ``odom``; None (no
            odometry): ``odom`` coincides with ``map``.
    """
    truth = np.asarray(truth, float)
    odom = truth if odom is None else np.asarray(odom, float)
    map_odom = planar_compose(truth, planar_inverse(odom))
    return [_planar_tf(stamp, MAP, frames.odom, map_odom),
            _planar_tf(stamp, frames.odom, frames.base_footprint, odom)]


def static_tf(stamp: float, frames: RobotFrames, spec, *, camera: bool = False
              ) -> list[TransformStamped]:
    """The mounts of one robot: base_footprint -> base_link -> base_scan, imu_link (and
    the camera's optical frame when ``camera``); ``spec``: a ``RobotSpec``."""
    ident = np.array([0.0, 0.0, 0.0, 1.0])
    out = [TransformStamped(Header(stamp, frames.base_footprint), frames.base_link,
                            np.array([0.0, 0.0, BASE_LINK_HEIGHT]), ident.copy()),
           TransformStamped(Header(stamp, frames.base_link), frames.base_scan,
                            np.array(spec.lidar_mount, float), ident.copy()),
           TransformStamped(Header(stamp, frames.base_link), frames.imu_link,
                            np.array(spec.imu_mount, float), ident.copy())]
    if camera:
        out.append(TransformStamped(Header(stamp, frames.base_link), frames.camera_optical,
                                    np.array(spec.camera_mount, float), OPTICAL_ROTATION.copy()))
    return out


def tf_message(transforms: list[TransformStamped]) -> TFMessage:
    return TFMessage(list(transforms))
