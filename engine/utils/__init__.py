"""Utilities every layer may use: :mod:`.geometry` (poses and the one geometry
convention: rotation, quaternions, angle wrap), :mod:`.npzfile` (versioned NPZ files),
:mod:`.llvm` (the LLVM library Dr.Jit needs), :mod:`.threads` (BLAS on one thread),
:mod:`.files` (reading a named file bounded and without blocking)."""

from .geometry import (
    DevicePose,
    antenna_pose,
    euler_to_quaternion,
    planar_pose,
    quaternion_to_yaw,
    rotation_matrix,
    sionna_orientation,
    wrap_angle,
    yaw_to_quaternion,
)

__all__ = ["DevicePose", "antenna_pose", "euler_to_quaternion", "planar_pose",
           "quaternion_to_yaw", "rotation_matrix", "sionna_orientation", "wrap_angle",
           "yaw_to_quaternion"]
