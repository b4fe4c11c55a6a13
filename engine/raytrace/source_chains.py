"""Every specular chain a source's rays follow: the candidate set of chain reuse.

Sionna's shoot-and-bounce generator (2.2) samples, per ray and interaction,
*one* of the enabled interaction types and keeps a chain as a candidate for a
target only if the ray's last interaction point sees that target; the image
method then decides whether the chain is a path to the target. Which chains a
trace finds is therefore limited by how many rays follow each chain: at the
default ``samples_per_src = 1e5`` a direct trace of the bundled lab missed
paths within 40 dB of a link's strongest (up to -18 dB) that 1e7 rays find.

:func:`shoot_chains` enumerates the chains once per source instead, with
neither sampling nor targets: each ray *branches* at every interaction into
its specular reflection and its refraction (where enabled), so one ray
follows every type sequence its directions allow, and every prefix of every
ray's chain is kept (a path may end after any interaction). A chain is
identified as Sionna identifies it (:class:`~isac_twin.raytrace.chains.ChainStore`):
the interaction types and, per specular reflection, the reflection plane.
The set is small (about 2,000 chains per access point in the bundled lab at
depth 3: its 224 triangles form 59 planes) and does not depend on the
target, so chain reuse gives every receiver the whole set and lets Sionna's
image method keep the chains that are paths to it: a receiver's paths depend
on its position only, and a grid point equals a live trace of the same point.

Rays leave the source along a Fibonacci lattice of the sphere (deterministic:
no seed). Units: metres.
"""

from __future__ import annotations

import numpy as np

from .base import INTERACTION_NONE, INTERACTION_REFRACTION, INTERACTION_SPECULAR

__all__ = ["MirrorFilter", "fibonacci_directions", "shoot_chains"]

#: Rays traced per Mitsuba call (bounds memory: ~200 B per ray and depth).
RAYS_PER_CALL = 1 << 20


def fibonacci_directions(n: int) -> np.ndarray:
    """``n`` unit vectors ``[n, 3]`` float64 spread evenly over the sphere."""
    i = np.arange(n, dtype=np.float64) + 0.5
    cos_t = 1.0 - 2.0 * i / n
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t ** 2))
    phi = np.pi * (1.0 + 5.0 ** 0.5) * i
    return np.stack([np.cos(phi) * sin_t, np.sin(phi) * sin_t, cos_t], axis=1)


def shoot_chains(mi_scene, planes, sources: np.ndarray, rays: int, max_depth: int, *,
                 specular: bool = True, refraction: bool = True) -> dict[str, np.ndarray]:
    """Distinct chains (every prefix) of ``rays`` branching rays per source.

    Args:
        mi_scene: the ``mitsuba.Scene``.
        planes: its :class:`~isac_twin.raytrace.planes.PlaneIndex`.
        sources: ``[S, 3]`` m.
        rays: rays per source.
        max_depth: interactions per chain at most (``D``).
        specular, refraction: interaction types followed.

    Returns:
        Columns of the chains (``C`` of them), in the layout
        :meth:`~isac_twin.raytrace.chains.ChainStore.add_columns` takes: ``src [C]``
        uint32; ``types, shapes, prims [C, D]`` uint32 (Sionna's shape ids and
        primitive indices of the first ray that followed the chain; unused
        depths are type NONE); ``probs [C, D]`` float32 (1 for each
        interaction: the chain was not sampled); ``vx, vy, vz [C, D]`` float32,
        that ray's interaction points; ``k_tx [C, 3]`` float32, its direction of
        departure. Chains are unique by (source, types, reflection planes).
    """
    import drjit as dr
    import mitsuba as mi
    from sionna.rt.constants import INVALID_PRIMITIVE, INVALID_SHAPE

    d_max = max(1, int(max_depth))
    kinds = [k for k, on in ((INTERACTION_SPECULAR, specular),
                             (INTERACTION_REFRACTION, refraction)) if on]
    sources = np.asarray(sources, np.float64).reshape(-1, 3)
    dirs = fibonacci_directions(int(rays)).astype(np.float32)
    out: list[dict[str, np.ndarray]] = []
    seen: set[bytes] = set()
    if int(max_depth) < 1 or not kinds:
        return _columns(out, d_max)
    for s, pos in enumerate(sources):
        for start in range(0, len(dirs), RAYS_PER_CALL):
            d0 = dirs[start:start + RAYS_PER_CALL]
            n = len(d0)
            o = np.repeat(pos[None].astype(np.float32), n, 0)
            d = d0
            hist = {"types": np.zeros((n, 0), np.uint32), "shapes": np.zeros((n, 0), np.uint32),
                    "prims": np.zeros((n, 0), np.uint32), "ident": np.zeros((n, 0), np.int64),
                    "v": np.zeros((n, 0, 3), np.float32)}
            first = np.arange(n)  # index into d0 of each ray's departure direction
            for depth in range(d_max):
                if len(o) == 0:
                    break
                ray = mi.Ray3f(mi.Point3f(*(mi.Float(np.ascontiguousarray(o[:, i]))
                                            for i in range(3))),
                               mi.Vector3f(*(mi.Float(np.ascontiguousarray(d[:, i]))
                                             for i in range(3))))
                si = mi_scene.ray_intersect(ray, ray_flags=mi.RayFlags.Minimal, coherent=True)
                dr.eval(si.p, si.n, si.prim_index, si.shape, si.t)
                hit = np.asarray(si.is_valid().numpy(), bool)
                shape = np.asarray(dr.reinterpret_array(mi.UInt, si.shape).numpy(), np.int64)
                prim = np.asarray(si.prim_index.numpy(), np.int64)
                plane = planes.planes_of(shape, prim)
                keep = np.flatnonzero(hit & (plane >= 0))
                if len(keep) == 0:
                    break
                p = np.stack([np.asarray(c.numpy(), np.float32) for c in si.p], 1)[keep]
                nrm = np.stack([np.asarray(c.numpy(), np.float32) for c in si.n], 1)[keep]
                d, plane = d[keep], plane[keep]
                shape, prim, first = shape[keep], prim[keep], first[keep]
                hist = {k: v[keep] for k, v in hist.items()}
                cos = np.einsum("ij,ij->i", d, nrm)
                # Offsets off the surface, as Mitsuba's spawn_ray does (relative
                # to the coordinates' magnitude).
                eps = (1e-5 * (1.0 + np.abs(p).max(axis=1)))[:, None].astype(np.float32)
                side = np.sign(cos).astype(np.float32)[:, None]  # + : ray arrived from the back
                branches = []
                for kind in kinds:
                    if kind == INTERACTION_SPECULAR:
                        nd = d - 2.0 * cos[:, None] * nrm
                        no = p - side * eps * nrm
                        ident = plane + 1
                    else:
                        nd = d
                        no = p + side * eps * nrm
                        ident = np.zeros_like(plane)
                    h = {"types": np.c_[hist["types"], np.full(len(p), kind, np.uint32)],
                         "shapes": np.c_[hist["shapes"], shape.astype(np.uint32)],
                         "prims": np.c_[hist["prims"], prim.astype(np.uint32)],
                         "ident": np.c_[hist["ident"], ident],
                         "v": np.concatenate([hist["v"], p[:, None]], axis=1)}
                    _collect(out, seen, s, h, d0[first], d_max, INVALID_SHAPE,
                             INVALID_PRIMITIVE)
                    branches.append((no, nd.astype(np.float32), h, first))
                o = np.concatenate([b[0] for b in branches])
                d = np.concatenate([b[1] for b in branches])
                hist = {k: np.concatenate([b[2][k] for b in branches]) for k in hist}
                first = np.concatenate([b[3] for b in branches])
    return _columns(out, d_max)


def _collect(out: list, seen: set, s: int, h: dict, k_tx: np.ndarray, d_max: int,
             invalid_shape: int, invalid_prim: int) -> None:
    """Append the chains of ``h`` (one per ray, all of one length) not in ``seen``."""
    k = h["types"].shape[1]
    ident = np.c_[h["types"].astype(np.int64), h["ident"]]
    rows = np.ascontiguousarray(ident)
    keys = rows.view(np.dtype((np.void, rows.dtype.itemsize * rows.shape[1]))).ravel()
    _, idx = np.unique(keys, return_index=True)
    new = [i for i in idx if (s, keys[i].tobytes()) not in seen]
    if not new:
        return
    new = np.asarray(new)
    seen.update((s, keys[i].tobytes()) for i in new)
    c, pad = len(new), d_max - k
    out.append({
        "src": np.full(c, s, np.uint32),
        "types": np.c_[h["types"][new], np.full((c, pad), INTERACTION_NONE, np.uint32)],
        "shapes": np.c_[h["shapes"][new], np.full((c, pad), invalid_shape, np.uint32)],
        "prims": np.c_[h["prims"][new], np.full((c, pad), invalid_prim, np.uint32)],
        "probs": np.c_[np.ones((c, k), np.float32), np.zeros((c, pad), np.float32)],
        **{f"v{a}": np.c_[h["v"][new][:, :, i], np.zeros((c, pad), np.float32)]
           for i, a in enumerate("xyz")},
        "k_tx": np.asarray(k_tx[new], np.float32)})


def _columns(out: list, d_max: int) -> dict[str, np.ndarray]:
    if not out:
        return {"src": np.zeros(0, np.uint32),
                **{k: np.zeros((0, d_max), np.uint32) for k in ("types", "shapes", "prims")},
                **{k: np.zeros((0, d_max), np.float32) for k in ("probs", "vx", "vy", "vz")},
                "k_tx": np.zeros((0, 3), np.float32)}
    return {k: np.concatenate([c[k] for c in out]) for k in out[0]}


class MirrorFilter:
    """Which chains can be paths to a target, by mirror geometry alone.

    For a chain, the image of its source after each specular reflection is the
    source mirrored across that reflection's plane (refractions do not move
    it). A path to target ``q`` exists only if, walking back from ``q``, the
    segment from each image to the current point crosses the reflection's
    plane (the image lies behind it) at a point inside the axis-aligned box of
    the plane's triangles, grown by ``margin`` -- Sionna's image method checks
    the same and more (the exact triangle, occlusion), so a chain this filter
    drops is never a path, and the image method runs on a fraction of the
    pairs (about 14 % in the bundled lab). Chains without a specular
    reflection always pass.

    Args:
        planes: the scene's :class:`~isac_twin.raytrace.planes.PlaneIndex`.
        sources: ``[S, 3]`` m.
        cols: chain columns (``src [C]``, ``types [C, D]``, ``shapes``,
            ``prims``), e.g. a :class:`~isac_twin.raytrace.chains.ChainStore`'s.
        margin: m added around each plane's box (float32 and Sionna's own
            offsets stay far below it).
    """

    def __init__(self, planes, sources: np.ndarray, cols: dict[str, np.ndarray],
                 margin: float = 1e-3):
        types = np.asarray(cols["types"])
        c, d = types.shape
        plane = planes.planes_of(cols["shapes"], cols["prims"])
        self.spec = (types == INTERACTION_SPECULAR) & (plane >= 0)
        self.plane = np.where(self.spec, plane, -1)
        self.planes, self.margin = planes, float(margin)
        img = np.empty((c, d + 1, 3))
        img[:, 0] = np.asarray(sources, np.float64).reshape(-1, 3)[np.asarray(cols["src"], int)]
        for j in range(d):
            p = np.where(self.spec[:, j], self.plane[:, j], 0)
            n = planes.normal[p]
            dist = np.einsum("ij,ij->i", n, img[:, j]) - planes.offset[p]
            img[:, j + 1] = np.where(self.spec[:, j][:, None],
                                     img[:, j] - 2.0 * dist[:, None] * n, img[:, j])
        #: ``[C, D + 1, 3]`` images of each chain's source after each interaction, m.
        self.images = img
        # Per chain, its reflections from the last to the first: [D, C] plane
        # (-1: none) and the image that reflection mirrors towards.
        order = np.argsort(-np.where(self.spec, np.arange(d)[None], -1), axis=1, kind="stable")
        self._steps = []
        for k in range(d):
            j = order[:, k]
            has = self.spec[np.arange(c), j]
            p = np.where(has, self.plane[np.arange(c), j], 0)
            self._steps.append((has, p, img[np.arange(c), j + 1]))
        self._dr = None  # the same as Dr.Jit arrays, made on first use

    def __call__(self, targets: np.ndarray) -> list[np.ndarray]:
        """Per target ``[T, 3]`` m, the sorted indices of the chains that pass."""
        import drjit as dr
        import mitsuba as mi

        targets = np.asarray(targets, np.float64).reshape(-1, 3)
        nc, nt = self.spec.shape[0], len(targets)
        if nc == 0 or nt == 0:
            return [np.zeros(0, np.int64) for _ in range(nt)]
        pts = lambda v: mi.Point3f(*(mi.Float(np.ascontiguousarray(v[:, k], np.float32))  # noqa: E731
                                     for k in range(3)))
        if self._dr is None:
            pl, m = self.planes, self.margin
            self._dr = [(mi.Bool(has), pts(a), pts(pl.normal[p]),
                         mi.Float(pl.offset[p].astype(np.float32)),
                         pts(pl.lo[p] - m), pts(pl.hi[p] + m))
                        for has, p, a in self._steps]
        # One kernel over every (target, chain) lane, in float32 (the margin is
        # ~1e3 x its rounding over a room).
        idx = dr.arange(mi.UInt32, nt * nc)
        ti = idx // nc
        ci = idx - ti * nc
        x = dr.gather(mi.Point3f, pts(targets), ti)
        ok = dr.full(mi.Bool, True, nt * nc)
        for has, a, n, off, lo, hi in self._dr:
            on = dr.gather(mi.Bool, has, ci)
            aa, nn = dr.gather(mi.Point3f, a, ci), mi.Vector3f(dr.gather(mi.Point3f, n, ci))
            o = dr.gather(mi.Float, off, ci)
            da = dr.dot(nn, mi.Vector3f(aa)) - o
            db = dr.dot(nn, mi.Vector3f(x)) - o
            t = da / (da - db)
            xn = aa + t * (x - aa)
            hit = (((da < 0) != (db < 0)) | (db == 0)) \
                & dr.all(xn >= dr.gather(mi.Point3f, lo, ci)) \
                & dr.all(xn <= dr.gather(mi.Point3f, hi, ci))
            ok &= ~on | hit
            x = dr.select(on, xn, x)
        sel = dr.compress(ok)
        dr.eval(sel)
        sel = np.asarray(sel.numpy(), np.int64)
        return np.split(sel % nc, np.cumsum(np.bincount(sel // nc, minlength=nt))[:-1])
