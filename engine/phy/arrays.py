"""Planar antenna arrays and their steering vectors.

Geometry mirrors ``sionna.rt.PlanarArray`` exactly, so the steering vectors
reproduce the phase shifts Sionna applies with ``synthetic_array=True``:

* Elements lie in the array's local y-z plane (boresight = local +x),
  numbered column-first from the top-left to the bottom-right corner:
  element ``i = c * rows + r`` (row ``r``, column ``c``) sits at
  ``y = c * d_h - (cols - 1) * d_h / 2``, ``z = -r * d_v + (rows - 1) * d_v / 2``
  (in wavelengths).
* ``orientation = [yaw, pitch, roll]`` = Sionna's ``(alpha, beta, gamma)``:
  rotations about z, y, x, ``R = Rz(yaw) Ry(pitch) Rx(roll)``; world
  element positions are ``R @ p_local`` (the one rotation,
  :func:`isac_twin.utils.geometry.rotation_matrix`, reached through
  :func:`~isac_twin.utils.geometry.sionna_orientation`). (``twin.toml`` lists
  ``[roll, pitch, yaw]``: reverse it before passing it here.)
* Directions use Sionna's spherical convention: zenith ``theta`` from +z,
  azimuth ``phi`` from +x towards +y,
  ``r_hat = [sin(theta) cos(phi), sin(theta) sin(phi), cos(theta)]``.
  Departure directions point away from the transmitter; arrival directions
  point from the receiver towards where the wave comes from (Sionna's
  ``theta_r, phi_r``).
* Steering vector: ``a_i(theta, phi) = g(theta', phi') * exp(+j 2 pi p_i . r_hat)``
  with ``p_i`` in wavelengths (world frame), i.e. an element displaced towards
  the path direction sees a shorter path. For the ``"iso"`` pattern ``g = 1``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Union

import numpy as np

from ..utils.geometry import rotation_matrix, sionna_orientation
from ._checks import positive_float, positive_int, real_array

__all__ = ["PlanarArray", "sionna_rotation", "r_hat", "ElementPattern"]

ElementPattern = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""Element field pattern hook: ``g(theta_local [L], phi_local [L]) -> [L]``
complex amplitude (sqrt of gain) in the array's local frame."""


def sionna_rotation(orientation) -> np.ndarray:
    """``[3, 3]`` rotation ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` of a Sionna-order
    ``orientation = [yaw, pitch, roll]`` [rad], checked (finite, 3 numbers): the
    engine's one :func:`~isac_twin.utils.geometry.rotation_matrix`, the order
    reversed at this boundary."""
    o = real_array("orientation", orientation, shape=(3,))
    return rotation_matrix(*sionna_orientation(o))


def r_hat(theta, phi) -> np.ndarray:
    """Unit direction vectors ``[..., 3]`` from zenith ``theta`` and azimuth
    ``phi`` [rad] (any equal shapes)."""
    theta = np.asarray(theta, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64)
    st = np.sin(theta)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], axis=-1)


@dataclass(frozen=True)
class PlanarArray:
    """Uniform planar array (single polarization), like ``sionna.rt.PlanarArray``.

    Args:
        num_rows: Rows (along local z), >= 1.
        num_cols: Columns (along local y), >= 1.
        vertical_spacing: Row spacing d_v [wavelengths].
        horizontal_spacing: Column spacing d_h [wavelengths].
        pattern: ``"iso"`` or a callable element pattern
            ``g(theta_local [L], phi_local [L]) -> [L]`` (field amplitude).
            When matching Sionna paths, keep ``"iso"``: Sionna's path
            coefficients ``a`` already contain the element pattern evaluated
            at the array centre.
    """

    num_rows: int
    num_cols: int
    vertical_spacing: float = 0.5
    horizontal_spacing: float = 0.5
    pattern: Union[str, ElementPattern] = "iso"

    def __post_init__(self) -> None:
        positive_int("num_rows", self.num_rows)
        positive_int("num_cols", self.num_cols)
        positive_float("vertical_spacing", self.vertical_spacing)
        positive_float("horizontal_spacing", self.horizontal_spacing)
        if not (self.pattern == "iso" or callable(self.pattern)):
            raise ValueError(f"pattern must be 'iso' or a callable, got {self.pattern!r}")

    @property
    def num_ant(self) -> int:
        """Number of elements rows * cols."""
        return self.num_rows * self.num_cols

    @property
    def normalized_positions(self) -> np.ndarray:
        """Local element positions ``[Nant, 3]`` [wavelengths], column-first."""
        r = np.arange(self.num_rows)
        c = np.arange(self.num_cols)
        cc, rr = np.meshgrid(c, r, indexing="ij")  # [cols, rows]: rows vary fastest
        cc, rr = cc.ravel(), rr.ravel()
        dv, dh = self.vertical_spacing, self.horizontal_spacing
        pos = np.zeros((self.num_ant, 3))
        pos[:, 1] = dh * cc - (self.num_cols - 1) * dh / 2
        pos[:, 2] = -dv * rr + (self.num_rows - 1) * dv / 2
        return pos

    def positions(self, orientation=(0.0, 0.0, 0.0)) -> np.ndarray:
        """Rotated element positions ``[Nant, 3]`` [wavelengths], world axes,
        relative to the array centre."""
        return self.normalized_positions @ sionna_rotation(orientation).T

    def steering_vectors(self, theta, phi, orientation=(0.0, 0.0, 0.0)) -> np.ndarray:
        """Steering vectors for ``L`` directions.

        Args:
            theta: Zenith angles ``[L]`` [rad] (world frame).
            phi: Azimuth angles ``[L]`` [rad] (world frame).
            orientation: Array orientation ``[yaw, pitch, roll]`` [rad].

        Returns:
            ``[L, Nant]`` complex128 steering vectors
            ``g * exp(j 2 pi p_i . r_hat(theta, phi))``.
        """
        theta = real_array("theta", theta, ndim=1)
        phi = real_array("phi", phi, shape=(theta.shape[0],))
        return self.steering_vectors_from_directions(r_hat(theta, phi), orientation)

    def steering_vectors_from_directions(self, k, orientation=(0.0, 0.0, 0.0)) -> np.ndarray:
        """Steering vectors ``[L, Nant]`` from unit direction vectors ``k [L, 3]``
        (world frame). Useful when the tracer provides directions directly,
        which is better conditioned near the poles than (theta, phi)."""
        k = real_array("directions", k, ndim=2)
        if k.shape[1] != 3:
            raise ValueError(f"directions must have shape [L, 3], got {list(k.shape)}")
        rot = sionna_rotation(orientation)
        phase = 2.0 * np.pi * (k @ (self.normalized_positions @ rot.T).T)  # [L, Nant]
        a = np.exp(1j * phase)
        if self.pattern != "iso":
            k_loc = k @ rot  # world -> local: R^T k, row-vector form
            th = np.arctan2(np.hypot(k_loc[:, 0], k_loc[:, 1]), k_loc[:, 2])
            ph = np.arctan2(k_loc[:, 1], k_loc[:, 0])
            g = np.asarray(self.pattern(th, ph), dtype=np.complex128)
            if g.shape != (k.shape[0],):
                raise ValueError(f"element pattern returned shape {g.shape}, "
                                 f"expected ({k.shape[0]},)")
            a = a * g[:, None]
        return a
