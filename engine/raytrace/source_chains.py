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
identified as Sionna identifies it (:class:`~engine.raytrace.chains.ChainStore`):
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

from engine.raytrace.base import INTERACTION_NONE, INTERACTION_REFRACTION, INTERACTION_SPECULAR

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
        planes: its :class:`~engine.raytrace.planes.PlaneIndex`.
        sources: ``[S, 3]`` m.
        rays: rays per source.
        max_depth: interactions per chain at most (``D``).
        specular, refraction: interaction types followed.

    Returns:
        Columns of the chains (``C`` of them), in the layout
        :meth:`~engine.raytrace.chains.ChainStore.add_columns` takes: ``src [C]``
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
        planes: the scene's :class:`~engine.raytrace.planes.PlaneIndex`.
        sources: ``[S, 3]`` m.
        cols: chain columns (``src [C]``, ``types [C, D]``, ``shapes``,
            ``prims``), e.g. a :class:`~engine.raytrace.chains.ChainStore`'s.
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
        has = self.spec.any(axis=1)
        self.always = np.flatnonzero(~has)
        self.reflecting = np.flatnonzero(has)
        self.last = d - 1 - np.argmax(self.spec[self.reflecting, ::-1], axis=1)

    def __call__(self, targets: np.ndarray) -> list[np.ndarray]:
        """Per target ``[T, 3]`` m, the sorted indices of the chains that pass."""
        # a segment parallel to a plane gives t = inf/nan: compared False, dropped
        with np.errstate(divide="ignore", invalid="ignore"):
            return self._pass(targets)

    def _pass(self, targets: np.ndarray) -> list[np.ndarray]:
        f32 = np.float32
        targets = np.asarray(targets, np.float64).reshape(-1, 3)
        pl, m = self.planes, self.margin
        rc, lj = self.reflecting, self.last
        p = self.plane[rc, lj]
        a = self.images[rc, lj + 1]
        # the last reflection, for every (target, chain), in float32 (the margin
        # is ~1e3 x its rounding over a room)
        da = (np.einsum("ij,ij->i", pl.normal[p], a) - pl.offset[p]).astype(f32)
        db = targets.astype(f32) @ pl.normal[p].T.astype(f32) - pl.offset[p].astype(f32)[None]
        t = da[None] / (da[None] - db)
        ok = (np.signbit(da)[None] != np.signbit(db)) | (db == 0)
        lo, hi = (pl.lo[p] - m).astype(f32), (pl.hi[p] + m).astype(f32)
        af, tg = a.astype(f32), targets.astype(f32)
        for k in range(3):
            xk = tg[:, None, k] - af[None, :, k]
            xk *= t
            xk += af[None, :, k]
            ok &= (xk >= lo[None, :, k]) & (xk <= hi[None, :, k])
        ti, ci = np.nonzero(ok)
        x = a[ci] + t[ti, ci].astype(np.float64)[:, None] * (targets[ti] - a[ci])
        c, j = rc[ci], lj[ci]
        # the earlier reflections, pair by pair (float64)
        d = self.spec.shape[1]
        while len(c):
            earlier = self.spec[c] & (np.arange(d)[None] < j[:, None])
            more = np.flatnonzero(earlier.any(axis=1))
            if len(more) == 0:
                break
            jj = d - 1 - np.argmax(earlier[more][:, ::-1], axis=1)
            cm = c[more]
            pp = self.plane[cm, jj]
            a2, b2 = self.images[cm, jj + 1], x[more]
            n2 = pl.normal[pp]
            da2 = np.einsum("ij,ij->i", n2, a2) - pl.offset[pp]
            db2 = np.einsum("ij,ij->i", n2, b2) - pl.offset[pp]
            t2 = da2 / (da2 - db2)
            x2 = a2 + t2[:, None] * (b2 - a2)
            ok2 = (((np.signbit(da2) != np.signbit(db2)) | (db2 == 0))
                   & ((x2 >= pl.lo[pp] - m) & (x2 <= pl.hi[pp] + m)).all(axis=1))
            keep = np.ones(len(c), bool)
            keep[more[~ok2]] = False
            x[more], j = x2, j.copy()
            j[more] = jj
            done = np.ones(len(c), bool)
            done[more] = False
            j[done] = -1  # no earlier reflection left to check
            ti, c, x, j = ti[keep], c[keep], x[keep], j[keep]
        order = np.lexsort((c, ti))
        parts = np.split(c[order], np.cumsum(np.bincount(ti, minlength=len(targets)))[:-1])
        if len(self.always) == 0:
            return parts
        return [np.sort(np.r_[self.always, q]) for q in parts]
