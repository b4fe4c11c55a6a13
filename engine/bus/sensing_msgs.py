"""Bus message types of the sensing layer.

``isac_twin_msgs/msg/Detections``: one step's radar detections and the
tracker's confirmed tracks, published by the twin's ``[[sensing]]`` radar on
:data:`DETECTIONS_TOPIC`. :func:`register` adds it to
:data:`isac_twin.bus.msgs.MESSAGE_TYPES` (so :func:`isac_twin.bus.bus.resolve_type` accepts
the class and its ROS name) without editing ``engine/bus/msgs.py``; its CDR
mapping (MCAP, zenoh) is :mod:`isac_twin.transport.sensing_cdr`, which registers
it on import. :func:`advertise` puts the topic on a bus.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .msgs import MESSAGE_TYPES, Header

__all__ = ["Detections", "DETECTIONS_TOPIC", "MSG_DEFINITION", "register", "advertise"]

#: Default topic of the radar estimator.
DETECTIONS_TOPIC = "/sensing/detections"


@dataclass
class Detections:
    """Radar detections and tracks (arrays of equal length ``M`` / ``T``).

    Fields:
        header: stamp (s, twin time) and ``frame_id = "map"``.
        link: sensing link ``"tx->rx"`` (``"*"``: all links of the estimator).
        path_length: ``[M]`` bistatic range sums (m).
        range_rate: ``[M]`` path-length rates (m/s).
        azimuth, zenith: ``[M]`` arrival angles at the receiver (rad; NaN: none).
        snr_db: ``[M]`` CFAR SNR (dB).
        position: ``[M, 3]`` geolocated positions (m; NaN rows: not located).
        track_id: ``[T]`` confirmed track ids.
        track_position: ``[T, 2]`` (m); track_velocity: ``[T, 2]`` (m/s).
    """

    ROS_TYPE = "isac_twin_msgs/msg/Detections"
    header: Header = field(default_factory=lambda: Header(frame_id="map"))
    link: str = ""
    path_length: np.ndarray = field(default_factory=lambda: np.zeros(0))
    range_rate: np.ndarray = field(default_factory=lambda: np.zeros(0))
    azimuth: np.ndarray = field(default_factory=lambda: np.zeros(0))
    zenith: np.ndarray = field(default_factory=lambda: np.zeros(0))
    snr_db: np.ndarray = field(default_factory=lambda: np.zeros(0))
    position: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    track_id: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    track_position: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    track_velocity: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))


#: ROS 2 ``.msg`` text of :class:`Detections` (for ``isac_twin.bus.twin_msgs``).
MSG_DEFINITION = """\
# Radar detections of the twin's sensing links and the tracker's confirmed tracks.
std_msgs/Header header
string link                 # "tx->rx", or "*" for several links
float64[] path_length       # [M] bistatic range sum |T-tx|+|T-rx|, m
float64[] range_rate        # [M] d(path length)/dt, m/s
float64[] azimuth           # [M] arrival azimuth at the receiver, rad (NaN: none)
float64[] zenith            # [M] arrival zenith, rad (NaN: none)
float64[] snr_db            # [M] CFAR SNR, dB
float64[] position          # [M * 3] row-major, m (NaN: not located)
int64[] track_id            # [T]
float64[] track_position    # [T * 2] row-major x, y, m
float64[] track_velocity    # [T * 2] row-major vx, vy, m/s
"""


def register() -> None:
    """Add :class:`Detections` to :data:`isac_twin.bus.msgs.MESSAGE_TYPES` (idempotent)."""
    MESSAGE_TYPES.setdefault(Detections.ROS_TYPE, Detections)


def advertise(bus, topic: str = DETECTIONS_TOPIC):
    """Register :class:`Detections` and advertise ``topic`` from node ``radar`` of
    ``bus`` (what a twin with ``[[sensing]]`` tables publishes). Returns the node."""
    register()
    node = bus.node("radar")
    node.advertise(topic, Detections)
    return node
