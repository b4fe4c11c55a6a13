"""The one geometry convention of the engine, and the one pose boundary.

Conventions (every layer calls these; none writes its own):

* Orientations are ``[roll, pitch, yaw]`` (rad), ZYX Euler angles of REP-103:
  body -> world is ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (:func:`rotation_matrix`).
  Sionna RT and ``isac_twin.phy`` take the same rotation as ``[yaw, pitch, roll]``
  (Sionna's ``rotation_matrix(angles)``, angles about z, y, x):
  :func:`sionna_orientation` reverses the order at that boundary, explicitly, both
  ways (the reversal is its own inverse).
* Quaternions are ROS's ``[x, y, z, w]`` (scalar last, as
  ``geometry_msgs/Quaternion`` and ``scipy.spatial.transform.Rotation.as_quat``):
  :func:`euler_to_quaternion`, and for a floor robot :func:`yaw_to_quaternion` and
  :func:`quaternion_to_yaw`.
* Angles are wrapped to ``[-pi, pi)`` by :func:`wrap_angle`.

Every layer that needs an array's world pose (the twin's step, the initial
poses of a config, the localization deployment) calls :func:`antenna_pose`; the
pose travels as one type, :class:`DevicePose`, with orientations in the
engine's ``[roll, pitch, yaw]`` order; :func:`sionna_orientation` is the
one conversion, called where a pose crosses into Sionna or ``isac_twin.phy``.

A leaf module (numpy only): every layer may import it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["DevicePose", "antenna_pose", "euler_to_quaternion", "planar_pose",
           "quaternion_to_yaw", "rotation_matrix", "sionna_orientation", "wrap_angle",
           "yaw_to_quaternion"]


@dataclass(frozen=True)
class DevicePose:
    """Pose of a device's array centre.

    Attributes:
        position: array centre ``[3]``, m (world frame).
        orientation: array orientation ``[roll, pitch, yaw]`` ``[3]``, rad.
        velocity: array-centre velocity ``[3]``, m/s.
    """

    position: tuple[float, float, float]
    orientation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self):
        for k in ("position", "orientation", "velocity"):
            v = np.asarray(getattr(self, k), dtype=float).reshape(-1)
            if v.shape != (3,):
                raise ValueError(f"DevicePose.{k}: expected 3 numbers, got {getattr(self, k)!r}")
            object.__setattr__(self, k, tuple(float(x) for x in v))


def rotation_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """``[3, 3]`` rotation body -> world for ZYX Euler angles (rad), REP-103:
    ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

    The one rotation of the engine. Sionna's ``rotation_matrix([a, b, c])`` is the same
    matrix for ``[a, b, c] = [yaw, pitch, roll]``: from a Sionna-order orientation
    ``o`` it is ``rotation_matrix(*sionna_orientation(o))``.
    """
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def sionna_orientation(orientation) -> tuple[float, float, float]:
    """``[roll, pitch, yaw]`` -> Sionna's / ``isac_twin.phy``'s ``[yaw, pitch, roll]``
    (rad), and back: reversing the order is its own inverse."""
    r, p, y = (float(x) for x in orientation)
    return (y, p, r)


def euler_to_quaternion(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Quaternion ``[x, y, z, w]`` (ROS order, scalar last) of ZYX Euler angles (rad),
    the rotation of :func:`rotation_matrix`."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return np.array([sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
                     cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy])


def yaw_to_quaternion(yaw: float) -> np.ndarray:
    """Quaternion ``[x, y, z, w]`` (ROS order, scalar last) of a rotation by ``yaw`` rad
    about z: ``[0, 0, sin(yaw / 2), cos(yaw / 2)]``."""
    return np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])


def quaternion_to_yaw(q) -> float:
    """Yaw (rad, in ``[-pi, pi]``) of a quaternion ``[x, y, z, w]`` (ROS order): the
    ZYX Euler yaw, ``atan2(2 (w z + x y), 1 - 2 (y^2 + z^2))``, for any unit quaternion
    (not only a rotation about z)."""
    x, y, z, w = q
    return float(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))


def wrap_angle(a):
    """Angle(s) ``a`` (rad) wrapped to ``[-pi, pi)``: ``(a + pi) mod 2 pi - pi`` (so
    ``pi`` maps to ``-pi``). A float for a scalar, else an array of ``a``'s shape."""
    w = (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi
    return float(w) if w.ndim == 0 else w


def planar_pose(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    """A floor robot's ``[x, y, yaw]`` as the 6-vector ``[x, y, z, 0, 0, yaw]`` (m, rad)."""
    return np.array([float(x), float(y), float(z), 0.0, 0.0, float(yaw)])


def antenna_pose(pose, antenna_offset=(0.0, 0.0, 0.0), v: float = 0.0,
                 w: float = 0.0) -> DevicePose:
    """World pose of an array mounted on a body.

    Args:
        pose: the body's (``base_link``) pose ``[x, y, z, roll, pitch, yaw]`` ``[6]``,
            m and rad.
        antenna_offset: array centre in the body frame ``[3]``, m.
        v: body speed along its own x axis, m/s.
        w: body yaw rate, rad/s.

    Returns:
        The array centre ``position + R(roll, pitch, yaw) @ antenna_offset``, the
        body's orientation, and the array-centre velocity
        ``v [cos yaw, sin yaw, 0] + [0, 0, w] x lever``.
    """
    p = np.asarray(pose, float).reshape(-1)
    if p.shape != (6,):
        raise ValueError(f"pose: expected [x, y, z, roll, pitch, yaw], got {pose!r}")
    roll, pitch, yaw = p[3:6]
    lever = rotation_matrix(roll, pitch, yaw) @ np.asarray(antenna_offset, float)
    vel = v * np.array([math.cos(yaw), math.sin(yaw), 0.0]) + np.cross([0.0, 0.0, w], lever)
    return DevicePose(tuple(p[:3] + lever), tuple(p[3:6]), tuple(vel))
