r"""Shared pieces of the tracer backends: the raw path record and its plumbing.

The leaf of ``engine/raytrace/`` (below it only :mod:`isac_twin.raytrace.base`):
the numpy copy of a solver result (:class:`RawPaths`), the conversion of
numpy points into Mitsuba's, zero-padding of the path axis, joining results
of consecutive receiver groups, the free-space test of points, the per-link
:class:`~isac_twin.raytrace.base.LinkPaths` builder, and the one
retry-on-truncation rule every backend follows (:func:`grow_cap`).

Layers (each imports only the ones below it; see ``docs/tracers.md``)::

    sionna.py   grid.py -> grid_backend.py   engine/sensing/tracer.py
        \        |
         chains.py  (chain reuse)        planes.py (reflection planes)
              |
         solver_core.py  (everything that touches Sionna's internals)
              |
         raw.py  (this module)  ->  base.py
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import TruncationError
from .base import DevicePose, LinkPaths, empty_link

__all__ = ["PATH_FIELDS", "MATCH_DELAY_RTOL", "MATCH_VERTEX_M", "REPEAT_DELAY_S", "REPEAT_VERTEX_M",
           "RawPaths", "concat_targets", "find_repeats", "free_points", "grow_cap",
           "link_paths", "match_paths", "pad_paths", "to_points"]

log = logging.getLogger(__name__)

#: The per-path arrays of a :class:`RawPaths` (``[R, T, P, ...]``) besides ``valid``.
PATH_FIELDS = ("a", "pol", "tau", "doppler", "theta_t", "phi_t", "theta_r", "phi_r",
               "interactions", "vertices")


@dataclass
class RawPaths:
    """Numpy copy of a Sionna ``Paths`` (synthetic arrays, single-element devices).

    Attributes (``R`` receivers, ``T`` transmitters, ``P`` max paths, ``D`` depth):
        valid: ``[R, T, P]`` bool.
        a: ``[R, T, P]`` complex128 passband coefficients of isotropic, vertically
            polarized elements in the devices' orientations.
        pol: ``[R, T, P, 2, 2]`` complex128 transfer matrices in the world
            spherical bases (:mod:`isac_twin.raytrace.polarization`).
        tau, doppler, theta_t, phi_t, theta_r, phi_r: ``[R, T, P]`` float64.
        interactions: ``[R, T, P, D]`` int32.
        vertices: ``[R, T, P, D, 3]`` float32.
        candidates_per_source: ``[T]`` candidates the generator stored.
        cap: the ``max_num_paths_per_src`` used.
    """

    valid: np.ndarray
    a: np.ndarray
    pol: np.ndarray
    tau: np.ndarray
    doppler: np.ndarray
    theta_t: np.ndarray
    phi_t: np.ndarray
    theta_r: np.ndarray
    phi_r: np.ndarray
    interactions: np.ndarray
    vertices: np.ndarray
    candidates_per_source: np.ndarray
    cap: int

    @property
    def truncated(self) -> bool:
        return bool(self.candidates_per_source.size
                    and self.candidates_per_source.max() >= self.cap)

    def link(self, r: int, t: int) -> dict[str, np.ndarray]:
        """Valid paths of receiver ``r`` / transmitter ``t``, sorted by delay."""
        m = self.valid[r, t]
        tau = self.tau[r, t][m]
        order = np.lexsort((-np.abs(self.a[r, t][m]), tau))
        out = {k: getattr(self, k)[r, t][m][order] for k in PATH_FIELDS}
        return out

    @classmethod
    def empty(cls, num_rx: int, num_tx: int, depth: int, counts: np.ndarray,
              cap: int) -> "RawPaths":
        """No path for any pair (``P = 0``)."""
        z = np.zeros((num_rx, num_tx, 0))
        return cls(valid=z.astype(bool), a=z.astype(complex),
                   pol=np.zeros((num_rx, num_tx, 0, 2, 2), complex), tau=z, doppler=z, theta_t=z,
                   phi_t=z, theta_r=z, phi_r=z,
                   interactions=np.zeros((num_rx, num_tx, 0, depth), np.int32),
                   vertices=np.zeros((num_rx, num_tx, 0, depth, 3), np.float32),
                   candidates_per_source=counts, cap=cap)


def to_points(v, n: int, cls):
    """``[n, 3]`` numpy (None: zeros) -> Mitsuba ``Point3f``/``Vector3f``.

    The components are copied into Dr.Jit's own (64-byte aligned) memory:
    kernels that read numpy's memory directly record its alignment in their
    IR, so a differently aligned array compiled the same kernel again (seen on
    about one live retrace in five)."""
    import drjit as dr
    import mitsuba as mi

    v = np.zeros((n, 3), np.float32) if v is None else np.asarray(v, np.float32).reshape(n, 3)
    comps = [dr.copy(mi.Float(np.ascontiguousarray(v[:, i]))) for i in range(3)]
    dr.eval(*comps)
    return cls(*comps)


def free_points(sionna_scene, points: np.ndarray) -> np.ndarray:
    """Which points ``[N, 3]`` lie in free space (see module doc) -> ``[N]`` bool."""
    import drjit as dr
    import mitsuba as mi

    pts = np.asarray(points, np.float32)
    free = np.ones(len(pts), bool)
    o = mi.Point3f(*(mi.Float(pts[:, i]) for i in range(3)))
    for dz in (1.0, -1.0):
        ray = mi.Ray3f(o, mi.Vector3f(0.0, 0.0, dz))
        si = sionna_scene.mi_scene.ray_intersect(ray)
        hit = si.is_valid()
        front = dr.dot(si.n, ray.d) < 0
        free &= np.asarray(hit.numpy(), bool) & np.asarray(front.numpy(), bool)
    return free


def pad_paths(v: np.ndarray, p: int) -> np.ndarray:
    """Zero-pad the path axis (axis 2) of ``v`` ``[R, T, P, ...]`` to ``p``."""
    pad = [(0, 0)] * v.ndim
    pad[2] = (0, p - v.shape[2])
    return np.pad(v, pad)



def concat_targets(parts: list[RawPaths]) -> RawPaths:
    """Join :class:`RawPaths` of consecutive target groups (pads the path axis)."""
    p = max(r.valid.shape[2] for r in parts)
    kw = {k: np.concatenate([pad_paths(getattr(r, k), p) for r in parts], axis=0)
          for k in ("valid",) + PATH_FIELDS}
    return RawPaths(**kw, candidates_per_source=parts[0].candidates_per_source,
                    cap=parts[0].cap)


def link_paths(raw: RawPaths, r: int, t: int, tx: str, rx: str, tx_pose: DevicePose,
               rx_pose: DevicePose, frequency_hz: float) -> LinkPaths:
    """The :class:`~isac_twin.raytrace.base.LinkPaths` of receiver ``r`` and
    transmitter ``t`` of ``raw`` (devices ``tx``/``rx`` at the given poses),
    sorted by delay; an empty link when there is no path."""
    d = raw.link(r, t)
    if d["tau"].size == 0:
        return empty_link(tx, rx, tx_pose, rx_pose, frequency_hz, raw.interactions.shape[-1])
    return LinkPaths(
        tx=tx, rx=rx, tx_position=np.asarray(tx_pose.position),
        rx_position=np.asarray(rx_pose.position),
        tx_orientation=np.asarray(tx_pose.orientation),
        rx_orientation=np.asarray(rx_pose.orientation), frequency_hz=frequency_hz,
        vertices=d["vertices"].astype(np.float64),
        **{k: d[k] for k in ("a", "pol", "tau", "doppler", "theta_t", "phi_t", "theta_r",
                             "phi_r", "interactions")})


def grow_cap(trace: Callable[[int], RawPaths], cap: int, max_cap: int, *, what: str,
             raise_at_once: bool = False) -> tuple[RawPaths, int]:
    """Run ``trace(cap)`` until no source reached the cap, doubling the cap.

    The one rule for truncation (Sionna drops candidates past
    ``max_num_paths_per_src`` without a word): a truncated result is never
    returned; the cap is doubled (with a warning) while it stays within
    ``max_cap``, else :class:`~isac_twin.raytrace.base.TruncationError`.

    Args:
        trace: runs the solver with a given ``max_num_paths_per_src``.
        cap: the first cap; max_cap: the largest cap tried.
        what: what is traced (for the messages), e.g. "a receiver at (1, 2, 0.3)".
        raise_at_once: raise on the first truncation (no retry).

    Returns:
        ``(raw, cap used)``.
    """
    while True:
        raw = trace(cap)
        if not raw.truncated:
            return raw, cap
        msg = (f"{what}: Sionna stored the maximum of {cap} path candidates for a source "
               f"(candidates per source {raw.candidates_per_source.tolist()}); paths would "
               "be dropped")
        if raise_at_once or 2 * cap > max_cap:
            raise TruncationError(f"{msg}; raise tracer.max_num_paths_per_src (limit {max_cap})")
        log.warning("%s: retrying with max_num_paths_per_src=%d", msg, 2 * cap)
        cap *= 2


#: Two paths of one link are the same path when their interaction types are
#: equal, their delays differ by at most this (s) ...
REPEAT_DELAY_S = 1e-15
#: ... and their interaction points by at most this (m, per coordinate).
REPEAT_VERTEX_M = 1e-4
#: A path of the reference is matched in a traced link by the same interaction
#: types, a delay within this relative tolerance (float32 kernels) ...
MATCH_DELAY_RTOL = 1e-6
#: ... and interaction points within this (m, per coordinate).
MATCH_VERTEX_M = 1e-3


def find_repeats(lp) -> list[tuple[int, int]]:
    """Pairs ``(i, j)``, ``i < j``, of paths of ``lp`` (a
    :class:`~isac_twin.raytrace.base.LinkPaths` or anything with ``tau [L]``,
    ``interactions [L, D]``, ``vertices [L, D, 3]``) that are the same path
    (same interaction types, delays within :data:`REPEAT_DELAY_S`, vertices
    within :data:`REPEAT_VERTEX_M`). A correct tracer returns none."""
    out = []
    order = np.argsort(lp.tau, kind="stable")
    tau = lp.tau[order]
    for a in range(len(order)):
        b = a + 1
        while b < len(order) and tau[b] - tau[a] <= REPEAT_DELAY_S:
            i, j = order[a], order[b]
            if (np.array_equal(lp.interactions[i], lp.interactions[j])
                    and np.abs(lp.vertices[i] - lp.vertices[j]).max(initial=0.0)
                    <= REPEAT_VERTEX_M):
                out.append((int(min(i, j)), int(max(i, j))))
            b += 1
    return out


def match_paths(got, ref) -> np.ndarray:
    """For each path of ``ref``, the index of the same path in ``got`` or -1
    (both with ``a, tau [L]``, ``interactions [L, D]``, ``vertices [L, D, 3]``)
    (same interaction types, delay within :data:`MATCH_DELAY_RTOL`, vertices
    within :data:`MATCH_VERTEX_M`; each path of ``got`` matches at most once)."""
    out = np.full(len(ref.tau), -1, np.int64)
    used = np.zeros(len(got.tau), bool)
    for i in np.argsort(-np.abs(ref.a), kind="stable"):
        cand = np.flatnonzero(~used & (np.abs(got.tau - ref.tau[i])
                                       <= MATCH_DELAY_RTOL * ref.tau[i]))
        for j in cand:
            if (np.array_equal(got.interactions[j], ref.interactions[i])
                    and np.abs(got.vertices[j] - ref.vertices[i]).max(initial=0.0)
                    <= MATCH_VERTEX_M):
                out[i] = j
                used[j] = True
                break
    return out
