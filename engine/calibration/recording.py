"""Measurements from a recording: the CSI a robot recorded, at the poses it was at.

Reads the CSI a robot recorded on ``/<robot>/csi`` (an MCAP written by
:func:`isac_twin.transport.record.record_twin`, compact or full CSI; every recorded link,
each transmitter seeing the room from its side, unless ``links`` names some) and the
robot's poses from ``/<robot>/ground_truth`` (interpolated at each CSI stamp; the array
centre is :func:`isac_twin.utils.geometry.antenna_pose` of it), as
:class:`~isac_twin.calibration.problem.Measurements`, with each snapshot's noise variance
estimated from the recorded subcarriers where they allow it.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from ..bus.msgs import Csi
from ..errors import CalibrationError
from ..phy.estimation import noise_power_from_delay_tail
from ..phy.ofdm import ResourceGrid
from ..raytrace import device_poses
from ..scene.config import TwinConfig
from ..transport.record import load_trajectories, read_messages, read_metadata
from ..utils.geometry import antenna_pose, sionna_orientation
from .problem import Measurements

log = logging.getLogger(__name__)


def _array(config: TwinConfig, name: str, path: Path) -> tuple:
    dev = next(d for d in config.devices if d.name == name)
    a = dev.array
    if a.pattern != "iso" or a.polarization != "V":
        raise CalibrationError(f"{path}: device {name!r} has a {a.pattern!r}/{a.polarization!r} "
                               "array; calibration models isotropic V elements only")
    return (a.rows, a.cols, a.vertical_spacing, a.horizontal_spacing)


#: A link whose noise estimate (median over its snapshots) is this far below its
#: channel power is taken as exact: the delay-tail estimate of a noise-free channel is
#: its Hann window's leakage (lab: 75.6-79.4 dB below), and adding that floor changed
#: the noise-free lab's fit (the tables' permittivity 0.8 -> 11.4 % off; the fits are
#: that sensitive to the route, docs/calibration.md)
NOISELESS_SNR_DB = 60.0


def measurements_from_recording(path: str | Path, config: TwinConfig, *,
                                links: list[tuple[str, str]] | None = None,
                                max_snapshots: int = 6, max_subcarriers: int = 16,
                                noise: bool = True
                                ) -> list[tuple[tuple[str, str], Measurements]]:
    """The recorded CSI of each link as :class:`~isac_twin.calibration.problem.Measurements`.

    Args:
        path: the ``.mcap``.
        config: the scene's config (OFDM grid, devices, arrays).
        links: ``[(tx, rx), ...]`` (default: every recorded link, in the order of
            their first CSI message).
        max_snapshots: at most this many CSI messages per link, evenly spread over the
            run.
        max_subcarriers: at most this many of the recorded subcarriers, evenly spread.
        noise: estimate each snapshot's noise variance from all its recorded
            subcarriers (:func:`~isac_twin.phy.estimation.noise_power_from_delay_tail`;
            ``Measurements.noise_power``, added to the model's power). None where the
            recorded subcarriers are too few or too far apart for a delay tail (logged),
            or the estimate is more than :data:`NOISELESS_SNR_DB` below the channel.
            False: no noise (the model's exact power is compared).

    Returns:
        ``[((tx, rx), measurements), ...]`` (first recorded OFDM symbol of each message).

    Raises:
        CalibrationError: no ``isac_twin`` metadata or CSI decimation in it, no CSI (of a
            link named), no ground truth of the robot, a CSI shape that does not fit the
            grid; naming the file.
    """
    path = Path(path)
    meta = read_metadata(path)
    m = re.search(r"subcarriers\[::(\d+)\]", meta.get("csi", ""))
    if m is None:
        raise CalibrationError(f"{path}: no 'csi' entry in the isac_twin metadata (how the CSI "
                               "was decimated); record with `isac-twin record`")
    step = int(m.group(1))
    by_link: dict[tuple[str, str], list] = {}
    for rm in read_messages(path):
        if rm.type_name == Csi.ROS_TYPE:
            c = rm.decode()
            by_link.setdefault((c.tx, c.rx), []).append(c)
    if not by_link:
        raise CalibrationError(f"{path}: no isac_twin_msgs/Csi messages")
    links = list(by_link) if links is None else [tuple(lk) for lk in links]
    missing = [lk for lk in links if lk not in by_link]
    if missing:
        raise CalibrationError(f"{path}: no isac_twin_msgs/Csi messages of link "
                               + ", ".join(f"{t}->{r}" for t, r in missing) + " (recorded: "
                               + ", ".join(f"{t}->{r}" for t, r in by_link) + ")")
    trajs = load_trajectories(path)
    return [(lk, _link_measurements(path, config, lk, by_link[lk], trajs, step,
                                    max_snapshots, max_subcarriers, noise)) for lk in links]


def _link_measurements(path: Path, config: TwinConfig, link: tuple[str, str], msgs: list,
                       trajs: dict, step: int, max_snapshots: int,
                       max_subcarriers: int, noise: bool = True) -> Measurements:
    """One link of :func:`measurements_from_recording`."""
    tx, rx = link
    if rx not in trajs:
        raise CalibrationError(f"{path}: no /{rx}/ground_truth poses for the CSI of {tx}->{rx}")
    o = config.ofdm
    grid = ResourceGrid(o.num_subcarriers, o.subcarrier_spacing_hz, o.num_symbols)
    offsets = grid.subcarrier_frequencies[::step]
    h0 = np.asarray(msgs[0].h)
    if h0.ndim != 4 or h0.shape[1] != len(offsets):
        raise CalibrationError(f"{path}: CSI of {tx}->{rx} has shape {h0.shape}, expected "
                               f"[symbols, {len(offsets)} subcarriers (1 in {step} of "
                               f"{o.num_subcarriers}), Nr, Nt]")
    pick = np.unique(np.linspace(0, len(msgs) - 1, min(max_snapshots, len(msgs))).round()
                     .astype(int))
    sub = np.unique(np.linspace(0, len(offsets) - 1, min(max_subcarriers, len(offsets)))
                    .round().astype(int))
    robot = next((d for d in config.devices if d.name == rx), None)
    if robot is None:
        raise CalibrationError(f"{path}: the CSI's receiver {rx!r} is not a device of the scene")
    pos, ori, csi, noise_power = [], [], [], []
    for i in pick:
        c = msgs[i]
        if noise and noise_power is not None:
            try:  # h[0]: [all recorded subcarriers, Nr, Nt] -> [Nr, Nt, K]
                noise_power.append(noise_power_from_delay_tail(
                    np.moveaxis(np.asarray(c.h)[0], 0, -1), offsets))
            except ValueError as e:
                log.warning("%s: %s->%s: no noise estimate, the model's exact power is "
                            "compared (%s)", path, tx, rx, e)
                noise_power = None
        pose, _, _ = trajs[rx].at(float(c.header.stamp))
        ap = antenna_pose(pose, robot.antenna_offset)
        pos.append(ap.position)
        ori.append(sionna_orientation(ap.orientation))
        csi.append(np.asarray(c.h)[0, sub])
    txp = device_poses(config).get(tx)
    if txp is None:
        raise CalibrationError(f"{path}: the CSI's transmitter {tx!r} is not a device of the "
                               "scene")
    m = Measurements(txp.position, np.array(pos), offsets[sub], np.array(csi),
                     tx_array=_array(config, tx, path), rx_array=_array(config, rx, path),
                     tx_orientation=sionna_orientation(txp.orientation),
                     rx_orientations=np.array(ori),
                     noise_power=np.array(noise_power) if noise and noise_power else None)
    if m.noise_power is not None and np.median(m.noise_snr_db()) > NOISELESS_SNR_DB:
        m.noise_power = None  # the window's leakage, not noise: an exact channel
    return m
