"""The one pose boundary: where a device's antenna array is, given a robot's state.

Every layer that needs an array's world pose (the twin's step, the initial
poses of a config, the localization deployment) calls :func:`antenna_pose`; the
pose travels as one type, :class:`DevicePose`, with orientations in the
engine's ``[roll, pitch, yaw]`` order (REP-103, ZYX Euler angles). Sionna RT
and ``isac_twin.phy`` take ``[yaw, pitch, roll]``: :func:`sionna_orientation` is the
one conversion, called where a pose crosses into them.

A leaf module (numpy only): every layer may import it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["DevicePose", "antenna_pose", "planar_pose", "rotation_matrix",
           "sionna_orientation"]


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
    ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def sionna_orientation(orientation) -> tuple[float, float, float]:
    """``[roll, pitch, yaw]`` -> Sionna's / ``isac_twin.phy``'s ``[yaw, pitch, roll]`` (rad)."""
    r, p, y = (float(x) for x in orientation)
    return (y, p, r)


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
