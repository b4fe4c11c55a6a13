"""Fingerprint database built from the twin: multipath delay profiles on a floor grid.

The database holds, for every point of a regular floor grid (5 cm default, at
the robot antenna height) and every access point (AP), the ``L`` strongest
propagation paths traced in the twin: path length ``c * tau`` (m), power
``|a|^2`` (single isotropic elements at the array centres), complex passband
coefficient ``a`` and the four angles (enough to synthesize the MIMO-OFDM CSI
of any array with :mod:`isac_twin.phy`, which the CSI-kNN baseline does).

It is built with the grid tracer (:func:`isac_twin.raytrace.grid.trace_grid`) and
stored as an NPZ file (format ``isac-twin-fingerprints``, see
:data:`DB_ARRAYS` and ``docs/casestudy.md``) with the metadata that decides
whether it may be used: the scene's content hash, the carrier frequency, the
AP names and positions, the grid and the tracer settings.
:func:`load_database` refuses a file built for another scene or frequency and
says why (:class:`DatabaseMismatchError`).

After an edit of the room (an object moved, a material changed) the scene's
content hash changes; a twin that registered the database
(:meth:`isac_twin.twin.twin.Twin.register_database`, done by :func:`attach`) lists
it in ``stale_databases()`` and logs a warning; :func:`cached_database`
then builds a new file, because the cache file name contains the hash.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DatabaseMismatchError
from ..raytrace.base import SPEED_OF_LIGHT
from ..utils.npzfile import NpzRecord, read_npz, write_npz

log = logging.getLogger(__name__)

DB_FORMAT = "isac-twin-fingerprints"
DB_FORMAT_VERSION = 1

#: Default grid spacing, m (the paper's 5 cm).
DEFAULT_SPACING = 0.05
#: Default number of strongest paths kept per point and AP.
DEFAULT_MAX_PATHS = 32

#: Arrays of a database file besides ``meta``: name -> (dtype, axes).
#: ``N`` grid points (``i = ix * ny + iy``), ``A`` APs, ``L`` path slots
#: (strongest first; missing paths have ``lengths`` NaN and ``power`` 0).
DB_ARRAYS = {
    "points": ("float64", "[N, 3]  grid point positions, m"),
    "free": ("bool", "[N]  point in free space (traced)"),
    "num_paths": ("int32", "[N, A]  valid path slots"),
    "lengths": ("float64", "[N, A, L]  path lengths c*tau, m (NaN pad)"),
    "power": ("float32", "[N, A, L]  |a|^2, linear (0 pad)"),
    "a": ("complex64", "[N, A, L]  passband path coefficient (iso elements)"),
    "theta_t": ("float32", "[N, A, L]  departure zenith, rad"),
    "phi_t": ("float32", "[N, A, L]  departure azimuth, rad"),
    "theta_r": ("float32", "[N, A, L]  arrival zenith, rad"),
    "phi_r": ("float32", "[N, A, L]  arrival azimuth, rad"),
}


@dataclass(frozen=True, eq=False)
class FingerprintDB(NpzRecord):
    """A fingerprint database (see the module doc and :data:`DB_ARRAYS`).

    Attributes:
        meta: metadata dictionary (format, version, scene_name, scene_hash,
            frequency_hz, ap_names, ap_positions, origin, spacing, shape,
            height, max_paths, tracer, created).
        arrays: name -> array as listed in :data:`DB_ARRAYS`.
        path: the file it was loaded from or saved to (None when fresh).
    """


    # ------------------------------------------------------------ properties

    @property
    def ap_names(self) -> list[str]:
        return list(self.meta["ap_names"])

    @property
    def scene_hash(self) -> str:
        return str(self.meta["scene_hash"])

    @property
    def frequency_hz(self) -> float:
        return float(self.meta["frequency_hz"])

    @property
    def spacing(self) -> float:
        """Grid spacing, m."""
        return float(self.meta["spacing"])

    @property
    def shape(self) -> tuple[int, int]:
        """``(nx, ny)``."""
        return tuple(int(v) for v in self.meta["shape"])

    @property
    def origin(self) -> np.ndarray:
        """``[2]`` m, x/y of grid point ``(0, 0)``."""
        return np.asarray(self.meta["origin"], float)

    @property
    def height(self) -> float:
        """Receiver height z of the grid, m."""
        return float(self.meta["height"])

    @property
    def free_indices(self) -> np.ndarray:
        """``[F]`` indices of the free (traced) points."""
        return np.flatnonzero(self.arrays["free"])

    @property
    def name(self) -> str:
        """A short name for logs and ``Twin.register_database``."""
        return str(self.path) if self.path else f"fingerprints:{self.scene_hash[:12]}"

    # ------------------------------------------------------------ look-ups

    def locate(self, xy, *, outside: str = "error") -> int:
        """Index of the free grid point nearest to ``xy`` ``[2]`` m.

        A position between grid points maps to the nearest point; a position
        on a point that is not free (inside furniture) maps to the nearest free
        point. A position more than half a spacing outside the grid raises
        (``outside="error"``) or maps to the nearest free point
        (``outside="nearest"``).

        Raises:
            ValueError: non-finite ``xy``, or outside the grid with ``outside="error"``.
        """
        if outside not in ("error", "nearest"):
            raise ValueError(f"outside: expected 'error' or 'nearest', got {outside!r}")
        xy = np.asarray(xy, float).reshape(-1)[:2]
        if xy.shape != (2,) or not np.isfinite(xy).all():
            raise ValueError(f"position: expected 2 finite numbers (m), got {xy!r}")
        nx, ny = self.shape
        f = (xy - self.origin) / self.spacing
        out = np.any(f < -0.5 - 1e-9) or f[0] > nx - 0.5 + 1e-9 or f[1] > ny - 0.5 + 1e-9
        if out and outside == "error":
            lo = self.origin
            hi = self.origin + (np.array([nx, ny]) - 1) * self.spacing
            raise ValueError(f"position ({xy[0]:.3f}, {xy[1]:.3f}) m is outside the "
                             f"fingerprint grid (x {lo[0]:.3f}..{hi[0]:.3f}, "
                             f"y {lo[1]:.3f}..{hi[1]:.3f} m)")
        ix, iy = np.clip(np.rint(f).astype(int), 0, [nx - 1, ny - 1])
        i = int(ix * ny + iy)
        if self.arrays["free"][i]:
            return i
        free = self.free_indices
        if free.size == 0:
            raise ValueError("the fingerprint grid has no free point")
        d = np.linalg.norm(self.arrays["points"][free, :2] - xy, axis=1)
        return int(free[np.argmin(d)])

    def mdp(self, i: int, num_paths: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Stored MDP of point ``i``: lengths ``[A, L']`` m (NaN pad) and powers ``[A, L']``."""
        n = self.arrays["lengths"].shape[2] if num_paths is None else int(num_paths)
        return self.arrays["lengths"][i, :, :n].copy(), self.arrays["power"][i, :, :n].copy()

    def check(self, scene, *, tx_positions: dict | None = None) -> None:
        """Raise :class:`DatabaseMismatchError` unless this database fits ``scene``.

        Checked: content hash (geometry, poses, materials), carrier frequency,
        AP names and AP positions (from the scene's config, or ``tx_positions``
        ``{name: [3] m}``).
        """
        check_compatible(self.meta, scene, tx_positions=tx_positions, where=self.name)

    def summary(self) -> dict:
        """Counts for printing."""
        n = self.arrays["num_paths"][self.arrays["free"]]
        return {"points": int(len(self.arrays["points"])), "free": int(self.arrays["free"].sum()),
                "shape": list(self.shape), "spacing_m": self.spacing, "height_m": self.height,
                "aps": self.ap_names, "max_paths": int(self.meta["max_paths"]),
                "mean_paths_per_ap": float(n.mean()) if n.size else 0.0,
                "scene_hash": self.scene_hash[:12], "frequency_hz": self.frequency_hz}


def check_compatible(meta: dict, scene, *, tx_positions: dict | None = None,
                     where: str = "database") -> None:
    """See :meth:`FingerprintDB.check`."""
    cfg = scene.config
    reasons = []
    now = scene.content_hash()
    if meta.get("scene_hash") != now:
        reasons.append(f"it was built for scene {meta.get('scene_name')!r} with content hash "
                       f"{str(meta.get('scene_hash'))[:12]}, this scene "
                       f"({cfg.scene.name!r}) hashes to {now[:12]} (another room, or the "
                       "room was edited since: an object moved or a material changed)")
    f_db, f_sc = float(meta.get("frequency_hz", float("nan"))), cfg.scene.frequency_hz
    if not abs(f_db - f_sc) <= 1e-6 * max(abs(f_sc), 1.0):
        reasons.append(f"it was traced at {f_db / 1e9:g} GHz, the scene is at "
                       f"{f_sc / 1e9:g} GHz (path powers and materials depend on frequency)")
    devs = {d.name: d for d in cfg.devices}
    for name, pos in zip(meta.get("ap_names", []), meta.get("ap_positions", [])):
        cur = (tx_positions or {}).get(name)
        if cur is None and name in devs:
            cur = devs[name].position
        if cur is None:
            reasons.append(f"access point {name!r} is not in this scene")
        elif np.linalg.norm(np.asarray(cur, float) - np.asarray(pos, float)) > 1e-6:
            reasons.append(f"access point {name!r} is at {list(np.round(cur, 4))} m, the "
                           f"database has it at {list(np.round(pos, 4))} m")
    if reasons:
        raise DatabaseMismatchError(f"{where}: refused: " + "; ".join(reasons)
                                    + ". Rebuild it (build_database / cached_database).")


# --------------------------------------------------------------------------- building


def from_grid(grid, scene, *, max_paths: int = DEFAULT_MAX_PATHS) -> FingerprintDB:
    """Reduce a traced :class:`~isac_twin.raytrace.grid.PathGrid` to a fingerprint database.

    Keeps the ``max_paths`` strongest paths (by ``|a|^2``) per point and AP,
    strongest first.
    """
    if max_paths < 1:
        raise ValueError(f"max_paths: expected >= 1, got {max_paths}")
    g = grid.arrays
    valid = g["valid"]
    n, s, p = valid.shape
    power = np.where(valid, np.abs(g["a"]) ** 2, -1.0)
    L = min(max_paths, p) if p else 0
    order = np.argsort(-power, axis=2, kind="stable")[:, :, :L]
    take = lambda v: np.take_along_axis(v, order, axis=2)  # noqa: E731
    ok = take(valid)
    lengths = np.where(ok, SPEED_OF_LIGHT * take(g["tau"]), np.nan)
    arrays = {
        "points": g["points"].astype(np.float64), "free": g["free"].astype(bool),
        "num_paths": ok.sum(-1).astype(np.int32), "lengths": lengths,
        "power": np.where(ok, take(power), 0.0).astype(np.float32),
        "a": np.where(ok, take(g["a"]), 0).astype(np.complex64),
    }
    for k in ("theta_t", "phi_t", "theta_r", "phi_r"):
        arrays[k] = np.where(ok, take(g[k]), 0).astype(np.float32)
    cfg = scene.config
    gm = grid.meta
    devs = {d.name: d for d in cfg.devices}
    meta = {
        "format": DB_FORMAT, "version": DB_FORMAT_VERSION,
        "scene_name": gm.get("scene_name", cfg.scene.name), "scene_hash": gm["scene_hash"],
        "frequency_hz": float(gm["frequency_hz"]),
        "ap_names": list(gm["tx_names"]),
        "ap_positions": [list(map(float, devs[t].position)) for t in gm["tx_names"]],
        "origin": list(gm["origin"]), "spacing": float(gm["spacing"]),
        "shape": list(gm["shape"]), "height": float(gm["height"]),
        "margin": float(gm.get("margin", 0.0)), "max_paths": int(max_paths),
        "tracer": gm.get("tracer", {}), "grid_verification": gm.get("verification", {}),
        "sionna_version": gm.get("sionna_version"),
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }
    return FingerprintDB(meta=meta, arrays=arrays)


def build_database(scene, *, spacing: float = DEFAULT_SPACING, height: float | None = None,
                   max_paths: int = DEFAULT_MAX_PATHS, margin: float = 0.0,
                   tracer_config=None, ap_names=None, progress: bool = False,
                   verify: int = 4, out: str | Path | None = None,
                   grid_tracer=None) -> FingerprintDB:
    """Trace the floor grid of ``scene`` and keep the strongest paths.

    Args:
        scene: the twin's :class:`~isac_twin.scene.twin_scene.TwinScene`.
        spacing: grid spacing, m (default 5 cm, the paper's).
        height: receiver height, m (default: the first robot's antenna height).
        max_paths: strongest paths kept per point and AP.
        margin: distance kept from the room's bounding box, m.
        tracer_config: :class:`~isac_twin.scene.config.TracerConfig` (default the scene's).
        ap_names: access points (default: every transmitter of a link).
        progress: tqdm progress bar.
        verify: points re-traced one per call to check the chunked trace.
        out: also save the database there.
        grid_tracer: what traces the grid, called like
            :func:`~isac_twin.raytrace.grid.trace_grid` (default that one; e.g. a
            ``functools.partial`` of
            :func:`isac_twin.scaleout.cluster.trace_grid_tiled` for a Dask cluster).

    Returns:
        The :class:`FingerprintDB`.
    """
    if grid_tracer is None:
        from ..raytrace.grid import trace_grid as grid_tracer

    grid = grid_tracer(scene, ap_names, spacing=spacing, height=height, margin=margin,
                      config=tracer_config, progress=progress, verify=verify)
    db = from_grid(grid, scene, max_paths=max_paths)
    if out is not None:
        db = save_database(db, out)
    return db


def cache_path(scene, spacing: float, cache_dir: str | Path = "out/cache") -> Path:
    """``<cache_dir>/<scene-hash[:16]>-<freq MHz>MHz-<spacing cm>cm.npz``."""
    f = scene.config.scene.frequency_hz
    return Path(cache_dir) / (f"{scene.content_hash()[:16]}-{f / 1e6:g}MHz-"
                              f"{spacing * 100:g}cm.npz")


def cached_database(scene, *, spacing: float = DEFAULT_SPACING,
                    cache_dir: str | Path = "out/cache", max_paths: int = DEFAULT_MAX_PATHS,
                    rebuild: bool = False, **kw) -> FingerprintDB:
    """Load the cached database for ``scene`` or build and cache it.

    A cached file that does not fit (another scene state, frequency, AP
    layout, fewer paths) is rebuilt, with a log message saying why.
    """
    path = cache_path(scene, spacing, cache_dir)
    if path.is_file() and not rebuild:
        try:
            db = load_database(path, scene=scene)
            from ..raytrace.chains import config_path_set_settings, path_set_settings

            want = config_path_set_settings(kw.get("tracer_config") or scene.config.tracer)
            have = path_set_settings(db.meta.get("tracer", {}))
            if int(db.meta["max_paths"]) >= max_paths and have == want:
                log.info("fingerprint database: using cache %s", path)
                return db
            if have != want:
                diff = ", ".join(f"{k} {have.get(k)!r} (requested {want[k]!r})"
                                 for k in want if have.get(k) != want[k])
                log.info("%s was traced with other tracer settings: %s; rebuilding", path,
                         diff)
            else:
                log.info("%s keeps %s paths, %d requested: rebuilding", path,
                         db.meta["max_paths"], max_paths)
        except ValueError as exc:
            log.warning("%s: %s; rebuilding", path, exc)
    log.info("fingerprint database: tracing a %.3g m grid of %s (cache %s)", spacing,
             scene.config.scene.name, path)
    return build_database(scene, spacing=spacing, max_paths=max_paths, out=path, **kw)


# --------------------------------------------------------------------------- files


def save_database(db: FingerprintDB, path: str | Path) -> FingerprintDB:
    """Write ``db`` as NPZ (``meta`` is a JSON string); returns it with ``path`` set."""
    missing = [k for k in DB_ARRAYS if k not in db.arrays]
    if missing:
        raise ValueError(f"save_database: missing arrays {', '.join(missing)}")
    path = write_npz(path, db.meta, db.arrays)
    log.info("wrote fingerprint database %s (%d points, %d APs)", path,
             len(db.arrays["points"]), len(db.ap_names))
    return dataclasses.replace(db, path=path)


def load_database(path: str | Path, *, scene=None, tx_positions: dict | None = None
                  ) -> FingerprintDB:
    """Read a database file; with ``scene`` also check that it fits (see
    :meth:`FingerprintDB.check`).

    Raises:
        ValueError: not a database file, unknown version, missing arrays.
        DatabaseMismatchError: built for another scene state, frequency or AP layout.
    """
    path = Path(path)
    meta, data = read_npz(path, fmt=DB_FORMAT, version=DB_FORMAT_VERSION, required=DB_ARRAYS,
                          what="fingerprint database")
    why = structure_error(meta, data)
    if why is not None:
        raise ValueError(f"{path}: not a consistent fingerprint database: {why}")
    db = FingerprintDB(meta=meta, arrays=data, path=path)
    if scene is not None:
        db.check(scene, tx_positions=tx_positions)
    return db


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)


#: Metadata a database must carry: key -> (check, what was expected).
_META = {
    "scene_name": (lambda v: isinstance(v, str), "a string"),
    "scene_hash": (lambda v: isinstance(v, str) and len(v) == 64, "a 64-digit hex string"),
    "frequency_hz": (lambda v: _is_num(v) and v > 0, "a positive number"),
    "ap_names": (lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v),
                 "a list of names"),
    "ap_positions": (lambda v: isinstance(v, list) and all(
        isinstance(p, list) and len(p) == 3 and all(map(_is_num, p)) for p in v),
        "a list of [x, y, z]"),
    "origin": (lambda v: isinstance(v, list) and len(v) >= 2 and all(map(_is_num, v)),
               "[x, y]"),
    "spacing": (lambda v: _is_num(v) and v > 0, "a positive number"),
    "shape": (lambda v: isinstance(v, list) and len(v) == 2
              and all(isinstance(x, int) and x > 0 for x in v), "[nx, ny] positive integers"),
    "height": (_is_num, "a number"),
    "max_paths": (lambda v: isinstance(v, int) and v >= 1, "an integer >= 1"),
    "tracer": (lambda v: isinstance(v, dict), "an object"),
}
_DTYPE_KIND = {"float64": "f", "float32": "f", "bool": "b", "int32": "iu", "complex64": "c"}


def structure_error(meta: dict, arrays: dict) -> str | None:
    """Why ``meta`` and ``arrays`` do not form a database (None when they do): every
    metadata key of the right type, every array of the right kind and shape
    (``N = nx * ny`` points, ``A`` access points, ``L <= max_paths`` slots)."""
    for k, (ok, what) in _META.items():
        if k not in meta:
            return f"metadata key {k!r} missing"
        if not ok(meta[k]):
            return f"metadata {k!r}: expected {what}, got {str(meta[k])[:40]!r}"
    if len(meta["ap_positions"]) != len(meta["ap_names"]):
        return (f"metadata: {len(meta['ap_names'])} ap_names for "
                f"{len(meta['ap_positions'])} ap_positions")
    n = meta["shape"][0] * meta["shape"][1]
    a = len(meta["ap_names"])
    L = arrays["lengths"].shape[2] if arrays["lengths"].ndim == 3 else -1
    want = {"points": (n, 3), "free": (n,), "num_paths": (n, a)}
    for k, (dtype, _) in DB_ARRAYS.items():
        arr = arrays[k]
        if arr.dtype.kind not in _DTYPE_KIND[dtype]:
            return f"array {k!r}: dtype {arr.dtype} is not {dtype}"
        shape = want.get(k, (n, a, L))
        if arr.shape != shape:
            return (f"array {k!r}: shape {list(arr.shape)}, expected {list(shape)} "
                    f"(grid {meta['shape'][0]} x {meta['shape'][1]}, {a} APs)")
    if L > meta["max_paths"]:
        return f"{L} path slots, more than max_paths = {meta['max_paths']}"
    return None


def attach(twin, db: FingerprintDB) -> None:
    """Register ``db`` with ``twin`` so that an edit of the room flags it stale.

    Raises:
        DatabaseMismatchError: ``db`` does not fit the twin's scene now.
    """
    db.check(twin.scene)
    twin.register_database(db.name, db.scene_hash)
