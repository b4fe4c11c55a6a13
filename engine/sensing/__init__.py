"""ISAC sensing: radar on the twin's OFDM resource grid (issue #8).

Modules: :mod:`~isac_twin.sensing.radar` (OFDM radar processing: range-Doppler
map, CA-CFAR, super-resolution refinement, angle of arrival),
:mod:`~isac_twin.sensing.link` (sensing links, sensing REs, ``y = H x + z``),
:mod:`~isac_twin.sensing.tracer` (echo / clutter paths with Sionna's RCS
solver), :mod:`~isac_twin.sensing.clutter` (background subtraction),
:mod:`~isac_twin.sensing.geometry` (range ellipse x angle),
:mod:`~isac_twin.sensing.tracker` (constant-velocity Kalman tracker),
:mod:`~isac_twin.sensing.estimator` (``RadarEstimator`` for ``Twin``),
:mod:`~isac_twin.sensing.isac` (rate vs sensing trade-off),
:mod:`~isac_twin.bus.sensing_msgs` (``isac_twin_msgs/msg/Detections``),
:mod:`~isac_twin.sensing.config` (``[[sensing]]`` tables).

Only :mod:`~isac_twin.sensing.tracer` and the estimator need Sionna.
"""

from ..bus.sensing_msgs import DETECTIONS_TOPIC, Detections
from ..errors import SensingError
from .clutter import BackgroundSubtractor
from .geometry import locate
from .link import SensingLinkSpec, SensingReceiver, echo_channel, sensing_resource_set
from .radar import Detection, OFDMRadar, RangeDopplerMap, ca_cfar, os_cfar
from .tracker import KalmanTracker, Track

__all__ = [
    "OFDMRadar", "RangeDopplerMap", "Detection", "SensingError", "ca_cfar", "os_cfar",
    "SensingLinkSpec", "SensingReceiver", "echo_channel", "sensing_resource_set",
    "BackgroundSubtractor", "locate", "KalmanTracker", "Track",
    "Detections", "DETECTIONS_TOPIC", "RadarEstimator",
]


def __getattr__(name):  # lazy: the estimator imports the Sionna tracer
    if name == "RadarEstimator":
        from .estimator import RadarEstimator

        return RadarEstimator
    raise AttributeError(name)
