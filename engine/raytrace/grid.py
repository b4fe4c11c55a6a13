"""Floor grids of traced paths: ``trace_grid`` writes them, ``load_grid`` reads them.

The paper (sec. III-A, last paragraph): with static transmitters and receivers
that move on the floor, the paths can be traced once for every grid position
and stored in a database. :func:`trace_grid` traces a regular grid of receiver
positions at one height against the static transmitters with a progress bar.

By default it reuses specular chains (:mod:`isac_twin.raytrace.chains`): every
chain of each transmitter is enumerated once, Sionna's image method keeps the
ones that are paths to each grid point. ``method="sbr"`` traces every point
by shoot-and-bounce, in chunks of receivers (bounded memory). No path is
dropped silently: a chunk whose solver buffer reached
``max_num_paths_per_src`` is split in halves (down to one receiver) and then
retried with a doubled cap; if that is still not enough,
:class:`~isac_twin.raytrace.base.TruncationError`.
The rest of this note is about the chunked shoot-and-bounce.

Receivers per solver call. Besides the cap, Sionna's shoot-and-bounce
generator de-duplicates specular chains through a hash table shared by all
receivers of a call (``sb_candidate_generator.py``: "this can cause loss of
candidates due to hash collisions"); a chain whose slot is taken by another
chain is dropped. Sionna sizes the table ``max(max_num_paths_per_src, 1e6)``
entries per source. Measured in the bundled lab with that size: up to 2
receivers per call give exactly the paths of one-receiver calls; 16 lose
~1.3 % of the paths (also among the 24 strongest per link), 64 lose ~3.5 %,
~900 lose ~19 %. :func:`trace_grid` therefore enlarges the table to
:data:`GRID_SPEC_TABLE_SIZE` (2**24) entries per source (see
``SolverCore.spec_table_size``), with which no path of one-receiver calls was
missing at 16, 64 or 256 receivers per call, and *verifies*: it re-traces
``verify`` random free points one per solver call and stores, in
``meta["verification"]``, how many paths the grid lacks (all, and among the
``verify_top`` (24) strongest per link), how many it has that the direct
trace lacks, and how many it repeats (and logs a warning
when any are). The fingerprint database needs only the strongest paths;
``keep_strongest`` stores only those.

Grid points that are not in free space (inside furniture or walls, or
outside the room) are found before tracing by casting one ray straight up and
one straight down from each point with Mitsuba: a point is *free* when both
rays hit a surface and both hit it from the front (the first surface met is
not the inside of a closed object, i.e. ``dot(ray_dir, normal) < 0``). Points
that are not free are not traced: ``free`` is False and ``num_paths`` is 0.

The file format (NPZ, every array documented with its shape) is described in
``docs/tracers.md``. :data:`GRID_FORMAT_VERSION` is bumped on any change;
:func:`load_grid` refuses files with an unknown version.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import logging
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..scene.config import TracerConfig
from ..utils.npzfile import NpzRecord, read_npz, write_npz
from .base import DevicePose, device_poses, sionna_orientation, validate_poses
from .chains import CHAIN_REUSE_VERSION, ChainTracer
from .conformance import grazing, scene_edges
from .raw import RawPaths, find_repeats, free_points, grow_cap, match_paths, pad_paths
from .solver_core import SolverCore

log = logging.getLogger(__name__)

GRID_FORMAT = "isac-twin-path-grid"
GRID_FORMAT_VERSION = 2

#: Arrays of a grid file besides ``meta``: name -> (dtype, axes).
GRID_ARRAYS = {
    "points": ("float64", "[N, 3]"),
    "free": ("bool", "[N]"),
    "tx_positions": ("float64", "[S, 3]"),
    "tx_orientations": ("float64", "[S, 3]"),
    "num_paths": ("int32", "[N, S]"),
    "valid": ("bool", "[N, S, P]"),
    "a": ("complex64", "[N, S, P]"),
    "tau": ("float64", "[N, S, P]"),
    "theta_t": ("float32", "[N, S, P]"),
    "phi_t": ("float32", "[N, S, P]"),
    "theta_r": ("float32", "[N, S, P]"),
    "phi_r": ("float32", "[N, S, P]"),
    "interactions": ("uint8", "[N, S, P, D]"),
    "vertices": ("float32", "[N, S, P, D, 3]"),
}

_PATH_KEYS = ("valid", "a", "tau", "theta_t", "phi_t", "theta_r", "phi_r", "interactions",
              "vertices")

#: Receivers per solver call (see the module doc for the accuracy trade-off).
DEFAULT_CHUNK_SIZE = 64

#: Chunks evaluated ahead of the thread that arranges their paths (chain
#: reuse; 0: no second thread).
PIPELINE_DEPTH = 2

#: Receivers per :class:`~isac_twin.raytrace.chains.ChainTracer` call (chain reuse).
CHAIN_CHUNK_SIZE = 1024

#: Entries per source of Sionna's specular-chain hash table in grid traces
#: (Sionna's own size is ``max(max_num_paths_per_src, 1e6)``). The
#: receivers-per-call loss described in the module doc is collisions in this
#: table; with 2**24 entries none was measured up to 256 receivers per call.
#: Memory: ``2 hashes x 4 B x sources`` per entry (2 APs: 256 MiB).
GRID_SPEC_TABLE_SIZE = 1 << 24

#: Strongest paths per point and transmitter whose presence the verification
#: checks (the fingerprint database uses at most this many per AP).
VERIFY_TOP_N = 24

#: Deterministic mode: the candidate generator materializes
#: ``num_sources * max_depth * samples_per_src * num_targets`` entries; chunks are
#: sized to keep that below this many.
DETERMINISTIC_BUDGET = 200_000_000


@dataclass(frozen=True, eq=False)
class PathGrid(NpzRecord):
    """A traced floor grid (``N = nx * ny`` points, ``S`` transmitters,
    ``P`` path slots, ``D`` interaction slots). Point ``i = ix * ny + iy`` sits at
    ``origin + (ix, iy) * spacing`` and ``z = height``.

    Attributes:
        meta: the metadata dictionary (see ``docs/tracers.md``).
        arrays: name -> numpy array, as listed in :data:`GRID_ARRAYS`.
        path: the file it was loaded from (None when fresh).
    """


    @property
    def tx_names(self) -> list[str]:
        return list(self.meta["tx_names"])

    @property
    def origin(self) -> np.ndarray:
        """``[2]`` m, x/y of point ``(0, 0)``."""
        return np.asarray(self.meta["origin"], float)

    @property
    def spacing(self) -> float:
        return float(self.meta["spacing"])

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.meta["shape"])

    @property
    def height(self) -> float:
        return float(self.meta["height"])

    def nearest(self, xy) -> tuple[int, float]:
        """Index of the grid point nearest to ``xy`` ``[2]`` m and its distance, m.

        Raises:
            ValueError: ``xy`` is more than half a spacing outside the grid.
        """
        xy = np.asarray(xy, float)[:2]
        nx, ny = self.shape
        f = (xy - self.origin) / self.spacing
        idx = np.rint(f).astype(int)
        if np.any(f < -0.5 - 1e-9) or f[0] > nx - 0.5 + 1e-9 or f[1] > ny - 0.5 + 1e-9:
            lo = self.origin
            hi = self.origin + (np.array([nx, ny]) - 1) * self.spacing
            raise ValueError(f"position ({xy[0]:.3f}, {xy[1]:.3f}) m is outside the stored grid "
                             f"(x {lo[0]:.3f}..{hi[0]:.3f}, y {lo[1]:.3f}..{hi[1]:.3f} m)")
        idx = np.clip(idx, 0, [nx - 1, ny - 1])
        i = int(idx[0] * ny + idx[1])
        return i, float(np.linalg.norm(self.points[i, :2] - xy))

    def paths(self, i: int, s: int) -> dict[str, np.ndarray]:
        """The valid paths of point ``i`` and transmitter ``s`` (sorted by delay)."""
        n = int(self.num_paths[i, s])
        return {k: self.arrays[k][i, s, :n] for k in _PATH_KEYS if k != "valid"}


# --------------------------------------------------------------------------- geometry


def grid_points(lo, hi, spacing: float, margin: float = 0.0) -> tuple[np.ndarray, tuple[int, int]]:
    """Cell-centred points of ``[lo, hi]`` (x, y ``[2]`` m) shrunk by ``margin``.

    Returns:
        ``origin [2]`` m and ``(nx, ny)``.
    """
    lo = np.asarray(lo, float)[:2] + margin
    hi = np.asarray(hi, float)[:2] - margin
    size = hi - lo
    if np.any(size < spacing):
        raise ValueError(f"grid area {size.tolist()} m is smaller than the spacing {spacing} m")
    n = np.floor(size / spacing + 1e-6).astype(int)
    # Rounded to 1 um: the bounds are Mitsuba's float32 bounding box (a grid
    # point meant to sit at a round coordinate must not be 1e-7 m off).
    origin = np.round(lo + (size - (n - 1) * spacing) / 2, 6)
    return origin, (int(n[0]), int(n[1]))


# --------------------------------------------------------------------------- tracing


def sorted_chunk(raw, keep_strongest: int | None = None) -> dict[str, np.ndarray]:
    """RawPaths ``[R, T, P]`` -> dict of ``[R, T, P']`` sorted by delay, valid first.

    ``keep_strongest``: keep only that many paths (largest ``|a|``) per
    receiver and transmitter.
    """
    valid = raw.valid
    if keep_strongest is not None and valid.shape[-1] > keep_strongest:
        mag = np.where(valid, np.abs(raw.a), -1.0)
        rank = np.argsort(np.argsort(-mag, axis=-1, kind="stable"), axis=-1, kind="stable")
        valid = valid & (rank < keep_strongest)
    key = np.where(valid, raw.tau, np.inf)
    order = np.argsort(key, axis=-1, kind="stable")
    out = {}
    for k in _PATH_KEYS:
        v = valid if k == "valid" else getattr(raw, k)
        idx = order.reshape(order.shape + (1,) * (v.ndim - 3))
        out[k] = np.take_along_axis(v, idx, axis=2)
    n = out["valid"].sum(-1)
    if keep_strongest is not None:  # zero what was dropped
        for k in _PATH_KEYS:
            if k != "valid":
                m = out["valid"].reshape(out["valid"].shape + (1,) * (out[k].ndim - 3))
                out[k] = np.where(m, out[k], np.zeros((), out[k].dtype))
    p = int(n.max()) if n.size else 0
    out = {k: v[:, :, :p] for k, v in out.items()}
    out["num_paths"] = n.astype(np.int32)
    return out


class _ChunkTracer:
    """Traces receiver chunks: a truncated chunk is split in halves, a single
    receiver's cap grown by :func:`~isac_twin.raytrace.raw.grow_cap`."""

    def __init__(self, core, sc, src, src_orient, cap: int, max_cap: int,
                 keep_strongest: int | None = None):
        self.core, self.sc, self.src, self.src_orient = core, sc, src, src_orient
        self.cap, self.max_cap = cap, max_cap
        self.keep_strongest = keep_strongest
        self.retries = 0

    def _solve(self, pts: np.ndarray, cap: int) -> RawPaths:
        return self.core.solve_endpoints(self.sc, self.src, pts, cap, self.src_orient)

    def __call__(self, pts: np.ndarray) -> list[dict]:
        if len(pts) == 1:
            cap = self.cap
            raw, self.cap = grow_cap(lambda c: self._solve(pts, c), cap, self.max_cap,
                                     what=f"a single receiver at {pts[0].tolist()}")
            self.retries += int(self.cap != cap)
            return [sorted_chunk(raw, self.keep_strongest)]
        raw = self._solve(pts, self.cap)
        if not raw.truncated:
            return [sorted_chunk(raw, self.keep_strongest)]
        self.retries += 1
        log.info("chunk of %d receivers reached max_num_paths_per_src=%d "
                 "(candidates per source %s): splitting", len(pts), self.cap,
                 raw.candidates_per_source.tolist())
        h = len(pts) // 2
        return self(pts[:h]) + self(pts[h:])


def trace_grid(scene, tx_names: Sequence[str] | None = None, spacing: float = 0.05,
               height: float | None = None, margin: float = 0.0, *,
               config: TracerConfig | None = None, chunk_size: int | None = None,
               deterministic: bool | None = None, max_cap: int | None = None,
               tx_poses: dict[str, DevicePose] | None = None, progress: bool = True,
               verify: int = 8, verify_top: int = VERIFY_TOP_N,
               keep_strongest: int | None = None,
               spec_table_size: int | None = GRID_SPEC_TABLE_SIZE,
               method: str | None = None,
               legacy: bool = False, out: str | Path | None = None) -> PathGrid:
    """Trace a floor grid of receiver positions against static transmitters.

    Args:
        scene: the :class:`~isac_twin.scene.twin_scene.TwinScene`.
        tx_names: transmitters (default: every device that is the ``tx`` of a link).
        spacing: grid spacing, m.
        height: receiver height z, m (default: the first robot's antenna height).
        margin: distance kept from the room's bounding box, m.
        config: tracer settings (default ``scene.config.tracer``).
        chunk_size: receivers per solver call (``"sbr"``; default
            :data:`DEFAULT_CHUNK_SIZE`, in deterministic mode at most what
            :data:`DETERMINISTIC_BUDGET` allows) or per :class:`ChainTracer`
            call (chain reuse; default :data:`CHAIN_CHUNK_SIZE`).
        deterministic: override ``config.deterministic`` for ``"sbr"`` and the
            verification (default for grids: False, because Sionna's
            deterministic generator needs memory proportional to samples x
            receivers; see ``docs/tracers.md``). Chain reuse enumerates its
            chains without sampling.
        max_cap: largest ``max_num_paths_per_src`` tried on truncation
            (default 16 x the configured cap).
        tx_poses: transmitter poses (default: from the config).
        progress: show a tqdm progress bar.
        verify: re-trace this many random free points one per solver call and
            record the path-count deficit in ``meta["verification"]``.
        verify_top: the verification also checks that the ``verify_top``
            strongest paths of each re-traced link are in the grid (same
            interactions, delay within 1e-6 relative).
        keep_strongest: store only this many paths (largest ``|a|``) per point
            and transmitter, still sorted by delay (None: all paths).
        spec_table_size: entries per source of Sionna's specular-chain hash
            table (default :data:`GRID_SPEC_TABLE_SIZE`; None: Sionna's own
            ``max(cap, 1e6)``, which loses candidates when many receivers share
            a call).
        method: ``"chains"`` (every specular chain of the transmitters, see
            :mod:`isac_twin.raytrace.chains`), ``"sbr"`` (shoot-and-bounce for
            every receiver, in chunks) or ``"auto"`` (default: ``config.method``,
            whose ``"auto"`` means chains when only specular reflection and
            refraction are enabled).
        legacy: trace with ``SolverCore(legacy=True)`` (Sionna's ``Paths``,
            full-size candidate buffer; with ``spec_table_size=None`` and
            ``chunk_size=16`` this is the code path before the optimization,
            for benchmarks).
        out: write the NPZ there as well.

    Returns:
        The :class:`PathGrid`.

    Raises:
        TruncationError: a single receiver overflows the largest cap.
        ValueError: bad arguments or transmitter poses.
    """
    cfg = scene.config
    config = config or cfg.tracer
    plan = _plan(scene, config, tx_names, spacing, height, margin, tx_poses, method, legacy,
                 keep_strongest)
    det = False if deterministic is None else bool(deterministic)
    core = SolverCore(config, deterministic=det, spec_table_size=spec_table_size,
                      legacy=legacy)
    chunk_size = _chunk_size(chunk_size, plan, config, det)
    log.info("tracing %d x %d grid (%d free points) at z=%.3f m against %s (%s)",
             *plan.shape, len(plan.todo), plan.height, ", ".join(plan.tx_names),
             "chain reuse" if plan.use_chains else "shoot-and-bounce")
    if plan.use_chains:
        pieces, cap_used, retries, chain_stats = _trace_by_chains(
            core, scene.sionna, plan, chunk_size, progress)
    else:
        pieces, cap_used, retries = _trace_by_sbr(
            core, scene.sionna, plan, chunk_size, max_cap or 16 * config.max_num_paths_per_src,
            progress)
        chain_stats = None
    arrays = assemble_grid(plan, pieces, max(1, config.max_depth))
    verification = _verify(core, scene.sionna, plan.src, plan.src_orient, plan.points, arrays,
                           plan.todo, int(verify), config.seed, int(verify_top),
                           plan.keep_strongest)
    meta = grid_metadata(scene, plan, spacing, margin, {
        **dataclasses.asdict(config), "deterministic": det,
        "max_num_paths_per_src_used": cap_used, "chunk_size": chunk_size,
        "truncation_retries": retries, "spec_table_size": spec_table_size,
        "keep_strongest": plan.keep_strongest,
        "method": "chains" if plan.use_chains else "sbr", "chains": chain_stats}, verification)
    grid = PathGrid(meta=meta, arrays=arrays)
    if out is not None:
        save_grid(grid, out)
    return grid


@dataclass
class _GridPlan:
    """What :func:`trace_grid` traces: the raster, its free points, the sources."""

    tx_names: list[str]
    src: np.ndarray          # [S, 3] m
    src_orient_cfg: np.ndarray  # [S, 3] roll, pitch, yaw
    src_orient: np.ndarray   # [S, 3] Sionna yaw, pitch, roll
    origin: np.ndarray       # [2] m
    shape: tuple[int, int]
    height: float
    points: np.ndarray       # [N, 3] m
    free: np.ndarray         # [N] bool
    todo: np.ndarray         # indices of the free points
    use_chains: bool
    keep_strongest: int | None


def _plan(scene, config: TracerConfig, tx_names, spacing, height, margin, tx_poses, method,
          legacy, keep_strongest) -> _GridPlan:
    """Check the arguments and lay out the raster (job 1 of :func:`trace_grid`)."""
    cfg = scene.config
    if not (spacing > 0 and np.isfinite(spacing)):
        raise ValueError(f"spacing: expected a positive number of metres, got {spacing!r}")
    if tx_names is None:
        tx_names = list(dict.fromkeys(lk.tx for lk in cfg.links))
    tx_names = list(tx_names)
    if not tx_names:
        raise ValueError("trace_grid: no transmitters (give tx_names or add [[links]])")
    poses = dict(device_poses(cfg))
    poses.update(tx_poses or {})
    validate_poses(scene, poses, tx_names)
    if height is None:
        robots = [d for d in cfg.devices if d.kind == "robot"]
        height = poses[robots[0].name].position[2] if robots else 1.0
    if method in (None, "auto"):
        use_chains = config.uses_chains
    elif method in ("chains", "sbr"):
        use_chains = method == "chains"
    else:
        raise ValueError(f"method: expected 'auto', 'chains' or 'sbr', got {method!r}")
    if keep_strongest is not None and int(keep_strongest) < 1:
        raise ValueError(f"keep_strongest: expected >= 1 or None, got {keep_strongest!r}")
    origin, (nx, ny) = grid_points(scene.bounds_min, scene.bounds_max, spacing, margin)
    ix, iy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    points = np.stack([origin[0] + ix.ravel() * spacing, origin[1] + iy.ravel() * spacing,
                       np.full(nx * ny, float(height))], axis=1)
    free = free_points(scene.sionna, points)
    orient_cfg = np.array([poses[n].orientation for n in tx_names], float)
    return _GridPlan(tx_names=tx_names,
                     src=np.array([poses[n].position for n in tx_names], float),
                     src_orient_cfg=orient_cfg,
                     src_orient=np.array([sionna_orientation(o) for o in orient_cfg]),
                     origin=origin, shape=(nx, ny), height=float(height), points=points,
                     free=free, todo=np.flatnonzero(free),
                     use_chains=use_chains and not legacy,
                     keep_strongest=None if keep_strongest is None else int(keep_strongest))


def _chunk_size(chunk_size: int | None, plan: _GridPlan, config: TracerConfig,
                det: bool) -> int:
    if chunk_size is None and plan.use_chains:
        chunk_size = CHAIN_CHUNK_SIZE
    elif chunk_size is None:
        chunk_size = DEFAULT_CHUNK_SIZE
        if det:
            per_target = len(plan.tx_names) * max(1, config.max_depth) * config.samples_per_src
            chunk_size = max(1, min(chunk_size, DETERMINISTIC_BUDGET // per_target))
    if int(chunk_size) < 1:
        raise ValueError(f"chunk_size: expected >= 1, got {chunk_size}")
    return int(chunk_size)


def _trace_by_chains(core, sc, plan: _GridPlan, chunk_size: int, progress: bool):
    """Job 2 (chain reuse): the transmitters' chains first, then the points chunk by chunk."""
    from tqdm import tqdm

    ct = ChainTracer(core)  # its first trace enumerates the chains

    def host_part(ev):
        return sorted_chunk(ct.assemble(ev), plan.keep_strongest)

    # Pipelined: while Dr.Jit evaluates a chunk (its kernels run in Dr.Jit's
    # own threads), a second thread arranges the previous chunk's paths in
    # numpy. At most PIPELINE_DEPTH chunks wait for that thread (memory).
    pieces, pending = [], []
    with tqdm(total=len(plan.todo), unit="pt", desc="grid", disable=not progress) as bar, \
            ThreadPoolExecutor(max_workers=1, thread_name_prefix="grid-assemble") as pool:
        for start in range(0, len(plan.todo), chunk_size):
            idx = plan.todo[start:start + chunk_size]
            ev = ct.evaluate(sc, plan.src, plan.points[idx], source_orientations=plan.src_orient)
            if PIPELINE_DEPTH:
                pending.append((idx, pool.submit(host_part, ev)))
            else:
                pieces.append((idx, host_part(ev)))
            while len(pending) > PIPELINE_DEPTH:
                i, fut = pending.pop(0)
                pieces.append((i, fut.result()))
            bar.update(len(idx))
        pieces += [(i, fut.result()) for i, fut in pending]
    stats = {"version": CHAIN_REUSE_VERSION, "rays_per_source": ct.rays,
             "chains": len(ct.store)}
    # no candidate buffer, nothing to grow: the configured cap, no retry
    return pieces, core.config.max_num_paths_per_src, 0, stats


def _trace_by_sbr(core, sc, plan: _GridPlan, chunk_size: int, max_cap: int, progress: bool):
    """Job 2 (shoot-and-bounce): chunks of receivers, split on truncation."""
    from tqdm import tqdm

    tracer = _ChunkTracer(core, sc, plan.src, plan.src_orient, core.config.max_num_paths_per_src,
                          max_cap, plan.keep_strongest)
    pieces = []
    with tqdm(total=len(plan.todo), unit="pt", desc="grid", disable=not progress) as bar:
        for start in range(0, len(plan.todo), chunk_size):
            idx = plan.todo[start:start + chunk_size]
            offs = 0
            for part in tracer(plan.points[idx]):
                n = part["num_paths"].shape[0]
                pieces.append((idx[offs:offs + n], part))
                offs += n
            bar.update(len(idx))
    return pieces, tracer.cap, tracer.retries


def assemble_grid(plan, pieces, depth: int) -> dict[str, np.ndarray]:
    """Job 3: the traced chunks into the arrays of :data:`GRID_ARRAYS`.

    Args:
        plan: the raster (``tx_names``, ``points [N, 3]``, ``free [N]``,
            ``src [S, 3]``, ``src_orient_cfg [S, 3]``), e.g. ``trace_grid``'s or
            :class:`isac_twin.scaleout.tiles.GridPlan`.
        pieces: ``(point indices [t], chunk)``, a chunk as :func:`sorted_chunk`
            returns it (``[t, S, P']`` arrays).
        depth: interaction slots ``D``.
    """
    s = len(plan.tx_names)
    p = max([part["valid"].shape[2] for _, part in pieces], default=0)
    n_all = len(plan.points)
    arrays = {
        "points": plan.points, "free": plan.free, "tx_positions": plan.src,
        "tx_orientations": plan.src_orient_cfg,
        "num_paths": np.zeros((n_all, s), np.int32),
        "valid": np.zeros((n_all, s, p), bool),
        "a": np.zeros((n_all, s, p), np.complex64),
        "tau": np.zeros((n_all, s, p), np.float64),
        **{k: np.zeros((n_all, s, p), np.float32) for k in ("theta_t", "phi_t", "theta_r",
                                                            "phi_r")},
        "interactions": np.zeros((n_all, s, p, depth), np.uint8),
        "vertices": np.zeros((n_all, s, p, depth, 3), np.float32),
    }
    for idx, part in pieces:
        arrays["num_paths"][idx] = part["num_paths"]
        for k in _PATH_KEYS:
            arrays[k][idx] = pad_paths(part[k], p).astype(arrays[k].dtype)
    return arrays


def grid_metadata(scene, plan, spacing: float, margin: float, tracer_meta: dict,
                  verification: dict) -> dict:
    """Job 5: the metadata (see ``docs/tracers.md``); ``plan`` as :func:`assemble_grid`'s
    plus ``origin [2]``, ``shape``, ``height``."""
    import mitsuba as mi
    import sionna.rt

    cfg = scene.config
    return {
        "format": GRID_FORMAT, "version": GRID_FORMAT_VERSION,
        "scene_name": cfg.scene.name, "scene_hash": scene.content_hash(),
        "frequency_hz": cfg.scene.frequency_hz,
        "origin": plan.origin.tolist(), "spacing": float(spacing), "shape": list(plan.shape),
        "height": plan.height, "margin": float(margin),
        "tx_names": plan.tx_names, "num_free": int(plan.free.sum()),
        "tracer": tracer_meta, "verification": verification,
        "sionna_version": sionna.rt.__version__ if hasattr(sionna.rt, "__version__")
        else _pkg_version("sionna-rt"),
        "mitsuba_variant": mi.variant(),
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }


def top_missing(ref: dict, grid: dict, n: int) -> tuple[int, int]:
    """Of ``ref``'s ``n`` strongest paths, how many are not in ``grid`` (see
    :func:`~isac_twin.raytrace.raw.match_paths`) -> (missing, checked).

    Both are dicts with ``a, tau [L]``, ``interactions [L, D]``, ``vertices [L, D, 3]``."""
    order = np.argsort(-np.abs(ref["a"]), kind="stable")[:n]
    m = match_paths(_Paths(grid), _Paths({k: v[order] for k, v in ref.items()}))
    return int((m < 0).sum()), len(order)


class _Paths:
    """Attribute view of a dict of path arrays (for :func:`match_paths`)."""

    def __init__(self, d: dict):
        self.a, self.tau = d["a"], d["tau"]
        self.interactions, self.vertices = d["interactions"], d["vertices"]


#: Ray-count factors (over ``samples_per_src``) of the traces that confirm a grid
#: path the verification's direct trace lacks, tried in turn for such links only.
CONFIRM_FACTORS = (10, 100)


def _verify(core, sc, src, src_orient, points, arrays, todo, n: int, seed: int,
            top_n: int = VERIFY_TOP_N, keep_strongest: int | None = None) -> dict:
    """Re-trace ``n`` random free points one per solver call (Sionna's own
    shoot-and-bounce, the grid's settings) and compare path by path
    (:func:`verify_point`: paths the grid lacks, all and among the ``top_n``
    strongest per link; paths the direct trace lacks, unless a trace with 10x,
    then 100x the rays holds them: ``paths_found_more``, real paths the direct
    trace's rays missed; repeated paths in the grid), summed by
    :func:`verification_summary`."""
    pick = verify_pick(todo, n, seed)
    confirm: dict = {}
    counts = [verify_point(core, sc, src, src_orient, points[i],
                           {k: arrays[k][i] for k in _STORED_AT_POINT},
                           top_n, keep_strongest, confirm) for i in pick]
    return verification_summary(pick, counts, top_n, keep_strongest)


#: The grid arrays :func:`verify_point` reads at a point.
_STORED_AT_POINT = ("num_paths", "a", "tau", "interactions", "vertices")


def _pkg_version(name: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(name)
    except PackageNotFoundError:
        return "unknown"


# --------------------------------------------------------------------------- files


def save_grid(grid: PathGrid, path: str | Path, *, compress: bool = False) -> Path:
    """Write ``grid`` as NPZ (``meta`` is a JSON string, see ``docs/tracers.md``)."""
    path = write_npz(path, grid.meta, grid.arrays, compress=compress)
    log.info("wrote %s (%d points, %d transmitters)", path, len(grid.arrays["points"]),
             len(grid.meta["tx_names"]))
    return path


def load_grid(path: str | Path) -> PathGrid:
    """Read a grid NPZ written by :func:`trace_grid` / :func:`save_grid`.

    Raises:
        ValueError: not a grid file, unknown format version, or a missing array.
    """
    meta, data = read_npz(path, fmt=GRID_FORMAT, version=GRID_FORMAT_VERSION,
                          required=GRID_ARRAYS, what="path grid")
    return PathGrid(meta=meta, arrays=data, path=Path(path))


def grid_summary(grid: PathGrid) -> dict:
    """Counts for printing: points, free points, mean/max valid paths per link."""
    n = grid.arrays["num_paths"][grid.arrays["free"]]
    return {"points": int(len(grid.arrays["points"])), "free": int(grid.arrays["free"].sum()),
            "shape": grid.shape, "spacing": grid.spacing, "height": grid.height,
            "mean_paths_per_link": float(n.mean()) if n.size else 0.0,
            "max_paths_per_link": int(n.max()) if n.size else 0,
            "truncation_retries": grid.meta["tracer"]["truncation_retries"],
            "verification": grid.meta.get("verification", {})}


# --------------------------------------------------------------------------- per-point verification


#: The counts :func:`verify_point` returns (summed over points by
#: :func:`verification_summary`).
VERIFY_COUNTS = ("paths_grid", "paths_single_calls", "paths_missing", "paths_extra",
                 "paths_grazing", "paths_found_more", "paths_repeated", "links_differing",
                 "links", "top_paths_checked", "top_paths_missing")


def verify_pick(todo: np.ndarray, n: int, seed: int) -> np.ndarray:
    """The grid indices ``trace_grid``'s verification re-traces: ``n`` of the
    free indices ``todo`` (``[F]``), drawn with ``seed`` (none when ``n <= 0``)."""
    if n <= 0 or len(todo) == 0:
        return np.zeros(0, np.int64)
    return np.random.default_rng(seed).choice(todo, size=min(n, len(todo)), replace=False)


def verify_point(core, sc, src, src_orient, point: np.ndarray, stored: dict[str, np.ndarray],
                 top_n: int = VERIFY_TOP_N, keep_strongest: int | None = None,
                 confirm: dict | None = None) -> dict:
    """Re-trace one grid point directly and compare with its stored paths, as
    ``trace_grid``'s verification does for each of its points (e.g. on the
    worker of a tiled grid: ``isac_twin.scaleout``).

    Args:
        core: the grid's :class:`~isac_twin.raytrace.solver_core.SolverCore`
            (its settings trace the direct reference; ``max_num_paths_per_src``
            is the cap).
        sc: the ``sionna.rt.Scene``.
        src: ``[S, 3]`` m; src_orient: ``[S, 3]`` rad Sionna ``[yaw, pitch, roll]``.
        point: ``[3]`` m, the grid point.
        stored: the grid's arrays at the point: ``num_paths [S]``, ``a, tau
            [S, P]``, ``interactions [S, P, D]``, ``vertices [S, P, D, 3]``.
        top_n, keep_strongest: as ``trace_grid``'s ``verify_top`` and
            ``keep_strongest``.
        confirm: a dict kept between calls (the solvers with 10x and 100x the
            rays that confirm paths the direct trace lacks; None: a new one).

    Returns:
        The counts :data:`VERIFY_COUNTS` of this point (paths the grid lacks,
        all and among the ``top_n`` strongest per link; paths the direct trace
        lacks that more rays do not confirm; paths more rays confirmed;
        repeated paths; links and links that differ). A stored path neither trace
        finds that touches a triangle edge (:func:`~isac_twin.raytrace.conformance.grazing`)
        counts as ``paths_grazing``, not ``paths_extra``.
    """
    confirm = {} if confirm is None else confirm
    if keep_strongest is not None:
        top_n = min(top_n, keep_strongest)
    cap = core.config.max_num_paths_per_src
    pt = np.asarray(point, np.float64).reshape(1, 3)
    raw = core.solve_endpoints(sc, src, pt, cap, src_orient)
    c = dict.fromkeys(VERIFY_COUNTS, 0)
    c["paths_grid"] = int(np.asarray(stored["num_paths"]).sum())
    for s in range(raw.valid.shape[1]):
        ref = raw.link(0, s)
        if keep_strongest is not None:  # the grid keeps only these
            top = np.sort(np.argsort(-np.abs(ref["a"]), kind="stable")[:keep_strongest])
            ref = {k: v[top] for k, v in ref.items()}
        k = int(stored["num_paths"][s])
        mine = {f: np.asarray(stored[f])[s, :k] for f in ("a", "tau", "interactions", "vertices")}
        m = match_paths(_Paths(mine), _Paths(ref))
        found = np.zeros(k, bool)
        found[m[m >= 0]] = True
        for factor in CONFIRM_FACTORS:  # more rays: real paths the direct trace missed?
            if found.all():
                break
            if factor not in confirm:
                confirm[factor] = SolverCore(dataclasses.replace(
                    core.config, samples_per_src=factor * core.config.samples_per_src),
                    deterministic=True)
            big = confirm[factor].solve_endpoints(sc, src, pt, cap, src_orient)
            mb = match_paths(_Paths(mine), _Paths(big.link(0, s)))
            real = np.zeros(k, bool)
            real[mb[mb >= 0]] = True
            c["paths_found_more"] += int((~found & real).sum())
            found |= real
        if not found.all():  # on an edge, whether a ray finds a path is float rounding
            key = ("edges", id(sc.mi_scene))
            if key not in confirm:
                confirm[key] = scene_edges(sc.mi_scene)
            graze = np.zeros(k, bool)
            graze[~found] = grazing(mine["interactions"][~found], mine["vertices"][~found],
                                    confirm[key])
            c["paths_grazing"] += int(graze.sum())
            found |= graze
        c["links"] += 1
        c["paths_single_calls"] += len(ref["tau"])
        c["paths_missing"] += int((m < 0).sum())
        c["paths_extra"] += int((~found).sum())
        c["links_differing"] += int((m < 0).any() or not found.all())
        c["paths_repeated"] += len(find_repeats(_Paths(mine)))
        tm, tc = top_missing(ref, mine, top_n)
        c["top_paths_missing"] += tm
        c["top_paths_checked"] += tc
    return c


def verification_summary(pick: np.ndarray, counts: Sequence[dict], top_n: int = VERIFY_TOP_N,
                         keep_strongest: int | None = None) -> dict:
    """``meta["verification"]`` from :func:`verify_point`'s counts of the
    points ``pick`` (grid indices, in :func:`verify_pick`'s order), as
    ``trace_grid`` records it; logs a warning when paths are missing, extra or
    repeated."""
    if len(pick) == 0:
        return {"points": 0}
    if keep_strongest is not None:
        top_n = min(top_n, keep_strongest)
    tot = {k: int(sum(c[k] for c in counts)) for k in VERIFY_COUNTS}
    out = {"points": int(len(pick)), "indices": [int(i) for i in pick], **tot,
           "top_n": int(top_n)}
    out = {k: out[k] for k in ("points", "indices", "paths_grid", "paths_single_calls",
                               "paths_missing", "paths_extra", "paths_grazing",
                               "paths_found_more",
                               "paths_repeated", "links_differing", "links", "top_n",
                               "top_paths_checked", "top_paths_missing")}
    if tot["paths_missing"] or tot["paths_extra"] or tot["paths_repeated"]:
        log.warning("grid verification at %d re-traced points: %d of %d paths missing "
                    "(%d of the %d strongest per link), %d extra, %d repeated", len(pick),
                    tot["paths_missing"], tot["paths_single_calls"], tot["top_paths_missing"],
                    tot["top_paths_checked"], tot["paths_extra"], tot["paths_repeated"])
    return out
