"""ISAC sensing: radar on the twin's OFDM resource grid (issue #8).

Modules: :mod:`~engine.sensing.radar` (OFDM radar processing: range-Doppler
map, CA-CFAR, super-resolution refinement, angle of arrival),
:mod:`~engine.sensing.link` (sensing links, sensing REs, ``y = H x + z``),
:mod:`~engine.sensing.tracer` (echo / clutter paths with Sionna's RCS
solver), :mod:`~engine.sensing.clutter` (background subtraction),
:mod:`~engine.sensing.geometry` (range ellipse x angle),
:mod:`~engine.sensing.tracker` (constant-velocity Kalman tracker),
:mod:`~engine.sensing.estimator` (``RadarEstimator`` for ``Twin``),
:mod:`~engine.sensing.isac` (rate vs sensing trade-off),
:mod:`~engine.sensing.msgs` (``isac_twin_msgs/msg/Detections``),
:mod:`~engine.sensing.config` (``[[sensing]]`` tables).

Only :mod:`~engine.sensing.tracer` and the estimator need Sionna.
"""

from engine.sensing.clutter import BackgroundSubtractor
from engine.sensing.geometry import locate
from engine.sensing.link import (SensingLinkSpec, SensingReceiver, echo_channel,
                                 sensing_resource_set)
from engine.sensing.msgs import DETECTIONS_TOPIC, Detections
from engine.sensing.radar import (Detection, OFDMRadar, RangeDopplerMap, SensingError, ca_cfar,
                                  os_cfar)
from engine.sensing.tracker import KalmanTracker, Track

__all__ = [
    "OFDMRadar", "RangeDopplerMap", "Detection", "SensingError", "ca_cfar", "os_cfar",
    "SensingLinkSpec", "SensingReceiver", "echo_channel", "sensing_resource_set",
    "BackgroundSubtractor", "locate", "KalmanTracker", "Track",
    "Detections", "DETECTIONS_TOPIC", "RadarEstimator",
]


def __getattr__(name):  # lazy: the estimator imports the Sionna tracer
    if name == "RadarEstimator":
        from engine.sensing.estimator import RadarEstimator

        return RadarEstimator
    raise AttributeError(name)
