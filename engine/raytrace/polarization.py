r"""Polarimetric path records: the 2 x 2 field transfer matrix of a path and
the local -> world rotation of an element's polarization.

The tracer records for every path the transfer matrix ``T`` (``pol [..., 2, 2]``,
complex) between the spherical unit vectors of the *world* frame at the two
ends: row ``i`` is the receive component (0: theta-hat, 1: phi-hat at the
arrival direction ``r_hat(theta_r, phi_r)``), column ``j`` the transmit
component (same at the departure direction ``r_hat(theta_t, phi_t)``). It is
Sionna RT's channel coefficient ``a[i][j]`` of two isotropic elements whose
field patterns are the unit vectors ``(C_theta, C_phi) = (1, 0)`` and
``(0, 1)`` at orientation zero (``SolverCore`` traces exactly these; Sionna's
own ``"VH"`` polarization gives the same up to ``cos(pi/2)`` in float32).

Any element of any orientation then follows exactly (Sionna's
``antenna_pattern_to_world_implicit`` is linear in ``(C_theta, C_phi)``):

.. math::

    a = (Q_r c_r)^T \, T \, (Q_t c_t)

with ``c = (C_theta, C_phi)`` the element's field pattern evaluated at the
direction in the array's local frame (``R^T k``) and ``Q`` (:func:`local_to_world`)
the 2 x 2 rotation from the local spherical basis (rotated into the world by
``R``) to the world spherical basis at ``k``. A vertically polarized
isotropic element has ``c = (1, 0)``: with :func:`v_world` at both ends this
gives the coefficient the tracer records in ``a``.

Reciprocity: the reversed link (``rx -> tx``) has ``T^T`` (the channel
between two given antennas is symmetric).
"""

from __future__ import annotations

import numpy as np

from ..utils.geometry import rotation_matrix, sionna_orientation

__all__ = ["local_to_world", "v_world", "world_basis"]


def world_basis(k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Spherical unit vectors ``theta_hat, phi_hat [..., 3]`` at unit
    directions ``k [..., 3]`` (Sionna's ``theta_hat`` / ``phi_hat``; at the
    poles ``phi = 0``)."""
    k = np.asarray(k, np.float64)
    th = np.arctan2(np.hypot(k[..., 0], k[..., 1]), k[..., 2])
    ph = np.arctan2(k[..., 1], k[..., 0])
    ct, st, cp, sp = np.cos(th), np.sin(th), np.cos(ph), np.sin(ph)
    t_hat = np.stack([ct * cp, ct * sp, -st], -1)
    p_hat = np.stack([-sp, cp, np.zeros_like(ph)], -1)
    return t_hat, p_hat


def local_to_world(k: np.ndarray, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The element frame seen from world directions.

    Args:
        k: world unit directions ``[L, 3]`` (away from the array).
        rot: array rotation ``[3, 3]`` or per direction ``[L, 3, 3]`` (local -> world).

    Returns:
        ``(theta_local [L], phi_local [L], Q [L, 2, 2])``: the direction in the
        array's frame (where its pattern is evaluated) and ``Q`` with
        ``[e_theta, e_phi]_world = Q @ [C_theta, C_phi]_local``.
    """
    k = np.asarray(k, np.float64).reshape(-1, 3)
    rot = np.broadcast_to(np.asarray(rot, np.float64), (len(k), 3, 3))
    k_loc = np.einsum("lji,lj->li", rot, k)  # R^T k
    th = np.arctan2(np.hypot(k_loc[:, 0], k_loc[:, 1]), k_loc[:, 2])
    ph = np.arctan2(k_loc[:, 1], k_loc[:, 0])
    tl, pl = world_basis(k_loc)
    tl_w = np.einsum("lij,lj->li", rot, tl)
    pl_w = np.einsum("lij,lj->li", rot, pl)
    tw, pw = world_basis(k)
    q = np.empty((len(k), 2, 2))
    q[:, 0, 0] = np.sum(tw * tl_w, -1)
    q[:, 0, 1] = np.sum(tw * pl_w, -1)
    q[:, 1, 0] = np.sum(pw * tl_w, -1)
    q[:, 1, 1] = np.sum(pw * pl_w, -1)
    return th, ph, q


#: Up to this many paths :func:`v_world` gathers one rotation per path and makes
#: one pass (a live step's few hundred paths: per-call overhead dominates);
#: more are computed once per distinct orientation (a grid chunk: no ``[L, 3,
#: 3]`` array). Both give the same values.
V_WORLD_GATHER = 4096


def v_world(k: np.ndarray, orientations: np.ndarray, index: np.ndarray) -> np.ndarray:
    """World spherical components ``[L, 2]`` (``theta_hat``, ``phi_hat`` at
    ``k``) of the V unit vector of elements in the Sionna orientations
    ``orientations[index]`` (``[N, 3]`` ``[yaw, pitch, roll]`` rad; ``index
    [L]``), seen from world unit directions ``k [L, 3]``.

    The same as ``local_to_world(k, R[index])[2][:, :, 0]`` with ``R [N, 3, 3]``
    the orientations' rotations (:func:`~isac_twin.utils.geometry.rotation_matrix` of
    each orientation reversed by :func:`~isac_twin.utils.geometry.sionna_orientation`), but for
    an orientation of zero, which is the world frame itself: exactly ``(1, 0)``."""
    k = np.asarray(k, np.float64).reshape(-1, 3)
    o = np.asarray(orientations, np.float64).reshape(-1, 3)
    index = np.asarray(index).reshape(-1)
    out = np.empty((len(k), 2))
    zero = ~np.any(o, axis=1)[index]
    out[zero] = (1.0, 0.0)
    rest = np.flatnonzero(~zero)
    if len(rest) == 0:
        return out
    if len(rest) <= V_WORLD_GATHER:
        mats = np.stack([rotation_matrix(*sionna_orientation(r)) for r in o])
        out[rest] = local_to_world(k[rest], mats[index[rest]])[2][:, :, 0]
        return out
    uniq, inv = np.unique(o, axis=0, return_inverse=True)
    per_path = np.asarray(inv).reshape(-1)[index]
    for u, ori in enumerate(uniq):
        m = (per_path == u) & ~zero
        if m.any():
            out[m] = local_to_world(k[m], rotation_matrix(*sionna_orientation(ori)))[2][:, :, 0]
    return out
