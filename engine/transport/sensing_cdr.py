"""CDR mapping of the sensing layer's ``isac_twin_msgs/msg/Detections``.

Self-contained beside :mod:`isac_twin.transport.cdr`: the ``.msg`` text
(:data:`MSG_DEFINITIONS`) goes into the typestore, :func:`to_ros` /
:func:`from_ros` convert the :class:`~isac_twin.bus.sensing_msgs.Detections`
dataclass (``position [M, 3]`` and ``track_* [T, 2]`` flattened row-major).
Importing this module registers the type on the topic bus.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from ..bus.sensing_msgs import MSG_DEFINITION, Detections, register

__all__ = ["MSG_DEFINITIONS", "to_ros", "from_ros"]

MSG_DEFINITIONS: dict[str, str] = {Detections.ROS_TYPE: MSG_DEFINITION}

register()


def _f64(a) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(a, float).ravel())


def to_ros(msg: Any, R: Callable, header: Callable):
    """The rosbags object for ``msg`` (``R``: its rosbags class, ``header``: the
    Header converter of :mod:`isac_twin.transport.cdr`), or None if not a sensing type."""
    if not isinstance(msg, Detections):
        return None
    return R(header=header(msg.header), link=msg.link, path_length=_f64(msg.path_length),
             range_rate=_f64(msg.range_rate), azimuth=_f64(msg.azimuth),
             zenith=_f64(msg.zenith), snr_db=_f64(msg.snr_db), position=_f64(msg.position),
             track_id=np.ascontiguousarray(np.asarray(msg.track_id, np.int64).ravel()),
             track_position=_f64(msg.track_position),
             track_velocity=_f64(msg.track_velocity))


def from_ros(obj: Any, type_name: str, header_from: Callable):
    """The dataclass of a rosbags object of ``type_name``, or None if not a sensing type."""
    if type_name != Detections.ROS_TYPE:
        return None
    return Detections(header=header_from(obj.header), link=obj.link,
                      path_length=np.asarray(obj.path_length, float),
                      range_rate=np.asarray(obj.range_rate, float),
                      azimuth=np.asarray(obj.azimuth, float),
                      zenith=np.asarray(obj.zenith, float),
                      snr_db=np.asarray(obj.snr_db, float),
                      position=np.asarray(obj.position, float).reshape(-1, 3),
                      track_id=np.asarray(obj.track_id, np.int64),
                      track_position=np.asarray(obj.track_position, float).reshape(-1, 2),
                      track_velocity=np.asarray(obj.track_velocity, float).reshape(-1, 2))
