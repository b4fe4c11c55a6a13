"""``twin.toml`` -> typed, validated configuration.

The format is documented in ``docs/config.md``. Every error raised here is a
:class:`ConfigError` whose message names the file, the key and what was
expected, e.g. ``twin.toml: devices[1].array.rows: expected an integer >= 1,
got 0``.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..contract import schema as shared
from ..errors import ConfigError
from ..utils.files import read_regular_file

# The names each key may take and the defaults are the add-on's (addon/contract/schema.py,
# the one definition both sides read); these are the engine's views of them.
SCHEMA_VERSION = shared.TWIN_TOML_SCHEMA

DEVICE_KINDS = tuple(shared.DEVICE_KINDS)
ROLES = tuple(shared.ROLES)
ROBOT_MODELS = tuple(shared.ROBOT_MODELS)
PATTERNS = tuple(shared.PATTERNS)
POLARIZATIONS = tuple(shared.POLARIZATIONS)
TRACER_METHODS = ("auto", "chains", "sbr")
TRACER_BACKENDS = ("sionna", "grid")
MCS_TABLES = ("he", "nr_cqi2")  #: see engine/phy/mcs.py


# --------------------------------------------------------------------------- types


@dataclass(frozen=True)
class SceneConfig:
    name: str
    file: Path  #: absolute path of the Mitsuba XML
    frequency_hz: float


@dataclass(frozen=True)
class OFDMConfig:
    num_subcarriers: int
    subcarrier_spacing_hz: float
    num_symbols: int
    cyclic_prefix_samples: int = 72

    @property
    def bandwidth_hz(self) -> float:
        """N * delta f, Hz."""
        return self.num_subcarriers * self.subcarrier_spacing_hz

    @property
    def symbol_time_s(self) -> float:
        """OFDM symbol duration with cyclic prefix, s."""
        n = self.num_subcarriers
        return (n + self.cyclic_prefix_samples) / (n * self.subcarrier_spacing_hz)


@dataclass(frozen=True)
class NoiseConfig:
    temperature_k: float = 290.0
    noise_figure_db: float = 7.0


@dataclass(frozen=True)
class TracerConfig:
    backend: str = "sionna"
    max_depth: int = 3
    samples_per_src: int = 100_000
    max_num_paths_per_src: int = 1_000_000
    los: bool = True
    specular_reflection: bool = True
    diffuse_reflection: bool = False
    refraction: bool = True
    diffraction: bool = False
    seed: int = 42
    deterministic: bool = True
    grid_file: str = ""  #: backend "grid": the grid NPZ, relative to twin.toml
    #: "auto" (chain reuse when only specular reflection/refraction are on),
    #: "chains" (every chain of the sources enumerated once, image method per
    #: receiver; see engine/raytrace/chains.py) or "sbr" (shoot-and-bounce per call)
    method: str = "auto"

    @property
    def uses_chains(self) -> bool:
        """Whether the Sionna backend reuses specular chains (``method``)."""
        if self.method == "auto":
            return not (self.diffuse_reflection or self.diffraction)
        return self.method == "chains"


@dataclass(frozen=True)
class ArrayConfig:
    rows: int
    cols: int
    vertical_spacing: float  #: wavelengths
    horizontal_spacing: float  #: wavelengths
    pattern: str = shared.DEFAULT_PATTERN
    polarization: str = shared.DEFAULT_POLARIZATION

    @property
    def num_ant(self) -> int:
        """Antenna ports (dual polarization doubles the elements)."""
        dual = self.polarization in shared.DUAL_POLARIZATIONS
        return self.rows * self.cols * (2 if dual else 1)


@dataclass(frozen=True)
class DeviceConfig:
    name: str
    kind: str
    role: str
    position: tuple[float, float, float]
    orientation: tuple[float, float, float]  #: roll, pitch, yaw (rad)
    power_dbm: float
    array: ArrayConfig
    subcarriers: tuple[int, int]
    symbols: tuple[int, int]
    model: str | None = None  #: robots only
    antenna_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    path: dict | None = None  #: robots only: what the robot follows (see docs/config.md)

    @property
    def is_tx(self) -> bool:
        return self.role in ("tx", "txrx")

    @property
    def is_rx(self) -> bool:
        return self.role in ("rx", "txrx")


@dataclass(frozen=True)
class LinkConfig:
    tx: str
    rx: str


@dataclass(frozen=True)
class SensingConfig:
    """One ``[[sensing]]`` table (docs/sensing.md): a radar link ``tx -> rx``
    (``rx == tx``: monostatic) run every ``every`` twin steps."""

    tx: str
    rx: str
    rho: float = 1.0  #: sensing share of the REs (subcarrier comb)
    subcarriers: tuple[int, int] | None = None  #: explicit half-open range
    symbols: tuple[int, int] | None = None
    power_dbm: float = 20.0  #: default: the tx device's power_dbm
    noise_figure_db: float = 7.0  #: default: [noise].noise_figure_db
    estimate_angles: bool = True
    target_height_m: float | None = 0.096  #: None: full 3-D geolocation
    every: int = 1  #: run the radar every this many steps
    #: "first_arrival" (the earliest CFAR peak, robust to clutter) or "nls"
    range_method: str = "first_arrival"

    @property
    def name(self) -> str:
        """``"tx->rx"``."""
        return f"{self.tx}->{self.rx}"


@dataclass(frozen=True)
class LinkAdaptationConfig:
    """``[link_adaptation]``: the rate a modem reaches beside the Shannon rate.

    ``table``: ``"he"`` (802.11ax HE MCS 0-11) or ``"nr_cqi2"`` (5G NR CQI
    table 2, TS 38.214 Table 5.2.2.1-3); ``evm_db``: transmitter EVM floor
    (dB, e.g. -35): the per-stream SINR is capped by ``1 / EVM``.
    """

    table: str = "he"
    evm_db: float = -35.0


@dataclass(frozen=True)
class RoomConfig:
    """``[room]``: which objects are the room's shell (walls, floor, ceiling, windows,
    doors: fixed structure) and which are furniture (movable contents).

    Written by the add-on from each object's *Room part* tag; editable by hand.
    Objects named in neither list are classified from their geometry
    (:func:`isac_twin.scene.room.shell_objects`). Names are checked against
    ``scene.xml`` when the scene loads.
    """

    shell: tuple[str, ...] = ()
    furniture: tuple[str, ...] = ()


@dataclass(frozen=True)
class LocalizationConfig:
    """``[localization]``: the twin localizes its robots every step (docs/config.md).

    ``method``: ``"MCA"``, ``"MCA-angles"``, ``"LOS-fix"``, ``"PDP"`` or
    ``"kNN-CSI"``; ``mode``: ``"pilots"`` (from the links' received pilots at
    ``snr_db``) or ``"tracer"`` (the traced delays); ``spacing_m``: the
    fingerprint database's grid (cached under ``cache_dir``, relative to the
    scene folder); ``fusion``: ``"ekf"`` (odometry + gated fixes) or
    ``"none"`` (the raw fix); ``fix_std_m``: the EKF's fix standard deviation.
    """

    method: str = "MCA-angles"
    mode: str = "pilots"
    snr_db: float = 20.0
    spacing_m: float = 0.05
    fusion: str = "ekf"
    fix_std_m: float = 0.05
    cache_dir: str = "out/cache"


@dataclass(frozen=True)
class LimitsConfig:
    """``[limits]``: the resource budget a twin is checked against at load
    (:func:`check_budget`).

    ``step_memory_mb``: the channels a step builds, summed over the links and the
    sensing links: ``symbols x subcarriers x (rx ports x tx ports) x 8 B`` each
    (complex64 on every symbol: a step with moving robots builds that many, a
    still one fewer), MB (2^20 B); ``devices`` and ``links`` (communication plus
    sensing): how many a twin may hold.
    """

    step_memory_mb: float = 2048.0
    devices: int = 256
    links: int = 1024


@dataclass(frozen=True)
class TwinConfig:
    """The whole ``twin.toml``, validated."""

    path: Path
    scene: SceneConfig
    ofdm: OFDMConfig
    noise: NoiseConfig
    tracer: TracerConfig
    devices: tuple[DeviceConfig, ...]
    links: tuple[LinkConfig, ...]
    schema: int = SCHEMA_VERSION
    sensing: tuple[SensingConfig, ...] = ()
    link_adaptation: LinkAdaptationConfig = field(default_factory=LinkAdaptationConfig)
    room: RoomConfig = field(default_factory=RoomConfig)
    localization: LocalizationConfig | None = None
    limits: LimitsConfig = field(default_factory=LimitsConfig)
    raw: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def folder(self) -> Path:
        return self.path.parent

    def device(self, name: str) -> DeviceConfig:
        for d in self.devices:
            if d.name == name:
                return d
        raise KeyError(f"{self.path.name}: no device named {name!r}")


# --------------------------------------------------------------------------- reader


class _Reader:
    """Pulls typed values out of a TOML table and reports errors by key path."""

    def __init__(self, file: Path):
        self.file = file

    def fail(self, key: str, msg: str) -> ConfigError:
        return ConfigError(f"{self.file}: {key}: {msg}")

    def table(self, data: dict, key: str, prefix: str, *, required: bool = True) -> dict:
        full = f"{prefix}{key}"
        if key not in data:
            if required:
                raise self.fail(full, "missing table")
            return {}
        val = data[key]
        if not isinstance(val, dict):
            raise self.fail(full, f"expected a table, got {type(val).__name__}")
        return val

    def check_keys(self, data: dict, allowed: tuple[str, ...], prefix: str) -> None:
        for k in data:
            if k not in allowed:
                raise self.fail(f"{prefix}{k}", f"unknown key (allowed: {', '.join(allowed)})")

    _MISSING = object()

    def get(self, data: dict, key: str, prefix: str, default: Any = _MISSING) -> Any:
        if key in data:
            return data[key]
        if default is self._MISSING:
            raise self.fail(f"{prefix}{key}", "missing required key")
        return default

    def number(self, data, key, prefix, default=_MISSING, *, positive=False,
               nonneg=False, minimum: float | None = None,
               maximum: float | None = None) -> float:
        v = self.get(data, key, prefix, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.fail(f"{prefix}{key}", f"expected a finite number, got {v!r}")
        if positive and v <= 0:
            raise self.fail(f"{prefix}{key}", f"expected a positive number, got {v!r}")
        if nonneg and v < 0:
            raise self.fail(f"{prefix}{key}", f"expected a number >= 0, got {v!r}")
        if minimum is not None and v < minimum:
            raise self.fail(f"{prefix}{key}", f"expected a number >= {minimum:g}, got {v!r}")
        if maximum is not None and v > maximum:
            raise self.fail(f"{prefix}{key}", f"expected a number <= {maximum:g} (the limit), "
                            f"got {v!r}")
        return float(v)

    def integer(self, data, key, prefix, default=_MISSING, *, minimum: int | None = None,
                maximum: int | None = None) -> int:
        v = self.get(data, key, prefix, default)
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(f"{prefix}{key}", f"expected an integer, got {v!r}")
        if minimum is not None and v < minimum:
            raise self.fail(f"{prefix}{key}", f"expected an integer >= {minimum}, got {v!r}")
        if maximum is not None and v > maximum:
            raise self.fail(f"{prefix}{key}", f"expected an integer <= {maximum} (the limit), "
                            f"got {v!r}")
        return v

    def boolean(self, data, key, prefix, default=_MISSING) -> bool:
        v = self.get(data, key, prefix, default)
        if not isinstance(v, bool):
            raise self.fail(f"{prefix}{key}", f"expected true or false, got {v!r}")
        return v

    def string(self, data, key, prefix, default=_MISSING, *, choices=None) -> str:
        v = self.get(data, key, prefix, default)
        if not isinstance(v, str) or not v:
            raise self.fail(f"{prefix}{key}", f"expected a non-empty string, got {v!r}")
        if choices is not None and v not in choices:
            raise self.fail(f"{prefix}{key}", f"expected one of {', '.join(choices)}, got {v!r}")
        return v

    def vector(self, data, key, prefix, n: int, default=_MISSING) -> tuple[float, ...]:
        v = self.get(data, key, prefix, default)
        ok = (isinstance(v, (list, tuple)) and len(v) == n
              and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                      and math.isfinite(x) for x in v))
        if not ok:
            raise self.fail(f"{prefix}{key}", f"expected {n} finite numbers, got {v!r}")
        return tuple(float(x) for x in v)

    def range_(self, data, key, prefix, default, upper: int) -> tuple[int, int]:
        v = self.get(data, key, prefix, default)
        ok = (isinstance(v, (list, tuple)) and len(v) == 2
              and all(isinstance(x, int) and not isinstance(x, bool) for x in v))
        if not ok:
            raise self.fail(f"{prefix}{key}", f"expected [start, stop] integers, got {v!r}")
        start, stop = v
        if not 0 <= start < stop <= upper:
            raise self.fail(f"{prefix}{key}",
                            f"expected 0 <= start < stop <= {upper}, got [{start}, {stop}]")
        return (start, stop)


#: Limits checked at load (a value beyond them is a typo or would exhaust memory):
#: OFDM grid (5G NR has at most 3,300 subcarriers per carrier, 802.11be 4,096 tones),
#: spacing (5G NR at most 960 kHz), array size, tracer effort, powers.
MAX_SUBCARRIERS = 65_536
#: Largest twin.toml read, bytes.
MAX_CONFIG_BYTES = 16 * 1024 * 1024
MAX_SYMBOLS = 4_096
MAX_SUBCARRIER_SPACING_HZ = 10e6
MAX_FREQUENCY_HZ = 1e12
MAX_ARRAY_SIDE = 256
MAX_TRACER_DEPTH = 32
MAX_SAMPLES_PER_SRC = 100_000_000
POWER_DBM_RANGE = (-150.0, 100.0)

_TOP_KEYS = ("schema", "scene", "ofdm", "noise", "tracer", "devices", "links", "sensing",
             "link_adaptation", "room", "localization", "limits")
#: ``[localization] method`` values (engine/localization/baselines.py METHODS)
LOCALIZATION_METHODS = ("MCA", "MCA-angles", "LOS-fix", "PDP", "kNN-CSI")
LOCALIZATION_KEYS = ("method", "mode", "snr_db", "spacing_m", "fusion", "fix_std_m",
                     "cache_dir")
SENSING_KEYS = ("tx", "rx", "rho", "subcarriers", "symbols", "power_dbm", "noise_figure_db",
                "estimate_angles", "target_height_m", "every", "range_method")
RANGE_METHODS = ("first_arrival", "nls")  #: see engine/sensing/radar.py
_DEVICE_KEYS = ("name", "kind", "role", "position", "orientation", "power_dbm", "array",
                "subcarriers", "symbols", "model", "antenna_offset", "path")
PATH_KINDS = ("circle", "polyline", "figure_eight", "goal")
_PATH_KEYS = {
    "circle": ("centre", "radius", "direction"),
    "polyline": ("waypoints", "closed"),
    "figure_eight": ("centre", "size"),
    "goal": ("goal",),
}
_ARRAY_KEYS = ("rows", "cols", "vertical_spacing", "horizontal_spacing", "pattern",
               "polarization")


#: polarizations the tracer and PHY model exactly (see engine/raytrace/antenna_patterns.py);
#: sensing links, localization and path grids carry V only (refused at load).
MODELLED_POLARIZATIONS = tuple(POLARIZATIONS)


def _parse_array(r: _Reader, data: dict, prefix: str) -> ArrayConfig:
    r.check_keys(data, _ARRAY_KEYS, prefix)
    pol = r.string(data, "polarization", prefix, shared.DEFAULT_POLARIZATION,
                   choices=POLARIZATIONS)
    if pol not in MODELLED_POLARIZATIONS:
        raise r.fail(f"{prefix}polarization", f"{pol!r} is not modelled: use one of "
                     f"{', '.join(MODELLED_POLARIZATIONS)}")
    return ArrayConfig(
        rows=r.integer(data, "rows", prefix, minimum=1, maximum=MAX_ARRAY_SIDE),
        cols=r.integer(data, "cols", prefix, minimum=1, maximum=MAX_ARRAY_SIDE),
        vertical_spacing=r.number(data, "vertical_spacing", prefix,
                                  shared.DEFAULT_ELEMENT_SPACING, positive=True),
        horizontal_spacing=r.number(data, "horizontal_spacing", prefix,
                                    shared.DEFAULT_ELEMENT_SPACING, positive=True),
        pattern=r.string(data, "pattern", prefix, shared.DEFAULT_PATTERN, choices=PATTERNS),
        polarization=pol,
    )


def _parse_path(r: _Reader, data: dict, prefix: str) -> dict:
    kind = r.string(data, "kind", prefix, choices=PATH_KINDS)
    r.check_keys(data, ("kind", "speed") + _PATH_KEYS[kind], prefix)
    out: dict[str, Any] = {"kind": kind}
    if "speed" in data:
        out["speed"] = r.number(data, "speed", prefix, positive=True)
    if kind in ("circle", "figure_eight"):
        out["centre"] = list(r.vector(data, "centre", prefix, 2))
    if kind == "circle":
        out["radius"] = r.number(data, "radius", prefix, positive=True)
        out["direction"] = r.string(data, "direction", prefix, shared.DEFAULT_PATH_DIRECTION,
                                    choices=tuple(shared.PATH_DIRECTIONS))
    elif kind == "figure_eight":
        out["size"] = r.number(data, "size", prefix, positive=True)
    elif kind == "goal":
        out["goal"] = list(r.vector(data, "goal", prefix, 2))
    elif kind == "polyline":
        wps = r.get(data, "waypoints", prefix)
        if not isinstance(wps, list) or len(wps) < 2:
            raise r.fail(f"{prefix}waypoints", f"expected at least 2 [x, y] points, got {wps!r}")
        if len(wps) > shared.MAX_WAYPOINTS:
            raise r.fail(f"{prefix}waypoints", f"{len(wps)} waypoints, beyond the limit of "
                         f"{shared.MAX_WAYPOINTS}")
        out["waypoints"] = [list(r.vector({"p": w}, "p", f"{prefix}waypoints[{j}].", 2))
                            for j, w in enumerate(wps)]
        out["closed"] = r.boolean(data, "closed", prefix, False)
    return out


def parse_path_spec(data: Any, file: Path, where: str = "path") -> dict:
    """Validate a path spec given outside twin.toml (a CLI option, an API argument)
    exactly as a ``[devices.path]`` table: ``{"kind": ..., ...}`` -> the clean dict.

    Raises:
        ConfigError: naming ``file``, ``where`` and the key at fault.
    """
    r = _Reader(Path(file))
    if not isinstance(data, dict):
        raise r.fail(where, f"expected a table with a kind, got {data!r}")
    return _parse_path(r, data, f"{where}.")


def _parse_device(r: _Reader, data: Any, i: int, ofdm: OFDMConfig) -> DeviceConfig:
    prefix = f"devices[{i}]."
    if not isinstance(data, dict):
        raise r.fail(f"devices[{i}]", "expected a table")
    r.check_keys(data, _DEVICE_KEYS, prefix)
    name = r.string(data, "name", prefix)
    why = shared.name_problem(name)
    if why is not None:
        raise r.fail(f"{prefix}name", why)
    prefix = f"devices[{i}] ({name})."
    kind = r.string(data, "kind", prefix, choices=DEVICE_KINDS)
    model = None
    path = None
    offset = (0.0, 0.0, 0.0)
    if kind == "robot":
        model = r.string(data, "model", prefix, shared.DEFAULT_ROBOT_MODEL,
                         choices=ROBOT_MODELS)
        offset = r.vector(data, "antenna_offset", prefix, 3,
                          list(shared.DEFAULT_ANTENNA_OFFSET))
        if "path" in data:
            path = _parse_path(r, r.table(data, "path", prefix), f"{prefix}path.")
    else:
        for k in ("model", "antenna_offset", "path"):
            if k in data:
                raise r.fail(f"{prefix}{k}", "only robots have this key")
    return DeviceConfig(
        name=name,
        kind=kind,
        role=r.string(data, "role", prefix, choices=ROLES),
        position=r.vector(data, "position", prefix, 3),
        orientation=r.vector(data, "orientation", prefix, 3, [0.0, 0.0, 0.0]),
        power_dbm=r.number(data, "power_dbm", prefix, minimum=POWER_DBM_RANGE[0],
                           maximum=POWER_DBM_RANGE[1]),
        array=_parse_array(r, r.table(data, "array", prefix), f"{prefix}array."),
        subcarriers=r.range_(data, "subcarriers", prefix, [0, ofdm.num_subcarriers],
                             ofdm.num_subcarriers),
        symbols=r.range_(data, "symbols", prefix, [0, ofdm.num_symbols], ofdm.num_symbols),
        model=model,
        antenna_offset=offset,
        path=path,
    )


def parse_config(data: dict, path: Path) -> TwinConfig:
    """Validate a parsed ``twin.toml`` dictionary.

    Args:
        data: the dictionary ``tomllib`` returned.
        path: the file it came from (used in messages and to resolve ``scene.file``).

    Raises:
        ConfigError: naming the file, key and what was expected.
    """
    path = Path(path)
    r = _Reader(path)
    r.check_keys(data, _TOP_KEYS, "")
    schema = r.integer(data, "schema", "", SCHEMA_VERSION)
    if schema != SCHEMA_VERSION:
        raise r.fail("schema", f"this engine reads schema {SCHEMA_VERSION}, got {schema}")

    s = r.table(data, "scene", "")
    r.check_keys(s, ("name", "file", "frequency_hz"), "scene.")
    try:
        scene_file = (path.parent / r.string(s, "file", "scene.")).resolve()
    except (OSError, RuntimeError):  # Python raises either for a symbolic-link loop
        raise r.fail("scene.file", "a symbolic-link loop, not a scene file") from None
    scene = SceneConfig(
        name=r.string(s, "name", "scene."),
        file=scene_file,
        frequency_hz=r.number(s, "frequency_hz", "scene.", positive=True,
                              maximum=MAX_FREQUENCY_HZ),
    )

    o = r.table(data, "ofdm", "")
    r.check_keys(o, ("num_subcarriers", "subcarrier_spacing_hz", "num_symbols",
                     "cyclic_prefix_samples"), "ofdm.")
    ofdm = OFDMConfig(
        num_subcarriers=r.integer(o, "num_subcarriers", "ofdm.", minimum=1,
                                  maximum=MAX_SUBCARRIERS),
        subcarrier_spacing_hz=r.number(o, "subcarrier_spacing_hz", "ofdm.", positive=True,
                                       maximum=MAX_SUBCARRIER_SPACING_HZ),
        num_symbols=r.integer(o, "num_symbols", "ofdm.", minimum=1, maximum=MAX_SYMBOLS),
        cyclic_prefix_samples=r.integer(o, "cyclic_prefix_samples", "ofdm.", 72, minimum=0),
    )

    n = r.table(data, "noise", "", required=False)
    r.check_keys(n, ("temperature_k", "noise_figure_db"), "noise.")
    noise = NoiseConfig(
        temperature_k=r.number(n, "temperature_k", "noise.", 290.0, positive=True,
                               maximum=1e4),
        noise_figure_db=r.number(n, "noise_figure_db", "noise.", 7.0, nonneg=True,
                                 maximum=100.0),
    )

    t = r.table(data, "tracer", "", required=False)
    d = TracerConfig()
    if "probe_spacing" in t:
        raise r.fail("tracer.probe_spacing", "no longer used: chain reuse enumerates every "
                     "chain of the sources (there is no probe lattice); remove the key")
    r.check_keys(t, tuple(d.__dataclass_fields__), "tracer.")
    tracer = TracerConfig(
        backend=r.string(t, "backend", "tracer.", d.backend, choices=TRACER_BACKENDS),
        max_depth=r.integer(t, "max_depth", "tracer.", d.max_depth, minimum=0,
                            maximum=MAX_TRACER_DEPTH),
        samples_per_src=r.integer(t, "samples_per_src", "tracer.", d.samples_per_src, minimum=1,
                                  maximum=MAX_SAMPLES_PER_SRC),
        max_num_paths_per_src=r.integer(t, "max_num_paths_per_src", "tracer.",
                                        d.max_num_paths_per_src, minimum=1,
                                        maximum=MAX_SAMPLES_PER_SRC),
        los=r.boolean(t, "los", "tracer.", d.los),
        specular_reflection=r.boolean(t, "specular_reflection", "tracer.",
                                      d.specular_reflection),
        diffuse_reflection=r.boolean(t, "diffuse_reflection", "tracer.", d.diffuse_reflection),
        refraction=r.boolean(t, "refraction", "tracer.", d.refraction),
        diffraction=r.boolean(t, "diffraction", "tracer.", d.diffraction),
        seed=r.integer(t, "seed", "tracer.", d.seed, minimum=0),
        deterministic=r.boolean(t, "deterministic", "tracer.", d.deterministic),
        grid_file=r.get(t, "grid_file", "tracer.", d.grid_file),
        method=r.string(t, "method", "tracer.", d.method, choices=TRACER_METHODS),
    )
    if tracer.method == "chains" and (tracer.diffuse_reflection or tracer.diffraction):
        raise r.fail("tracer.method", '"chains" reuses specular chains only; with '
                     'diffuse_reflection or diffraction on use "sbr" (or "auto")')
    if not isinstance(tracer.grid_file, str):
        raise r.fail("tracer.grid_file", f"expected a file name, got {tracer.grid_file!r}")
    if tracer.backend == "grid" and not tracer.grid_file:
        raise r.fail("tracer.grid_file", 'required when backend = "grid" (the NPZ '
                     "written by `isac-twin grid`)")

    devs = r.get(data, "devices", "")
    if not isinstance(devs, list) or not devs:
        raise r.fail("devices", "expected a non-empty array of tables [[devices]]")
    devices = tuple(_parse_device(r, dv, i, ofdm) for i, dv in enumerate(devs))
    seen: set[str] = set()
    for i, dv in enumerate(devices):
        if dv.name in seen:
            raise r.fail(f"devices[{i}].name", f"duplicate device name {dv.name!r}")
        seen.add(dv.name)

    lks = r.get(data, "links", "", [])
    if not isinstance(lks, list):
        raise r.fail("links", "expected an array of tables [[links]]")
    by_name = {dv.name: dv for dv in devices}
    links = []
    for i, lk in enumerate(lks):
        prefix = f"links[{i}]."
        if not isinstance(lk, dict):
            raise r.fail(f"links[{i}]", "expected a table")
        r.check_keys(lk, ("tx", "rx"), prefix)
        tx, rx = r.string(lk, "tx", prefix), r.string(lk, "rx", prefix)
        for key, nm, want in (("tx", tx, "is_tx"), ("rx", rx, "is_rx")):
            if nm not in by_name:
                raise r.fail(f"{prefix}{key}", f"unknown device {nm!r} "
                             f"(devices: {', '.join(by_name)})")
            if not getattr(by_name[nm], want):
                raise r.fail(f"{prefix}{key}", f"device {nm!r} has role "
                             f"{by_name[nm].role!r}, which cannot {key[:2]}")
        if tx == rx:
            raise r.fail(prefix.rstrip("."), f"a link needs two devices, got {tx!r} twice")
        links.append(LinkConfig(tx=tx, rx=rx))

    la = r.table(data, "link_adaptation", "", required=False)
    r.check_keys(la, ("table", "evm_db"), "link_adaptation.")
    link_adaptation = LinkAdaptationConfig(
        table=r.string(la, "table", "link_adaptation.", "he", choices=MCS_TABLES),
        evm_db=r.number(la, "evm_db", "link_adaptation.", -35.0))
    if link_adaptation.evm_db >= 0:
        raise r.fail("link_adaptation.evm_db", "expected a negative EVM floor in dB "
                     f"(e.g. -35), got {link_adaptation.evm_db!r}")

    room = _parse_room(r, data)
    sensing = _parse_sensing(r, data, devices, noise, ofdm)
    for i, s_ in enumerate(sensing):
        for key in ("tx", "rx"):
            dev = by_name[getattr(s_, key)]
            if dev.array.pattern != "iso":
                raise r.fail(f"sensing[{i}].{key}", f"device {dev.name!r} has pattern "
                             f"{dev.array.pattern!r}; sensing links model iso elements only")
            if dev.array.polarization != "V":
                raise r.fail(f"sensing[{i}].{key}", f"device {dev.name!r} has polarization "
                             f"{dev.array.polarization!r}; sensing links model V elements only")
    if tracer.backend == "grid":
        for i, dev in enumerate(devices):
            if dev.array.polarization != "V":
                raise r.fail(f"devices[{i}] ({dev.name}).array.polarization",
                             f"{dev.array.polarization!r} needs the paths' polarization "
                             "transfer matrices, which a path grid does not store (V only); "
                             'use tracer.backend = "sionna"')
    limits = _parse_limits(r, data)
    check_budget(r, limits, ofdm, devices, links, sensing)
    return TwinConfig(path=path, scene=scene, ofdm=ofdm, noise=noise, tracer=tracer,
                      devices=devices, links=tuple(links), schema=schema, raw=data,
                      sensing=sensing, link_adaptation=link_adaptation, room=room,
                      localization=_parse_localization(r, data, devices), limits=limits)


def _parse_limits(r: _Reader, data: dict) -> LimitsConfig:
    t = r.table(data, "limits", "", required=False)
    d = LimitsConfig()
    r.check_keys(t, tuple(d.__dataclass_fields__), "limits.")
    return LimitsConfig(
        step_memory_mb=r.number(t, "step_memory_mb", "limits.", d.step_memory_mb,
                                positive=True),
        devices=r.integer(t, "devices", "limits.", d.devices, minimum=1),
        links=r.integer(t, "links", "limits.", d.links, minimum=1))


def check_budget(r: _Reader, limits: LimitsConfig, ofdm: OFDMConfig, devices, links,
                 sensing) -> None:
    """Refuse a twin whose step would outgrow ``limits`` (:class:`LimitsConfig`), before
    anything is allocated: each key may be within its own limit while their product
    is not (65,536 subcarriers x 4,096 symbols x a 256 x 256 array).

    Raises:
        ConfigError: one line naming the product (its factors and the link that
            dominates it) and the limit, under ``limits.<key>``.
    """
    if len(devices) > limits.devices:
        raise r.fail("limits.devices", f"{len(devices)} devices, beyond the limit of "
                     f"{limits.devices} (raise [limits] devices to allow more)")
    pairs = [(lk.tx, lk.rx) for lk in links] + [(s.tx, s.rx) for s in sensing]
    if len(pairs) > limits.links:
        raise r.fail("limits.links", f"{len(pairs)} links (communication and sensing), beyond "
                     f"the limit of {limits.links} (raise [limits] links to allow more)")
    if not pairs:
        return
    ports = {d.name: d.array.num_ant for d in devices}
    per_pair = [(ports[tx] * ports[rx], tx, rx) for tx, rx in pairs]
    total_pairs = sum(p for p, _, _ in per_pair)
    k_, n_ = ofdm.num_symbols, ofdm.num_subcarriers
    need = 8 * k_ * n_ * total_pairs  # complex64 [K, N, Nr, Nt] per link, all held at once
    budget = limits.step_memory_mb * 2 ** 20
    if need > budget:
        big, tx, rx = max(per_pair, key=lambda p: p[0])  # the first of the largest
        where = (f"{tx} -> {rx} (1 link)" if len(pairs) == 1 else
                 f"{tx} -> {rx} ... ({len(pairs)} links)")
        factor = (f"{big} antenna pairs" if len(pairs) == 1 else
                  f"{big} antenna pairs (the largest; {total_pairs} in all)")
        raise r.fail("limits.step_memory_mb",
                     f"a step's channels need {k_} symbols x {n_} subcarriers x {factor} x "
                     f"8 B on {where} = {need:.2g} B, beyond the budget of "
                     f"{limits.step_memory_mb:g} MB (raise [limits] step_memory_mb, or use "
                     "fewer subcarriers, symbols, antennas or links)")


def _parse_room(r: _Reader, data: dict) -> RoomConfig:
    t = r.table(data, "room", "", required=False)
    r.check_keys(t, ("shell", "furniture"), "room.")
    lists = {}
    for key in ("shell", "furniture"):
        v = r.get(t, key, "room.", [])
        if not isinstance(v, list) or not all(isinstance(x, str) and x for x in v):
            raise r.fail(f"room.{key}", f"expected a list of object names, got {v!r}")
        lists[key] = tuple(v)
    both = sorted(set(lists["shell"]) & set(lists["furniture"]))
    if both:
        raise r.fail("room", f"{', '.join(map(repr, both))} listed as both shell and furniture")
    return RoomConfig(**lists)


def _parse_localization(r: _Reader, data: dict, devices) -> LocalizationConfig | None:
    if "localization" not in data:
        return None
    t = r.table(data, "localization", "")
    pre = "localization."
    r.check_keys(t, LOCALIZATION_KEYS, pre)
    d = LocalizationConfig()
    cfg = LocalizationConfig(
        method=r.string(t, "method", pre, d.method, choices=LOCALIZATION_METHODS),
        mode=r.string(t, "mode", pre, d.mode, choices=("pilots", "tracer")),
        snr_db=r.number(t, "snr_db", pre, d.snr_db),
        spacing_m=r.number(t, "spacing_m", pre, d.spacing_m, positive=True),
        fusion=r.string(t, "fusion", pre, d.fusion, choices=("ekf", "none")),
        fix_std_m=r.number(t, "fix_std_m", pre, d.fix_std_m, positive=True),
        cache_dir=r.string(t, "cache_dir", pre, d.cache_dir))
    if not any(dv.kind == "robot" for dv in devices):
        raise r.fail("localization", "no robot to localize (no device of kind 'robot')")
    for i, dv in enumerate(devices):
        if dv.array.polarization != "V":
            raise r.fail("localization", f"devices[{i}] ({dv.name}) has polarization "
                         f"{dv.array.polarization!r}; fingerprints model V elements only")
    if cfg.method in ("MCA-angles", "LOS-fix") and not any(
            dv.kind == "access_point" and dv.array.rows * dv.array.cols > 1 for dv in devices):
        raise r.fail("localization.method", f"{cfg.method!r} needs an access point with more "
                     "than one antenna; every access point here has one")
    return cfg


def _parse_sensing(r: _Reader, data: dict, devices, noise: NoiseConfig,
                   ofdm: OFDMConfig) -> tuple[SensingConfig, ...]:
    tables = r.get(data, "sensing", "", [])
    if not isinstance(tables, list):
        raise r.fail("sensing", "expected an array of tables [[sensing]]")
    by_name = {d.name: d for d in devices}
    out = []
    for i, t in enumerate(tables):
        prefix = f"sensing[{i}]."
        if not isinstance(t, dict):
            raise r.fail(f"sensing[{i}]", "expected a table")
        r.check_keys(t, SENSING_KEYS, prefix)
        for k in ("tx", "rx"):
            if t.get(k) not in by_name:
                raise r.fail(f"{prefix}{k}", f"unknown device {t.get(k)!r} "
                             f"(devices: {', '.join(by_name)})")
        tx = by_name[t["tx"]]
        rho = r.number(t, "rho", prefix, 1.0)
        if not 0 < rho <= 1:
            raise r.fail(f"{prefix}rho", f"expected a share in (0, 1], got {t['rho']!r}")
        h = t.get("target_height_m", 0.096)
        height = None if h is False else r.number(t, "target_height_m", prefix, 0.096)
        out.append(SensingConfig(
            tx=tx.name, rx=t["rx"], rho=rho,
            subcarriers=(r.range_(t, "subcarriers", prefix, None, ofdm.num_subcarriers)
                         if "subcarriers" in t else None),
            symbols=(r.range_(t, "symbols", prefix, None, ofdm.num_symbols)
                     if "symbols" in t else None),
            power_dbm=r.number(t, "power_dbm", prefix, tx.power_dbm,
                               minimum=POWER_DBM_RANGE[0], maximum=POWER_DBM_RANGE[1]),
            noise_figure_db=r.number(t, "noise_figure_db", prefix, noise.noise_figure_db,
                                     nonneg=True),
            estimate_angles=r.boolean(t, "estimate_angles", prefix, True),
            target_height_m=height,
            every=r.integer(t, "every", prefix, 1, minimum=1),
            range_method=r.string(t, "range_method", prefix, "first_arrival",
                                  choices=RANGE_METHODS)))
    return tuple(out)


def load_config(path: str | Path) -> TwinConfig:
    """Read and validate a ``twin.toml`` (or a scene folder holding one).

    Args:
        path: the file, or its folder.

    Raises:
        ConfigError: the file is missing, not TOML, or invalid; the message names
            the file, key and reason.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "twin.toml"
    if not path.exists() and not path.is_symlink():
        raise ConfigError(f"{path}: no such file (expected a twin.toml or a scene folder)")
    blob = read_regular_file(path, MAX_CONFIG_BYTES, error=ConfigError, what="a twin.toml")
    try:
        data = tomllib.loads(blob.decode("utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    except UnicodeDecodeError as exc:
        bad = exc.object[exc.start:exc.start + 1]
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start}: {bad!r}); TOML files "
                          "are UTF-8") from None
    return parse_config(data, path)
