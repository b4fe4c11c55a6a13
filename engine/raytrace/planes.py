"""Reflection planes of a scene: which triangles Sionna treats as one surface.

Sionna RT's shoot-and-bounce generator identifies a specular chain by the
sequence of its interaction *types* and, for each specular reflection, the
*plane* it reflected on (``PlaneHasher``: the unit normal, oriented so that
its first non-zero component of z, y, x is positive, and the offset
``n . p``, quantized to 1e-5 and 1e-3 m); which surface a transmission went
through is not part of it. Its image method accepts a reflection point on any
triangle coplanar with the recorded one. Two chains through different
triangles of one plane are therefore one path, and anything that caches
chains (:mod:`isac_twin.raytrace.chains`) must identify them by plane too.

:class:`PlaneIndex` groups the triangles of every mesh of a Mitsuba scene
into planes once: triangles whose oriented normals differ by at most
:data:`NORMAL_TOLERANCE` (per component) and whose offsets differ by at most
:data:`OFFSET_TOLERANCE` m are the same plane (transitively). Each plane has
a canonical triangle (the first in scene order) and a point on it, so that a
chain's representative never depends on which ray found it first.
"""

from __future__ import annotations

import numpy as np

__all__ = ["NORMAL_TOLERANCE", "OFFSET_TOLERANCE", "PlaneIndex"]

#: Largest difference per component of two unit normals of one plane.
NORMAL_TOLERANCE = 1e-4

#: Largest difference of the offsets ``n . p`` of two triangles of one plane, m.
OFFSET_TOLERANCE = 1e-3

#: Sionna's ``PlaneHasher`` flips a normal when this component test says so.
_FLIP_EPS = 1e-4


def oriented_normals(n: np.ndarray) -> np.ndarray:
    """Unit normals ``[N, 3]`` oriented as Sionna's ``PlaneHasher`` does
    (positive z; else positive y; else positive x)."""
    n = np.asarray(n, np.float64)
    flip = ((n[:, 2] < -_FLIP_EPS)
            | ((np.abs(n[:, 2]) < _FLIP_EPS) & (n[:, 1] < -_FLIP_EPS))
            | ((np.abs(n[:, 2]) < _FLIP_EPS) & (np.abs(n[:, 1]) < _FLIP_EPS)
               & (n[:, 0] < -_FLIP_EPS)))
    return np.where(flip[:, None], -n, n)


class PlaneIndex:
    """The planes of every triangle of a Mitsuba scene.

    Args:
        mi_scene: the ``mitsuba.Scene`` (``sionna.rt.Scene.mi_scene``).

    Attributes:
        plane: ``[F]`` int64 plane id of every triangle (scene order: shape by
            shape, primitive by primitive); -1 for a degenerate triangle.
        num_planes: number of distinct planes.
        canonical_shape, canonical_prim: ``[num_planes]`` uint32, the shape id
            (as Sionna stores it in a ``PathsBuffer``) and primitive index of
            each plane's first triangle.
        canonical_point: ``[num_planes, 3]`` float32, a vertex of that triangle, m.
        normal: ``[num_planes, 3]`` float64 unit normal (oriented as above).
        offset: ``[num_planes]`` float64, ``normal . x`` of the plane's points, m.
        lo, hi: ``[num_planes, 3]`` float64 corners of the axis-aligned box of
            the plane's triangles, m.
    """

    def __init__(self, mi_scene):
        import drjit as dr
        import mitsuba as mi
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components
        from scipy.spatial import cKDTree

        ids = np.asarray(dr.reinterpret_array(mi.UInt, mi_scene.shapes_dr()).numpy(),
                         np.int64)
        shapes = mi_scene.shapes()
        self._base = np.full(int(ids.max(initial=-1)) + 2, -1, np.int64)
        self._count = np.zeros_like(self._base)
        normals, points, owner, prims, los, his = [], [], [], [], [], []
        start = 0
        for sid, s in zip(ids, shapes):
            if not s.is_mesh() or s.face_count() == 0:
                continue
            v = np.asarray(s.vertex_positions_buffer().numpy(), np.float32).reshape(-1, 3)
            f = np.asarray(s.faces_buffer().numpy(), np.int64).reshape(-1, 3)
            p0, p1, p2 = (v[f[:, i]].astype(np.float64) for i in range(3))
            n = np.cross(p1 - p0, p2 - p0)
            norm = np.linalg.norm(n, axis=1)
            n = np.divide(n, norm[:, None], out=np.zeros_like(n), where=norm[:, None] > 0)
            normals.append(n)
            points.append(v[f[:, 0]])
            los.append(np.minimum(np.minimum(p0, p1), p2))
            his.append(np.maximum(np.maximum(p0, p1), p2))
            owner.append(np.full(len(f), sid, np.int64))
            prims.append(np.arange(len(f), dtype=np.int64))
            self._base[sid], self._count[sid] = start, len(f)
            start += len(f)
        if not normals:
            self.plane = np.zeros(0, np.int64)
            self.num_planes = 0
            self.canonical_shape = self.canonical_prim = np.zeros(0, np.uint32)
            self.canonical_point = np.zeros((0, 3), np.float32)
            self.normal = self.lo = self.hi = np.zeros((0, 3))
            self.offset = np.zeros(0)
            return
        n = oriented_normals(np.concatenate(normals))
        p = np.concatenate(points)
        owner, prims = np.concatenate(owner), np.concatenate(prims)
        d = np.einsum("ij,ij->i", n, p.astype(np.float64))
        ok = np.linalg.norm(n, axis=1) > 0.5
        feats = np.c_[n / NORMAL_TOLERANCE, d / OFFSET_TOLERANCE][ok]
        pairs = cKDTree(feats).query_pairs(1.0, p=np.inf, output_type="ndarray")
        m = len(feats)
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
        _, label = connected_components(graph, directed=False)
        # Number planes by their first triangle, so ids follow scene order.
        first = np.full(label.max(initial=-1) + 1, m, np.int64)
        np.minimum.at(first, label, np.arange(m))
        order = np.argsort(first)
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        plane = np.full(len(n), -1, np.int64)
        plane[ok] = rank[label]
        self.plane = plane
        self.num_planes = int(len(order))
        head = np.flatnonzero(ok)[first[order]]
        self.canonical_shape = owner[head].astype(np.uint32)
        self.canonical_prim = prims[head].astype(np.uint32)
        self.canonical_point = p[head].astype(np.float32)
        self.normal = n[head]
        self.offset = d[head]
        lo, hi = np.concatenate(los)[ok], np.concatenate(his)[ok]
        self.lo = np.full((self.num_planes, 3), np.inf)
        self.hi = np.full((self.num_planes, 3), -np.inf)
        np.minimum.at(self.lo, plane[ok], lo)
        np.maximum.at(self.hi, plane[ok], hi)

    def planes_of(self, shapes: np.ndarray, prims: np.ndarray) -> np.ndarray:
        """Plane ids of (shape id, primitive) pairs (any equal shapes) -> int64,
        -1 where the pair is not a triangle of this scene (e.g. no interaction)."""
        s = np.asarray(shapes, np.int64)
        q = np.asarray(prims, np.int64)
        inside = (s >= 0) & (s < len(self._base))
        sc = np.where(inside, s, len(self._base) - 1)
        base, count = self._base[sc], self._count[sc]
        ok = inside & (base >= 0) & (q >= 0) & (q < count)
        out = np.full(s.shape, -1, np.int64)
        out[ok] = self.plane[base[ok] + q[ok]]
        return out
