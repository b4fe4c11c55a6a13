"""Specular-chain reuse: every chain of a source enumerated once, the image method everywhere.

Sionna's path solver (2.2) has two stages. The *candidate generator* shoots
``samples_per_src`` rays from every source, samples one interaction type per
hit, and records each distinct specular chain (the types and, per specular
reflection, the plane reflected on) whose last interaction point sees the
target. The *image method* then computes, for every (candidate, target), the
exact path through those surfaces or rejects it, and the *field calculator*
gives its gain. The first stage is nearly all of the cost (rays x depth x an
inner loop over targets), and its sampling decides which paths are found: at
1e5 rays a direct trace of the bundled lab misses paths within 40 dB of a
link's strongest that 1e7 rays find (8 of 28 links; the strongest missed at
-26.7 dB).

:class:`ChainTracer` splits the stages:

1. **Chains of the sources.** :func:`~isac_twin.raytrace.source_chains.shoot_chains`
   follows ``samples_per_src`` rays per source without targets, branching at
   every hit into reflection and refraction, and keeps every distinct chain
   (every prefix). A :class:`ChainStore` holds them, identified as Sionna
   identifies them. In the lab that is ~2,000 chains per access point.
2. **Evaluation.** Every receiver gets every chain; Sionna's own image method
   and field calculator keep those that are paths to it and give their gains,
   delays and angles; line of sight comes from Sionna's own LoS test.

A receiver's paths therefore depend on its position only (never on what was
traced before: a grid point equals a live trace), and against Sionna's own
``PathSolver`` at 1e7 rays per source the bundled lab's links have the same
path set (none missing within 40 dB, none extra, none repeated) and channels
within 5e-5 (``bench/bench_paths.py``, ``tests/engine/raytrace/test_exact_paths.py``).

Only specular chains are reused: with diffuse reflection or diffraction
enabled, use the direct solver (``tracer.method = "sbr"``).
"""

from __future__ import annotations

import gc
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..scene.twin_scene import live_sionna_scenes
from .base import INTERACTION_REFRACTION, INTERACTION_SPECULAR
from .planes import PlaneIndex
from .raw import RawPaths, concat_targets, to_points
from .solver_core import arrays_to_raw, chain_arrays
from .source_chains import MirrorFilter, shoot_chains

#: Bumped whenever a change of this module changes which paths are found;
#: stored in grid metadata so that caches traced by another version are rebuilt.
#: 3: chains enumerated from the sources (no probe lattice).
CHAIN_REUSE_VERSION = 3

#: Candidate-target pairs evaluated per image-method call (bounds memory:
#: ~150 B per pair).
MAX_PAIRS_PER_CALL = 400_000



#: Recordings of the frozen evaluation kept (LRU): one per combination of
#: numbers of sources, targets and padded pairs (:func:`pad_pairs`).
FROZEN_RECORDINGS = 8


#: Extra calls made right after the frozen evaluation records a new size,
#: until one replays (Dr.Jit recorded the same size on the next two calls).
PRIME_CALLS = 3

def live_scene_objects(mi_scene=None) -> list:
    """What a call on radio materials may dispatch to besides ``mi_scene``'s own
    shapes: every live registered scene's radio materials (those no shape uses any
    more included: a material replaced by an edit stays registered) and the Mitsuba
    scenes other than ``mi_scene``."""
    out = []
    for sc in live_sionna_scenes():  # one order: a frozen call's state is keyed
        if sc.mi_scene is not mi_scene:
            out.append(sc.mi_scene)
        out.extend(m for _, m in sorted(sc.radio_materials.items()))
    return out


def neighbour_buckets(b: int) -> list[int]:
    """The :func:`pad_pairs` buckets just below (if any: none below 1024) and
    just above the bucket ``b``."""
    out = []
    if b > 1024:
        out.append(b - (1 << (int(b - 1).bit_length() - 4)))
    out.append(pad_pairs(b + 1))
    return out


def pad_pairs(n: int) -> int:
    """The padded size of ``n`` (chain, target) pairs in a frozen evaluation:
    at least 1024, else ``n`` rounded up to a multiple of an eighth of its
    power-of-two octave (at most 12.5 % padding; 8 sizes per octave)."""
    if n <= 1024:
        return 1024
    step = 1 << (int(n).bit_length() - 4)
    return -(-int(n) // step) * step


def method_tag(tracer_meta: dict) -> str:
    """How a grid was traced, from its ``meta["tracer"]``: ``"sbr"`` or
    ``"chains v<CHAIN_REUSE_VERSION>"`` (``v0``: before versions were stored)."""
    if tracer_meta.get("method", "sbr") != "chains":
        return "sbr"
    return f"chains v{(tracer_meta.get('chains') or {}).get('version', 0)}"


def config_method_tag(config) -> str:
    """The :func:`method_tag` a grid traced now with ``TracerConfig`` would get."""
    return f"chains v{CHAIN_REUSE_VERSION}" if config.uses_chains else "sbr"


#: ``[tracer]`` settings that decide which paths a trace finds (a cached grid or
#: database traced with other values is not the same database).
PATH_SET_SETTINGS = ("max_depth", "samples_per_src", "los", "specular_reflection",
                     "diffuse_reflection", "refraction", "diffraction", "seed")


def path_set_settings(tracer_meta: dict) -> dict:
    """What decided a grid's path set, from its ``meta["tracer"]``: the method tag
    (:func:`method_tag`) and :data:`PATH_SET_SETTINGS`."""
    return {"method": method_tag(tracer_meta),
            **{k: tracer_meta.get(k) for k in PATH_SET_SETTINGS}}


def config_path_set_settings(config) -> dict:
    """:func:`path_set_settings` of a grid traced now with ``TracerConfig`` ``config``."""
    return {"method": config_method_tag(config),
            **{k: getattr(config, k) for k in PATH_SET_SETTINGS}}


def chains_supported(config) -> bool:
    """Whether a ``TracerConfig`` traces specular chains only (reflection/refraction)."""
    return not (config.diffuse_reflection or config.diffraction)


class ChainStore:
    """Distinct candidate specular chains for fixed sources in a fixed scene.

    A chain is identified as Sionna's generator identifies it: by its source
    index and, per depth, the interaction type and, for a specular reflection,
    the reflection *plane* (:class:`~isac_twin.raytrace.planes.PlaneIndex`);
    which triangle of a plane was hit, and which surface a transmission went
    through, are not part of it (Sionna's image method finds the path through
    any coplanar triangle and whatever surfaces the segments cross). Keying by
    triangle instead made chains found through different triangles of one
    wall the same path, two or three times (issue 12).

    A stored specular interaction carries its plane's canonical triangle and
    point, so a chain's evaluation does not depend on which ray found it.

    Args:
        max_depth: the solver's ``max_depth`` (``D = max(1, max_depth)``).
        planes: the scene's :class:`~isac_twin.raytrace.planes.PlaneIndex`.
    """

    _FIELDS = ("src", "types", "shapes", "prims", "probs", "vx", "vy", "vz", "k_tx")

    def __init__(self, max_depth: int, planes):
        self.max_depth = int(max_depth)
        self.depth = max(1, self.max_depth)
        self.planes = planes
        self._index: dict[bytes, int] = {}
        self._chunks: list[dict[str, np.ndarray]] = []
        self._cols: dict[str, np.ndarray] | None = None
        self._arrays = None

    def __len__(self) -> int:
        return len(self._index)

    def add_columns(self, f: dict[str, np.ndarray]) -> np.ndarray:
        """Add chains given as columns (the fields of :meth:`columns`, e.g. from
        :func:`~isac_twin.raytrace.source_chains.shoot_chains`); specular
        interactions are canonicalized in place. Returns the store index of
        each row ``[C]`` (a chain already stored keeps its index)."""
        if len(f["src"]) == 0:
            return np.zeros(0, np.int64)
        rows = self._keys(f)
        keys = rows.view(np.dtype((np.void, rows.dtype.itemsize * rows.shape[1]))).ravel()
        uniq, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
        ids = np.empty(len(uniq), np.int64)
        new = []
        for u, k in enumerate(uniq):
            kb = k.tobytes()
            g = self._index.get(kb)
            if g is None:
                g = self._index[kb] = len(self._index)
                new.append(first[u])
            ids[u] = g
        if new:
            new = np.asarray(new)
            self._chunks.append({k: v[new] for k, v in f.items()})
            self._cols = None
            self._arrays = None
        return ids[inverse.ravel()]

    def _keys(self, f: dict[str, np.ndarray]) -> np.ndarray:
        """Identity rows ``[C, 1 + 2 D]`` uint32 of chains ``f`` (source, types,
        plane + 1 of each specular interaction, else 0); canonicalizes the
        specular interactions of ``f`` in place."""
        types = f["types"]
        spec = types == INTERACTION_SPECULAR
        plane = self.planes.planes_of(f["shapes"], f["prims"])
        if np.any(spec & (plane < 0)):
            bad = np.argwhere(spec & (plane < 0))[0]
            raise ValueError(f"chain {bad[0]}: specular interaction at depth {bad[1] + 1} on "
                             f"shape id {f['shapes'][tuple(bad)]}, primitive "
                             f"{f['prims'][tuple(bad)]}, which is no triangle of the scene")
        pid = np.where(spec, plane, 0)
        f["shapes"] = np.where(spec, self.planes.canonical_shape[pid], f["shapes"])
        f["prims"] = np.where(spec, self.planes.canonical_prim[pid], f["prims"])
        point = self.planes.canonical_point[pid]
        for i, k in enumerate(("vx", "vy", "vz")):
            f[k] = np.where(spec, point[..., i], f[k]).astype(np.float32)
        # A transmission is identified by its type only; its stored surface
        # would be the first ray's (only the image method's offset of the ray
        # target along that surface's normal reads it). None (a null shape:
        # Sionna's primitive lookups return zeros for it) keeps the evaluation
        # independent of which ray found the chain.
        refr = types == INTERACTION_REFRACTION
        f["shapes"] = np.where(refr, 0, f["shapes"]).astype(np.uint32)
        f["prims"] = np.where(refr, 0, f["prims"]).astype(np.uint32)
        ident = np.where(spec, plane + 1, 0).astype(np.uint32)
        return np.ascontiguousarray(np.concatenate([f["src"][:, None], types, ident], axis=1))

    def columns(self) -> dict[str, np.ndarray]:
        """All chains as numpy columns (``src [C]``, ``types/shapes/prims [C, D]``, ...)."""
        if self._cols is None:
            if not self._chunks:
                d = self.depth
                self._cols = {"src": np.zeros(0, np.uint32),
                              **{k: np.zeros((0, d), np.uint32)
                                 for k in ("types", "shapes", "prims")},
                              **{k: np.zeros((0, d), np.float32)
                                 for k in ("probs", "vx", "vy", "vz")},
                              "k_tx": np.zeros((0, 3), np.float32)}
            else:
                self._cols = {k: np.concatenate([c[k] for c in self._chunks])
                              for k in self._FIELDS}
                self._chunks = [self._cols]
        return self._cols

    def arrays(self) -> dict:
        """The chains as :func:`~isac_twin.raytrace.solver_core.chain_arrays`
        (Dr.Jit arrays; entries from ``len(self)`` on are empty chains)."""
        if self._arrays is None:
            self._arrays = chain_arrays(self.columns(), self.max_depth)
        return self._arrays


class ChainTracer:
    """Traces receivers with every chain of the sources (see the module doc).

    Args:
        core: the :class:`~isac_twin.raytrace.solver_core.SolverCore` (its settings,
            image method and field calculator; ``samples_per_src`` is the number
            of branching rays per source).
        max_pairs: candidate-target pairs per image-method call.
        mirror_filter: pass each receiver only the chains mirror geometry allows
            (default) instead of all of them.

    The cache (chains) belongs to one scene state and one set of source
    positions: :meth:`trace` drops it when its ``context`` argument or the
    sources change.
    """

    def __init__(self, core, max_pairs: int = MAX_PAIRS_PER_CALL, mirror_filter: bool = True,
                 freeze: bool = False):
        if not chains_supported(core.config):
            raise ValueError("chain reuse traces specular chains only: disable "
                             "tracer.diffuse_reflection and tracer.diffraction, or use "
                             'tracer.method = "sbr"')
        self.core = core
        self.max_pairs = int(max_pairs)
        #: Give the image method only the chains that mirror geometry allows
        #: (:class:`~isac_twin.raytrace.source_chains.MirrorFilter`; the paths are
        #: the same, tested), else every chain.
        self.mirror_filter = bool(mirror_filter)
        #: Replay the evaluation's recorded kernels (``drjit.freeze``) while the
        #: chains, the scene state and the numbers of sources, targets and pairs
        #: stay the same (a live trace of the same devices step after step):
        #: Dr.Jit then skips tracing Sionna's image method and field
        #: calculator in Python, most of a step's cost. Same paths, bit for bit
        #: (tested). Recordings are dropped with the chains.
        self.freeze = bool(freeze)
        #: Why Dr.Jit refused to record the evaluation (None: it did not);
        #: the tracer then evaluates unfrozen.
        self.freeze_error: str | None = None
        self.rays = int(core.config.samples_per_src)
        self._context = None
        self._mi_scene = None
        self.reset()

    def reset(self) -> None:
        """Forget the chains."""
        #: The chains (:class:`ChainStore`), enumerated at the first
        #: :meth:`prepare` after a reset.
        self.store: ChainStore | None = None
        self._all: np.ndarray | None = None
        self._filter: MirrorFilter | None = None
        self._sources: np.ndarray | None = None
        #: Sources whose chains were enumerated since the reset.
        self.sources_shot = 0
        self._evaluate = self._frozen() if self.freeze else None
        #: The (sources, targets, padded pairs) sizes of the frozen calls since
        #: the reset: each is recorded once (:attr:`recordings`), then replayed.
        #: The most recently used last: at most ``FROZEN_RECORDINGS``, as Dr.Jit
        #: keeps (it evicts the least recently used recording; a size
        #: evicted there must be primed again when it returns).
        self.frozen_sizes: dict[tuple[int, int, int], None] = {}
        self._inputs = _InputSlots()

    def _frozen(self):
        import drjit as dr

        def sizes(mi_scene, chains, chain_idx, target_idx, src, tgt, *rest):
            # Widths enter Sionna's code as Python ints (literals in the
            # recorded kernels): a call with other widths must record anew.
            # The other live scenes: a call on radio materials dispatches over
            # every registered instance, those of every scene loaded (the
            # real room beside the twin's), and Dr.Jit traverses only the
            # instances it finds in the inputs and this state; else it refused
            # to record ("no such object instance was found in the function's
            # inputs") and the evaluation ran unfrozen.
            return (dr.width(chains["_src_indices"]), dr.width(chain_idx), dr.width(src),
                    dr.width(tgt), *live_scene_objects(mi_scene))

        return dr.freeze(self.core.evaluate_chains, state_fn=sizes, limit=FROZEN_RECORDINGS,
                         warn_after=16, auto_opaque=False)

    @property
    def recordings(self) -> int:
        """Recordings of the frozen evaluation since the last reset (0 unfrozen)."""
        return int(getattr(self._evaluate, "n_recordings", 0))

    def prepare(self, sc, src, targets: np.ndarray) -> list[np.ndarray]:
        """Enumerate the chains of the sources ``src`` (once per reset).

        ``src``: the sources, ``[S, 3]`` m (numpy or Mitsuba ``Point3f``).

        Returns:
            Per target, the store indices of its candidate chains: those that
            pass the :class:`~isac_twin.raytrace.source_chains.MirrorFilter` (all
            of them without :attr:`mirror_filter`).
        """
        if self.store is None:
            self.store = ChainStore(self.core.config.max_depth, PlaneIndex(sc.mi_scene))
        if self._all is None:
            pts = src if isinstance(src, np.ndarray) else \
                np.stack([np.asarray(c.numpy(), np.float64) for c in src], 1)
            cfg = self.core.config
            self.store.add_columns(shoot_chains(
                sc.mi_scene, self.store.planes, pts, self.rays, cfg.max_depth,
                specular=cfg.specular_reflection, refraction=cfg.refraction))
            self._all = np.arange(len(self.store), dtype=np.int64)
            self._sources = pts
            self.sources_shot += len(pts)
        if not self.mirror_filter:
            return [self._all] * len(targets)
        if self._filter is None:
            self._filter = MirrorFilter(self.store.planes, self._sources, self.store.columns())
        return self._filter(np.asarray(targets, np.float64).reshape(-1, 3))

    def use_chains(self, sc, sources: np.ndarray, columns: dict[str, np.ndarray],
                   context=None, planes: PlaneIndex | None = None) -> None:
        """Take chains enumerated elsewhere instead of shooting them: the next
        :meth:`trace` with these ``sources`` and ``context`` evaluates
        ``columns`` (and shoots nothing; :attr:`sources_shot` stays 0).

        Args:
            sc: the ``sionna.rt.Scene`` the chains belong to.
            sources: ``[S, 3]`` m, as :meth:`trace` will be given them.
            columns: the chains of these sources, as :meth:`ChainStore.columns`
                gives them (e.g. another tracer's ``store.columns()`` of the same
                scene), with this process's shape ids; ``src`` indexes ``sources``.
            context: the ``context`` :meth:`trace` will be given.
            planes: the scene's :class:`~isac_twin.raytrace.planes.PlaneIndex`
                (built when None).

        The store holds the same chains in the same order as one that shot
        them: :meth:`ChainStore.add_columns` orders new chains by identity.
        """
        sources = np.asarray(sources, np.float64).reshape(-1, 3)
        src = np.asarray(columns["src"])
        if len(src) and int(src.max()) >= len(sources):
            raise ValueError(f"use_chains: a chain of source {int(src.max())}, but "
                             f"{len(sources)} sources were given")
        self.reset()
        self._context = (context, np.round(sources, 6).tobytes())
        self._mi_scene = sc.mi_scene
        self.store = ChainStore(self.core.config.max_depth,
                                planes if planes is not None else PlaneIndex(sc.mi_scene))
        self.store.add_columns({k: np.array(v) for k, v in columns.items()})
        self._all = np.arange(len(self.store), dtype=np.int64)
        # (the sources as float32 values, as trace() gives them to prepare())
        self._sources = sources.astype(np.float32).astype(np.float64)

    # ----------------------------------------------------------------- tracing

    def trace(self, sc, sources: np.ndarray, targets: np.ndarray, *,
              source_orientations=None, source_velocities=None,
              target_orientations=None, target_velocities=None, context=None):
        """Trace every source to every target.

        Args:
            sc: the ``sionna.rt.Scene`` (geometry and materials).
            sources: ``[S, 3]`` m; targets: ``[T, 3]`` m.
            source_orientations, target_orientations: ``[S|T, 3]`` Sionna
                ``[yaw, pitch, roll]`` rad (default 0).
            source_velocities, target_velocities: ``[S|T, 3]`` m/s (default 0).
            context: anything that identifies the scene state (e.g. its
                revision); the cache is dropped when it changes.

        Returns:
            :class:`~isac_twin.raytrace.sionna.RawPaths` ``[T, S, P]``, paths of a
            link in no particular order; ``candidates_per_source`` counts the
            chains in the store and ``cap`` exceeds it: chain enumeration has no
            candidate buffer to overflow, so the result is never truncated.

        The same as :meth:`assemble` of :meth:`evaluate`.
        """
        return self.assemble(self.evaluate(
            sc, sources, targets, source_orientations=source_orientations,
            source_velocities=source_velocities, target_orientations=target_orientations,
            target_velocities=target_velocities, context=context))

    def evaluate(self, sc, sources: np.ndarray, targets: np.ndarray, *,
                 source_orientations=None, source_velocities=None,
                 target_orientations=None, target_velocities=None,
                 context=None) -> "Evaluated":
        """The Dr.Jit part of :meth:`trace` (same arguments): the image method
        and field calculator of every (chain, target) pair, read into numpy.
        :meth:`assemble` makes the :class:`RawPaths` from it; it touches no
        Dr.Jit state, so a caller may run it in another thread while the next
        targets are evaluated (``trace_grid`` does)."""
        import drjit as dr
        import mitsuba as mi

        sources = np.asarray(sources, np.float64).reshape(-1, 3)
        targets = np.asarray(targets, np.float64).reshape(-1, 3)
        ctx = (context, np.round(sources, 6).tobytes())
        # A new Mitsuba scene is new geometry even when the context says
        # nothing changed: Sionna rebuilds ``sc.mi_scene`` when an object is
        # added (the radar's sensing targets, at its first frame). The chains
        # hold the old scene's shapes; kept, Dr.Jit refused the next recording
        # (instances of the old scene that the new one's traversal does not
        # reach) and the trace ran unfrozen from then on.
        if ctx != self._context or sc.mi_scene is not self._mi_scene:
            old_scene = self._mi_scene
            self.reset()
            self._context = ctx
            self._mi_scene = sc.mi_scene
            if old_scene is not None and old_scene is not sc.mi_scene:
                # free the old scene now, not whenever the collector next runs
                # (its shapes stay in Dr.Jit's registry until then)
                del old_scene
                gc.collect()
        core = self.core
        ns, nt = len(sources), len(targets)
        tgt_o_all = np.zeros((nt, 3)) if target_orientations is None else \
            np.asarray(target_orientations, float).reshape(nt, 3)
        v_rx_all = np.zeros((nt, 3)) if target_velocities is None else \
            np.asarray(target_velocities, float).reshape(nt, 3)
        # (the sources as float32 values, as the chains were always shot from)
        per_target = self.prepare(sc, sources.astype(np.float32).astype(np.float64), targets)
        counts = np.bincount(self.store.columns()["src"].astype(np.int64), minlength=ns)
        cap = int(counts.max(initial=0)) + 1
        depth = core.config.max_depth

        groups, cur, size = [], [], 0
        for t, ids in enumerate(per_target):
            if cur and size + len(ids) > self.max_pairs:
                groups.append(cur)
                cur, size = [], 0
            cur.append(t)
            size += len(ids)
        if cur:
            groups.append(cur)
        chains = self.store.arrays()
        src_o_np = np.zeros((ns, 3)) if source_orientations is None else \
            np.asarray(source_orientations, float).reshape(ns, 3)
        v_tx_np = np.zeros((ns, 3)) if source_velocities is None else \
            np.asarray(source_velocities, float).reshape(ns, 3)
        out = Evaluated(ns=ns, depth=depth, counts=counts, cap=cap, src_o=src_o_np)
        for g in groups:
            g = np.asarray(g)
            chain_idx = np.concatenate([per_target[t] for t in g])
            if len(chain_idx) == 0 and not core.config.los:
                out.groups.append((len(g), None, tgt_o_all[g]))
                continue
            tgt_idx = np.repeat(np.arange(len(g)), [len(per_target[t]) for t in g])
            # Lanes stay target-major. Chain-major lanes (one chain to
            # neighbouring targets side by side) cost ~3x less kernel time,
            # but Embree's ray packets then differ from a single receiver's,
            # and at grazing incidence (a segment within float32 rounding of
            # an edge) that decides whether a path exists: on the lab 2 of
            # 600 links of a batch differed from the same points traced alone
            # (one path at -12.4 dB), 0 of 600 target-major. A grid point must
            # equal a live trace.
            # (a frozen call with empty inputs aborts in Dr.Jit: no pairs, no freezing)
            frozen = self.freeze and self.freeze_error is None and len(chain_idx) > 0

            def run(frozen_call, inputs, ci, ti, pad=None):
                args = (sc.mi_scene, chains, inputs("chain", ci, mi.UInt),
                        inputs("target", ti, mi.UInt), inputs("src", sources, mi.Point3f),
                        inputs("tgt", targets[g], mi.Point3f),
                        inputs("v_tx", v_tx_np, mi.Vector3f),
                        inputs("v_rx", v_rx_all[g], mi.Vector3f),
                        sc.wavelength, bool(core.config.los),
                        None if pad is None else inputs("pad", pad, mi.UInt))
                if not frozen_call:
                    return core.evaluate_chains(*args)
                # No garbage collection inside a frozen call: Mitsuba objects
                # collected while Dr.Jit records (e.g. the Mitsuba scene the
                # chains were dropped with, in a reference cycle) abort the
                # process (seen in the test session).
                gc_was_on = gc.isenabled()
                gc.disable()
                try:
                    return self._evaluate(*args)
                finally:
                    if gc_was_on:
                        gc.enable()

            if frozen:
                # Padded to a bucket of sizes (pad_pairs), so that the varying
                # pair counts of mirror-filtered receivers replay a few
                # recordings instead of recording every call.
                n = len(chain_idx)
                b = pad_pairs(n)
                empty = dr.width(chains["_src_indices"]) - 1

                def padded(m):
                    """(chains, targets, pad flags) of ``m`` pairs: these ``n``
                    padded with done pairs, or (priming a smaller size, values
                    not kept) the first ``m``."""
                    if m < n:
                        return chain_idx[:m], tgt_idx[:m], np.zeros(m, np.uint32)
                    return (np.concatenate([chain_idx, np.full(m - n, empty, chain_idx.dtype)]),
                            np.concatenate([tgt_idx, np.zeros(m - n, tgt_idx.dtype)]),
                            np.concatenate([np.zeros(n, np.uint32), np.ones(m - n, np.uint32)]))

                ci, ti, pad = padded(b)
                try:
                    size = (ns, len(g), b)
                    before = self.recordings
                    cols = run(True, self._inputs, ci, ti, pad)
                    if size not in self.frozen_sizes and self.recordings > before:
                        # Dr.Jit records a new size again on its next call or
                        # two; do it now, in the call that records anyway,
                        # not in the steps after (a paced run's overruns).
                        cols = self._prime(run, cols, ci, ti, pad)
                        # and the buckets either side: a pair count near a
                        # bucket's edge crosses it back and forth (the 4-robot
                        # lab: 2560 from step 1, 2304 at step 7, a 30 ms trace)
                        dr.eval(*cols)
                        for m in neighbour_buckets(b):
                            if (ns, len(g), m) not in self.frozen_sizes:
                                pm = padded(m)
                                dr.eval(*self._prime(run, run(True, self._inputs, *pm), *pm))
                                self._remember((ns, len(g), m))
                    self._remember(size)
                except RuntimeError as e:
                    # Dr.Jit refused to record (e.g. a material call it cannot
                    # traverse): evaluate unfrozen from now on, and say why.
                    # (Dr.Jit's own reason is the cause: "error encountered
                    # while recording ... (see above)" says nothing)
                    self.freeze_error = str(e.__cause__ or e).splitlines()[0][:300]
                    warnings.warn(f"chain reuse: evaluation not frozen ({self.freeze_error})",
                                  RuntimeWarning, stacklevel=2)
                    frozen = False
            if not frozen:
                cols = run(False, _fresh, chain_idx, tgt_idx)
            dr.eval(*cols)
            out.groups.append((len(g), [c.numpy() for c in cols], tgt_o_all[g]))
        return out

    def _prime(self, run, cols, ci, ti, pad):
        """Call the frozen evaluation again (at most :data:`PRIME_CALLS` times)
        until a call replays; returns the last call's columns."""
        import drjit as dr

        for _ in range(PRIME_CALLS):
            dr.eval(*cols)
            n_rec = self.recordings
            cols = run(True, self._inputs, ci, ti, pad)
            if self.recordings == n_rec:
                break
        return cols

    def _remember(self, size: tuple) -> None:
        """``size`` was used last (Dr.Jit's recordings are least-recently-used)."""
        self.frozen_sizes.pop(size, None)
        self.frozen_sizes[size] = None
        while len(self.frozen_sizes) > FROZEN_RECORDINGS:
            del self.frozen_sizes[next(iter(self.frozen_sizes))]

    @staticmethod
    def assemble(ev: "Evaluated") -> RawPaths:
        """:class:`RawPaths` ``[T, S, P]`` of an :meth:`evaluate` result (numpy
        only: thread-safe)."""
        results = []
        for nr, cols, tgt_o in ev.groups:
            if cols is None:
                results.append(RawPaths.empty(nr, ev.ns, ev.depth, ev.counts, ev.cap))
            else:
                results.append(arrays_to_raw(cols[1:], nr, ev.ns, ev.depth, ev.counts, ev.cap,
                                             ev.src_o, tgt_o, keep=cols[0].astype(bool)))
        if len(results) == 1:
            return results[0]
        return concat_targets(results)


@dataclass
class Evaluated:
    """:meth:`ChainTracer.evaluate`'s result: per group of targets, ``(targets
    R, the evaluated columns as numpy (``[keep, *buffer_arrays]``) or None
    when the group has no pair, target orientations [R, 3])``; ``ns`` sources
    of orientations ``src_o [S, 3]``; ``depth``, ``counts [S]`` and ``cap`` as
    :class:`RawPaths` reports them."""

    ns: int
    depth: int
    counts: np.ndarray
    cap: int
    src_o: np.ndarray
    groups: list = field(default_factory=list)


def _fresh(name: str, values: np.ndarray, cls):
    """``values`` (``[n]`` indices or ``[n, 3]``) as a new Dr.Jit array of ``cls``
    (``mi.UInt``, ``mi.Point3f`` or ``mi.Vector3f``)."""
    import drjit as dr
    import mitsuba as mi

    if cls is mi.UInt:
        out = dr.copy(mi.UInt(np.ascontiguousarray(values, np.uint32)))
        dr.eval(out)
        return out
    return to_points(values, len(values), cls)
class _InputSlots:
    """The per-call inputs of a frozen evaluation, in Dr.Jit arrays allocated
    once per name and shape and overwritten in place (LLVM backend: host
    memory, written through ``numpy()``'s zero-copy view).

    Fresh arrays each call made ``drjit.freeze`` record the evaluation again on
    most calls (its dry run of the recording failed for some allocations;
    bench_retrace: 18 of 30 calls), which cost more than it saved; the same
    arrays every call replay the recording."""

    def __init__(self):
        self._slots: dict[tuple, tuple] = {}

    def __call__(self, name: str, values: np.ndarray, cls):
        import drjit as dr
        import mitsuba as mi

        values = np.asarray(values)
        n = len(values)
        slot = self._slots.get((name, n))
        if slot is None:
            if cls is mi.UInt:
                arrays = [dr.empty(mi.UInt, n)]
            else:
                arrays = [dr.empty(mi.Float, n) for _ in range(3)]
            dr.eval(*arrays)
            views = [a.numpy() for a in arrays]
            if dr.backend_v(arrays[0]) != dr.JitBackend.LLVM or \
                    any(not v.flags.writeable for v in views):
                raise RuntimeError("frozen chain evaluation needs Dr.Jit's LLVM backend")
            out = arrays[0] if cls is mi.UInt else cls(*arrays)
            slot = self._slots[(name, n)] = (out, views)
        out, views = slot
        dr.sync_thread()  # no kernel still reads the previous values
        if cls is mi.UInt:
            views[0][:] = values.astype(np.uint32, copy=False)
        else:
            v = values.reshape(n, 3)
            for i in range(3):
                views[i][:] = v[:, i]
        return out
