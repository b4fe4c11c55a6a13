"""Utilities every layer may use: :mod:`.geometry` (poses, the one rotation convention),
:mod:`.npzfile` (versioned NPZ files), :mod:`.llvm` (the LLVM library Dr.Jit needs),
:mod:`.threads` (BLAS on one thread)."""

from .geometry import DevicePose, antenna_pose, planar_pose, rotation_matrix, sionna_orientation

__all__ = ["DevicePose", "antenna_pose", "planar_pose", "rotation_matrix",
           "sionna_orientation"]
