"""Floor radio maps: Sionna RT's own ``RadioMapSolver`` on a horizontal plane.

One map per scene state: a plane at the robot antenna height covering the
scene's floor extent, cut into square cells; for every access point the
*path gain* of each cell (Sionna's planar radio map: the incoherent sum of
the power of every ray tube that crosses the cell, averaged over the cell's
area), then derived quantities:

* ``rss_dbm = path_gain_db + power_dbm`` of that access point;
* the *best server* (the access point with the largest RSS) and its RSS;
* SNR of the best server against thermal noise over the OFDM band
  (``k T B NF`` with ``[noise]`` of ``twin.toml``), and SINR under full
  reuse (every access point transmitting on every resource element, all
  other access points count as interference): a worst case, since the twin's
  links may split the OFDM grid.

Antennas: a single isotropic, vertically polarized element at both ends
(the same convention as the project's grid traces), so the map shows the
propagation, not an array's gain or beam.

Arrays are ``[S, ny, nx]`` (S access points, ``ny`` rows along y, ``nx``
columns along x); cell ``(iy, ix)`` is centred at
``origin + (ix, iy) * cell_size`` (m) at ``z = height``. A cell no ray
reached holds ``-inf`` dB (path gain 0); a cell whose centre is not in free
space (inside a wall or a piece of furniture, or outside the room; the
project's grid-trace test, :func:`isac_twin.raytrace.raw.free_points`) holds NaN
and ``free`` is False there.

Sionna's scene is shared with the twin's tracer: :func:`compute_radio_map`
adds its own transmitters and isotropic arrays only for the duration of
the call and puts back what was there.
"""

from __future__ import annotations

import logging
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..phy.units import thermal_noise_power, watt_to_dbm
from ..raytrace.base import device_poses, sionna_orientation, validate_poses
from ..raytrace.raw import free_points
from ..raytrace.solver_core import load_sionna_rt
from ..utils.npzfile import NpzRecord, read_npz, write_npz

log = logging.getLogger(__name__)

RADIOMAP_FORMAT = "isac-twin-radio-map"
RADIOMAP_FORMAT_VERSION = 1

#: Default cell size, m (coarse: a live view needs it fast; the CLI takes --cell).
DEFAULT_CELL_M = 0.25
#: Default rays launched per access point. Sionna's one shoot-and-bounce kernel is the whole
#: cost (a bare RadioMapSolver call takes the same time), linear in rays: on 2 CPU cores
#: 0.45 s for the lab's two APs at 5 cm, median 0.89 dB from the project's grid trace there
#: (1e6 rays: 0.88 s, 0.59 dB; 250k: 0.24 s, 1.40 dB; bench/bench_radiomap.py, load 2.2).
DEFAULT_SAMPLES = 500_000

#: Arrays of a radio-map record besides ``meta``: name -> (dtype, axes, unit).
RADIOMAP_ARRAYS = {
    "path_gain_db": ("float32", "[S, ny, nx]", "dB"),
    "rss_dbm": ("float32", "[S, ny, nx]", "dBm"),
    "best_server": ("int16", "[ny, nx]", "index into tx_names, -1: no coverage"),
    "best_rss_dbm": ("float32", "[ny, nx]", "dBm"),
    "snr_db": ("float32", "[ny, nx]", "dB, best server against thermal noise"),
    "sinr_db": ("float32", "[ny, nx]", "dB, best server, full reuse"),
    "free": ("bool", "[ny, nx]", "cell centre in free space"),
    "tx_positions": ("float64", "[S, 3]", "m"),
    "tx_power_dbm": ("float64", "[S]", "dBm"),
}


@dataclass(frozen=True, eq=False)
class RadioMap(NpzRecord):
    """A floor radio map (see the module doc for axes and units).

    ``meta`` holds ``tx_names``, ``origin`` ``[2]`` m (centre of cell (0, 0)),
    ``cell_size`` m, ``height`` m, ``shape`` ``[ny, nx]``, ``frequency_hz``,
    ``noise_dbm``, ``samples_per_tx``, ``max_depth`` and ``scene_hash``.
    """

    @property
    def tx_names(self) -> list[str]:
        return list(self.meta["tx_names"])

    @property
    def origin(self) -> np.ndarray:
        """``[2]`` m: x, y of the centre of cell (0, 0)."""
        return np.asarray(self.meta["origin"], float)

    @property
    def cell_size(self) -> float:
        return float(self.meta["cell_size"])

    @property
    def height(self) -> float:
        return float(self.meta["height"])

    @property
    def shape(self) -> tuple[int, int]:
        """``(ny, nx)``."""
        return tuple(int(x) for x in self.meta["shape"])

    def cell_centers(self) -> np.ndarray:
        """``[ny, nx, 3]`` m: the centre of every cell."""
        ny, nx = self.shape
        ix, iy = np.meshgrid(np.arange(nx), np.arange(ny))
        c = self.cell_size
        return np.stack([self.origin[0] + ix * c, self.origin[1] + iy * c,
                         np.full((ny, nx), self.height)], axis=-1)

    def extent(self) -> tuple[float, float, float, float]:
        """``(x_min, x_max, y_min, y_max)`` m of the outer cell edges."""
        ny, nx = self.shape
        c = self.cell_size
        x0, y0 = self.origin - c / 2
        return (x0, x0 + nx * c, y0, y0 + ny * c)

    def cell_of(self, xy) -> tuple[int, int]:
        """``(iy, ix)`` of the cell holding the point ``xy`` ``[2]`` m.

        Raises:
            ValueError: the point lies outside the map.
        """
        x0, x1, y0, y1 = self.extent()
        x, y = float(xy[0]), float(xy[1])
        if not (x0 <= x < x1 and y0 <= y < y1):
            raise ValueError(f"point ({x:.3f}, {y:.3f}) m is outside the radio map "
                             f"(x {x0:.3f}..{x1:.3f}, y {y0:.3f}..{y1:.3f} m)")
        c = self.cell_size
        return int((y - y0) // c), int((x - x0) // c)


@contextmanager
def _own_devices(sc, rt):
    """Empty ``sc`` of transmitters and receivers and give it isotropic arrays; restore
    the previous devices (the same objects) and arrays afterwards."""
    saved_tx = list(sc.transmitters.values())
    saved_rx = list(sc.receivers.values())
    saved_arrays = (sc.tx_array, sc.rx_array)
    for d in saved_tx + saved_rx:
        sc.remove(d.name)
    iso = rt.PlanarArray(num_rows=1, num_cols=1, vertical_spacing=0.5, horizontal_spacing=0.5,
                         pattern="iso", polarization="V")
    sc.tx_array = iso
    sc.rx_array = iso
    try:
        yield
    finally:
        for name in list(sc.transmitters) + list(sc.receivers):
            sc.remove(name)
        if saved_tx or saved_rx:
            sc.add(saved_tx + saved_rx)
        if saved_arrays[0] is not None:
            sc.tx_array = saved_arrays[0]
        if saved_arrays[1] is not None:
            sc.rx_array = saved_arrays[1]


def default_height(config) -> float:
    """The first robot's antenna height, m (1.0 without robots)."""
    poses = device_poses(config)
    robots = [d.name for d in config.devices if d.kind == "robot"]
    return float(poses[robots[0]].position[2]) if robots else 1.0


def access_points(config) -> list[str]:
    """Every device of kind ``access_point`` (config order)."""
    return [d.name for d in config.devices if d.kind == "access_point"]


def compute_radio_map(scene, tx_names=None, *, cell_size: float = DEFAULT_CELL_M,
                      height: float | None = None, samples_per_tx: int = DEFAULT_SAMPLES,
                      max_depth: int | None = None, poses=None, seed: int | None = None
                      ) -> RadioMap:
    """Compute the floor radio map of ``scene`` with Sionna's ``RadioMapSolver``.

    Args:
        scene: the :class:`~isac_twin.scene.twin_scene.TwinScene` (its current edits included).
        tx_names: access points to map (default: every ``access_point`` device).
        cell_size: square cell edge, m.
        height: plane height z, m (default: the first robot's antenna height).
        samples_per_tx: rays launched per access point (more: less Monte-Carlo noise).
        max_depth: interactions per ray (default ``[tracer] max_depth``).
        poses: device name -> :class:`~isac_twin.utils.geometry.DevicePose` (default: from the config).
        seed: Sionna's sampling seed (default ``[tracer] seed``).

    Returns:
        the :class:`RadioMap`; the plane covers the scene's x/y bounding box
        (Sionna rounds the size up to whole cells, keeping the centre).

    Raises:
        ValueError: no access point, an unknown or misplaced device, a bad cell size
            or height (each message names the value).
    """
    cfg = scene.config
    if not (isinstance(cell_size, (int, float)) and np.isfinite(cell_size) and cell_size > 0):
        raise ValueError(f"cell_size: expected a positive number of metres, got {cell_size!r}")
    if int(samples_per_tx) < 1:
        raise ValueError(f"samples_per_tx: expected >= 1, got {samples_per_tx!r}")
    names = access_points(cfg) if tx_names is None else [str(n) for n in tx_names]
    if not names:
        raise ValueError(f"{cfg.path}: no access point to map (add a device of kind "
                         "'access_point' or pass tx_names)")
    known = {d.name: d for d in cfg.devices}
    for n in names:
        if n not in known:
            raise ValueError(f"radio map: unknown device {n!r} (devices: "
                             f"{', '.join(sorted(known))})")
    poses = dict(device_poses(cfg), **(poses or {}))
    validate_poses(scene, poses, names)
    h = default_height(cfg) if height is None else float(height)
    lo, hi = scene.bounds_min, scene.bounds_max
    if not (np.isfinite(h) and lo[2] <= h <= hi[2]):
        raise ValueError(f"height: {height!r} m is outside the scene (z {lo[2]:.2f}.."
                         f"{hi[2]:.2f} m)")
    depth = cfg.tracer.max_depth if max_depth is None else int(max_depth)
    seed = cfg.tracer.seed if seed is None else int(seed)
    power = np.array([known[n].power_dbm for n in names], float)

    rt = load_sionna_rt()
    import mitsuba as mi

    sc = scene.sionna
    centre = (lo[:2] + hi[:2]) / 2
    size = hi[:2] - lo[:2]
    t = cfg.tracer
    with _own_devices(sc, rt):
        for n, p_dbm in zip(names, power):
            p = poses[n]
            sc.add(rt.Transmitter(name=n, position=mi.Point3f(*map(float, p.position)),
                                  orientation=mi.Point3f(*map(float, sionna_orientation(
                                      p.orientation))),
                                  power_dbm=float(p_dbm)))
        rm = rt.RadioMapSolver()(
            sc, center=mi.Point3f(float(centre[0]), float(centre[1]), h),
            orientation=mi.Point3f(0.0, 0.0, 0.0),
            size=mi.Point2f(float(size[0]), float(size[1])),
            cell_size=mi.Point2f(float(cell_size), float(cell_size)),
            samples_per_tx=int(samples_per_tx), max_depth=depth, los=t.los,
            specular_reflection=t.specular_reflection,
            diffuse_reflection=t.diffuse_reflection, refraction=t.refraction,
            diffraction=t.diffraction, seed=seed)
        gain = np.array(rm.path_gain.numpy(), np.float64)          # [S, ny, nx]
        centres = np.array(rm.cell_centers.numpy(), np.float64)     # [ny, nx, 3]
    free = free_points(sc, centres.reshape(-1, 3)).reshape(centres.shape[:2])
    ofdm, noise = cfg.ofdm, cfg.noise
    noise_w = thermal_noise_power(ofdm.num_subcarriers * ofdm.subcarrier_spacing_hz,
                                  noise.temperature_k, noise.noise_figure_db)
    return radio_map_from_gain(
        gain, names, origin=centres[0, 0, :2], cell_size=float(cell_size), height=h,
        tx_positions=np.array([poses[n].position for n in names], float), tx_power_dbm=power,
        noise_dbm=float(watt_to_dbm(noise_w)), free=free,
        meta={"frequency_hz": float(cfg.scene.frequency_hz), "samples_per_tx":
              int(samples_per_tx), "max_depth": depth, "seed": seed,
              "scene_hash": scene.content_hash(), "scene": cfg.scene.name})


#: Received powers this close (relative) are a tie for the best server: the first wins.
TIE_REL = 1e-9


def radio_map_from_gain(gain: np.ndarray, tx_names, *, origin, cell_size: float, height: float,
                        tx_positions, tx_power_dbm, noise_dbm: float, free=None,
                        meta: dict | None = None) -> RadioMap:
    """Derive RSS, best server, SNR and SINR from linear path gains.

    Args:
        gain: ``[S, ny, nx]`` linear path gain (0: no ray reached the cell).
        tx_names: the S access points.
        origin: ``[2]`` m, centre of cell (0, 0); cell_size, height: m.
        tx_positions: ``[S, 3]`` m; tx_power_dbm: ``[S]`` dBm.
        noise_dbm: thermal noise power over the band, dBm.
        free: ``[ny, nx]`` bool, cells in free space (default: all); the others are NaN.
    """
    gain = np.asarray(gain, np.float64)
    if gain.ndim != 3 or gain.shape[0] != len(tx_names):
        raise ValueError(f"gain: expected [S={len(tx_names)}, ny, nx], got {gain.shape}")
    p_w = 10.0 ** ((np.asarray(tx_power_dbm, float) - 30.0) / 10.0)
    rss_w = gain * p_w[:, None, None]                                 # [S, ny, nx]
    with np.errstate(divide="ignore", invalid="ignore"):
        pg_db = 10 * np.log10(gain)
        rss_dbm = 10 * np.log10(rss_w) + 30.0
        # a tie (within float rounding: 20 dBm + -60 dB against 30 dBm + -70 dB came
        # out 2e-16 apart where NumPy's vectorised power rounds differently, on AVX-512)
        # goes to the first transmitter
        best = np.argmax(rss_w >= rss_w.max(axis=0) * (1.0 - TIE_REL), axis=0).astype(np.int16)
        best_w = np.take_along_axis(rss_w, best[None].astype(int), 0)[0]
        covered = best_w > 0
        best[~covered] = -1
        noise_w = 10.0 ** ((noise_dbm - 30.0) / 10.0)
        snr_db = 10 * np.log10(best_w / noise_w)
        sinr_db = 10 * np.log10(best_w / (rss_w.sum(0) - best_w + noise_w))
    arrays = {"path_gain_db": pg_db.astype(np.float32), "rss_dbm": rss_dbm.astype(np.float32),
              "best_server": best, "best_rss_dbm": (10 * np.log10(np.where(
                  covered, best_w, np.nan)) + 30.0).astype(np.float32),
              "snr_db": np.where(covered, snr_db, -np.inf).astype(np.float32),
              "sinr_db": np.where(covered, sinr_db, -np.inf).astype(np.float32),
              "tx_positions": np.asarray(tx_positions, np.float64).reshape(-1, 3),
              "tx_power_dbm": np.asarray(tx_power_dbm, np.float64)}
    arrays["best_rss_dbm"][~covered] = -np.inf
    free = np.ones(gain.shape[1:], bool) if free is None else np.asarray(free, bool)
    if free.shape != gain.shape[1:]:
        raise ValueError(f"free: expected shape {gain.shape[1:]}, got {free.shape}")
    arrays["free"] = free
    for k in ("path_gain_db", "rss_dbm", "best_rss_dbm", "snr_db", "sinr_db"):
        arrays[k][..., ~free] = np.nan
    arrays["best_server"][~free] = -1
    m = {"format": RADIOMAP_FORMAT, "version": RADIOMAP_FORMAT_VERSION,
         "tx_names": list(tx_names), "origin": [float(x) for x in np.asarray(origin)[:2]],
         "cell_size": float(cell_size), "height": float(height),
         "shape": [int(gain.shape[1]), int(gain.shape[2])], "noise_dbm": float(noise_dbm),
         "units": {k: v[2] for k, v in RADIOMAP_ARRAYS.items()}}
    m.update(meta or {})
    return RadioMap(meta=m, arrays=arrays)


def save_radio_map(rm: RadioMap, path: str | Path) -> Path:
    """Write ``rm`` as a versioned NPZ (arrays as in :data:`RADIOMAP_ARRAYS`)."""
    return write_npz(path, rm.meta, rm.arrays, compress=True)


def load_radio_map(path: str | Path) -> RadioMap:
    """Read a file written by :func:`save_radio_map` (refuses foreign or newer files)."""
    meta, arrays = read_npz(path, fmt=RADIOMAP_FORMAT, version=RADIOMAP_FORMAT_VERSION,
                            required=RADIOMAP_ARRAYS, what="radio map")
    return RadioMap(meta=meta, arrays=arrays, path=Path(path))
