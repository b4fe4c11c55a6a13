"""The transmitters' chains of a tiled grid: each AP's shot once, on one worker, used by all.

Chain reuse (:mod:`isac_twin.raytrace.chains`) enumerates every specular chain
of the sources before it evaluates any receiver: ~0.65 s per AP in the bundled
lab on one core. When every worker enumerated every AP's chains, that was
time on a 2-worker build's critical path that a 1-worker build pays only
once (the lab's 2 APs: ~1.3 s of a ~17 s build). Now the client submits one
task per AP (:func:`~isac_twin.scaleout.tiles.shoot_source`), which a worker runs after loading the
scene; every tile task takes all of their results, so Dask sends each AP's
chains to each worker once (and keeps them there while the build runs), and
the worker hands them to its :class:`~isac_twin.raytrace.chains.ChainTracer`
(:meth:`~isac_twin.raytrace.chains.ChainTracer.use_chains`) instead of shooting.

A chain names the triangle of each specular reflection by Mitsuba's shape id,
which is a number of the *process* (the registry id of the shape object: a
process that loaded another scene before numbers shapes otherwise). Between
processes chains travel *portable* (:func:`portable`): each specular
interaction by its reflection plane's index in the scene's
:class:`~isac_twin.raytrace.planes.PlaneIndex` (scene order, the same in every
process that loads the same scene folder), turned back into the receiving
process's canonical triangle of that plane (:func:`local`). The plane table's
signature travels with them, and a worker whose planes differ refuses them.

Per AP the chains are those the AP's own enumeration gives (sources are
enumerated one by one, independently), so the store a worker builds from
the shipped chains holds the same chains in the same order as a tracer that
shot them (``tests/engine/scaleout/test_shared_chains.py``).
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence

import numpy as np

from ..raytrace.base import INTERACTION_SPECULAR

__all__ = ["local", "merge", "plane_signature", "portable"]


def plane_signature(planes) -> str:
    """A digest of a :class:`~isac_twin.raytrace.planes.PlaneIndex`'s planes in
    order (count, canonical points, normals, offsets): equal in two processes
    that loaded the same scene."""
    h = hashlib.sha1(str(planes.num_planes).encode())
    for a in (planes.canonical_point, planes.normal.astype(np.float32),
              planes.offset.astype(np.float32)):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def portable(columns: dict[str, np.ndarray], planes) -> dict:
    """Chains of this process (:meth:`~isac_twin.raytrace.chains.ChainStore.columns`
    layout, specular interactions on their plane's canonical triangle) in a
    form any process with the same scene can use.

    Returns:
        ``{"columns": ..., "planes": plane_signature}``; in the columns a
        specular interaction's ``shapes`` is its plane index and ``prims`` 0.

    Raises:
        ValueError: a specular interaction on no triangle of ``planes``.
    """
    cols = {k: np.array(v) for k, v in columns.items()}
    spec = cols["types"] == INTERACTION_SPECULAR
    pid = planes.planes_of(cols["shapes"], cols["prims"])
    if np.any(spec & (pid < 0)):
        bad = np.argwhere(spec & (pid < 0))[0]
        raise ValueError(f"chain {bad[0]}: specular interaction at depth {bad[1] + 1} on shape "
                         f"id {cols['shapes'][tuple(bad)]}, primitive "
                         f"{cols['prims'][tuple(bad)]}, which is no triangle of the scene")
    cols["shapes"] = np.where(spec, pid, cols["shapes"]).astype(np.uint32)
    cols["prims"] = np.where(spec, 0, cols["prims"]).astype(np.uint32)
    return {"columns": cols, "planes": plane_signature(planes)}


def local(chains: dict, planes) -> dict[str, np.ndarray]:
    """:func:`portable` chains as columns of this process (specular
    interactions on this process's canonical triangle of their plane).

    Raises:
        ValueError: the chains were enumerated in a scene whose planes differ
            from ``planes`` (another scene, or another version of it), or name
            a plane ``planes`` does not have.
    """
    if chains.get("planes") != plane_signature(planes):
        raise ValueError(f"shipped chains: enumerated in a scene with other reflection planes "
                         f"(signature {str(chains.get('planes'))[:12]}, this process's "
                         f"{plane_signature(planes)[:12]}): every worker needs the same scene "
                         "folder (docs/scaleout.md)")
    cols = {k: np.array(v) for k, v in chains["columns"].items()}
    spec = cols["types"] == INTERACTION_SPECULAR
    pid = np.where(spec, cols["shapes"], 0).astype(np.int64)
    if np.any(pid >= planes.num_planes):
        raise ValueError(f"shipped chains: plane {int(pid.max())}, but the scene has "
                         f"{planes.num_planes} planes")
    if planes.num_planes:
        cols["shapes"] = np.where(spec, planes.canonical_shape[pid], cols["shapes"])
        cols["prims"] = np.where(spec, planes.canonical_prim[pid], cols["prims"])
    cols["shapes"] = cols["shapes"].astype(np.uint32)
    cols["prims"] = cols["prims"].astype(np.uint32)
    return cols


def merge(shipped: Sequence[dict]) -> dict:
    """One :func:`portable` chain set from several (e.g. one per AP; their
    ``src`` already index the grid's sources).

    Raises:
        ValueError: none given, or enumerated in scenes with other planes.
    """
    if not shipped:
        raise ValueError("merge: no chains given")
    sigs = {c["planes"] for c in shipped}
    if len(sigs) != 1:
        raise ValueError(f"shipped chains: enumerated in {len(sigs)} scenes with different "
                         "reflection planes (every worker needs the same scene folder)")
    keys = shipped[0]["columns"].keys()
    return {"columns": {k: np.concatenate([c["columns"][k] for c in shipped]) for k in keys},
            "planes": shipped[0]["planes"]}

