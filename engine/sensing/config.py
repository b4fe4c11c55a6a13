"""``[[sensing]]`` tables of ``twin.toml`` -> :class:`SensingLinkSpec` list.

Read from ``TwinConfig.raw`` (the raw TOML dict). Keys of one table::

    [[sensing]]
    tx = "AP2"                 # transmitting device
    rx = "AP1"                 # receiving device (= tx: monostatic)
    rho = 0.25                 # sensing share of the REs (subcarrier comb); or:
    # subcarriers = [0, 1024]  # explicit half-open ranges (like devices)
    # symbols = [0, 14]
    power_dbm = 20.0           # default: the tx device's power_dbm
    noise_figure_db = 7.0      # default: [noise].noise_figure_db
    estimate_angles = true
    target_height_m = 0.096    # geolocate on this plane (false: full 3-D)
"""

from __future__ import annotations

from engine.config import ConfigError, TwinConfig
from engine.phy.arrays import PlanarArray
from engine.sensing.link import SensingLinkSpec

__all__ = ["parse_sensing", "SENSING_KEYS"]

SENSING_KEYS = ("tx", "rx", "rho", "subcarriers", "symbols", "power_dbm", "noise_figure_db",
                "estimate_angles", "target_height_m")


def _range(v, key, prefix, path):
    if v is None:
        return None
    if (not isinstance(v, list) or len(v) != 2
            or not all(isinstance(x, int) and not isinstance(x, bool) for x in v)):
        raise ConfigError(f"{path}: {prefix}{key}: expected [start, stop] integers, got {v!r}")
    return (int(v[0]), int(v[1]))


def parse_sensing(config: TwinConfig) -> list[SensingLinkSpec]:
    """The sensing links of a config (empty when there is no ``[[sensing]]``).

    Raises:
        ConfigError: unknown keys or devices, bad values (names the table).
    """
    tables = config.raw.get("sensing", [])
    if not isinstance(tables, list):
        raise ConfigError(f"{config.path}: sensing: expected an array of tables [[sensing]]")
    out = []
    names = {d.name: d for d in config.devices}
    for i, t in enumerate(tables):
        prefix = f"sensing[{i}]."
        if not isinstance(t, dict):
            raise ConfigError(f"{config.path}: sensing[{i}]: expected a table")
        bad = sorted(set(t) - set(SENSING_KEYS))
        if bad:
            raise ConfigError(f"{config.path}: {prefix}{bad[0]}: unknown key "
                              f"(allowed: {', '.join(SENSING_KEYS)})")
        for k in ("tx", "rx"):
            if t.get(k) not in names:
                raise ConfigError(f"{config.path}: {prefix}{k}: unknown device {t.get(k)!r} "
                                  f"(devices: {', '.join(names)})")
        tx, rx = names[t["tx"]], names[t["rx"]]
        a = rx.array
        if a.pattern != "iso" or a.polarization != "V":
            raise ConfigError(f"{config.path}: {prefix}rx: device {rx.name!r} array must be "
                              "iso/V for sensing")
        rho = t.get("rho", 1.0)
        if isinstance(rho, bool) or not isinstance(rho, (int, float)) or not 0 < rho <= 1:
            raise ConfigError(f"{config.path}: {prefix}rho: expected a share in (0, 1], "
                              f"got {rho!r}")
        h = t.get("target_height_m", 0.096)
        out.append(SensingLinkSpec(
            tx=tx.name, rx=rx.name,
            rx_array=PlanarArray(a.rows, a.cols, a.vertical_spacing, a.horizontal_spacing),
            rx_orientation=tuple(rx.orientation),
            power_dbm=float(t.get("power_dbm", tx.power_dbm)), rho=float(rho),
            subcarriers=_range(t.get("subcarriers"), "subcarriers", prefix, config.path),
            symbols=_range(t.get("symbols"), "symbols", prefix, config.path),
            noise_figure_db=float(t.get("noise_figure_db", config.noise.noise_figure_db)),
            estimate_angles=bool(t.get("estimate_angles", True)),
            target_height_m=None if h is False else float(h)))
    return out
